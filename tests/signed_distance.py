"""An independent signed distance to a triangle mesh, for the acceptance tests.

It shares no code with cloth/: exact closest points on triangles (Ericson, Real-Time
Collision Detection 5.1.5), found through a uniform grid rebuilt for every body pose. Negative
inside, where inside is a winding number of one or more: the signed count of the surface's
crossings on a ray straight up from the point (`winding_numbers`). A skinned body intersects
itself (a thigh raised into the belly, an arm's shoulder cap into the chest), and there the
sign of the nearest face's angle-weighted pseudo-normal (Bærentzen & Aanæs 2005), exact only
for a surface that does not, says "outside" for a point 2-3 cm deep in the thigh whose
nearest face is the belly's skin buried inside it (`pseudo_normal_sign=True` keeps that sign,
to compare). The distance inside is to the nearest face of any sheet: a lower bound of how
far the point is from getting out.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

FACE, EDGE, VERTEX = 0, 1, 2


@njit(cache=True, inline="always")
def _dot(ax, ay, az, bx, by, bz):
    return ax * bx + ay * by + az * bz


@njit(cache=True, inline="always")
def _closest(p, x, tri):
    """Closest point to p on triangle tri (rows of x): returns (qx, qy, qz, feature kind, local index):
    FACE; EDGE 0 (ab), 1 (bc), 2 (ca); VERTEX 0 (a), 1 (b), 2 (c)."""
    a, b, c = tri[0], tri[1], tri[2]
    abx, aby, abz = x[b, 0] - x[a, 0], x[b, 1] - x[a, 1], x[b, 2] - x[a, 2]
    acx, acy, acz = x[c, 0] - x[a, 0], x[c, 1] - x[a, 1], x[c, 2] - x[a, 2]
    apx, apy, apz = p[0] - x[a, 0], p[1] - x[a, 1], p[2] - x[a, 2]
    d1 = _dot(abx, aby, abz, apx, apy, apz)
    d2 = _dot(acx, acy, acz, apx, apy, apz)
    if d1 <= 0.0 and d2 <= 0.0:
        return x[a, 0], x[a, 1], x[a, 2], VERTEX, 0
    bpx, bpy, bpz = p[0] - x[b, 0], p[1] - x[b, 1], p[2] - x[b, 2]
    d3 = _dot(abx, aby, abz, bpx, bpy, bpz)
    d4 = _dot(acx, acy, acz, bpx, bpy, bpz)
    if d3 >= 0.0 and d4 <= d3:
        return x[b, 0], x[b, 1], x[b, 2], VERTEX, 1
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        w = d1 / (d1 - d3)
        return x[a, 0] + w * abx, x[a, 1] + w * aby, x[a, 2] + w * abz, EDGE, 0
    cpx, cpy, cpz = p[0] - x[c, 0], p[1] - x[c, 1], p[2] - x[c, 2]
    d5 = _dot(abx, aby, abz, cpx, cpy, cpz)
    d6 = _dot(acx, acy, acz, cpx, cpy, cpz)
    if d6 >= 0.0 and d5 <= d6:
        return x[c, 0], x[c, 1], x[c, 2], VERTEX, 2
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)
        return x[a, 0] + w * acx, x[a, 1] + w * acy, x[a, 2] + w * acz, EDGE, 2
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return (x[b, 0] + w * (x[c, 0] - x[b, 0]), x[b, 1] + w * (x[c, 1] - x[b, 1]),
                x[b, 2] + w * (x[c, 2] - x[b, 2]), EDGE, 1)
    denom = 1.0 / (va + vb + vc)
    v = vb * denom
    w = vc * denom
    return x[a, 0] + abx * v + acx * w, x[a, 1] + aby * v + acy * w, x[a, 2] + abz * v + acz * w, FACE, 0


@njit(cache=True)
def _angle(x, p, q, r):
    """Angle at vertex p of triangle pqr."""
    ux, uy, uz = x[q, 0] - x[p, 0], x[q, 1] - x[p, 1], x[q, 2] - x[p, 2]
    wx, wy, wz = x[r, 0] - x[p, 0], x[r, 1] - x[p, 1], x[r, 2] - x[p, 2]
    cosang = _dot(ux, uy, uz, wx, wy, wz) / math.sqrt(_dot(ux, uy, uz, ux, uy, uz) * _dot(wx, wy, wz, wx, wy, wz))
    return math.acos(min(1.0, max(-1.0, cosang)))


@njit(cache=True)
def _face_normal(x, tris, t, w, out):
    """Add w times the unit normal of triangle t to out."""
    a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
    ux, uy, uz = x[b, 0] - x[a, 0], x[b, 1] - x[a, 1], x[b, 2] - x[a, 2]
    wx, wy, wz = x[c, 0] - x[a, 0], x[c, 1] - x[a, 1], x[c, 2] - x[a, 2]
    nx, ny, nz = uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx
    ln = math.sqrt(nx * nx + ny * ny + nz * nz)
    if ln > 0.0:
        out[0] += w * nx / ln
        out[1] += w * ny / ln
        out[2] += w * nz / ln


@njit(cache=True)
def _pseudo_normal(x, tris, t, kind, loc, tri_edges, edge_faces, vt_start, vt_ids, out):
    """Pseudo-normal of the closest feature: the face's normal; an edge's two face normals
    summed; a vertex's incident face normals weighted by their angle at the vertex."""
    out[:] = 0.0
    if kind == FACE:
        _face_normal(x, tris, t, 1.0, out)
    elif kind == EDGE:
        e = tri_edges[t, loc]
        for f in range(2):
            if edge_faces[e, f] >= 0:
                _face_normal(x, tris, edge_faces[e, f], 1.0, out)
    else:
        p = tris[t, loc]
        for k in range(vt_start[p], vt_start[p + 1]):
            f = vt_ids[k]
            c = 0
            while tris[f, c] != p:
                c += 1
            _face_normal(x, tris, f, _angle(x, p, tris[f, (c + 1) % 3], tris[f, (c + 2) % 3]), out)


