"""A garment worn over another of the same depth: its coarse cloth kept over the other's.

S101 simulates each garment against the body alone, and `cloth.layers` keeps one drawn surface
over the other where they meet within a centimetre: enough where a top's hem lies over a
bottom's waistband, where the two coarse cloths stay within millimetres of each other. Two
garments made to lie at the same depth (two tops, mixed: `cloth.garment.mix_terms`) hang
apart by several centimetres in places (a loose silk blouse, a tight T-shirt), and each went
through the other in patches the size of a hand.

Decision (worn over, not in the patent): where two garments' coarse cloths at rest lie within
LAYER_BAND of each other over more than SAME_DEPTH of either (`same_depth_pairs`), the one named
later in the outfit (a mix's terms in order: `shirt+jacket`) is worn over the one named
earlier. Each frame, after its substeps and before its contact passes, every particle of the
outer garment that lies behind the inner garment's coarse surface, or in front of it by less
than the outer fabric's thickness, by at most COARSE_DEPTH, is put that thickness in front of it
along its normal, and loses the velocity it had into it (`keep_over`). The inner garment's
coarse surface it is held against is last frame's, carried by the body into this frame's pose
(`carry_with_body`, the body following's move): the two garments are stepped on parallel
threads, and neither waits for the other; the result does not depend on which thread steps
which (the carried surface is computed before either starts).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .geometry import closest_on_sheet, closest_point_triangle, vertex_normals, walk_nearest_vertex
from .jit import kernel
from .layers import FACING, LAYER_BAND, RING_STRETCH, SAME_DEPTH, UNDER
from .topology import unique_edges, vertex_cells, vertex_neighbours

COARSE_DEPTH = 0.04  # m: an outer particle at most this far behind the inner cloth is brought over it
# (two tops crossed by up to 3 cm on the walk; an arm's far side is farther behind than that)
COARSE_REACH = 0.05  # m: outer particles this near the inner cloth at rest are tested every frame
WALK_STEPS = 64  # at most this many particles walked per tested particle and frame (a coarse cloth has ~400)


@dataclass
class CoarseLayerModel:
    """What does not change: one (outer, inner) pair of an outfit's garments, worn one over the other."""

    outer: int  # garment indices in the outfit
    inner: int
    candidates: np.ndarray  # (C,) int32: the outer's particles tested every frame
    rest_nearest: np.ndarray  # (C,) int32: each one's nearest particle of the inner garment at rest
    nbr_start: np.ndarray  # (Ni + 1,) int64: CSR of the inner's particles' neighbours
    nbr_ids: np.ndarray  # int32
    tri_start: np.ndarray  # (Ni + 1,) int64: CSR of the inner's coarse triangles around each particle
    tri_ids: np.ndarray  # int32
    triangles: np.ndarray  # (Ti, 3) int32: the inner's coarse triangles
    ring_reach: np.ndarray  # (Ni,) m: RING_STRETCH x the longest rest edge at each inner particle
    gap: float  # m: the outer is kept this far over the inner (the outer fabric's thickness)
    depth: float = COARSE_DEPTH
    overlap: tuple[float, float] = (0.0, 0.0)  # share of the outer's and the inner's particles within LAYER_BAND


class CoarseLayerState:
    """Per-frame arrays of one pair: the inner cloth carried into this frame's pose, its normals,
    and each tested outer particle's nearest inner particle (tracked)."""

    def __init__(self, m: CoarseLayerModel, n_inner: int):
        self.nearest = m.rest_nearest.copy()
        self.inner_x = np.zeros((n_inner, 3))
        self.inner_n = np.zeros((n_inner, 3))
        self.q = np.zeros(3)
        self.ready = np.zeros(1, dtype=np.uint8)  # 1 once inner_x holds a carried surface (the frame's)
        self.moved = 0  # outer particles put over the inner cloth in the last frame


@kernel
def carry_with_body(x, follow_w, face, bary, height, body_x, tris, face_n, out):
    """Where the body following of the next step puts each particle (S101's relative coordinates,
    the face, barycentric coordinates and height of the last frame, on the body's new pose,
    blended by the last frame's following weight), without changing the garment's state."""
    for i in range(x.shape[0]):
        t = face[i]
        w = follow_w[i] if follow_w[i] >= 0.0 else 1.0
        for k in range(3):
            a = (bary[i, 0] * body_x[tris[t, 0], k] + bary[i, 1] * body_x[tris[t, 1], k]
                 + bary[i, 2] * body_x[tris[t, 2], k])
            out[i, k] = x[i, k] + w * (a + height[i] * face_n[t, k] - x[i, k])


