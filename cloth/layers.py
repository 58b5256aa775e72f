"""Garments worn over one another: the outer garment's detailed surface kept over the inner one's.

S101-S106 simulate each garment against the body alone, so where a top's hem overlaps a
bottom's waistband both lie a few millimetres off the same skin, the one with the thicker
collision layer comes out on top (denim's 4 mm against cotton's 3 mm), and the jeans' wrinkles
show through the T-shirt's hem in a jagged line.

Decision (layering, not in the patent): after every garment of an outfit has run S101-S106,
each outer garment's detailed vertices that lie within LAYER_GAP over the inner garment's
detailed surface of this frame, or behind it by less than LAYER_DEPTH, are lifted along their
own normals until they are LAYER_GAP over it; the lifts then ease off along the outer surface
by LAYER_SLOPE (so the outer cloth drapes over the inner one's edge and bumps instead of
stepping), a lower lift rises where two neighbours' lifts part them beyond the outer's maximum
neighbour distance (or their length before the lifts), and lifts are never negative. It is a
pass on the drawn surfaces only: no garment's state (its coarse cloth, its Δh) sees it, so each
garment's simulation stays what it is alone, and the pass never moves a vertex towards the body.

Which garment is outer, and which of its vertices can meet the inner one, is found once from the
rest surfaces: where two garments come within LAYER_BAND of each other, the one farther from the
body there is outer (the shipped tops sit 1-2 mm outside the bottoms' waistbands), and its
vertices within LAYER_REACH of the inner garment are tested each frame, each tracking its nearest
inner vertex by a walk over the inner mesh (as S101 tracks the body's).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .geometry import closest_point_triangle, nearest_vertices
from .jit import helper, kernel
from .surface import SurfaceModel, SurfaceState
from .surface import rest_surface as surface_at_rest
from .topology import vertex_cells, vertex_neighbours

LAYER_BAND = 0.01  # m: two garments' rest surfaces this close overlap there
LAYER_REACH = 0.03  # m: an outer vertex this near the inner garment at rest is tested every frame
LAYER_GAP = 0.002  # m: the outer surface is kept this far over the inner one
LAYER_DEPTH = 0.01  # m: an outer vertex at most this far behind the inner surface is brought over it
# (the inner's wrinkles poking through are 6-10 mm high; farther behind it is another sheet)
LAYER_SLOPE = 0.5  # m of lift given up per m along the outer surface away from a lifted vertex
MAX_LAYER_LIFT = 0.03  # m: no vertex is lifted farther (the inner garment's heights reach 3 cm)
SPREAD_SWEEPS = 2  # forward and backward sweeps over the outer edges that ease the lifts off
BOUND_SWEEPS = 1  # ... that keep lifted neighbours within their edge's bound (a second changed 0.1 % of edges)
FACING = 0.25  # an outer vertex whose normal is within about 75° of the inner surface's is over it
# an outer vertex is under (or over) the inner surface where it lies within 45° of the inner's
# normal at its closest point q ((p - q)·n_q)² >= UNDER |p - q|²), beside it (past its edge) elsewhere
UNDER = 0.5
# a lift along an outer normal leaning more than 45° off the inner's is taken as if it leaned
# 45°: it stops short of the tangent plane rather than climbing up to 4 times as far (FACING)
# and stepping away from its neighbours
LEAN = 0.7
WALK_STEPS = 256  # at most this many vertices walked per tracked vertex and frame
RING_STRETCH = 1.5  # the inner's detailed edges are taken to stretch at most this much (for ring_reach)


@dataclass
class LayerModel:
    """What does not change: one (outer, inner) pair of an outfit's garments."""

    outer: int  # garment indices in the outfit
    inner: int
    candidates: np.ndarray  # (C,) int32: the outer detailed vertices tested every frame
    rest_nearest: np.ndarray  # (C,) int32: each one's nearest inner detailed vertex at rest
    nbr_start: np.ndarray  # (Ni + 1,) int64: CSR of the inner detailed vertices' neighbours
    nbr_ids: np.ndarray  # int32
    tri_start: np.ndarray  # (Ni + 1,) int64: CSR of the inner detailed triangles around each vertex
    tri_ids: np.ndarray  # int32
    triangles: np.ndarray  # (Ti, 3) int32: the inner detailed triangles
    ring_reach: np.ndarray  # (Ni,) m: RING_STRETCH × the longest rest edge at each inner vertex (how far
    # its triangles reach from it): a point farther than depth + this from the vertex is over none of them
    spread_edges: np.ndarray  # (S, 2) int32: outer detailed edges between candidates, as candidate indices
    spread_drop: np.ndarray  # (S,) m: LAYER_SLOPE × each one's rest length
    spread_limit: np.ndarray  # (S,) m: each one's maximum neighbour distance (S106's d_max; inf: none)
    gap: float = LAYER_GAP
    depth: float = LAYER_DEPTH
    max_lift: float = MAX_LAYER_LIFT