@njit(cache=True, inline="always")
def _hash(i, j, k, mask):
    return ((i * 73856093) ^ (j * 19349663) ^ (k * 83492791)) & mask


@njit(cache=True, inline="always")
def _cell_range(x, tri, cell, axis):
    a = min(x[tri[0], axis], min(x[tri[1], axis], x[tri[2], axis]))
    b = max(x[tri[0], axis], max(x[tri[1], axis], x[tri[2], axis]))
    return int(math.floor(a / cell)), int(math.floor(b / cell))


@njit(cache=True)
def _build_grid(x, tris, cell, start, ids, columns=False):
    """Bucket every triangle into the hashed cells its bounding box overlaps (CSR: start, ids).
    A small hash table stays in cache; cells that share a bucket only add candidates.
    columns: the cells are vertical columns (x, z; j = 0), for `_winding`'s rays.
    Returns the number of entries; when it exceeds len(ids), nothing is filled."""
    mask = start.shape[0] - 2
    counts = np.zeros(start.shape[0] - 1, dtype=np.int64)
    for fill in (False, True):
        if fill:
            total = counts.sum()
            if total > ids.shape[0]:
                return total
            start[0] = 0
            for c in range(counts.shape[0]):
                start[c + 1] = start[c] + counts[c]
            counts[:] = 0
        for t in range(tris.shape[0]):
            i0, i1 = _cell_range(x, tris[t], cell, 0)
            j0, j1 = (0, 0) if columns else _cell_range(x, tris[t], cell, 1)
            k0, k1 = _cell_range(x, tris[t], cell, 2)
            for i in range(i0, i1 + 1):
                for j in range(j0, j1 + 1):
                    for k in range(k0, k1 + 1):
                        c = _hash(i, j, k, mask)
                        if fill:
                            ids[start[c] + counts[c]] = t
                        counts[c] += 1
    return counts.sum()


@njit(cache=True)
def _nearest_in_ball(p, x, tris, cell, start, ids, radius, best_q):
    """Closest point among the triangles in the grid cells overlapping the ball (p, radius)."""
    best = np.inf
    best_t = -1
    best_kind = 0
    best_k = 0
    mask = start.shape[0] - 2
    i0, i1 = int(math.floor((p[0] - radius) / cell)), int(math.floor((p[0] + radius) / cell))
    j0, j1 = int(math.floor((p[1] - radius) / cell)), int(math.floor((p[1] + radius) / cell))
    k0, k1 = int(math.floor((p[2] - radius) / cell)), int(math.floor((p[2] + radius) / cell))
    for i in range(i0, i1 + 1):
        for j in range(j0, j1 + 1):
            for k in range(k0, k1 + 1):
                c = _hash(i, j, k, mask)
                for e in range(start[c], start[c + 1]):
                    t = ids[e]
                    qx, qy, qz, kind, loc = _closest(p, x, tris[t])
                    d = (p[0] - qx) ** 2 + (p[1] - qy) ** 2 + (p[2] - qz) ** 2
                    if d < best:
                        best, best_t, best_kind, best_k = d, t, kind, loc
                        best_q[0], best_q[1], best_q[2] = qx, qy, qz
    return best, best_t, best_kind, best_k


