"""A first run compiles the detailed surface's kernels in a second process (services/warmup.py)."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np

from cloth.surface import SurfaceSettings
from services.cloth_job import OutfitSession, build_outfit, collision_body
from skinning.animate import BodyAnimator

ROOT = Path(__file__).resolve().parents[1]


def run_python(code: str, cache: Path, timeout: float, **env) -> str:
    """`code` in a fresh interpreter whose numba cache is `cache`; its stdout."""
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=ROOT, capture_output=True, text=True,
                         timeout=timeout, env={**os.environ, "NUMBA_CACHE_DIR": str(cache), **env})
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


def test_compiled_here_reads_the_cache_of_this_cpu(tmp_path):
    # an empty cache: not compiled; after one call it is, for this process and the next
    code = """
        import numpy as np
        from cloth.jit import compiled_here
        from cloth.wrinkles import offset_along_normals
        print(compiled_here(offset_along_normals))
        p = np.zeros((3, 3)); n = np.ones((3, 3)); h = np.full(3, 0.5); out = np.zeros((3, 3))
        offset_along_normals(p, n, h, out)
        assert (out == 0.5).all()
        print(compiled_here(offset_along_normals))
    """
    assert run_python(code, tmp_path, 120).split() == ["False", "True"]
    assert run_python(code, tmp_path, 120).split() == ["True", "True"]


def test_the_surface_alone_steps_on_the_coarse_cloth_as_it_is(body, data):
    # step_cloth(coarse=False), what the second process runs: S101 is not stepped, the detailed surfaces
    # are built over the coarse cloth and layered, the same on one thread as on two
    animator = BodyAnimator(body)
    body_mesh = collision_body(body)
    outfit, surface_models, layers = build_outfit(body, animator, body_mesh, data / "garments" / "female_casualsuit01",
                                                  surface=SurfaceSettings())
    results = []
    for threads in (1, 2):
        session = OutfitSession(body, animator, body_mesh, outfit, surface_models=surface_models, threads=threads,
                                layers=layers)
        before = [sim.state.x.copy() for sim in session.sims]
        v_before = [sim.state.v.copy() for sim in session.sims]
        out = session.step_cloth(outfit.rest_body, 1.0 / 60.0, coarse=False)
        session.close()
        for sim, x, v, x_out in zip(session.sims, before, v_before, out):
            np.testing.assert_array_equal(sim.state.x, x)
            np.testing.assert_array_equal(sim.state.v, v)
            np.testing.assert_array_equal(x_out, x)
        assert len(session.detailed) == 2
        for p, n in session.detailed:
            assert p.shape[0] > 10_000 and np.isfinite(p).all() and np.isfinite(n).all()
        results.append([p.copy() for p, _ in session.detailed])
    for a, b in zip(*results):
        np.testing.assert_array_equal(a, b)
    # the detailed surface lies on its coarse cloth: within a few centimetres of the fitted particles
    for (p, _), sim in zip(session.detailed, session.sims):
        d = np.linalg.norm(p[:, None, :] - sim.state.x[None, :, :], axis=2).min(axis=1)
        assert np.median(d) < 0.05


def test_a_cold_cache_starts_a_second_process_that_compiles_the_surface(tmp_path, data):
    # on an empty cache: TRYON_WARMUP=0 keeps the second process off; else it starts, and stops with the
    # command (stop_compiling); let run, it compiles the surface's kernels into the cache for this CPU,
    # and then a command starts none
    code = f"""
        import os
        from pathlib import Path
        from services.warmup import start_compiling, stop_compiling, surface_compiled
        data, outfit = Path({str(data)!r}), Path({str(data / "garments" / "female_sportsuit01")!r})
        print(surface_compiled())
        os.environ["TRYON_WARMUP"] = "0"
        print(start_compiling(data, outfit) is None)
        os.environ["TRYON_WARMUP"] = "1"
        proc = start_compiling(data, outfit)
        print(proc is not None and proc.poll() is None)
        stop_compiling(proc)
        print(proc.poll() is not None)
        proc = start_compiling(data, outfit)
        print(proc.wait(timeout=500) == 0)
        print(surface_compiled())
        print(start_compiling(data, outfit) is None)
    """
    assert run_python(code, tmp_path, 600, TRYON_WARMUP="1").split() == ["False"] + ["True"] * 6
    # and a process started afterwards reads them there
    assert run_python("from services.warmup import surface_compiled; print(surface_compiled())",
                      tmp_path, 120).split() == ["True"]
