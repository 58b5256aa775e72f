"""How the per-frame kernels are compiled.

    @kernel                      # cached, releases the GIL, no reference counting
    def step(x, v, ...): ...

    @kernel(fastmath=True)
    def spring_forces(...): ...

The kernels only read and write arrays they are given; they never allocate. Numba's runtime
still counts references to those arrays: every row view (`x[i]`) and every array handed to
an inlined helper is an atomic increment and decrement, which its pruning pass removes only
in small functions. In the S103 walk, a few lines long but inlined into a loop of thousands
of blocks, that was over half of the time (215 → 83 ns per tested particle). A kernel
compiled without the runtime (numba's `_nrt=False` option) cannot allocate, which is what
we want of a per-frame kernel anyway: an allocation in one is a compile error, not a slow
frame. Where numba lacks the option, kernels compile with the runtime, unchanged otherwise.

An index read from an array (a CSR offset, a face's corner, a spring's end) is converted to
`np.uint64` before it indexes: numba wraps a negative signed index around (`i += n` when
`i < 0`), a compare and a select per access, which also keeps LLVM from seeing a run of loads
as contiguous. Unsigned, there is nothing to wrap: the winding number's box tests vectorised
once their loop ran over unsigned indices (a query 122 → 70 ns), and the constraint rounds of
S106 and S101's springs lost 7-24 % of their time alone (seventy-sixth session). Where such an
index is also assigned to a variable that holds -1, keep that variable signed (numba unifies
int64 and uint64 to float64).

Division follows numpy's error model: x / 0 is inf or NaN, not a ZeroDivisionError. Python's
model puts a test-and-raise branch before every division, and that branch alone keeps LLVM
from vectorising a loop with a division in it (the spring kernel's arithmetic: 10.6 → 3.4 µs
when written as a separate pass). A NaN from a degenerate spring is caught by the instability
check (`sim.recover_unstable`) and counted, where an exception would have stopped a service.
"""

from __future__ import annotations

import ast
import hashlib
import json
import os
from pathlib import Path

from numba import njit
from numba.core.options import DefaultOptions

NO_REFCOUNT = {"_nrt": False} if hasattr(DefaultOptions, "_nrt") else {}
# LLVM's inlining of the helpers where numba offers it, numba's own otherwise (see `helper`)
INLINE = {"forceinline": True} if hasattr(DefaultOptions, "forceinline") else {"inline": "always"}

# fastmath without the no-NaN and no-inf assumptions: reassociation, fused multiply-add,
# reciprocals and approximate functions, for kernels whose sums and products need no fixed order
# (the detailed surface's per-edge scatter loops: 10-20 % faster). A NaN still reads as one, and
# the result is deterministic on one machine (the replay test).
FAST_ARITHMETIC = {"nsz", "arcp", "contract", "afn", "reassoc"}


def kernel(fn=None, **options):
    """njit(cache=True, nogil=True, error_model="numpy") without numba's reference-counting
    runtime (see module)."""
    opts = {"cache": True, "nogil": True, "error_model": "numpy", **NO_REFCOUNT, **options}
    if fn is None:
        return njit(**opts)
    return njit(**opts)(fn)


def helper(fn=None, **options):
    """A small function the kernels call in their loops: compiled as a kernel is, and inlined
    into each caller by LLVM (`forceinline`), so a call costs nothing.

    Not numba's own inlining (`inline="always"`), which copies the helper's typed code into
    every caller before compiling it: the same machine code (S103's outputs bit for bit, its
    time within the noise), but the S103 kernels, with the face walk inlined several levels
    deep, took minutes to compile, and a first run (`make run` on a fresh clone) spent 415 s
    compiling against 84 s now. One difference: a helper keeps its own fastmath flags where
    numba's inlining gave it its caller's (`geometry.add_face_normal` in `shading_normals`
    rounds in the last bits as `vertex_normals` does)."""
    opts = {"cache": True, "nogil": True, "error_model": "numpy", **INLINE, **NO_REFCOUNT, **options}
    if fn is None:
        return njit(**opts)
    return njit(**opts)(fn)