@njit(cache=True)
def _bounding_spheres(x, tris, centre):
    for t in range(tris.shape[0]):
        r = 0.0
        for k in range(3):
            centre[t, k] = (x[tris[t, 0], k] + x[tris[t, 1], k] + x[tris[t, 2], k]) / 3.0
        for c in range(3):
            v = tris[t, c]
            r = max(r, math.sqrt((x[v, 0] - centre[t, 0]) ** 2 + (x[v, 1] - centre[t, 1]) ** 2
                                 + (x[v, 2] - centre[t, 2]) ** 2))
        centre[t, 3] = r


@njit(cache=True)
def _query(points, x, tris, tri_edges, edge_faces, vt_start, vt_ids, cell, start, ids, centre, out):
    best_q = np.empty(3)
    n = np.empty(3)
    for s in range(points.shape[0]):
        p = points[s]
        # Every triangle within `radius` of p overlaps a searched cell, so a hit no farther than
        # `radius` is the true nearest; otherwise widen the ball, and at last search everything.
        best = np.inf
        for radius in (0.5 * cell, 2.0 * cell):
            best, best_t, best_kind, best_k = _nearest_in_ball(p, x, tris, cell, start, ids, radius, best_q)
            if best <= radius * radius:
                break
        if best > (2.0 * cell) ** 2:
            # far from the surface: every triangle, pruned by its bounding sphere against an
            # upper bound from the nearest vertex
            for u in range(x.shape[0]):
                d = (p[0] - x[u, 0]) ** 2 + (p[1] - x[u, 1]) ** 2 + (p[2] - x[u, 2]) ** 2
                best = min(best, d)
            for t in range(tris.shape[0]):
                dc = math.sqrt((p[0] - centre[t, 0]) ** 2 + (p[1] - centre[t, 1]) ** 2 + (p[2] - centre[t, 2]) ** 2)
                if dc - centre[t, 3] > 0.0 and (dc - centre[t, 3]) ** 2 > best:
                    continue
                qx, qy, qz, kind, loc = _closest(p, x, tris[t])
                d = (p[0] - qx) ** 2 + (p[1] - qy) ** 2 + (p[2] - qz) ** 2
                if d <= best:
                    best, best_t, best_kind, best_k = d, t, kind, loc
                    best_q[0], best_q[1], best_q[2] = qx, qy, qz
        _pseudo_normal(x, tris, best_t, best_kind, best_k, tri_edges, edge_faces, vt_start, vt_ids, n)
        side = _dot(p[0] - best_q[0], p[1] - best_q[1], p[2] - best_q[2], n[0], n[1], n[2])
        out[s] = math.sqrt(best) if side >= 0.0 else -math.sqrt(best)


@njit(cache=True, inline="always")
def _edge(x, u, v, px, pz):
    """Twice the signed area of (u, v, p) in the x-z plane, computed from the lower vertex
    index, so that the two faces on an edge get exactly opposite values."""
    lo, hi = min(u, v), max(u, v)
    w = (x[hi, 0] - x[lo, 0]) * (pz - x[lo, 2]) - (x[hi, 2] - x[lo, 2]) * (px - x[lo, 0])
    return w if u == lo else -w


@njit(cache=True, inline="always")
def _owns(x, u, v, flip):
    """Top-left rule: which of the two faces on an edge counts a point exactly on it (the edge
    u -> v as the face, turned counter-clockwise in x-z, runs along it)."""
    dx = x[v, 0] - x[u, 0]
    dz = x[v, 2] - x[u, 2]
    if flip:
        dx, dz = -dx, -dz
    return dz > 0.0 or (dz == 0.0 and dx < 0.0)