class LayerState:
    """Per-frame arrays of one layer pair."""

    def __init__(self, m: LayerModel):
        self.nearest = m.rest_nearest.copy()  # each candidate's nearest inner vertex, tracked
        self.lift = np.zeros(len(m.candidates))  # m, along the outer normal
        self.room = np.zeros(len(m.candidates))  # m: how far each may rise (lift_over_inner)
        self.no_heights = np.zeros(int(m.candidates.max()) + 1 if len(m.candidates) else 0)
        self.q = np.zeros(3)
        self.lifted = 0  # candidates lifted in the last frame (before the easing)
        self.bound = np.zeros(len(m.spread_edges))  # m: how long each spread edge may be after the lifts


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


@kernel
def lift_over_inner(p_out, n_out, p_in, n_in, candidates, nearest, nbr_start, nbr_ids, tri_start, tri_ids, tris,
                    ring_reach, gap, depth, max_lift, dh, ceiling, free_ceiling, q, lift, room):
    """Each candidate's lift along its normal n_o that puts it `gap` over the inner surface
    (its closest point q on the triangles around its nearest inner vertex, the inner's normal
    n_q there interpolated from the inner's shading normals): where it lies over it by less
    than gap, or behind it by less than depth (side = (p - q)·n_q), lift until it is gap over
    the inner's tangent plane at q: s = (gap - side) / max(n_o·n_q, LEAN). None where p lies
    beside the inner surface rather than over or under it (past its edge: (p - q) more than 45°
    off n_q, farther than gap), and none where n_o turns away from n_q. Returns how many were
    lifted.

    room[c]: how far the candidate may rise without going into the body: where S103 found a
    body part above it or another one near it (its S106 ceiling under free_ceiling, the
    max_height it has with none), its ceiling less its drawn height (dh: Δh, or the fold across
    the compression drawn there); elsewhere max_lift."""
    lifted = 0
    for c in range(candidates.shape[0]):
        i = candidates[c]
        room[c] = max_lift if ceiling[i] >= free_ceiling else min(max_lift, max(0.0, ceiling[i] - dh[i]))
        px, py, pz = p_out[i, 0], p_out[i, 1], p_out[i, 2]
        v = walk_nearest_vertex(px, py, pz, p_in, nbr_start, nbr_ids, nearest[c], WALK_STEPS)
        nearest[c] = v
        lift[c] = 0.0
        far = max(gap, depth) + ring_reach[v]
        if (p_in[v, 0] - px) ** 2 + (p_in[v, 1] - py) ** 2 + (p_in[v, 2] - pz) ** 2 > far * far:
            continue  # nowhere near the inner surface (most of a loose top's band, most frames)
        best, bt, bv, bw = np.inf, -1, 0.0, 0.0
        qx, qy, qz = 0.0, 0.0, 0.0
        for k in range(tri_start[v], tri_start[v + 1]):
            t = tri_ids[k]
            wv, ww = closest_point_triangle(px, py, pz, p_in, tris[t, 0], tris[t, 1], tris[t, 2], q)
            d2 = (px - q[0]) ** 2 + (py - q[1]) ** 2 + (pz - q[2]) ** 2
            if d2 < best:
                best, bt, bv, bw = d2, t, wv, ww
                qx, qy, qz = q[0], q[1], q[2]
        if bt < 0:
            continue
        a, b, e = tris[bt, 0], tris[bt, 1], tris[bt, 2]
        bu = 1.0 - bv - bw
        nx = bu * n_in[a, 0] + bv * n_in[b, 0] + bw * n_in[e, 0]
        ny = bu * n_in[a, 1] + bv * n_in[b, 1] + bw * n_in[e, 1]
        nz = bu * n_in[a, 2] + bv * n_in[b, 2] + bw * n_in[e, 2]
        nn = math.sqrt(nx * nx + ny * ny + nz * nz)
        if nn == 0.0:
            continue
        facing = (n_out[i, 0] * nx + n_out[i, 1] * ny + n_out[i, 2] * nz) / nn
        if facing < FACING:
            continue  # the outer sheet turned away from the inner one (a fold's far side): not over it
        side = ((px - qx) * nx + (py - qy) * ny + (pz - qz) * nz) / nn
        if side >= gap or -side > depth:
            continue  # over it by the gap already, or another sheet far behind it
        if side * side < UNDER * best and best >= gap * gap:
            continue  # beside the inner surface (past its edge), neither over nor under it
        s = (gap - side) / max(facing, LEAN)  # along n_o, to the gap over the inner's tangent plane at q
        if room[c] > 0.0:
            lift[c] = min(s, room[c])
            lifted += 1
    return lifted


