"""Meshes in fewer bytes on the bus: positions on a 16-bit grid, normals octahedral.

A level-6 garment of 11,000 vertices is 264 kB as float32 positions and normals; this is 110 kB
(10 bytes a vertex instead of 24). Loopback puts and arrivals take time in proportion (a second
process's subscriber, 60 puts a second: 264 kB arrived 0.71 ms after its put began, 110 kB
0.46 ms, the put itself 0.50 against 0.19 ms), a live frame publishes two garments one after the
other, and a display on another machine needs half the bandwidth (2 x 110 kB x 60 Hz = 106 Mbit/s
where float32 needed 253).

positions: per axis, origin = the garment's minimum this frame (float32) and step = its extent /
  65535 (float32); each coordinate is round((x - origin) / step) as uint16, decoded as
  origin + step * q. A garment 1 m across is on a 15 µm grid: at most 8 µm from where the
  simulation put it, far below the 1 mm the method's bounds are stated in.
normals: octahedral (Cigolle et al., "A Survey of Efficient Representations for Independent Unit
  Vectors", JCGT 2014): the unit vector projected onto the octahedron |x| + |y| + |z| = 1, its
  lower half folded over the upper, the two coordinates as int16 snorm. At most 0.004° off.

The body's vertices (schema 4) take the same grid, 6 bytes a vertex instead of 12: the
13,380-vertex body is 80 kB instead of 160 kB, on a grid of at most 28 µm (1.8 m tall), at most
14 µm from where the skinning put it; the cloth service steps on the decoded body, so a replay
of the recorded body stream still reproduces its garments bit for bit.

The encoding is a pure function of the arrays, so a replayed body stream still gives the same
garment messages bit for bit. `float32` meshes stay valid messages (schema 2 and an option of the
cloth service and the ingest, `--float32-meshes`); `garment_mesh` and `body_vertices` read either.
"""

from __future__ import annotations

import numpy as np

from cloth.jit import FAST_ARITHMETIC, kernel

GRID = 65535  # uint16 steps across a garment's extent on each axis
SNORM = 32767.0  # int16 snorm scale of the octahedral coordinates


@kernel(fastmath=FAST_ARITHMETIC)  # min, max and a finiteness sum: any order gives the same
def quantize_positions(p, origin, step, q):
    """Each axis's grid for p (n, 3): origin its minimum (float32) and step its extent / GRID
    (float32; 1 where p is flat along it); q[i, a] = round((p[i, a] - origin[a]) / step[a]), kept
    to [0, GRID]. False, and q untouched, when p holds a NaN or an infinity."""
    lo0 = lo1 = lo2 = np.inf
    hi0 = hi1 = hi2 = -np.inf
    total = 0.0  # not finite iff some coordinate is not (positions are far below overflow)
    for i in range(p.shape[0]):
        x, y, z = p[i, 0], p[i, 1], p[i, 2]
        lo0, lo1, lo2 = min(lo0, x), min(lo1, y), min(lo2, z)
        hi0, hi1, hi2 = max(hi0, x), max(hi1, y), max(hi2, z)
        total += x + y + z
    if not np.isfinite(total):
        return False
    origin[0], origin[1], origin[2] = lo0, lo1, lo2
    step[0] = (hi0 - np.float64(origin[0])) / GRID
    step[1] = (hi1 - np.float64(origin[1])) / GRID
    step[2] = (hi2 - np.float64(origin[2])) / GRID
    for a in range(3):
        if not step[a] > 0.0:
            step[a] = 1.0
    o0, o1, o2 = np.float64(origin[0]), np.float64(origin[1]), np.float64(origin[2])
    r0, r1, r2 = 1.0 / np.float64(step[0]), 1.0 / np.float64(step[1]), 1.0 / np.float64(step[2])
    top = GRID + 0.49  # + 0.5 then truncation: round half up, the values being >= 0
    for i in range(p.shape[0]):
        q[i, 0] = np.uint16(min(max((p[i, 0] - o0) * r0 + 0.5, 0.0), top))
        q[i, 1] = np.uint16(min(max((p[i, 1] - o1) * r1 + 0.5, 0.0), top))
        q[i, 2] = np.uint16(min(max((p[i, 2] - o2) * r2 + 0.5, 0.0), top))
    return True


@kernel
def dequantize_positions(q, origin, step, p):
    """p = origin + step * q, in float32 arithmetic."""
    for i in range(q.shape[0]):
        for a in range(3):
            p[i, a] = origin[a] + step[a] * np.float32(q[i, a])