@njit(cache=True)
def _winding(points, x, tris, cell, start, ids, seen, out):
    """out[s]: the surface's crossings on the ray from points[s] towards +y, +1 where it leaves
    through a face (normal y > 0), -1 where it enters: the winding number of a closed mesh.
    seen (n_tris,) int64, -1: a face whose box spans two cells of one hash bucket is there
    twice, and counted once."""
    mask = start.shape[0] - 2
    seen[:] = -1
    for s in range(points.shape[0]):
        px, py, pz = points[s, 0], points[s, 1], points[s, 2]
        c = _hash(int(math.floor(px / cell)), 0, int(math.floor(pz / cell)), mask)
        w = 0
        for e in range(start[c], start[c + 1]):
            t = ids[e]
            if seen[t] == s:
                continue
            seen[t] = s
            a, b, d = tris[t, 0], tris[t, 1], tris[t, 2]
            area = (x[b, 0] - x[a, 0]) * (x[d, 2] - x[a, 2]) - (x[b, 2] - x[a, 2]) * (x[d, 0] - x[a, 0])
            if area == 0.0:
                continue  # seen edge-on from below: its neighbours count the crossing
            flip = area < 0.0
            wa = _edge(x, b, d, px, pz)  # opposite a
            wb = _edge(x, d, a, px, pz)
            wc = _edge(x, a, b, px, pz)
            if flip:
                wa, wb, wc = -wa, -wb, -wc
            if wa < 0.0 or wb < 0.0 or wc < 0.0:
                continue
            if (wa == 0.0 and not _owns(x, b, d, flip)) or (wb == 0.0 and not _owns(x, d, a, flip)) \
                    or (wc == 0.0 and not _owns(x, a, b, flip)):
                continue
            hit_y = (wa * x[a, 1] + wb * x[b, 1] + wc * x[d, 1]) / (wa + wb + wc)
            if hit_y > py:
                w += 1 if flip else -1  # clockwise in (x, z): its normal points up, the ray leaves
        out[s] = w


class SignedDistance:
    """Signed distance to a triangle mesh of fixed topology whose vertices move per frame.

        sd = SignedDistance(triangles, n_vertices)
        d = sd(vertices, points)     # (k,) m, negative inside
    """

    def __init__(self, triangles: np.ndarray, n_vertices: int, cell: float = 0.01, table_bits: int = 17,
                 pseudo_normal_sign: bool = False):
        self.tris = np.ascontiguousarray(triangles, dtype=np.int64)
        e = np.sort(np.stack([self.tris[:, [0, 1]], self.tris[:, [1, 2]], self.tris[:, [2, 0]]], axis=1), axis=2)
        uniq, inverse = np.unique(e.reshape(-1, 2), axis=0, return_inverse=True)
        self.tri_edges = inverse.reshape(-1, 3).astype(np.int64)
        self.edge_faces = np.full((len(uniq), 2), -1, dtype=np.int64)
        for t, row in enumerate(self.tri_edges):  # once per topology
            for e in row:
                self.edge_faces[e, 0 if self.edge_faces[e, 0] < 0 else 1] = t
        owner = self.tris.ravel()
        order = np.argsort(owner, kind="stable")
        self.vt_ids = (order // 3).astype(np.int64)
        self.vt_start = np.concatenate([[0], np.cumsum(np.bincount(owner, minlength=n_vertices))]).astype(np.int64)
        self.n_vertices = n_vertices
        self.cell = cell
        self.start = np.zeros((1 << table_bits) + 1, dtype=np.int64)
        self.ids = np.zeros(len(self.tris) * 8, dtype=np.int64)
        self.centre = np.zeros((len(self.tris), 4))  # bounding sphere per triangle: centre, radius
        self.pseudo_normal_sign = pseudo_normal_sign
        self.column_cell = 2.0 * cell
        self.column_start = np.zeros((1 << table_bits) + 1, dtype=np.int64)
        self.column_ids = np.zeros(len(self.tris) * 4, dtype=np.int64)
        self.column_seen = np.zeros(len(self.tris), dtype=np.int64)

    def winding_numbers(self, vertices: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(k,) int64: how many times the closed surface wraps each point (0 outside, 1 inside,
        2 where two intersecting parts of it overlap)."""
        x = np.ascontiguousarray(vertices[: self.n_vertices], dtype=np.float64)
        while True:
            used = _build_grid(x, self.tris, self.column_cell, self.column_start, self.column_ids, True)
            if used <= len(self.column_ids):
                break
            self.column_ids = np.zeros(int(used), dtype=np.int64)
        out = np.zeros(len(points), dtype=np.int64)
        _winding(np.ascontiguousarray(points, dtype=np.float64), x, self.tris, self.column_cell, self.column_start,
                 self.column_ids, self.column_seen, out)
        return out

    def __call__(self, vertices: np.ndarray, points: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(vertices[: self.n_vertices], dtype=np.float64)
        while True:
            used = _build_grid(x, self.tris, self.cell, self.start, self.ids)
            if used <= len(self.ids):
                break
            self.ids = np.zeros(int(used), dtype=np.int64)
        _bounding_spheres(x, self.tris, self.centre)
        out = np.empty(len(points))
        _query(np.ascontiguousarray(points, dtype=np.float64), x, self.tris, self.tri_edges, self.edge_faces,
               self.vt_start, self.vt_ids, self.cell, self.start, self.ids, self.centre, out)
        if self.pseudo_normal_sign:
            return out
        return np.where(self.winding_numbers(vertices, points) > 0, -np.abs(out), np.abs(out))
