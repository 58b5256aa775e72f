"""Independent ray casts against a triangle mesh, for the acceptance's count of one garment showing
through another (tests/surface_acceptance.py). Shares no code with cloth/: Möller-Trumbore ray-triangle
tests over the triangles bucketed by tests/signed_distance.py's hashed grid.

    rays = RayCaster(triangles)
    t, face = rays.first_hits(vertices, origins, directions, reach)   # (k,) m along each unit direction
                                                                      # (inf: none), (k,) the triangle met (-1)
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from tests.signed_distance import _build_grid, _hash


@njit(cache=True, inline="always")
def _ray_triangle(ox, oy, oz, dx, dy, dz, x, tri):
    """Distance along the unit direction d from o to triangle tri (rows of x), or inf."""
    a, b, c = tri[0], tri[1], tri[2]
    e1x, e1y, e1z = x[b, 0] - x[a, 0], x[b, 1] - x[a, 1], x[b, 2] - x[a, 2]
    e2x, e2y, e2z = x[c, 0] - x[a, 0], x[c, 1] - x[a, 1], x[c, 2] - x[a, 2]
    px, py, pz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
    det = e1x * px + e1y * py + e1z * pz
    if abs(det) < 1e-18:
        return np.inf  # the ray runs in the triangle's plane
    inv = 1.0 / det
    sx, sy, sz = ox - x[a, 0], oy - x[a, 1], oz - x[a, 2]
    u = (sx * px + sy * py + sz * pz) * inv
    if u < 0.0 or u > 1.0:
        return np.inf
    qx, qy, qz = sy * e1z - sz * e1y, sz * e1x - sx * e1z, sx * e1y - sy * e1x
    v = (dx * qx + dy * qy + dz * qz) * inv
    if v < 0.0 or u + v > 1.0:
        return np.inf
    t = (e2x * qx + e2y * qy + e2z * qz) * inv
    return t if t >= 0.0 else np.inf


@njit(cache=True)
def _first_hits(origins, dirs, reach, x, tris, cell, start, ids, out, face):
    """Each ray's nearest hit within reach: every triangle in the grid cells that the segment's
    bounding box overlaps (a triangle the segment meets overlaps one of them)."""
    mask = start.shape[0] - 2
    for r in range(origins.shape[0]):
        ox, oy, oz = origins[r, 0], origins[r, 1], origins[r, 2]
        dx, dy, dz = dirs[r, 0], dirs[r, 1], dirs[r, 2]
        ex, ey, ez = ox + reach * dx, oy + reach * dy, oz + reach * dz
        best = np.inf
        face[r] = -1
        for i in range(int(math.floor(min(ox, ex) / cell)), int(math.floor(max(ox, ex) / cell)) + 1):
            for j in range(int(math.floor(min(oy, ey) / cell)), int(math.floor(max(oy, ey) / cell)) + 1):
                for k in range(int(math.floor(min(oz, ez) / cell)), int(math.floor(max(oz, ez) / cell)) + 1):
                    c = _hash(i, j, k, mask)
                    for e in range(start[c], start[c + 1]):
                        t = _ray_triangle(ox, oy, oz, dx, dy, dz, x, tris[ids[e]])
                        if t <= reach and t < best:
                            best = t
                            face[r] = ids[e]
        out[r] = best


class RayCaster:
    """First hits of rays on one triangle mesh whose vertices move (its grid rebuilt per call)."""

    def __init__(self, triangles: np.ndarray, cell: float = 0.01, table_bits: int = 16):
        self.tris = np.ascontiguousarray(triangles, dtype=np.int64)
        self.cell = cell
        self.start = np.zeros((1 << table_bits) + 1, dtype=np.int64)
        self.ids = np.zeros(len(self.tris) * 8, dtype=np.int64)

    def first_hits(self, vertices: np.ndarray, origins: np.ndarray, directions: np.ndarray,
                   reach: float) -> tuple[np.ndarray, np.ndarray]:
        """(k,) m: how far along each unit direction from its origin the mesh is first met, within
        reach (inf: not within it); (k,) int64: the triangle met there (-1: none)."""
        x = np.ascontiguousarray(vertices, dtype=np.float64)
        while True:
            used = _build_grid(x, self.tris, self.cell, self.start, self.ids)
            if used <= len(self.ids):
                break
            self.ids = np.zeros(int(used), dtype=np.int64)
        out = np.empty(len(origins))
        face = np.empty(len(origins), dtype=np.int64)
        _first_hits(np.ascontiguousarray(origins, dtype=np.float64), np.ascontiguousarray(directions, dtype=np.float64),
                    float(reach), x, self.tris, self.cell, self.start, self.ids, out, face)
        return out, face
