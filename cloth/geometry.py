"""Small geometric kernels shared by the cloth stages (numba, no allocation)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .jit import helper, kernel


@helper
def dot3(a0, a1, a2, b0, b1, b2):
    return a0 * b0 + a1 * b1 + a2 * b2


@helper
def plane_barycentric(x, a, b, c, px, py, pz):
    """Weights (wb, wc) of corners b and c of the projection of p onto the plane of triangle
    (x[a], x[b], x[c]) (wa = 1 - wb - wc; inside where all three are >= 0), and whether the
    triangle has an area (False: the weights are 0)."""
    e1x, e1y, e1z = x[b, 0] - x[a, 0], x[b, 1] - x[a, 1], x[b, 2] - x[a, 2]
    e2x, e2y, e2z = x[c, 0] - x[a, 0], x[c, 1] - x[a, 1], x[c, 2] - x[a, 2]
    wx, wy, wz = px - x[a, 0], py - x[a, 1], pz - x[a, 2]
    d11 = e1x * e1x + e1y * e1y + e1z * e1z
    d12 = e1x * e2x + e1y * e2y + e1z * e2z
    d22 = e2x * e2x + e2y * e2y + e2z * e2z
    dp1 = wx * e1x + wy * e1y + wz * e1z
    dp2 = wx * e2x + wy * e2y + wz * e2z
    det = d11 * d22 - d12 * d12
    if det <= 0.0:
        return 0.0, 0.0, False
    return (d22 * dp1 - d12 * dp2) / det, (d11 * dp2 - d12 * dp1) / det, True


@helper
def ray_triangle(px, py, pz, dx, dy, dz, x, a, b, c):
    """Where the line p + t d meets triangle (x[a], x[b], x[c]) (Möller and Trumbore, 1997):
    (t, wb, wc), the weights of corners b and c there; t = inf where it misses (or lies in the
    triangle's plane)."""
    e1x, e1y, e1z = x[b, 0] - x[a, 0], x[b, 1] - x[a, 1], x[b, 2] - x[a, 2]
    e2x, e2y, e2z = x[c, 0] - x[a, 0], x[c, 1] - x[a, 1], x[c, 2] - x[a, 2]
    hx, hy, hz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
    det = e1x * hx + e1y * hy + e1z * hz
    if abs(det) < 1e-14:
        return math.inf, 0.0, 0.0
    inv = 1.0 / det
    sx, sy, sz = px - x[a, 0], py - x[a, 1], pz - x[a, 2]
    wb = (sx * hx + sy * hy + sz * hz) * inv
    if wb < 0.0 or wb > 1.0:
        return math.inf, 0.0, 0.0
    qx, qy, qz = sy * e1z - sz * e1y, sz * e1x - sx * e1z, sx * e1y - sy * e1x
    wc = (dx * qx + dy * qy + dz * qz) * inv
    if wc < 0.0 or wb + wc > 1.0:
        return math.inf, 0.0, 0.0
    return (e2x * qx + e2y * qy + e2z * qz) * inv, wb, wc


@helper
def closest_point_triangle(px, py, pz, x, a, b, c, out):
    """Closest point to p on triangle (x[a], x[b], x[c]) (Ericson, Real-Time Collision Detection 5.1.5).

    Writes the point to out and returns its barycentric weight of (b, c) as (v, w). The corners
    are read by index (not passed as row views): in the per-frame walks this is most of the
    cost, and a view per corner costs more than the arithmetic."""
    ax, ay, az = x[a, 0], x[a, 1], x[a, 2]
    abx, aby, abz = x[b, 0] - ax, x[b, 1] - ay, x[b, 2] - az
    acx, acy, acz = x[c, 0] - ax, x[c, 1] - ay, x[c, 2] - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = dot3(abx, aby, abz, apx, apy, apz)
    d2 = dot3(acx, acy, acz, apx, apy, apz)
    v = 0.0
    w = 0.0
    if d1 <= 0.0 and d2 <= 0.0:
        v, w = 0.0, 0.0
    else:
        # p - b = ap - ab, p - c = ap - ac
        bpx, bpy, bpz = apx - abx, apy - aby, apz - abz
        d3 = dot3(abx, aby, abz, bpx, bpy, bpz)
        d4 = dot3(acx, acy, acz, bpx, bpy, bpz)
        cpx, cpy, cpz = apx - acx, apy - acy, apz - acz
        d5 = dot3(abx, aby, abz, cpx, cpy, cpz)
        d6 = dot3(acx, acy, acz, cpx, cpy, cpz)
        vc = d1 * d4 - d3 * d2
        vb = d5 * d2 - d1 * d6
        va = d3 * d6 - d5 * d4
        if d3 >= 0.0 and d4 <= d3:
            v, w = 1.0, 0.0
        elif d6 >= 0.0 and d5 <= d6:
            v, w = 0.0, 1.0
        elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
            v, w = d1 / (d1 - d3), 0.0
        elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
            v, w = 0.0, d2 / (d2 - d6)
        elif va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
            w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
            v = 1.0 - w
        else:
            denom = 1.0 / (va + vb + vc)
            v = vb * denom
            w = vc * denom
    out[0] = ax + v * abx + w * acx
    out[1] = ay + v * aby + w * acy
    out[2] = az + v * abz + w * acz
    return v, w


@helper
def closest_in_fan(px, py, pz, x, v, tri_start, tri_ids, tris, q):
    """Closest point to p on the triangles around vertex v of (x, tris): (d², triangle, a, b, c,
    wb, wc, qx, qy, qz), the triangle's corners (a, b, c) from v on and the point's weights of b
    and c. A triangle whose two edges from v both point away from p ((p - v)·(b - v) <= 0 and
    (p - v)·(c - v) <= 0) has v itself as its closest point and is not computed (a third of them)."""
    dx, dy, dz = px - x[v, 0], py - x[v, 1], pz - x[v, 2]
    best = dx * dx + dy * dy + dz * dz
    bt, ba, bb, bc, bv, bw = -1, v, v, v, 0.0, 0.0
    qx, qy, qz = x[v, 0], x[v, 1], x[v, 2]
    for k in range(tri_start[v], tri_start[v + 1]):
        t = tri_ids[k]
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        if b == v:
            a, b, c = b, c, a
        elif c == v:
            a, b, c = c, a, b
        if bt < 0:
            bt, ba, bb, bc = t, a, b, c  # at v, with weights (1, 0, 0), until a triangle is nearer
        db = (x[b, 0] - x[v, 0]) * dx + (x[b, 1] - x[v, 1]) * dy + (x[b, 2] - x[v, 2]) * dz
        dc = (x[c, 0] - x[v, 0]) * dx + (x[c, 1] - x[v, 1]) * dy + (x[c, 2] - x[v, 2]) * dz
        if db <= 0.0 and dc <= 0.0:
            continue
        wb, wc = closest_point_triangle(px, py, pz, x, a, b, c, q)
        d2 = (px - q[0]) ** 2 + (py - q[1]) ** 2 + (pz - q[2]) ** 2
        if d2 < best:
            best, bt, ba, bb, bc, bv, bw = d2, t, a, b, c, wb, wc
            qx, qy, qz = q[0], q[1], q[2]
    return best, bt, ba, bb, bc, bv, bw, qx, qy, qz


@helper
def closest_on_sheet(px, py, pz, x, normals, v, tri_start, tri_ids, tris, q):
    """The closest point to p on the triangles around vertex v of a sheet (x, tris;
    `closest_in_fan`) and the sheet's normal there, interpolated from its vertex normals (not
    unit): (d², triangle (-1: none), qx, qy, qz, nx, ny, nz)."""
    best, t, a, b, c, wb, wc, qx, qy, qz = closest_in_fan(px, py, pz, x, v, tri_start, tri_ids, tris, q)
    if t < 0:
        return best, t, qx, qy, qz, 0.0, 0.0, 0.0
    wa = 1.0 - wb - wc
    nx = wa * normals[a, 0] + wb * normals[b, 0] + wc * normals[c, 0]
    ny = wa * normals[a, 1] + wb * normals[b, 1] + wc * normals[c, 1]
    nz = wa * normals[a, 2] + wb * normals[b, 2] + wc * normals[c, 2]
    return best, t, qx, qy, qz, nx, ny, nz


@kernel
def region_masks(points, vertices, regions, radius, out):
    """OR of the regions of every vertex within radius of each point (at least the nearest one's)."""
    r2 = radius * radius
    for i in range(points.shape[0]):
        mask = 0
        best = np.inf
        nearest = 0
        for j in range(vertices.shape[0]):
            d = ((vertices[j, 0] - points[i, 0]) ** 2 + (vertices[j, 1] - points[i, 1]) ** 2
                 + (vertices[j, 2] - points[i, 2]) ** 2)
            if d < r2:
                mask |= regions[j]
            if d < best:
                best = d
                nearest = j
        out[i] = mask | regions[nearest]


@njit(cache=True, nogil=True)  # allocates its scratch: setup only
def nearest_triangles(points, vertices, triangles, tri_out, bary_out):
    """Brute force: the closest triangle to each point and the point's barycentric coordinates there.

    Setup-time only (garment mapping); per-frame queries use local walks instead."""
    q = np.empty(3)
    for i in range(points.shape[0]):
        best = np.inf
        for t in range(triangles.shape[0]):
            v, w = closest_point_triangle(points[i, 0], points[i, 1], points[i, 2], vertices, triangles[t, 0],
                                          triangles[t, 1], triangles[t, 2], q)
            d = (q[0] - points[i, 0]) ** 2 + (q[1] - points[i, 1]) ** 2 + (q[2] - points[i, 2]) ** 2
            if d < best:
                best = d
                tri_out[i] = t
                bary_out[i, 0] = 1.0 - v - w
                bary_out[i, 1] = v
                bary_out[i, 2] = w


# point-vertex pairs up to which trying every vertex is quicker than building a grid over the
# vertices (about 6 ms on the 13,380-vertex body, a numpy sort and a count over up to 128³ cells,
# before any search): the few hundred particles a recovery resets in a frame take 1-2 ms by brute
# force, where the grid took 56 ms a call on average (up to 330 ms, its rings widening through
# empty cells to a particle's own body regions) in a live session that reset on every clip loop
BRUTE_PAIRS = 1 << 24


def nearest_vertices(points, vertices, out, regions, masks, within: float = math.inf) -> None:
    """out[i]: the nearest vertex to points[i] among the vertices of its regions (regions[j] &
    masks[i] != 0), the lowest index among equally near ones; left as it was where none is of its
    regions (setup, and the few particles a recovery resets), or (within) none is within that
    distance. Brute force for a few points (`BRUTE_PAIRS`); for many, the same answers through a
    grid over the vertices (`nearest_vertices_in_grid`): the layering's setup asks, of each of a
    garment's 11,000 detailed vertices, which of the other garment's is nearest within a few
    centimetres (0.5 s per outfit by brute force)."""
    few = len(points) * len(vertices) <= BRUTE_PAIRS and within == math.inf
    if few or len(points) < 64 or len(vertices) < 64 or not np.isfinite(vertices).all():
        nearest_vertices_brute(points, vertices, out, regions, masks)
        return
    nearest_vertices_in_grid(points, vertices, out, regions, masks, within)


def nearest_vertices_in_grid(points, vertices, out, regions, masks, within: float = math.inf) -> None:
    """`nearest_vertices` through a grid over the (finite) vertices, built for the call."""
    lo = vertices.min(axis=0)
    span = vertices.max(axis=0) - lo
    # about two vertices per occupied cell on a surface, at most 128 cells an axis
    h = max(float(span.max()) / 128.0, math.sqrt(float(np.sort(span)[1:].prod()) * 2.0 / len(vertices)), 1e-9)
    dims = (np.floor(span / h).astype(np.int64) + 1).astype(np.int64)
    cell = np.minimum(((vertices - lo) / h).astype(np.int64), dims - 1)
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    ids = np.argsort(key, kind="stable").astype(np.int64)
    start = np.zeros(int(dims.prod()) + 1, dtype=np.int64)
    np.cumsum(np.bincount(key, minlength=len(start) - 1), out=start[1:])
    nearest_vertices_grid(points, vertices, lo, h, dims, start, ids, out, regions, masks, within)


@kernel
def nearest_vertices_brute(points, vertices, out, regions, masks):
    """`nearest_vertices` by trying every vertex."""
    for i in range(points.shape[0]):
        best = np.inf
        for j in range(vertices.shape[0]):
            if not (regions[j] & masks[i]):
                continue
            d = ((vertices[j, 0] - points[i, 0]) ** 2 + (vertices[j, 1] - points[i, 1]) ** 2
                 + (vertices[j, 2] - points[i, 2]) ** 2)
            if d < best:
                best = d
                out[i] = j


@kernel
def nearest_vertices_grid(points, vertices, lo, h, dims, start, ids, out, regions, masks, within):
    """`nearest_vertices` through a grid of cells h wide from lo (dims cells an axis; start, ids:
    each cell's vertices, CSR): the cells around the point's, ring after ring, until the nearest
    found is nearer than any cell not yet searched can be (less a nanometre, more than rounding
    moves a vertex across a cell's face), so the answer is the brute force's, ties included; or
    until every cell not yet searched is farther than `within` (out[i] then as it was, unless a
    vertex within it was found)."""
    margin = 1e-9
    for i in range(points.shape[0]):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        if not (math.isfinite(px) and math.isfinite(py) and math.isfinite(pz)):
            continue  # (no vertex is nearer than infinity to it: as the brute force leaves it)
        cx = int(math.floor((px - lo[0]) / h))
        cy = int(math.floor((py - lo[1]) / h))
        cz = int(math.floor((pz - lo[2]) / h))
        # rings nearer than the grid hold no cell of it
        r0 = max(0, max(-cx, cx - (dims[0] - 1)), max(-cy, cy - (dims[1] - 1)), max(-cz, cz - (dims[2] - 1)))
        r_end = r0 + dims[0] + dims[1] + dims[2]
        best = np.inf
        bj = -1
        for r in range(r0, r_end):
            for ix in range(max(cx - r, 0), min(cx + r, dims[0] - 1) + 1):
                edge_x = ix == cx - r or ix == cx + r
                for iy in range(max(cy - r, 0), min(cy + r, dims[1] - 1) + 1):
                    whole = edge_x or iy == cy - r or iy == cy + r
                    z0, z1 = max(cz - r, 0), min(cz + r, dims[2] - 1)
                    iz = z0 if whole else (cz - r if cz - r >= 0 else cz + r)
                    while iz <= z1:
                        c = (ix * dims[1] + iy) * dims[2] + iz
                        for k in range(start[c], start[c + 1]):
                            j = ids[k]
                            if not (regions[j] & masks[i]):
                                continue
                            d = (vertices[j, 0] - px) ** 2 + (vertices[j, 1] - py) ** 2 + (vertices[j, 2] - pz) ** 2
                            if d < best or (d == best and j < bj):
                                best = d
                                bj = j
                        # off the ring's faces across x and y, only its two ends along z
                        iz = iz + 1 if (whole or r == 0) else (cz + r if iz < cz + r else z1 + 1)
            # any cell beyond ring r is at least this far along some axis
            gap = min(px - (lo[0] + (cx - r) * h), lo[0] + (cx + r + 1) * h - px,
                      py - (lo[1] + (cy - r) * h), lo[1] + (cy + r + 1) * h - py,
                      pz - (lo[2] + (cz - r) * h), lo[2] + (cz + r + 1) * h - pz) - margin
            if gap > 0.0 and ((bj >= 0 and best < gap * gap) or gap > within):
                break
        if bj >= 0 and not best > within * within:
            out[i] = bj


@helper
def add_face_normal(x, triangles, t, out):
    """Add triangle t's area-weighted normal (the cross product of two edges) to its three corners' rows of out."""
    a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
    ux, uy, uz = x[b, 0] - x[a, 0], x[b, 1] - x[a, 1], x[b, 2] - x[a, 2]
    vx, vy, vz = x[c, 0] - x[a, 0], x[c, 1] - x[a, 1], x[c, 2] - x[a, 2]
    nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
    for p in (a, b, c):
        out[p, 0] += nx
        out[p, 1] += ny
        out[p, 2] += nz


@kernel
def vertex_normals(x, triangles, out):
    """Area-weighted unit normals of a triangle mesh at its vertices (the cloth's air drag, S102's
    coarse N_i, S106's n_deform)."""
    out[:] = 0.0
    for t in range(triangles.shape[0]):
        add_face_normal(x, triangles, t, out)
    for i in range(out.shape[0]):
        norm = math.sqrt(out[i, 0] ** 2 + out[i, 1] ** 2 + out[i, 2] ** 2)
        if norm > 0.0:
            out[i, 0] /= norm
            out[i, 1] /= norm
            out[i, 2] /= norm


def morton_order(points: np.ndarray, cell: float) -> np.ndarray:
    """Indices that sort points along a Morton (Z-order) curve over a grid of `cell`: points
    near in space come near in the order (ties keep their order)."""
    q = np.floor((points - points.min(axis=0)) / cell).astype(np.int64)
    q = np.minimum(q, (1 << 20) - 1)
    key = np.zeros(len(points), dtype=np.int64)
    for bit in range(20):
        for axis in range(3):
            key |= ((q[:, axis] >> bit) & 1) << (3 * bit + axis)
    return np.argsort(key, kind="stable")


@kernel
def walk_nearest_vertex(px, py, pz, x, nbr_start, nbr_ids, start, steps):
    """The vertex of x nearest p reached by walking from `start` to ever nearer neighbours."""
    v = start
    best = (x[v, 0] - px) ** 2 + (x[v, 1] - py) ** 2 + (x[v, 2] - pz) ** 2
    for _ in range(steps):
        nxt = v
        for k in range(nbr_start[v], nbr_start[v + 1]):
            w = nbr_ids[k]
            d2 = (x[w, 0] - px) ** 2 + (x[w, 1] - py) ** 2 + (x[w, 2] - pz) ** 2
            if d2 < best:
                best, nxt = d2, w
        if nxt == v:
            break
        v = nxt
    return v
