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
