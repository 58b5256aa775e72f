"""S102 reference surface: PN triangles over the coarse cloth, tessellated at a fixed level.

The tessellation is built once per garment (`Tessellation`); per frame only positions and
normals are evaluated (`pn_surface`). Lattice point (b, c) of a coarse triangle (A, B, C)
at level L has barycentric weights ((L - b - c)/L, b/L, c/L). Detailed vertices are numbered:
the coarse vertices first (so coarse particle i is detailed vertex i), then L - 1 per coarse
edge (from its lower to its higher vertex index), then the interior points of every face.
A vertex on a shared edge or corner exists once and is evaluated once, from the one face
that owns it, so the mesh has no cracks by construction (PN edge curves depend only on the
edge's two end points and normals, so either face would give the same point).

PN triangles: Vlachos, Peters, Boyd, Mitchell, "Curved PN Triangles", I3D 2001.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .geometry import vertex_normals
from .jit import helper, kernel
from .topology import unique_edges


def lattice_points(level: int) -> np.ndarray:
    """(P, 2) int (b, c) of the level-L lattice, row by row; P = (L + 1)(L + 2) / 2."""
    return np.array([(b, c) for c in range(level + 1) for b in range(level + 1 - c)], dtype=np.int64)


def lattice_triangles(level: int) -> np.ndarray:
    """(L², 3) local triangles over lattice_points, wound like the coarse triangle (A, B, C)."""
    index = {tuple(p): k for k, p in enumerate(lattice_points(level))}
    tris = []
    for c in range(level):
        for b in range(level - c):
            tris.append((index[b, c], index[b + 1, c], index[b, c + 1]))  # "up"
            if b + c <= level - 2:
                tris.append((index[b + 1, c], index[b + 1, c + 1], index[b, c + 1]))  # "down"
    return np.array(tris, dtype=np.int32)


def subdivision_levels(level: int) -> list[int]:
    """Lattice spacings from coarse to fine, each dividing the previous: 6 -> [6, 3, 1]."""
    out = [level]
    s = level
    while s > 1:
        p = next(d for d in range(2, s + 1) if s % d == 0)
        s //= p
        out.append(s)
    return out


@dataclass
class Tessellation:
    """Everything about the detailed mesh that does not change during a session."""

    level: int
    n_coarse: int
    coarse_triangles: np.ndarray  # (T, 3) int32
    coarse_edges: np.ndarray  # (E, 2) int32, sorted pairs
    face_ids: np.ndarray  # (T, P) int32: detailed vertex of each lattice point of each face
    owner_face: np.ndarray  # (N,) int32: the face a detailed vertex is evaluated from
    owner_weights: np.ndarray  # (N, 3) float64: its barycentric weights there (A, B, C)
    edge_ids: np.ndarray  # (E, L + 1) int32: detailed vertices along each coarse edge, low to high
    face_edges: np.ndarray  # (T, 3) int32: coarse edge of AB, BC, CA
    triangles: np.ndarray  # (T * L², 3) int32 detailed triangles
    detail_edges: np.ndarray  # (D, 2) int32: the detailed mesh's edges, sorted pairs
    lattice: np.ndarray  # (P, 2) (b, c)
    # hierarchical order for S103: local lattice points sorted coarse to fine, and up to 3
    # coarser-level "parents" each (-1 padded; corners have none)
    order: np.ndarray  # (P,) int32
    parents: np.ndarray  # (P, 3) int32 local indices
    interior_local: np.ndarray  # (I,) int32 local indices of face-interior lattice points
    # S104 step 4: every face's interior lattice lines (constant a, b or c, at least one interior
    # point), face by face, as detailed vertices. S104 steps 2-4 walk them after the coarse edges,
    # all as one array of chains: every coarse edge's edge_ids row, then the face lines, line k
    # at chain_ids[E (L + 1) + line_start[k] : E (L + 1) + line_start[k + 1]]
    line_start: np.ndarray  # (K + 1,) int32
    chain_ids: np.ndarray  # (E (L + 1) + sum of lengths,) int32
    # S102 per face: the Bernstein weights of every lattice point (the same in every face) and
    # which of a face's lattice points it owns
    cubic: np.ndarray  # (10, P) float64, in the order of pn_control_points' ctrl
    quadratic: np.ndarray  # (6, P) float64, in the order of its nctrl
    owned: np.ndarray  # (T, P) uint8: 1 where owner_face[face_ids[t, k]] == t

    @property
    def n_vertices(self) -> int:
        return len(self.owner_face)


def build_tessellation(coarse_triangles: np.ndarray, n_coarse: int, level: int) -> Tessellation:
    if level < 1:
        raise ValueError(f"tessellation level must be >= 1, got {level}")
    tris = np.ascontiguousarray(coarse_triangles, dtype=np.int32)
    L = level
    edges, _ = unique_edges(tris)
    edges = edges.astype(np.int32)
    edge_index = {(int(a), int(b)): e for e, (a, b) in enumerate(edges)}
    lat = lattice_points(L)
    P = len(lat)
    local = {tuple(p): k for k, p in enumerate(lat)}
    interior = [k for k, (b, c) in enumerate(lat) if b >= 1 and c >= 1 and b + c <= L - 1]
    n_int = len(interior)
    E, T = len(edges), len(tris)
    N = n_coarse + E * (L - 1) + T * n_int
    face_ids = np.empty((T, P), dtype=np.int32)
    face_edges = np.empty((T, 3), dtype=np.int32)
    owner_face = np.full(N, -1, dtype=np.int32)
    owner_w = np.zeros((N, 3))

    def edge_vertex(u: int, w: int, t: int) -> int:
        """Detailed vertex t steps from coarse vertex u towards w (0 < t < L)."""
        e = edge_index[(min(u, w), max(u, w))]
        s = t if u < w else L - t
        return n_coarse + e * (L - 1) + s - 1

    for f, (A, B, C) in enumerate(tris):
        face_edges[f] = (edge_index[(min(A, B), max(A, B))], edge_index[(min(B, C), max(B, C))],
                         edge_index[(min(C, A), max(C, A))])
        for k, (b, c) in enumerate(lat):
            a = L - b - c
            if a == L:
                vid = A
            elif b == L:
                vid = B
            elif c == L:
                vid = C
            elif c == 0:
                vid = edge_vertex(A, B, b)
            elif b == 0:
                vid = edge_vertex(A, C, c)
            elif a == 0:
                vid = edge_vertex(B, C, c)
            else:
                vid = n_coarse + E * (L - 1) + f * n_int + interior.index(k)
            face_ids[f, k] = vid
            if owner_face[vid] < 0:
                owner_face[vid] = f
                owner_w[vid] = (a / L, b / L, c / L)
    if np.any(owner_face < 0):
        raise ValueError("tessellation: a coarse vertex belongs to no triangle")
    edge_ids = np.empty((E, L + 1), dtype=np.int32)
    for e, (u, w) in enumerate(edges):
        edge_ids[e, 0] = u
        edge_ids[e, L] = w
        for t in range(1, L):
            edge_ids[e, t] = edge_vertex(int(u), int(w), t)
    local_tris = lattice_triangles(L)
    triangles = face_ids[:, local_tris].reshape(-1, 3)
    d_edges = unique_edges(triangles)[0].astype(np.int32)
    order, parents = _hierarchy(lat, L)
    by_direction: list[list[list[int]]] = [[], [], []]  # local lattice points of each line, per direction
    for m in range(1, L):
        # constant a: from edge AB (c = 0) to edge CA (b = 0), b decreasing
        by_direction[0].append([local[(b, L - m - b)] for b in range(L - m, -1, -1)])
        # constant b: from edge AB (c = 0) to edge BC (a = 0)
        by_direction[1].append([local[(m, c)] for c in range(0, L - m + 1)])
        # constant c: from edge CA (b = 0) to edge BC (a = 0)
        by_direction[2].append([local[(b, m)] for b in range(0, L - m + 1)])
    lines = [pts for direction in by_direction for pts in direction if len(pts) >= 3]
    local_ids = np.array([k for pts in lines for k in pts], dtype=np.int32)
    line_ids = face_ids[:, local_ids].ravel().astype(np.int32)
    lengths = np.tile(np.array([len(pts) for pts in lines], dtype=np.int64), T)
    line_start = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int32)
    cubic, quadratic = bernstein_weights(L)
    owned = (owner_face[face_ids] == np.arange(T, dtype=np.int32)[:, None]).astype(np.uint8)
    return Tessellation(L, n_coarse, tris, edges, face_ids, owner_face, owner_w, edge_ids, face_edges,
                        triangles.astype(np.int32), d_edges, lat, order, parents,
                        np.array(interior, dtype=np.int32), line_start,
                        np.concatenate([edge_ids.ravel(), line_ids]).astype(np.int32), cubic, quadratic, owned)


def bernstein_weights(level: int) -> tuple[np.ndarray, np.ndarray]:
    """(10, P) cubic and (6, P) quadratic weights of the level-L lattice points, the products
    pn_evaluate forms from (w, u, v), in the same order of operations (so both give the same bits)."""
    lat = lattice_points(level)
    cubic, quadratic = np.zeros((10, len(lat))), np.zeros((6, len(lat)))
    for k, (b, c) in enumerate(lat):
        w, u, v = (level - b - c) / level, b / level, c / level
        w2, u2, v2 = w * w, u * u, v * v
        cubic[:, k] = (w2 * w, u2 * u, v2 * v, 3.0 * w2 * u, 3.0 * w * u2, 3.0 * u2 * v, 3.0 * u * v2, 3.0 * w * v2,
                       3.0 * w2 * v, 6.0 * w * u * v)
        quadratic[:, k] = (w2, u2, v2, w * u, u * v, w * v)
    return cubic, quadratic


def _hierarchy(lat: np.ndarray, L: int) -> tuple[np.ndarray, np.ndarray]:
    """Top-down order of the lattice and each point's parents: the points of the next coarser
    spacing whose sub-triangle contains it (S103's hierarchical test)."""
    spacings = subdivision_levels(L)
    a = L - lat[:, 0] - lat[:, 1]
    coords = np.stack([a, lat[:, 0], lat[:, 1]], axis=1)
    level_of = np.full(len(lat), len(spacings) - 1)
    for lv in range(len(spacings) - 1, -1, -1):
        level_of[np.all(coords % spacings[lv] == 0, axis=1)] = lv
    parents = np.full((len(lat), 3), -1, dtype=np.int32)
    for k in range(len(lat)):
        lv = level_of[k]
        if lv == 0:
            continue
        s = spacings[lv - 1]
        cand = np.flatnonzero((level_of < lv) & np.all(np.abs(coords - coords[k]) <= s, axis=1)
                              & np.all(coords % s == 0, axis=1))
        # the enclosing coarser sub-triangle: the nearest such points (2 on its edge, 3 inside)
        dist = np.abs(coords[cand] - coords[k]).sum(axis=1)
        cand = cand[np.argsort(dist, kind="stable")][:3]
        parents[k, : len(cand)] = cand
    order = np.argsort(level_of, kind="stable").astype(np.int32)
    return order, parents


@kernel
def pn_control_points(x, normals, triangles, ctrl, nctrl):
    """Per coarse triangle: the 10 cubic Bézier control points and 6 quadratic normal
    coefficients of its PN triangle (S102 step 2-3).

    ctrl (T, 10, 3): b300 b030 b003 b210 b120 b021 b012 b102 b201 b111
    nctrl (T, 6, 3): n200 n020 n002 n110 n011 n101"""
    for t in range(triangles.shape[0]):
        i1, i2, i3 = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        for k in range(3):
            ctrl[t, 0, k] = x[i1, k]
            ctrl[t, 1, k] = x[i2, k]
            ctrl[t, 2, k] = x[i3, k]
        # b_ij = (2 P_i + P_j - w_ij N_i) / 3 with w_ij = (P_j - P_i) . N_i
        _edge_point(x, normals, i1, i2, ctrl, t, 3)
        _edge_point(x, normals, i2, i1, ctrl, t, 4)
        _edge_point(x, normals, i2, i3, ctrl, t, 5)
        _edge_point(x, normals, i3, i2, ctrl, t, 6)
        _edge_point(x, normals, i3, i1, ctrl, t, 7)
        _edge_point(x, normals, i1, i3, ctrl, t, 8)
        for k in range(3):
            e = (ctrl[t, 3, k] + ctrl[t, 4, k] + ctrl[t, 5, k] + ctrl[t, 6, k] + ctrl[t, 7, k] + ctrl[t, 8, k]) / 6.0
            v = (x[i1, k] + x[i2, k] + x[i3, k]) / 3.0
            ctrl[t, 9, k] = e + 0.5 * (e - v)
            nctrl[t, 0, k] = normals[i1, k]
            nctrl[t, 1, k] = normals[i2, k]
            nctrl[t, 2, k] = normals[i3, k]
        _edge_normal(x, normals, i1, i2, nctrl, t, 3)
        _edge_normal(x, normals, i2, i3, nctrl, t, 4)
        _edge_normal(x, normals, i3, i1, nctrl, t, 5)


@helper
def _edge_point(x, normals, i, j, ctrl, t, slot):
    w = ((x[j, 0] - x[i, 0]) * normals[i, 0] + (x[j, 1] - x[i, 1]) * normals[i, 1]
         + (x[j, 2] - x[i, 2]) * normals[i, 2])
    for k in range(3):
        ctrl[t, slot, k] = (2.0 * x[i, k] + x[j, k] - w * normals[i, k]) / 3.0


@helper
def _edge_normal(x, normals, i, j, nctrl, t, slot):
    """n_ij = normalize(N_i + N_j - v_ij (P_j - P_i)), v_ij = 2 (P_j - P_i).(N_i + N_j) / |P_j - P_i|²."""
    dx, dy, dz = x[j, 0] - x[i, 0], x[j, 1] - x[i, 1], x[j, 2] - x[i, 2]
    sx, sy, sz = normals[i, 0] + normals[j, 0], normals[i, 1] + normals[j, 1], normals[i, 2] + normals[j, 2]
    d2 = dx * dx + dy * dy + dz * dz
    v = 2.0 * (dx * sx + dy * sy + dz * sz) / d2 if d2 > 0.0 else 0.0
    hx, hy, hz = sx - v * dx, sy - v * dy, sz - v * dz
    n = math.sqrt(hx * hx + hy * hy + hz * hz)
    inv = 1.0 / n if n > 0.0 else 0.0
    nctrl[t, slot, 0] = hx * inv
    nctrl[t, slot, 1] = hy * inv
    nctrl[t, slot, 2] = hz * inv


@kernel
def pn_evaluate(ctrl, nctrl, owner_face, owner_weights, p_out, n_out):
    """Every detailed vertex from its owner face's PN triangle: cubic position, quadratic
    normal (normalised). w, u, v are the weights of corners A, B, C."""
    for i in range(owner_face.shape[0]):
        t = owner_face[i]
        w = owner_weights[i, 0]
        u = owner_weights[i, 1]
        v = owner_weights[i, 2]
        w2, u2, v2 = w * w, u * u, v * v
        c300, c030, c003 = w2 * w, u2 * u, v2 * v
        c210, c120, c021 = 3.0 * w2 * u, 3.0 * w * u2, 3.0 * u2 * v
        c012, c102, c201 = 3.0 * u * v2, 3.0 * w * v2, 3.0 * w2 * v
        c111 = 6.0 * w * u * v
        nx = ny = nz = 0.0
        for k in range(3):
            p_out[i, k] = (c300 * ctrl[t, 0, k] + c030 * ctrl[t, 1, k] + c003 * ctrl[t, 2, k]
                           + c210 * ctrl[t, 3, k] + c120 * ctrl[t, 4, k] + c021 * ctrl[t, 5, k]
                           + c012 * ctrl[t, 6, k] + c102 * ctrl[t, 7, k] + c201 * ctrl[t, 8, k]
                           + c111 * ctrl[t, 9, k])
        nx = (w2 * nctrl[t, 0, 0] + u2 * nctrl[t, 1, 0] + v2 * nctrl[t, 2, 0] + w * u * nctrl[t, 3, 0]
              + u * v * nctrl[t, 4, 0] + w * v * nctrl[t, 5, 0])
        ny = (w2 * nctrl[t, 0, 1] + u2 * nctrl[t, 1, 1] + v2 * nctrl[t, 2, 1] + w * u * nctrl[t, 3, 1]
              + u * v * nctrl[t, 4, 1] + w * v * nctrl[t, 5, 1])
        nz = (w2 * nctrl[t, 0, 2] + u2 * nctrl[t, 1, 2] + v2 * nctrl[t, 2, 2] + w * u * nctrl[t, 3, 2]
              + u * v * nctrl[t, 4, 2] + w * v * nctrl[t, 5, 2])
        norm = math.sqrt(nx * nx + ny * ny + nz * nz)
        inv = 1.0 / norm if norm > 0.0 else 0.0
        n_out[i, 0] = nx * inv
        n_out[i, 1] = ny * inv
        n_out[i, 2] = nz * inv


@kernel
def pn_evaluate_faces(ctrl, nctrl, face_ids, owned, cubic, quadratic, buf, p_out, n_out):
    """pn_evaluate, face by face: every lattice point of a face from its Bernstein weights
    (one table for all faces, not recomputed per vertex) into a small buffer, then the points
    the face owns are written out. The same arithmetic as pn_evaluate, so the same bits, in
    two thirds of the time (11,000 vertices, AMD EPYC: 115 against 175 µs).
    buf (7, P): scratch."""
    P = cubic.shape[1]
    for t in range(face_ids.shape[0]):
        for a in range(3):
            b0, b1, b2, b3, b4 = ctrl[t, 0, a], ctrl[t, 1, a], ctrl[t, 2, a], ctrl[t, 3, a], ctrl[t, 4, a]
            b5, b6, b7, b8, b9 = ctrl[t, 5, a], ctrl[t, 6, a], ctrl[t, 7, a], ctrl[t, 8, a], ctrl[t, 9, a]
            n0, n1, n2 = nctrl[t, 0, a], nctrl[t, 1, a], nctrl[t, 2, a]
            n3, n4, n5 = nctrl[t, 3, a], nctrl[t, 4, a], nctrl[t, 5, a]
            for k in range(P):
                buf[a, k] = (cubic[0, k] * b0 + cubic[1, k] * b1 + cubic[2, k] * b2 + cubic[3, k] * b3
                             + cubic[4, k] * b4 + cubic[5, k] * b5 + cubic[6, k] * b6 + cubic[7, k] * b7
                             + cubic[8, k] * b8 + cubic[9, k] * b9)
                buf[3 + a, k] = (quadratic[0, k] * n0 + quadratic[1, k] * n1 + quadratic[2, k] * n2
                                 + quadratic[3, k] * n3 + quadratic[4, k] * n4 + quadratic[5, k] * n5)
        for k in range(P):
            norm = math.sqrt(buf[3, k] * buf[3, k] + buf[4, k] * buf[4, k] + buf[5, k] * buf[5, k])
            buf[6, k] = 1.0 / norm if norm > 0.0 else 0.0
        for k in range(P):
            if owned[t, k]:
                i = face_ids[t, k]
                p_out[i, 0] = buf[0, k]
                p_out[i, 1] = buf[1, k]
                p_out[i, 2] = buf[2, k]
                n_out[i, 0] = buf[3, k] * buf[6, k]
                n_out[i, 1] = buf[4, k] * buf[6, k]
                n_out[i, 2] = buf[5, k] * buf[6, k]


@helper
def _lattice_index(b, c, level):
    """Local index of lattice point (b, c) in `lattice_points(level)`'s order (row c after rows 0..c-1)."""
    return c * (level + 1) - (c * (c - 1)) // 2 + b


@kernel
def resample_heights(face_ids, level, owner_face, owner_weights, values, out):
    """Per-particle values of one tessellation (face_ids, level: the source's) at the particles of
    another tessellation of the same coarse triangles (owner_face, owner_weights: the target's), by
    linear interpolation over the source's lattice triangle that holds each target particle: a
    particle's barycentric weights in its owner face place it on the source's lattice there. Exact
    at the points both lattices share and for values linear over each lattice triangle; a convex
    blend elsewhere (never beyond the source's values). Used when a session changes its level of
    detail: Δh carried over, the wrinkles kept where they were (`DetailedSurface.carry_heights_from`)."""
    L = level
    for v in range(out.shape[0]):
        f = owner_face[v]
        b = owner_weights[v, 1] * L
        c = owner_weights[v, 2] * L
        i = min(max(int(math.floor(b)), 0), L - 1)
        j = min(max(int(math.floor(c)), 0), L - 1 - i)
        fb, fc = b - i, c - j
        if fb + fc <= 1.0 or i + j == L - 1:  # the "up" triangle (i, j), (i + 1, j), (i, j + 1)
            k0, w0 = _lattice_index(i, j, L), 1.0 - fb - fc
            k1, w1 = _lattice_index(i + 1, j, L), fb
            k2, w2 = _lattice_index(i, j + 1, L), fc
        else:  # the "down" triangle (i + 1, j + 1), (i, j + 1), (i + 1, j)
            k0, w0 = _lattice_index(i + 1, j + 1, L), fb + fc - 1.0
            k1, w1 = _lattice_index(i, j + 1, L), 1.0 - fb
            k2, w2 = _lattice_index(i + 1, j, L), 1.0 - fc
        out[v] = w0 * values[face_ids[f, k0]] + w1 * values[face_ids[f, k1]] + w2 * values[face_ids[f, k2]]


def load_resample_heights() -> None:
    """Compile `resample_heights`, or load it from numba's cache, ahead of its first real call (a
    live session's first change of level, which would otherwise wait for it)."""
    resample_heights(np.zeros((1, 3), np.int32), 1, np.zeros(1, np.int32), np.zeros((1, 3)), np.zeros(1),
                     np.zeros(1))


def pn_surface(tess: Tessellation, x: np.ndarray, coarse_normals: np.ndarray, ctrl: np.ndarray, nctrl: np.ndarray,
               p_smoothed: np.ndarray, n_pn: np.ndarray, scratch: np.ndarray | None = None) -> None:
    """S102: coarse positions -> detailed reference positions p_smoothed and PN normals n_pn
    (all arrays preallocated; coarse_normals is filled here). scratch: (7, P) float64, allocated
    here when not given."""
    if scratch is None:
        scratch = np.empty((7, tess.cubic.shape[1]))
    vertex_normals(x, tess.coarse_triangles, coarse_normals)
    pn_control_points(x, coarse_normals, tess.coarse_triangles, ctrl, nctrl)
    pn_evaluate_faces(ctrl, nctrl, tess.face_ids, tess.owned, tess.cubic, tess.quadratic, scratch, p_smoothed, n_pn)
