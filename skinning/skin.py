"""Linear blend skinning and per-frame vertex normals, numba over preallocated arrays."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def skin_matrices(global_rot, global_pos, rest_heads, out):
    """Bone skinning transforms (B, 3, 4): x -> R_b (x - head_b) + p_b.

    The character's bones have identity rest orientation, so the inverse bind
    matrix is a translation by -head_b.
    """
    for b in range(global_rot.shape[0]):
        for a in range(3):
            t = global_pos[b, a]
            for m in range(3):
                r = global_rot[b, a, m]
                out[b, a, m] = r
                t -= r * rest_heads[b, m]
            out[b, a, 3] = t


@njit(cache=True)
def linear_blend_skinning(rest, weight_bones, weight_values, matrices, out):
    """out_v = sum_k w_vk M_{b_vk} [rest_v; 1] for every vertex."""
    n, k_max = weight_bones.shape
    for v in range(n):
        x = rest[v, 0]
        y = rest[v, 1]
        z = rest[v, 2]
        ox = 0.0
        oy = 0.0
        oz = 0.0
        for k in range(k_max):
            w = weight_values[v, k]
            if w == 0.0:
                continue
            m = matrices[weight_bones[v, k]]
            ox += w * (m[0, 0] * x + m[0, 1] * y + m[0, 2] * z + m[0, 3])
            oy += w * (m[1, 0] * x + m[1, 1] * y + m[1, 2] * z + m[1, 3])
            oz += w * (m[2, 0] * x + m[2, 1] * y + m[2, 2] * z + m[2, 3])
        out[v, 0] = ox
        out[v, 1] = oy
        out[v, 2] = oz


@njit(cache=True)
def vertex_normals(vertices, triangles, out):
    """Area-weighted vertex normals of a triangle mesh into out (n, 3); unused rows get 0."""
    out[:] = 0.0
    for t in range(triangles.shape[0]):
        a = triangles[t, 0]
        b = triangles[t, 1]
        c = triangles[t, 2]
        e1x = vertices[b, 0] - vertices[a, 0]
        e1y = vertices[b, 1] - vertices[a, 1]
        e1z = vertices[b, 2] - vertices[a, 2]
        e2x = vertices[c, 0] - vertices[a, 0]
        e2y = vertices[c, 1] - vertices[a, 1]
        e2z = vertices[c, 2] - vertices[a, 2]
        nx = e1y * e2z - e1z * e2y
        ny = e1z * e2x - e1x * e2z
        nz = e1x * e2y - e1y * e2x
        for v in (a, b, c):
            out[v, 0] += nx
            out[v, 1] += ny
            out[v, 2] += nz
    for v in range(out.shape[0]):
        l2 = out[v, 0] ** 2 + out[v, 1] ** 2 + out[v, 2] ** 2
        if l2 > 0.0:
            inv = 1.0 / np.sqrt(l2)
            out[v, 0] *= inv
            out[v, 1] *= inv
            out[v, 2] *= inv