@helper
def _ease_edge(edges, drop, lift, k):
    a, b = edges[k, 0], edges[k, 1]
    if lift[b] - drop[k] > lift[a]:
        lift[a] = lift[b] - drop[k]
    elif lift[a] - drop[k] > lift[b]:
        lift[b] = lift[a] - drop[k]


@kernel
def ease_lifts(edges, drop, lift, sweeps):
    """Each lift at least its neighbour's minus the edge's drop (LAYER_SLOPE × its length),
    relaxed by sweeps over the edges in both orders: the lifts fall off along the outer
    surface as a cone, never below what lift_over_inner asked."""
    for _ in range(sweeps):
        for k in range(edges.shape[0]):
            _ease_edge(edges, drop, lift, k)
        for k in range(edges.shape[0] - 1, -1, -1):
            _ease_edge(edges, drop, lift, k)


@kernel
def edge_bounds(p_out, candidates, edges, limit, bound):
    """How long each edge between candidates may be once lifted: its maximum neighbour distance,
    or its length before the lifts where that is longer (the lifts make no edge too long that
    was not so already)."""
    for k in range(edges.shape[0]):
        a, b = candidates[edges[k, 0]], candidates[edges[k, 1]]
        d = math.sqrt((p_out[a, 0] - p_out[b, 0]) ** 2 + (p_out[a, 1] - p_out[b, 1]) ** 2
                      + (p_out[a, 2] - p_out[b, 2]) ** 2)
        bound[k] = max(limit[k], d)


@helper
def _raise_to_bound(p_out, n_out, i, li, j, lj, bound):
    """The smallest lift of i, at least li, that puts it within bound of j lifted by lj (the
    lower root of |c + l n_i|² = bound², c = p_i - p_j - lj n_j); li where no lift reaches it."""
    cx = p_out[i, 0] - p_out[j, 0] - lj * n_out[j, 0]
    cy = p_out[i, 1] - p_out[j, 1] - lj * n_out[j, 1]
    cz = p_out[i, 2] - p_out[j, 2] - lj * n_out[j, 2]
    cn = cx * n_out[i, 0] + cy * n_out[i, 1] + cz * n_out[i, 2]
    disc = cn * cn - (cx * cx + cy * cy + cz * cz) + bound * bound
    if disc < 0.0:
        return li
    low = -cn - math.sqrt(disc)
    return low if low > li else li


