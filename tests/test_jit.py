"""Per-frame kernels compile without numba's reference-counting runtime (cloth/jit.py)."""

import numpy as np
import pytest

from cloth.jit import NO_REFCOUNT, kernel


def test_a_kernel_works_on_the_arrays_it_is_given():
    @kernel
    def scale_rows(x, s):
        for i in range(x.shape[0]):
            row = x[i]  # a view: fine without reference counting, it never outlives the call
            for k in range(3):
                row[k] *= s

    x = np.arange(12, dtype=np.float64).reshape(4, 3)
    scale_rows(x, 2.0)
    np.testing.assert_array_equal(x, 2.0 * np.arange(12).reshape(4, 3))


@pytest.mark.skipif(not NO_REFCOUNT, reason="this numba has no option to compile without its runtime")
def test_a_kernel_that_allocates_does_not_compile():
    @kernel
    def allocates(n):
        return np.zeros(n).sum()

    with pytest.raises(Exception, match="(?i)nrt|runtime|allocat"):
        allocates(3)


def test_sibling_imports_are_read_from_the_source():
    from cloth.jit import _sibling_imports

    source = b"""
import numpy as np
import pkg.alpha
from . import beta, gamma
from .delta import f
from pkg.epsilon.sub import g
from pkg import zeta
from other.eta import h

def lazy():
    from .theta import k
"""
    assert _sibling_imports(source, "pkg") == {"alpha", "beta", "gamma", "delta", "epsilon", "zeta", "theta"}


PACKAGE = {
    "__init__.py": "from pathlib import Path\nfrom cloth.jit import drop_stale_caches\n"
                   "drop_stale_caches(Path(__file__).parent, __name__)\n",
    "helpers.py": "from cloth.jit import helper\n\n\n@helper\ndef offset(x):\n    return x + 1.0\n",
    "kernels.py": "from cloth.jit import kernel\n\nfrom .helpers import offset\n\n\n"
                  "@kernel\ndef shift(x):\n    return offset(x)\n",
    "other.py": "from cloth.jit import kernel\n\n\n@kernel\ndef double(x):\n    return 2.0 * x\n",
}
RUN = ("import pkg.kernels, pkg.other\n"
       "print(pkg.kernels.shift(1.0), pkg.other.double(1.0),\n"
       "      sum(pkg.kernels.shift.stats.cache_hits.values()), sum(pkg.other.double.stats.cache_hits.values()))\n")


def test_a_kernel_whose_imported_helper_changed_is_compiled_afresh(tmp_path):
    # numba checks a cached kernel against its own file only: a helper inlined from another module
    # stays as it was cached (a git pull that changes only that module) unless the package drops
    # the stale caches first (cloth.jit.drop_stale_caches, as cloth/__init__.py does)
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    for name, text in PACKAGE.items():
        (pkg / name).write_text(text)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache"),
           "PYTHONPATH": os.pathsep.join([str(tmp_path), str(root)])}

    def run() -> list[str]:
        out = subprocess.run([sys.executable, "-c", RUN], capture_output=True, text=True, env=env, timeout=300)
        assert out.returncode == 0, out.stderr[-2000:]
        return out.stdout.split()

    assert run() == ["2.0", "2.0", "0", "0"]  # compiled
    assert run() == ["2.0", "2.0", "1", "1"]  # both from the cache
    (pkg / "helpers.py").write_text(PACKAGE["helpers.py"].replace("x + 1.0", "x + 5.25"))
    # the kernel that inlines the helper is compiled afresh; the module that does not import it stays cached
    assert run() == ["6.25", "2.0", "0", "1"]
    assert run() == ["6.25", "2.0", "1", "1"]