def compiled_here(dispatcher) -> bool:
    """Whether numba's on-disk cache holds machine code of `dispatcher` (a kernel) for this
    machine's CPU, from its current source: if not, its first call compiles it. Read from
    numba's cache index (not a public API: where that is not as expected, True)."""
    try:
        index = dispatcher._cache._cache_file._load_index()  # {} when missing or stale
        magic = dispatcher.targetctx.codegen().magic_tuple()  # (target triple, CPU, features)
        return any(key[1] == magic for key in index)
    except Exception:  # noqa: BLE001 - another numba: take it as compiled
        return True


STALE_STAMP = "tryon-sources.json"  # in a package's numba cache folder: each module's key when last checked


def drop_stale_caches(folder: str | Path, package: str) -> list[str]:
    """Delete numba's cached machine code of the modules of `package` (the *.py files in `folder`)
    that depend on a module whose source changed since the last call; returns their names.

    numba checks a cached kernel only against its own file's time stamp and size. A kernel that
    calls or inlines a function of another module (S103's `wrinkles.avoid_penetration` inlines
    `collision.face_walk_distance`) keeps running the old code after that module changes: a
    `git pull` that changes only collision.py left S103 reading the old distances (the sum of its
    readings 44.0 m before and after a change to the face walk that adds 0.5 m to each, seventy-eighth
    session). So each module's key is a digest of its source and of every module of the package
    it imports (`from .x import`, `from package.x import`, also inside functions, and theirs in
    turn), kept in STALE_STAMP in the package's cache folder; where a key changed, that module's
    cache files go, and numba compiles it afresh at its first call. To be called before any
    kernel of the package runs (a package's `__init__`). Errors (a read-only cache, an unusual
    numba) leave the caches as numba keeps them."""
    try:
        return _drop_stale_caches(Path(folder), package)
    except Exception:  # noqa: BLE001 - never stops an import
        return []


def _drop_stale_caches(folder: Path, package: str) -> list[str]:
    sources = {p.stem: p.read_bytes() for p in sorted(folder.glob("*.py"))}
    imports = {m: _sibling_imports(src, package) & sources.keys() for m, src in sources.items()}
    digests = {m: hashlib.sha256(src).hexdigest() for m, src in sources.items()}
    keys = {}
    for m in sources:
        seen, todo = {m}, [m]
        while todo:
            for d in imports[todo.pop()] - seen:
                seen.add(d)
                todo.append(d)
        keys[m] = hashlib.sha256("".join(f"{d}:{digests[d]};" for d in sorted(seen)).encode()).hexdigest()
    cache = _cache_folder(folder)
    stamp = cache / STALE_STAMP
    try:
        old = json.loads(stamp.read_text())
    except (OSError, ValueError):
        old = {}  # (never checked here: any cache files are of unknown age)
    dropped = sorted(m for m in keys if old.get(m) != keys[m])
    for m in dropped:
        for f in cache.glob(f"{m}.*.nb[ic]"):
            f.unlink(missing_ok=True)
    if dropped or old.keys() != keys.keys():
        tmp = stamp.with_name(f"{stamp.name}.{os.getpid()}.part")
        tmp.write_text(json.dumps(keys, indent=0, sort_keys=True))
        os.replace(tmp, stamp)  # (whole: another process may read it meanwhile)
    return dropped


def _sibling_imports(source: bytes, package: str) -> set[str]:
    """The modules of `package` that a module's source imports (first component after the package)."""
    names = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom):
            parts = (node.module or "").split(".")
            if node.level == 1 or (node.level == 0 and parts[0] == package):
                rest = parts if node.level == 1 else parts[1:]
                if rest and rest[0]:
                    names.add(rest[0])
                else:  # from . import x / from package import x
                    names.update(a.name for a in node.names)
        elif isinstance(node, ast.Import):
            for a in node.names:
                parts = a.name.split(".")
                if parts[0] == package and len(parts) > 1:
                    names.add(parts[1])
    return names


def _cache_folder(folder: Path) -> Path:
    """Where numba keeps the cache files of the functions defined in `folder`'s modules (its
    __pycache__, or NUMBA_CACHE_DIR's folder for it, or the user-wide one), as numba's own
    locator finds it for a function defined there."""
    from numba.core.caching import CompileResultCacheImpl

    probe: dict = {}
    exec(compile("def probe():\n    pass\n", str(folder / "__init__.py"), "exec"), probe)
    return Path(CompileResultCacheImpl(probe["probe"]).locator.get_cache_path())


__all__ = ["FAST_ARITHMETIC", "compiled_here", "drop_stale_caches", "helper", "kernel"]