@kernel
def keep_over(x, v, normals, inv_mass, candidates, nearest, p_in, n_in, nbr_start, nbr_ids, tri_start, tri_ids, tris,
              ring_reach, gap, depth, q):
    """The module's Decision for the outer garment's particles (x, v: its state, in place;
    normals: its particle normals of this frame): a candidate whose closest point q on the inner
    cloth (p_in, n_in: its carried positions and unit normals; the triangles around its nearest
    particle, tracked by a walk) has h = (p - q)·n_q in (-depth, gap) is moved by gap - h along
    n_q, and the part of its velocity into the inner cloth is taken out. Not moved: a gripped
    particle, one beside the inner cloth (past its edge: p - q more than 45° off n_q, farther
    than gap), one whose normal turns away from n_q (a fold's far side). Returns how many moved."""
    moved = 0
    for c in range(candidates.shape[0]):
        i = candidates[c]
        px, py, pz = x[i, 0], x[i, 1], x[i, 2]
        u = walk_nearest_vertex(px, py, pz, p_in, nbr_start, nbr_ids, nearest[c], WALK_STEPS)
        nearest[c] = u
        if inv_mass[i] == 0.0:
            continue
        far = depth + ring_reach[u]
        if (p_in[u, 0] - px) ** 2 + (p_in[u, 1] - py) ** 2 + (p_in[u, 2] - pz) ** 2 > far * far:
            continue
        best, t, qx, qy, qz, nx, ny, nz = closest_on_sheet(px, py, pz, p_in, n_in, u, tri_start, tri_ids, tris, q)
        if t < 0:
            continue
        nn = math.sqrt(nx * nx + ny * ny + nz * nz)
        if nn == 0.0:
            continue
        nx, ny, nz = nx / nn, ny / nn, nz / nn
        if normals[i, 0] * nx + normals[i, 1] * ny + normals[i, 2] * nz < FACING:
            continue
        h = (px - qx) * nx + (py - qy) * ny + (pz - qz) * nz
        if h >= gap or -h > depth:
            continue
        if h * h < UNDER * best and best >= gap * gap:
            continue  # beside the inner cloth, neither over nor under it
        s = gap - h
        x[i, 0] += s * nx
        x[i, 1] += s * ny
        x[i, 2] += s * nz
        vn = v[i, 0] * nx + v[i, 1] * ny + v[i, 2] * nz
        if vn < 0.0:
            v[i, 0] -= vn * nx
            v[i, 1] -= vn * ny
            v[i, 2] -= vn * nz
        moved += 1
    return moved


@kernel
def closest_on_mesh(points, x, tris, q, dist, tri, at):
    """(setup, checks) For each point the nearest triangle of (x, tris) by brute force: its
    distance, the triangle and the closest point on it (dist, tri, at: written)."""
    for i in range(points.shape[0]):
        best = math.inf
        for t in range(tris.shape[0]):
            closest_point_triangle(points[i, 0], points[i, 1], points[i, 2], x, tris[t, 0], tris[t, 1], tris[t, 2], q)
            d2 = (points[i, 0] - q[0]) ** 2 + (points[i, 1] - q[1]) ** 2 + (points[i, 2] - q[2]) ** 2
            if d2 < best:
                best = d2
                tri[i] = t
                at[i, 0], at[i, 1], at[i, 2] = q[0], q[1], q[2]
        dist[i] = math.sqrt(best)


