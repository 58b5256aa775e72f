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


@kernel
def nearest_vertices(points, vertices, out, regions, masks):
    """Brute force nearest vertex per point among vertices of its regions (setup and recovery only)."""
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
