# skinning sets the OpenMP wait policy before pinocchio (imported by several services) loads libgomp
from pathlib import Path as _Path

import skinning
from cloth.jit import drop_stale_caches as _drop_stale_caches

# and skinning's numba caches of a module whose imports changed are dropped before any of its kernels
# runs (cloth.jit; skinning itself cannot import cloth, and cloth's own __init__ checks cloth's)
_drop_stale_caches(_Path(skinning.__file__).parent, skinning.__name__)
