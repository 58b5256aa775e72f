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


__all__ = ["FAST_ARITHMETIC", "compiled_here", "helper", "kernel"]
