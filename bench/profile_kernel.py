"""Where a numba kernel's time goes, source line by source line (Linux `perf`, sampling).

    .venv/bin/python bench/profile_kernel.py avoid_penetration [--outfit female_casualsuit01]
        [--clip cmu_131_01_walk_3dsmax] [--frame 60] [--seconds 8] [--depth 2]

1. Runs the outfit through the clip (60 Hz) to --frame and keeps the arguments of every call of
   the kernel in that frame (a kernel the pipeline calls from Python: `cloth.surface`,
   `cloth.sim`, `cloth.layers`, ...; one called from another kernel is profiled as part of it).
2. In a child process, with numba's profiling build (`NUMBA_ENABLE_PROFILING=1`: line tables in
   the machine code; its own cache folder, so the project's cache stays as it is), calls the
   kernel on fresh copies of those arguments for --seconds under `perf record -e cpu-clock`.
3. Maps each sample inside the kernel, or inside a kernel it calls, to its source line and the
   chain of helpers inlined there (`addr2line` on the object code numba loads from its cache)
   and prints the shares: at depth 1 the kernels' own lines, at depth 2 each of those split by
   the line of the helper it runs, ...

The first run compiles the kernel's profiling build (20-60 s for the S103 kernels). Needs `perf`
(software clock events suffice: this works in a VM without hardware counters) and binutils
(`addr2line`, `objdump`). Timings in the child are of one core with warm caches: compare lines within
one profile, not with `bench_surface.py`'s in-pipeline figures.
"""

from __future__ import annotations

import argparse
import bisect
import collections
import importlib
import linecache
import os
import pickle
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PROFILE_CACHE = Path(tempfile.gettempdir()) / "tryon-numba-profile-cache"


def find_kernel(name: str):
    """The dispatcher called `name` in one of the cloth modules."""
    for mod in ("cloth.wrinkles", "cloth.collision", "cloth.creases", "cloth.pn", "cloth.layers", "cloth.dynamics",
                "cloth.geometry", "cloth.winding", "cloth.sim", "cloth.surface"):
        f = getattr(importlib.import_module(mod), name, None)
        if f is not None and hasattr(f, "py_func"):
            return mod, f
    raise SystemExit(f"profile_kernel: no numba kernel called {name!r} in cloth/")


def copied(args) -> list:
    """A copy of a call's arguments, arrays inside tuples included (S101's kernels take the model,
    body and state as tuples of arrays, and write into the state's)."""
    def copy(a):
        if isinstance(a, np.ndarray):
            return a.copy()
        return tuple(copy(x) for x in a) if isinstance(a, tuple) else a
    return [copy(a) for a in args]


def capture(name: str, outfit: str, clip: str, frame: int, data: str | None) -> list:
    """The arguments of every call of kernel `name` (from Python) in walk frame `frame`."""
    sys.path.insert(0, str(ROOT))
    from services.cloth_job import run_cloth_clip
    from skinning.body import load_body
    from skinning.data import data_dir
    from cloth.surface import SurfaceSettings

    _, kernel = find_kernel(name)
    current = {"frame": 0}
    calls: list = []

    def wrapper(*args):
        if current["frame"] == frame:
            calls.append(copied(args))
        return kernel(*args)

    root = data_dir(data)
    body = load_body(root)
    # every kernel compiled first: one that calls this kernel would otherwise be compiled against the wrapper
    run_cloth_clip(body, root / "garments" / outfit, root / "mocap" / f"{clip}.bvh", every=2, max_frames=3,
                   surface=SurfaceSettings())
    patched = []
    for mod in list(sys.modules.values()):
        if getattr(mod, "__name__", "").startswith(("cloth.", "services.", "skinning.")) \
                and getattr(mod, name, None) is kernel:
            setattr(mod, name, wrapper)
            patched.append(mod)
    if not patched:
        raise SystemExit(f"profile_kernel: {name} is not called from Python by the pipeline")

    class Captured(Exception):
        pass

    def on_frame(i, session, body_frame, positions):
        current["frame"] += 1
        if current["frame"] > frame:
            raise Captured

    try:
        run_cloth_clip(body, root / "garments" / outfit, root / "mocap" / f"{clip}.bvh", every=2,
                       on_frame=on_frame, surface=SurfaceSettings())
    except Captured:
        pass
    finally:
        for mod in patched:
            setattr(mod, name, kernel)
    if not calls:
        raise SystemExit(f"profile_kernel: {name} was not called in frame {frame}")
    return calls