def mesh_distances(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray,
                   closest: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(n,) m: each point's distance to the triangle mesh (setup and checks only); closest: also
    (n,) the nearest triangle and (n, 3) the closest point on it."""
    n = len(points)
    dist, tri, at = np.zeros(n), np.zeros(n, dtype=np.int64), np.zeros((n, 3))
    closest_on_mesh(np.ascontiguousarray(points, dtype=np.float64), np.ascontiguousarray(vertices, dtype=np.float64),
                    np.ascontiguousarray(triangles, dtype=np.int32), np.zeros(3), dist, tri, at)
    return (dist, tri, at) if closest else dist


def coarse_pair(outer: int, inner: int, outer_rest: np.ndarray, inner_rest: np.ndarray, inner_triangles: np.ndarray,
                gap: float, reach: float = COARSE_REACH) -> CoarseLayerModel:
    """The pair's model from the two coarse cloths at rest (m): the outer's particles within reach
    of the inner cloth are its candidates; gap: the outer fabric's thickness."""
    tris = np.ascontiguousarray(inner_triangles, dtype=np.int32)
    inner_rest = np.ascontiguousarray(inner_rest, dtype=np.float64)
    candidates = np.flatnonzero(mesh_distances(outer_rest, inner_rest, tris) < reach).astype(np.int32)
    d = np.linalg.norm(outer_rest[candidates, None, :] - inner_rest[None, :, :], axis=2)
    rest_nearest = (np.argmin(d, axis=1) if len(candidates) else np.zeros(0, dtype=np.int64)).astype(np.int32)
    edges, _ = unique_edges(tris)
    edges = np.asarray(edges, dtype=np.int64)
    ns, ni = vertex_neighbours(len(inner_rest), edges)
    ts, ti = vertex_cells(len(inner_rest), tris)
    longest = np.zeros(len(inner_rest))
    length = np.linalg.norm(inner_rest[edges[:, 0]] - inner_rest[edges[:, 1]], axis=1)
    np.maximum.at(longest, edges[:, 0], length)
    np.maximum.at(longest, edges[:, 1], length)
    return CoarseLayerModel(outer, inner, candidates, rest_nearest, ns, ni, ts, ti, tris, RING_STRETCH * longest,
                            float(gap))


def same_depth_pairs(rest: list[np.ndarray], triangles: list[np.ndarray],
                     thickness: list[float]) -> list[CoarseLayerModel]:
    """The pairs of an outfit's garments made to lie at the same depth (the module's Decision),
    from their coarse cloths at rest (rest[k]: (n_k, 3) m, triangles[k], thickness[k]: each
    garment's fabric thickness): the later garment of each over the earlier."""
    pairs = []
    for a in range(len(rest)):
        for b in range(a + 1, len(rest)):
            share_a = float(np.mean(mesh_distances(rest[a], rest[b], triangles[b]) < LAYER_BAND))
            share_b = float(np.mean(mesh_distances(rest[b], rest[a], triangles[a]) < LAYER_BAND))
            if max(share_a, share_b) > SAME_DEPTH:
                pair = coarse_pair(b, a, rest[b], rest[a], triangles[a], thickness[b])
                pair.overlap = (share_b, share_a)
                pairs.append(pair)
    return pairs


def carry_inner(m: CoarseLayerModel, s: CoarseLayerState, inner_state, body_x: np.ndarray, body_triangles: np.ndarray,
                face_n: np.ndarray) -> None:
    """The inner cloth as the outer meets it this frame (before either is stepped): its particles
    carried by the body into the new pose, and their normals. inner_state: its `ClothState`."""
    st = inner_state
    carry_with_body(st.x, st.follow_w, st.face, st.bary, st.height, body_x, body_triangles, face_n, s.inner_x)
    vertex_normals(s.inner_x, m.triangles, s.inner_n)
    s.ready[0] = 1


def hold_over(m: CoarseLayerModel, s: CoarseLayerState, outer_state, inv_mass: np.ndarray) -> int:
    """`keep_over` for the outer garment's state (its substeps done); returns how many particles moved."""
    if not s.ready[0]:
        return 0
    st = outer_state
    s.moved = keep_over(st.x, st.v, st.normals, inv_mass, m.candidates, s.nearest, s.inner_x, s.inner_n, m.nbr_start,
                        m.nbr_ids, m.tri_start, m.tri_ids, m.triangles, m.ring_reach, m.gap, m.depth, s.q)
    return s.moved


__all__ = ["COARSE_DEPTH", "COARSE_REACH", "CoarseLayerModel", "CoarseLayerState", "carry_inner", "carry_with_body",
           "closest_on_mesh", "coarse_pair", "hold_over", "keep_over", "mesh_distances", "same_depth_pairs"]
