import os as _os

# numba's parallel kernels (skinning) run on GNU OpenMP, which pinocchio loads at import. Its
# idle workers spin-wait by default, burning a whole core between parallel calls that the cloth's
# garment threads and the other services need (a frame took 19 ms with two garment threads
# instead of 11). Passive waiting must be set before libgomp loads; a user's setting wins.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
