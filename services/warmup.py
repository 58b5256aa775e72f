"""A first run compiles the detailed surface's kernels in a second process.

numba compiles a kernel at its first call and caches the machine code on disk (`cache=True`,
`cloth.jit`). On a machine whose cache is empty (a fresh clone, a new CPU, a changed kernel) a
session therefore starts by compiling for about 110 s (AMD EPYC, 2 cores), on one core: numba
compiles under one lock per process. A session needs its kernels in order: the body's, then
S101's (the pre-roll), then S102-S106's and the layering's, about half of the time.

So a command that will step a detailed surface (`tryon session`, `tryon cloth`, `tryon
cloth-service`) first asks numba's cache whether the surface's kernels are compiled for this CPU
(`surface_compiled`). If not, it starts this module in a second process (`compiling_ahead`), which
steps the detailed surfaces of one outfit on the body's rest pose without S101 (`compile_surface`)
and so compiles S102-S106 into the cache while the command compiles the body and S101. When the
session reaches its first surface, numba loads those kernels from the cache. The cache's files are
written whole (numba writes a temporary file and renames it), so two processes can fill it at
once; a kernel both reach, each compiles. `tryon session` on an empty cache: 112-123 → 74-83 s (AMD
EPYC, seventy-eighth session). The second process runs at a lower priority and is stopped when the
command ends; nothing it does changes a result (the same machine code, loaded instead of
compiled). TRYON_WARMUP=0 turns it off (the tests do: their subprocesses would compete with them).

    python -m services.warmup [--data DIR] [--outfit NAME]     # what the second process runs
"""

from __future__ import annotations

import argparse
import contextlib
import os
import subprocess
import sys
from pathlib import Path

WARMUP_ENV = "TRYON_WARMUP"
NICENESS = 10  # the second process yields a core to the command's own threads


def surface_kernels() -> list:
    """The kernels that take the longest to compile among those a detailed surface needs and S101 does not."""
    from cloth.creases import leave_creases, out_along_normals
    from cloth.pn import pn_surface
    from cloth.wrinkles import apply_constraints, avoid_penetration, fold_across, shading_normals

    return [pn_surface, avoid_penetration, apply_constraints, fold_across, shading_normals, leave_creases,
            out_along_normals]


def surface_compiled() -> bool:
    """Whether numba's cache holds the detailed surface's kernels for this CPU (`cloth.jit.compiled_here`)."""
    from cloth.jit import compiled_here

    return all(compiled_here(k) for k in surface_kernels())


def compile_surface(data: Path, outfit_dir: Path) -> None:
    """Step the detailed surfaces of the outfit in `outfit_dir` once, on the body's rest pose and
    the coarse cloth as fitted (no S101), and layer them: numba compiles (or loads) S102-S106."""
    from cloth.surface import SurfaceSettings
    from skinning.animate import BodyAnimator
    from skinning.body import load_body

    from .cloth_job import OutfitSession, build_outfit, collision_body
    from .model_cache import ModelCache

    body = load_body(data)
    animator = BodyAnimator(body)
    body_mesh = collision_body(body)
    outfit, surface_models, layers = build_outfit(body, animator, body_mesh, outfit_dir, None, None,
                                                  SurfaceSettings(), ModelCache.from_env())
    session = OutfitSession(body, animator, body_mesh, outfit, surface_models=surface_models, threads=1,
                            layers=layers)
    try:
        session.step_cloth(outfit.rest_body, 1.0 / 60.0, coarse=False)
    finally:
        session.close()


def start_compiling(data: Path, outfit_dir: Path) -> subprocess.Popen | None:
    """Start `compile_surface` in a second process if the surface's kernels are not compiled for
    this CPU (and TRYON_WARMUP is not 0); None otherwise."""
    if os.environ.get(WARMUP_ENV, "1") == "0" or surface_compiled():
        return None
    try:  # (from the folder that holds this package, which `python -m` puts first on the path)
        return subprocess.Popen([sys.executable, "-m", "services.warmup", "--data", str(data),
                                 "--outfit", str(outfit_dir)], cwd=Path(__file__).resolve().parents[1],
                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    except OSError:  # (no second process: the command compiles everything itself, as before)
        return None


def stop_compiling(proc: subprocess.Popen | None) -> None:
    """End the second process if it is still compiling (the command is done)."""
    if proc is None or proc.poll() is not None:
        return
    proc.terminate()
    try:
        proc.wait(timeout=5)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


@contextlib.contextmanager
def compiling_ahead(data: Path, outfit_dir: Path):
    """`start_compiling` for the body of a `with`, `stop_compiling` at its end; yields the process (or None)."""
    proc = start_compiling(data, outfit_dir)
    try:
        yield proc
    finally:
        stop_compiling(proc)


def main(argv: list[str] | None = None) -> int:
    from skinning.data import data_dir

    from .cloth_job import OUTFITS, find_outfit

    p = argparse.ArgumentParser(prog="python -m services.warmup", description=__doc__.split("\n\n")[0])
    p.add_argument("--data", default=None, help="data folder (default: $TRYON_DATA or ../shared/data)")
    p.add_argument("--outfit", default=OUTFITS[0], help=f"outfit folder or name (default {OUTFITS[0]})")
    args = p.parse_args(argv)
    with contextlib.suppress(OSError, AttributeError):
        os.nice(NICENESS)
    data = data_dir(args.data)
    compile_surface(data, find_outfit(data, args.outfit))
    return 0


if __name__ == "__main__":
    sys.exit(main())