def child(name: str, calls_file: str, seconds: float, out_dir: str) -> None:
    """Run in the profiling build: write the object code and load address of the kernel and of every
    other kernel of cloth/ loaded with it (those it calls), then call it on copies of the captured
    arguments for `seconds`."""
    from numba.core import codegen

    loaded = []  # (library, its object code) of every kernel numba loads from its cache (it then drops the code)
    unserialize = codegen.JITCodeLibrary._unserialize.__func__

    def keep_object(cls, cg, state):
        library = unserialize(cls, cg, state)
        if state[1] == "object":
            loaded.append((library, state[2][0]))
        return library

    codegen.JITCodeLibrary._unserialize = classmethod(keep_object)
    sys.path.insert(0, str(ROOT))
    _, kernel = find_kernel(name)
    calls = pickle.load(open(calls_file, "rb"))
    for args in calls:  # compiles (first run) or loads from the profiling cache
        kernel(*copied(args))
    entry = kernel.overloads[tuple(kernel.typeof_pyval(a) for a in calls[0])]
    if not any(library is entry.library for library, _ in loaded):
        print("compiled", flush=True)  # a first run: the parent runs this again, from the cache
        return
    # where each library's code sections were loaded: from a global function's address (a weak one
    # may resolve to another library's copy)
    index = []
    for k, (library, code) in enumerate(loaded):
        obj = Path(out_dir, f"{k}.o")
        obj.write_bytes(code)
        functions = function_symbols(obj)
        for section in {f[1] for f in functions}:
            mine = [f for f in functions if f[1] == section]
            anchor = next((f for f in mine if f[0] == "g"), None)
            if anchor is None:
                continue
            address = library.get_pointer_to_function(anchor[4])
            if not address:
                continue
            base = address - anchor[2]
            lo, hi = min(f[2] for f in mine), max(f[2] + f[3] for f in mine)
            entry_size = next((f[3] for f in mine if f[4] == entry.fndesc.llvm_func_name), 0) \
                if library is entry.library else 0
            index.append(f"{base + lo} {base + hi} {base} {obj} {section} {entry_size}")
    Path(out_dir, "index").write_text("\n".join(index) + "\n")
    if seconds <= 0:
        return  # (the parent's first call: the profiling build is in the cache)
    spent, n, t0 = 0.0, 0, time.perf_counter()
    while n == 0 or time.perf_counter() - t0 < seconds:
        for args in calls:
            copies = copied(args)
            t = time.perf_counter()
            kernel(*copies)
            spent += time.perf_counter() - t
            n += 1
    print(f"{n} calls, {spent / n * 1e6:.0f} us per call", flush=True)


def function_symbols(obj: Path) -> list[tuple[str, str, int, int, str]]:
    """(binding "g"/"w"/"l", section, offset, size, name) of every function in an object file."""
    out = subprocess.run(["objdump", "-t", str(obj)], capture_output=True, text=True, check=True).stdout
    functions = []
    for line in out.splitlines():
        parts = line.split()
        if len(parts) >= 6 and "F" in parts[1:-3]:
            binding = parts[1] if parts[1] in ("g", "w", "l") else "l"
            functions.append((binding, parts[-3], int(parts[0], 16), int(parts[-2], 16), parts[-1]))
    return functions


def line_chains(obj: Path, section: str, offsets: list[int]) -> dict[int, list[str]]:
    """offset in `section` -> [innermost source line, ..., the function's own line] (inlined helpers
    between)."""
    out = subprocess.run(["addr2line", "-a", "-i", "-j", section, "-e", str(obj)] + [hex(o) for o in offsets],
                         capture_output=True, text=True, check=True).stdout.splitlines()
    chains: dict[int, list[str]] = {}
    current = None
    for line in out:
        if line.startswith("0x"):
            current = int(line, 16)
            chains[current] = []
        elif current is not None:
            chains[current].append(line.replace(str(ROOT) + "/", ""))
    return chains