@kernel(fastmath=FAST_ARITHMETIC)
def octahedral_normals(n, e):
    """Unit vectors n (m, 3) -> int16 snorm octahedral coordinates e (m, 2); a zero vector gives
    (0, 0), which reads back as +z."""
    for i in range(n.shape[0]):
        x, y, z = n[i, 0], n[i, 1], n[i, 2]
        r = SNORM / max(abs(x) + abs(y) + abs(z), 1e-300)  # onto |x| + |y| + |z| = 1, in snorm units
        u = x * r
        v = y * r
        if z < 0.0:  # the lower half folded over the diagonals onto the upper's outside
            su = SNORM if u >= 0.0 else -SNORM
            sv = SNORM if v >= 0.0 else -SNORM
            u, v = (1.0 - abs(v) / SNORM) * su, (1.0 - abs(u) / SNORM) * sv
        e[i, 0] = np.int32(np.rint(u))
        e[i, 1] = np.int32(np.rint(v))


@kernel
def normals_from_octahedral(e, n):
    """int16 snorm octahedral coordinates e (m, 2) -> unit vectors n (m, 3)."""
    for i in range(e.shape[0]):
        u = np.float32(e[i, 0]) / np.float32(SNORM)
        v = np.float32(e[i, 1]) / np.float32(SNORM)
        z = np.float32(1.0) - abs(u) - abs(v)
        if z < 0.0:
            su = np.float32(1.0) if u >= 0.0 else np.float32(-1.0)
            sv = np.float32(1.0) if v >= 0.0 else np.float32(-1.0)
            u, v = (np.float32(1.0) - abs(v)) * su, (np.float32(1.0) - abs(u)) * sv
        r = np.float32(1.0) / np.sqrt(u * u + v * v + z * z)
        n[i, 0] = u * r
        n[i, 1] = v * r
        n[i, 2] = z * r


class CompactPositions:
    """Reusable buffers that turn positions (n, 3) into the compact arrays of a message (`arrays`:
    a body's vertices), every frame without allocating."""

    def __init__(self, n: int):
        self.origin, self.step = np.empty(3, np.float32), np.empty(3, np.float32)
        self.q = np.empty((n, 3), np.uint16)
        self.arrays = {"positions_u16": self.q, "position_origin": self.origin, "position_step": self.step}

    def encode(self, positions: np.ndarray) -> dict[str, np.ndarray]:
        if not quantize_positions(positions, self.origin, self.step, self.q):
            raise ValueError("positions hold NaN or infinite values")
        return self.arrays


class CompactMesh(CompactPositions):
    """The same for one garment's positions and normals (n, 3): the compact arrays of a garment
    message."""

    def __init__(self, n: int):
        super().__init__(n)
        self.e = np.empty((n, 2), np.int16)
        self.arrays["normals_oct16"] = self.e

    def encode(self, positions: np.ndarray, normals: np.ndarray) -> dict[str, np.ndarray]:
        if not quantize_positions(positions, self.origin, self.step, self.q):
            raise ValueError("garment positions hold NaN or infinite values")
        octahedral_normals(normals, self.e)
        return self.arrays


def vertex_count(arrays: dict[str, np.ndarray]) -> int:
    """How many vertices a decoded body or garment message carries, in either form."""
    for name in ("positions", "vertices", "positions_u16"):
        if name in arrays:
            return len(arrays[name])
    raise KeyError("no positions in the message's arrays")



def _positions(arrays: dict[str, np.ndarray], name: str, out: np.ndarray | None = None) -> np.ndarray:
    if name in arrays:
        if out is None:
            return arrays[name]
        out[:] = arrays[name]
        return out
    q = arrays["positions_u16"]
    p = np.empty(q.shape, np.float32) if out is None else out
    dequantize_positions(q, arrays["position_origin"], arrays["position_step"], p)
    return p


def body_vertices(arrays: dict[str, np.ndarray], out: np.ndarray | None = None) -> np.ndarray:
    """The vertices (n, 3) of a decoded body message: float32, compact (decoded into a new array)
    or float32 (its own array, as it is); or written into `out` (any float dtype, the same
    values either way: decoding is float32 arithmetic)."""
    return _positions(arrays, "vertices", out)


def garment_mesh(arrays: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """float32 positions and normals (n, 3) of a decoded garment message, compact (decoded into
    new arrays) or float32 (its own arrays, as they are)."""
    p = _positions(arrays, "positions")
    if "normals" in arrays:
        n = arrays["normals"]
    else:
        e = arrays["normals_oct16"]
        n = np.empty((e.shape[0], 3), np.float32)
        normals_from_octahedral(e, n)
    return p, n
