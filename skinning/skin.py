"""Linear blend skinning and per-frame vertex normals, numba over preallocated arrays.

Both kernels run in parallel over vertices (prange) with a fixed summation order
per vertex, so results are identical from run to run whatever the thread count.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange


@dataclass(frozen=True)
class SkinWeights:
    """Skin weights in compressed rows: vertex v uses entries start[v]:start[v+1]."""

    start: np.ndarray  # (n + 1,) int64
    bones: np.ndarray  # (nnz,) int64
    weights: np.ndarray  # (nnz,) float64

    @classmethod
    def from_padded(cls, bones: np.ndarray, values: np.ndarray) -> "SkinWeights":
        keep = values > 0
        start = np.zeros(len(values) + 1, dtype=np.int64)
        start[1:] = np.cumsum(keep.sum(axis=1))
        return cls(start, bones[keep].astype(np.int64), values[keep].astype(np.float64))


@njit(cache=True, nogil=True)
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


@njit(cache=True, nogil=True, parallel=True)
def linear_blend_skinning(rest, start, bones, weights, matrices, out):
    """out_v = sum_k w_vk M_{b_vk} [rest_v; 1] for every vertex."""
    for v in prange(rest.shape[0]):
        x = rest[v, 0]
        y = rest[v, 1]
        z = rest[v, 2]
        ox = 0.0
        oy = 0.0
        oz = 0.0
        for k in range(start[v], start[v + 1]):
            w = weights[k]
            m = bones[k]
            ox += w * (matrices[m, 0, 0] * x + matrices[m, 0, 1] * y + matrices[m, 0, 2] * z + matrices[m, 0, 3])
            oy += w * (matrices[m, 1, 0] * x + matrices[m, 1, 1] * y + matrices[m, 1, 2] * z + matrices[m, 1, 3])
            oz += w * (matrices[m, 2, 0] * x + matrices[m, 2, 1] * y + matrices[m, 2, 2] * z + matrices[m, 2, 3])
        out[v, 0] = ox
        out[v, 1] = oy
        out[v, 2] = oz


def vertex_faces(triangles: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Faces around each vertex in compressed rows (start (n + 1,), faces), built once per mesh."""
    flat = triangles.reshape(-1).astype(np.int64)
    order = np.argsort(flat, kind="stable")
    start = np.zeros(n_vertices + 1, dtype=np.int64)
    start[1:] = np.cumsum(np.bincount(flat, minlength=n_vertices))
    return start, (order // 3).astype(np.int64)


@njit(cache=True, nogil=True)
def _face_normal(vertices, triangles, t, out):
    """out[t] = triangle t's unnormalised normal (the cross product: length twice the area)."""
    a = triangles[t, 0]
    b = triangles[t, 1]
    c = triangles[t, 2]
    e1x = vertices[b, 0] - vertices[a, 0]
    e1y = vertices[b, 1] - vertices[a, 1]
    e1z = vertices[b, 2] - vertices[a, 2]
    e2x = vertices[c, 0] - vertices[a, 0]
    e2y = vertices[c, 1] - vertices[a, 1]
    e2z = vertices[c, 2] - vertices[a, 2]
    out[t, 0] = e1y * e2z - e1z * e2y
    out[t, 1] = e1z * e2x - e1x * e2z
    out[t, 2] = e1x * e2y - e1y * e2x


@njit(cache=True, nogil=True)
def _vertex_normal(v, adj_start, adj_faces, face_normals, out):
    """out[v] = the unit sum of the face normals around vertex v (0 where it has no faces)."""
    nx = 0.0
    ny = 0.0
    nz = 0.0
    for k in range(adj_start[v], adj_start[v + 1]):
        f = adj_faces[k]
        nx += face_normals[f, 0]
        ny += face_normals[f, 1]
        nz += face_normals[f, 2]
    l2 = nx * nx + ny * ny + nz * nz
    inv = 1.0 / np.sqrt(l2) if l2 > 0.0 else 0.0
    out[v, 0] = nx * inv
    out[v, 1] = ny * inv
    out[v, 2] = nz * inv


@njit(cache=True, nogil=True, parallel=True)
def face_normals(vertices, triangles, out):
    """Unnormalised face normals (cross products: length = twice the area)."""
    for t in prange(triangles.shape[0]):
        _face_normal(vertices, triangles, t, out)


@njit(cache=True, nogil=True, parallel=True)
def vertex_normals(vertices, triangles, adj_start, adj_faces, face_scratch, out):
    """Area-weighted unit vertex normals into out (n, 3); vertices without faces get 0.

    face_scratch (m, 3) receives the face normals; adj_* come from `vertex_faces`.
    """
    face_normals(vertices, triangles, face_scratch)
    for v in prange(out.shape[0]):
        _vertex_normal(v, adj_start, adj_faces, face_scratch, out)


@njit(cache=True, nogil=True)
def vertex_normals_at(x, tris, adj_start, adj_faces, faces, verts, out):
    """Area-weighted unit normals at the vertices `verts` only, into out (n, 3); faces (m, 3)
    scratch: what `vertex_normals` gives there, bit for bit, on the calling thread (the skin
    contact's clothed vertices: its parallel loops over the whole body mostly waited for the
    other thread to wake)."""
    for t in range(tris.shape[0]):
        _face_normal(x, tris, t, faces)
    for q in range(verts.shape[0]):
        _vertex_normal(verts[q], adj_start, adj_faces, faces, out)


class MeshNormals:
    """Vertex normals of one fixed-topology mesh, with adjacency and scratch allocated once."""

    def __init__(self, triangles: np.ndarray, n_vertices: int):
        self.triangles = np.ascontiguousarray(triangles, dtype=np.int32)
        self.adj_start, self.adj_faces = vertex_faces(self.triangles, n_vertices)
        self._faces = np.empty((len(self.triangles), 3))

    def __call__(self, vertices: np.ndarray, out: np.ndarray) -> np.ndarray:
        vertex_normals(vertices, self.triangles, self.adj_start, self.adj_faces, self._faces, out)
        return out