@kernel
def bound_lift_steps(p_out, n_out, candidates, edges, bound, lift, room, sweeps):
    """Where two neighbours' lifts part them farther than their edge's bound (`edge_bounds`:
    the lifts pull apart neighbours whose normals diverge), the lower lift rises until they are
    within it, as far as its room allows; sweeps over the edges in both orders."""
    for _ in range(sweeps):
        for r in range(2):
            for q in range(edges.shape[0]):
                k = q if r == 0 else edges.shape[0] - 1 - q
                a, b = edges[k, 0], edges[k, 1]
                la, lb = min(lift[a], room[a]), min(lift[b], room[b])
                if la <= 0.0 and lb <= 0.0:
                    continue  # neither lifted: the edge is as it was
                i, j = candidates[a], candidates[b]
                if la <= lb:
                    lift[a] = min(_raise_to_bound(p_out, n_out, i, la, j, lb, bound[k]), room[a])
                else:
                    lift[b] = min(_raise_to_bound(p_out, n_out, j, lb, i, la, bound[k]), room[b])


@kernel
def apply_lifts(p_out, n_out, candidates, lift, room):
    """Each candidate moved along its normal by its eased lift, within its room."""
    for c in range(candidates.shape[0]):
        s = min(lift[c], room[c])
        if s > 0.0:
            i = candidates[c]
            p_out[i, 0] += s * n_out[i, 0]
            p_out[i, 1] += s * n_out[i, 1]
            p_out[i, 2] += s * n_out[i, 2]


def stack_layer(m: LayerModel, s: LayerState, p_out: np.ndarray, n_out: np.ndarray, p_in: np.ndarray,
                n_in: np.ndarray, outer: SurfaceState | None = None, max_height: float = 0.0) -> None:
    """Lift the outer garment's detailed positions p_out (N, 3), in place, over the inner
    garment's detailed surface (p_in, n_in) of the same frame (the module's Decision).
    n_out: the outer's shading normals (unit, away from the body); outer: its surface state,
    whose drawn heights and S106 ceilings the lifts keep to where S103 found a body part above or
    beside a vertex (a ceiling under max_height, its SurfaceSettings'); None: no body near."""
    if outer is None:
        dh = ceiling = s.no_heights
    else:
        dh, ceiling = outer.height, outer.ceiling
    s.lifted = lift_over_inner(p_out, n_out, p_in, n_in, m.candidates, s.nearest, m.nbr_start, m.nbr_ids, m.tri_start,
                               m.tri_ids, m.triangles, m.ring_reach, m.gap, m.depth, m.max_lift, dh, ceiling,
                               max_height, s.q, s.lift, s.room)
    if s.lifted:
        ease_lifts(m.spread_edges, m.spread_drop, s.lift, SPREAD_SWEEPS)
        edge_bounds(p_out, m.candidates, m.spread_edges, m.spread_limit, s.bound)
        bound_lift_steps(p_out, n_out, m.candidates, m.spread_edges, s.bound, s.lift, s.room, BOUND_SWEEPS)
        apply_lifts(p_out, n_out, m.candidates, s.lift, s.room)


