# numba's cached kernels of a module whose imports changed are stale: dropped before any runs (cloth.jit)
from pathlib import Path as _Path

from .jit import drop_stale_caches as _drop_stale_caches

_drop_stale_caches(_Path(__file__).parent, __name__)