def report(out_dir: Path, depth: int) -> None:
    """The samples in the kernels' machine code, by source line (see module)."""
    ranges = []  # (start, end, section base, object file, section) in the child's memory
    entry_bytes = 0
    for line in (out_dir / "index").read_text().split("\n"):
        if line:
            start, end, base, obj, section, size = line.split()
            ranges.append((int(start), int(end), int(base), Path(obj), section))
            entry_bytes = max(entry_bytes, int(size))
    ranges.sort(key=lambda r: r[0])
    starts = [r[0] for r in ranges]
    ips = subprocess.run(["perf", "script", "-i", str(out_dir / "perf.data"), "-F", "ip"], capture_output=True,
                         text=True, check=True).stdout.split()
    by_section: dict[tuple, collections.Counter] = collections.defaultdict(collections.Counter)
    for ip in (int(x, 16) for x in ips):
        k = bisect.bisect_right(starts, ip) - 1
        if k >= 0 and ip < ranges[k][1]:
            by_section[ranges[k][3], ranges[k][4]][ip - ranges[k][2]] += 1
    total = sum(sum(c.values()) for c in by_section.values())
    print(f"{len(ips)} samples, {total} in the kernel ({entry_bytes:,} bytes of machine code) and the kernels it "
          f"calls")
    if not total:
        return
    samples = []  # (chain, count)
    for (obj, section), counts in by_section.items():
        chains = line_chains(obj, section, sorted(counts))
        samples += [(chains.get(offset) or ["?"], count) for offset, count in counts.items()]
    for d in range(1, depth + 1):
        shares = collections.Counter()
        for chain, count in samples:
            shares[" <- ".join(reversed(chain[-d:]))] += count
        print(f"\n== the kernels' own lines{' and the helpers they run, ' + str(d) + ' deep' if d > 1 else ''}")
        for where, count in shares.most_common(25):
            file, _, line = where.rsplit(" <- ", 1)[-1].rpartition(":")
            text = linecache.getline(str(ROOT / file), int(line)).strip() if line.isdigit() else ""
            print(f"{count / total * 100:5.1f} %  {where:60s}  {text[:70]}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("kernel", help="a per-frame kernel's name, e.g. avoid_penetration, apply_constraints")
    ap.add_argument("--outfit", default="female_casualsuit01")
    ap.add_argument("--clip", default="cmu_131_01_walk_3dsmax")
    ap.add_argument("--frame", type=int, default=60, help="the 60 Hz frame whose calls are profiled")
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--depth", type=int, default=2, help="how many levels of inlined helpers to split by")
    ap.add_argument("--data")
    ap.add_argument("--child", nargs=3, metavar=("CALLS", "SECONDS", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args.kernel, args.child[0], float(args.child[1]), args.child[2])
        return
    for tool in ("perf", "addr2line", "objdump"):
        if shutil.which(tool) is None:
            raise SystemExit(f"profile_kernel: `{tool}` is not installed (perf: linux-perf; addr2line, objdump: binutils)")
    calls = capture(args.kernel, args.outfit, args.clip, args.frame, args.data)
    print(f"{args.kernel}: {len(calls)} calls in frame {args.frame} ({args.outfit}, {args.clip})", flush=True)
    env = {**os.environ, "NUMBA_ENABLE_PROFILING": "1", "NUMBA_CACHE_DIR": str(PROFILE_CACHE)}
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        pickle.dump(calls, open(out / "calls.pkl", "wb"))
        me = [sys.executable, str(Path(__file__).resolve()), args.kernel, "--child", str(out / "calls.pkl")]
        first = subprocess.run(me + ["0", str(out)], env=env, capture_output=True, text=True)
        if first.returncode < 0:
            # killed by a signal, silently: numba checks a cached kernel against its own file only, so a
            # profiling build cached before a helper it inlines changed can crash. Build afresh once.
            shutil.rmtree(PROFILE_CACHE, ignore_errors=True)
            first = subprocess.run(me + ["0", str(out)], env=env, capture_output=True, text=True)
        if first.returncode != 0:
            raise SystemExit(f"profile_kernel: the profiling build failed (exit status {first.returncode}):\n"
                             f"{first.stderr[-2000:]}")
        rec = subprocess.run(["perf", "record", "-q", "-e", "cpu-clock", "-F", "4000", "-o", str(out / "perf.data"),
                              "--"] + me + [str(args.seconds), str(out)], env=env, capture_output=True, text=True)
        if rec.returncode != 0 or not (out / "index").exists():
            raise SystemExit(f"profile_kernel: perf record failed:\n{(rec.stderr or rec.stdout)[-2000:]}")
        print(rec.stdout.strip())
        report(out, args.depth)


if __name__ == "__main__":
    main()