def nearest(points: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distance, index) of the nearest of targets to each point (brute force, setup only)."""
    pts = np.ascontiguousarray(points, dtype=np.float64)
    tgt = np.ascontiguousarray(targets, dtype=np.float64)
    index = np.zeros(len(pts), dtype=np.int64)
    nearest_vertices(pts, tgt, index, np.ones(len(tgt), dtype=np.uint8), np.ones(len(pts), dtype=np.uint8))
    return np.linalg.norm(pts - tgt[index], axis=1), index.astype(np.int32)


def layer_pair(outer: int, inner: int, outer_rest: np.ndarray, outer_edges: np.ndarray, inner_rest: np.ndarray,
               inner_triangles: np.ndarray, inner_edges: np.ndarray, reach: float = LAYER_REACH,
               outer_limit: np.ndarray | None = None) -> LayerModel:
    """The layer model of one pair from the two garments' detailed meshes at rest (m);
    outer_limit: the outer's maximum neighbour distance per edge (None: no limit)."""
    dist, index = nearest(outer_rest, inner_rest)
    candidates = np.flatnonzero(dist < reach).astype(np.int32)
    slot = np.full(len(outer_rest), -1, dtype=np.int64)
    slot[candidates] = np.arange(len(candidates))
    e = np.asarray(outer_edges, dtype=np.int64)
    keep = (slot[e[:, 0]] >= 0) & (slot[e[:, 1]] >= 0)
    spread = slot[e[keep]].astype(np.int32)
    rest_len = np.linalg.norm(outer_rest[e[keep, 0]] - outer_rest[e[keep, 1]], axis=1)
    limit = np.full(len(rest_len), np.inf) if outer_limit is None else np.asarray(outer_limit, dtype=float)[keep]
    ns, ni = vertex_neighbours(len(inner_rest), np.asarray(inner_edges))
    ts, ti = vertex_cells(len(inner_rest), np.asarray(inner_triangles))
    ie = np.asarray(inner_edges, dtype=np.int64)
    longest = np.zeros(len(inner_rest))
    inner_len = np.linalg.norm(inner_rest[ie[:, 0]] - inner_rest[ie[:, 1]], axis=1)
    np.maximum.at(longest, ie[:, 0], inner_len)
    np.maximum.at(longest, ie[:, 1], inner_len)
    return LayerModel(outer, inner, candidates, index[candidates].copy(), ns, ni, ts, ti,
                      np.ascontiguousarray(inner_triangles, dtype=np.int32), RING_STRETCH * longest,
                      np.ascontiguousarray(spread), LAYER_SLOPE * rest_len, limit)


def rest_surface(model: SurfaceModel) -> np.ndarray:
    """(N, 3) a garment's detailed surface at rest (`surface.rest_surface`)."""
    return surface_at_rest(model.tess, model.cloth.rest_positions)


def layer_outfit(models: list[SurfaceModel], body_rest: np.ndarray) -> list[LayerModel]:
    """The layer pairs of an outfit's garments, fitted together on the body at rest (body_rest:
    (n, 3) the rest body's vertices, m): for every two garments whose rest surfaces come within
    LAYER_BAND, the one farther from the body where they do is outer. In the order they are to
    be stacked (`stacking_order`): a garment is lifted over another only once that one has been
    lifted over what it is worn over (a jacket over a shirt over trousers)."""
    rest = [rest_surface(m) for m in models]
    pairs = []
    for a in range(len(models)):
        for b in range(a + 1, len(models)):
            d_ab, _ = nearest(rest[a], rest[b])
            d_ba, _ = nearest(rest[b], rest[a])
            in_a, in_b = d_ab < LAYER_BAND, d_ba < LAYER_BAND
            if not (in_a.any() and in_b.any()):
                continue
            off_a, _ = nearest(rest[a][in_a], body_rest)
            off_b, _ = nearest(rest[b][in_b], body_rest)
            outer, inner = (a, b) if np.median(off_a) >= np.median(off_b) else (b, a)
            mo, mi = models[outer], models[inner]
            pairs.append(layer_pair(outer, inner, rest[outer], mo.d_edges, rest[inner], mi.tess.triangles,
                                    mi.d_edges, outer_limit=mo.d_max))
    return stacking_order(pairs, len(models))


def stacking_order(pairs: list[LayerModel], n_garments: int) -> list[LayerModel]:
    """The pairs sorted by how many layers lie under their outer garment (its longest chain of
    garments worn under it), so each garment is lifted over a surface already in its place.
    A cycle (A over B over C over A, in different places) is cut after n_garments rounds."""
    depth = [0] * n_garments
    for _ in range(n_garments):
        changed = False
        for m in pairs:
            if depth[m.outer] < depth[m.inner] + 1 <= n_garments:
                depth[m.outer] = depth[m.inner] + 1
                changed = True
        if not changed:
            break
    return sorted(pairs, key=lambda m: (depth[m.outer], m.outer, m.inner))


__all__ = ["LAYER_BAND", "LAYER_DEPTH", "LAYER_GAP", "LAYER_REACH", "LAYER_SLOPE", "LayerModel", "LayerState",
           "bound_lift_steps", "ease_lifts", "edge_bounds", "layer_outfit", "layer_pair", "lift_over_inner", "nearest",
           "rest_surface", "stack_layer", "stacking_order"]
