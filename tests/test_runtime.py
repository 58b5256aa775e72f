"""Process-wide runtime settings the packages make on import."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# A parallel numba kernel, then 0.2 s of work on the main thread: with spinning OpenMP workers the
# process uses about twice the CPU time of the wall time (a second core busy doing nothing).
_SPIN_PROBE = """
import time, resource, numpy as np
from numba import njit, prange
@njit(parallel=True)
def bump(a):
    for i in prange(a.shape[0]):
        a[i] += 1.0
a = np.zeros(100000)
bump(a)
cpu0, wall0 = resource.getrusage(resource.RUSAGE_SELF).ru_utime, time.perf_counter()
for _ in range(40):
    bump(a)
    t = time.perf_counter()
    while time.perf_counter() - t < 0.005:
        pass
print((resource.getrusage(resource.RUSAGE_SELF).ru_utime - cpu0) / (time.perf_counter() - wall0))
"""


def _run(code: str, env_value: str | None) -> str:
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if env_value is not None:
        env["OMP_WAIT_POLICY"] = env_value
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, check=True)
    return out.stdout.strip()


def test_openmp_wait_policy_is_passive_unless_the_user_sets_one():
    # pinocchio loads libgomp, which reads OMP_WAIT_POLICY once, when it loads
    for entry in ("skinning", "services"):
        assert _run(f"import {entry}, os, pinocchio; print(os.environ.get('OMP_WAIT_POLICY'))", None) == "PASSIVE"
    assert _run("import services, os; print(os.environ['OMP_WAIT_POLICY'])", "ACTIVE") == "ACTIVE"


def test_idle_openmp_workers_do_not_burn_a_core():
    if (os.cpu_count() or 1) < 2:
        pytest.skip("needs two cores")
    spinning = float(_run("import pinocchio\n" + _SPIN_PROBE, "ACTIVE"))
    if spinning < 1.5:
        pytest.skip(f"the machine is too busy to see spinning workers (CPU/wall {spinning:.2f} with ACTIVE)")
    assert float(_run("import services, pinocchio\n" + _SPIN_PROBE, None)) < 1.3
