"""Garments worn over one another: the outer garment's detailed surface kept over the inner one's.

S101-S106 simulate each garment against the body alone, so where a top's hem overlaps a
bottom's waistband both lie a few millimetres off the same skin, the one with the thicker
collision layer comes out on top (denim's 4 mm against cotton's 3 mm), and the jeans' wrinkles
show through the T-shirt's hem in a jagged line.

Decision (layering, not in the patent): after every garment of an outfit has run S101-S106,
each outer garment's detailed vertices that lie within LAYER_GAP over the inner garment's
detailed surface of this frame, or behind it by less than LAYER_DEPTH, are lifted along their
reference normals (the PN surface's, smooth across the wrinkles; until the eighty-third session
along the shading normals, which scatter 30° between neighbours on a wrinkle: lifts of a centimetre
parted neighbours far beyond their bound) until they are LAYER_GAP over it; the lifts then ease off
along the outer surface by LAYER_SLOPE (so the outer cloth drapes over the inner one's edge and bumps instead of
stepping), a lower lift rises where two neighbours' lifts part them beyond the outer's maximum
neighbour distance (or their length before the lifts), and where its room stops it short the
higher lift gives way to that bound; lifts are never negative. Since the eighty-fourth session,
where the closest point finds no lift, an outer vertex whose own normal crosses the inner surface
from behind within CROSS_REACH (a ray over the triangles around its nearest inner vertex) is lifted
to LAYER_GAP past the crossing: the closest point can lie on a fold of the inner turned away, or
beside the part of it lying 1-3 cm over the vertex. A lift stops where S103 left a
body part above the outer vertex (a hand on the hip). What is left there is done from below:
the inner garment's vertices still within LAYER_GAP under the (lifted) outer surface, or in
front of it by less than LAYER_DEPTH, are pressed along their reference normals to LAYER_GAP
under it, as far as the body below them allows (S103's distance, `SurfaceState.body_floor`),
eased off and kept within the inner's edge bounds the same way.
Decision (never into the body, sixty-fifth session): a move that would take a vertex from outside the
body as a whole (its winding number, `cloth.winding`) to inside it is halved until it does not, and
dropped after KEEP_OUT_HALVINGS halvings: the rooms above come from S103's distances at the heights it
tested, and the drawn surface has moved since (S106, the moves out of creases), so a lift within its room
could still end in the thigh under a top's hem in the walk's stride (47 of the casual T-shirt's 156
vertex-frames deeper than 1 mm over the walk's first 250 frames).
It is a pass on the drawn surfaces only: no garment's state (its coarse cloth, its Δh) sees
it, so each garment's simulation stays what it is alone; the outer never moves towards the
body, the inner never away from it.

Which garment is outer, and which of its vertices can meet the inner one, is found once from the
rest surfaces: where two garments come within LAYER_BAND of each other, the one farther from the
body there is outer (the shipped tops sit 1-2 mm outside the bottoms' waistbands), and each
garment's vertices within LAYER_REACH of the other are tested each frame, each tracking its
nearest vertex of the other garment by a walk over that one's mesh (as S101 tracks the body's);
since the eighty-third session also the outer's vertices over the body the inner covers, and the
inner's under the outer, however far apart the two hang at rest (`over_covered_body`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .geometry import closest_on_sheet, nearest_vertices, ray_triangle, walk_nearest_vertex
from .jit import helper, kernel
from .surface import SurfaceModel, SurfaceState
from .surface import rest_surface as surface_at_rest
from .topology import vertex_cells, vertex_neighbours
from .winding import winding_number

LAYER_BAND = 0.01  # m: two garments' rest surfaces this close overlap there
# a garment's coarse cloth within LAYER_BAND of another's over more than this share of it at rest (either):
# made to lie at the same depth (two tops; a shipped outfit's pair: at most 0.23 of either), worn one
# over the other from the coarse cloth up (`cloth.coarse_layers`)
SAME_DEPTH = 0.5
LAYER_REACH = 0.03  # m: a vertex this near the other garment at rest is tested every frame
LAYER_GAP = 0.002  # m: the outer surface is kept this far over the inner one
LAYER_DEPTH = 0.01  # m: a vertex at most this far on the wrong side of the other surface is brought past it
# (the inner's wrinkles poking through are 6-10 mm high; farther behind it is another sheet)
LAYER_SLOPE = 0.5  # m of lift given up per m along the surface away from a lifted (pressed) vertex
MAX_LAYER_LIFT = 0.03  # m: no vertex is moved farther (the inner garment's heights reach 3 cm)
# m: an outer vertex that the inner surface crosses over along its normal within this is lifted over it
# (`offsets_from_sheet`'s rays: a skirt 1-3 cm over a silk blouse's hem at the hip)
CROSS_REACH = 0.03
# sweeps each way over the edges that keep moved neighbours within their bound (a second changed 0.1 % of edges)
BOUND_SWEEPS = 1
FACING = 0.25  # a vertex whose normal is within about 75° of the other surface's faces it
# a vertex is under (or over) the other surface where it lies within 45° of that one's normal
# at its closest point q ((p - q)·n_q)² >= UNDER |p - q|²), beside it (past its edge) elsewhere
UNDER = 0.5
# a move along a normal leaning more than 45° off the other surface's is taken as if it leaned
# 45°: it stops short of the tangent plane rather than going up to 4 times as far (FACING)
# and stepping away from its neighbours
LEAN = 0.7
WALK_STEPS = 256  # at most this many vertices walked per tracked vertex and frame
RING_STRETCH = 1.5  # the detailed edges are taken to stretch at most this much (for ring_reach)
KEEP_OUT_HALVINGS = 3  # a move into the body is halved at most this many times, then dropped
OVER_SIDE, UNDER_SIDE = 1.0, -1.0  # the side of the other surface a garment is kept on (the way it moves)
# a garment with more candidates is measured against the other in two halves, one on a helper thread
# (`stack_layer`'s helper): two tops have 8,000-11,000 each, the elegant outfit's blouse 1,107 and
# skirt 3,093 (the blouse's rays make its half worth the hand-over: its layering 1.35-1.45 → 1.06-1.08
# ms a frame on two threads, eighty-fifth session), the casual outfit's 898 / 820 (no gain measured)
SPLIT_CANDIDATES = 1000


@dataclass
class SheetTrack:
    """What does not change for one garment of a pair: its detailed vertices that can meet the
    other garment (the candidates), the other's mesh they are tracked on, and the edges between
    candidates along which their moves ease off."""

    candidates: np.ndarray  # (C,) int32: the garment's detailed vertices tested every frame
    rest_nearest: np.ndarray  # (C,) int32: each one's nearest detailed vertex of the other garment at rest
    nbr_start: np.ndarray  # (No + 1,) int64: CSR of the other garment's detailed vertices' neighbours
    nbr_ids: np.ndarray  # int32
    tri_start: np.ndarray  # (No + 1,) int64: CSR of the other's detailed triangles around each vertex
    tri_ids: np.ndarray  # int32
    triangles: np.ndarray  # (To, 3) int32: the other's detailed triangles
    ring_reach: np.ndarray  # (No,) m: RING_STRETCH × the longest rest edge at each of the other's vertices (how
    # far its triangles reach from it): a point farther than depth + this from the vertex is over none of them
    spread_edges: np.ndarray  # (S, 2) int32: the garment's detailed edges between candidates, as candidate indices
    spread_limit: np.ndarray  # (S,) m: each one's maximum neighbour distance (S106's d_max; inf: none)
    spread_start: np.ndarray  # (C + 1,) int64: CSR of each candidate's spread edges, both ways
    spread_nbrs: np.ndarray  # int32: the candidate at the other end
    spread_nbr_drop: np.ndarray  # m: that edge's drop, LAYER_SLOPE × its rest length


@dataclass
class LayerModel:
    """What does not change: one (outer, inner) pair of an outfit's garments."""

    outer: int  # garment indices in the outfit
    inner: int
    over: SheetTrack  # the outer's vertices, lifted over the inner
    under: SheetTrack  # the inner's vertices, pressed under the outer where it did not rise enough
    gap: float = LAYER_GAP
    depth: float = LAYER_DEPTH
    max_lift: float = MAX_LAYER_LIFT
    cross_reach: float = CROSS_REACH  # how far over an outer vertex along its normal the inner's surface is looked for
    keep_out: bool = True  # no move into the body (the Decision never into the body; False: the rooms alone)
    # the share of the outer's and of the inner's rest vertices within LAYER_BAND of the other: a
    # few tenths where a top's hem lies over a bottom's waistband, most of both where the two are
    # made to lie at the same depth (two tops, `SAME_DEPTH`: their coarse cloths are kept apart too)
    overlap: tuple[float, float] = (0.0, 0.0)


class SheetMoves:
    """Per-frame arrays of one garment of a pair: how far each candidate moves along its normal
    (outwards for the outer, inwards for the inner)."""

    def __init__(self, t: SheetTrack):
        self.nearest = t.rest_nearest.copy()  # each candidate's nearest vertex of the other garment, tracked
        self.move = np.zeros(len(t.candidates))  # m, along its normal, out (lift) or in (press)
        self.room = np.zeros(len(t.candidates))  # m: how far each may move (lift_room, press_room)
        self.limits = np.zeros(3)  # m: the pair's gap, depth and cross reach this frame (offsets_from_sheet)
        self.queue = np.zeros(len(t.candidates), dtype=np.int32)  # ease_lifts' scratch
        self.queued = np.zeros(len(t.candidates), dtype=np.uint8)
        self.moved = 0  # candidates moved in the last frame (before the easing)
        self.held = 0  # of the moved, those held back out of the body (keep_out_of_body)
        size = int(t.candidates.max()) + 1 if len(t.candidates) else 0
        self.no_heights = np.zeros(size)  # a garment with no body near: height 0, nothing above
        self.no_floor = np.full(size, -np.inf)  # ... nothing below


class LayerState:
    """Per-frame arrays of one layer pair."""

    def __init__(self, m: LayerModel):
        self.lift = SheetMoves(m.over)
        self.press = SheetMoves(m.under)
        self.q = np.zeros(3)
        self.helper_q = np.zeros(3)  # the helper thread's half's scratch
        # the inner garment's drawn heights over its body floors this frame (offsets_from_sheet's ref_height), and
        # none taken for the outer's: an inner vertex in front of the outer is brought under it within LAYER_DEPTH only
        self.inner_height = np.zeros(len(m.over.nbr_start) - 1)
        self.press_ref_height = np.zeros(len(m.under.nbr_start) - 1)


@kernel
def lift_room(candidates, height, ceiling, facing, free_ceiling, max_lift, room):
    """How far each outer candidate may rise without going into the body: where S103 found a
    body part above it (facing < 0, its S106 ceiling under free_ceiling, the max_height it has
    with none), its ceiling less its drawn height (Δh, or the fold across the compression drawn
    there); elsewhere max_lift. Decision (eighty-third session): another body part merely near
    (S106's ceiling from the ball around the particle) does not stop a lift; `keep_out_of_body`
    keeps it out of that part exactly (a skirt pinched between the thighs in the stride is lifted
    over the leggings there)."""
    for c in range(candidates.shape[0]):
        i = candidates[c]
        free = ceiling[i] >= free_ceiling or facing[i] >= 0.0
        room[c] = max_lift if free else min(max_lift, max(0.0, ceiling[i] - height[i]))


@kernel
def press_room(candidates, height, body_floor, max_lift, room):
    """How far each inner candidate may come down along its normal without coming nearer the
    body than S103's clearance: its drawn height less its body floor, at most max_lift."""
    for c in range(candidates.shape[0]):
        i = candidates[c]
        room[c] = min(max_lift, max(0.0, height[i] - body_floor[i]))


@helper
def _crossing_move(p, n, i, side, p_ref, n_ref, v0, nbr_start, nbr_ids, tri_start, tri_ids, tris, gap, reach):
    """How far candidate i moves along side × n_i to lie gap past the other garment's surface where
    the ray from it that way crosses that surface last from behind, within reach (the triangles
    around v0 and its neighbours; where the surface there faces the other way, cos < FACING, it is
    a sheet turned over, not crossed): t + gap / max(cos, LEAN); -inf where it crosses none."""
    dx, dy, dz = side * n[i, 0], side * n[i, 1], side * n[i, 2]
    best = -math.inf
    for r in range(nbr_start[v0] - 1, nbr_start[v0 + 1]):
        v = v0 if r < nbr_start[v0] else nbr_ids[r]
        for k in range(tri_start[v], tri_start[v + 1]):
            f = tri_ids[k]
            a, b, c = tris[f, 0], tris[f, 1], tris[f, 2]
            if v != v0 and (a == v0 or b == v0 or c == v0):
                continue  # in v0's own fan, met already
            t, wb, wc = ray_triangle(p[i, 0], p[i, 1], p[i, 2], dx, dy, dz, p_ref, a, b, c)
            if t < -gap or t > reach:
                continue
            wa = 1.0 - wb - wc
            nx = wa * n_ref[a, 0] + wb * n_ref[b, 0] + wc * n_ref[c, 0]
            ny = wa * n_ref[a, 1] + wb * n_ref[b, 1] + wc * n_ref[c, 1]
            nz = wa * n_ref[a, 2] + wb * n_ref[b, 2] + wc * n_ref[c, 2]
            nn = math.sqrt(nx * nx + ny * ny + nz * nz)
            if nn == 0.0:
                continue
            cos = (n[i, 0] * nx + n[i, 1] * ny + n[i, 2] * nz) / nn
            if cos >= FACING:
                best = max(best, t + gap / max(cos, LEAN))
    return best


@kernel
def offsets_from_sheet(p, n, p_ref, n_ref, ref_height, candidates, nearest, nbr_start, nbr_ids, tri_start, tri_ids,
                       tris, ring_reach, side, limits, room, q, move):
    """How far each candidate of a garment (p, its normals n) moves along side × n to lie `gap`
    on its side of the other garment's surface (p_ref: its closest point q on the triangles
    around its nearest vertex there, and the other's normal n_q at q interpolated
    from its shading normals n_ref, `closest_on_sheet`): side +1 keeps an outer garment over the inner one, side -1
    an inner one under the outer. With h = side (p - q)·n_q how far p lies on its side: where
    h < gap but h > -depth, the move s = (gap - h) / max(n·n_q, LEAN) puts it gap past the
    other's tangent plane at q, within room. Decision (eighty-third session): where the other
    sheet stands farther off the body than depth at its nearest vertex v (ref_height[v], at most
    MAX_LAYER_LIFT: leggings bridging the crotch), a p that far behind it lies between it and the
    body, not on another sheet, and is moved too. None where p lies beside the other surface rather
    than over or under it (past its edge: (p - q) more than 45° off n_q, farther than gap), and
    none where n turns away from n_q. Decision (eighty-fourth session): where that finds no move
    (but for p gap on its side of q already), and the ray from p along side × n crosses the
    other's surface from behind within cross_reach (`_crossing_move`; 0: not looked for), p moves
    past it: the closest point q can lie on a fold of the other garment turned away, or beside the
    part of it that lies over p (a skirt 1-3 cm over a silk blouse's hem at the hip). Returns how
    many candidates move. limits: (gap, depth, cross_reach), m (one array: numba 0.68's dispatcher
    keeps 400 bytes of every call of a function of exactly 20 arguments, which this one had)."""
    gap, depth, cross_reach = limits[0], limits[1], limits[2]
    moved = 0
    for c in range(candidates.shape[0]):
        i = candidates[c]
        px, py, pz = p[i, 0], p[i, 1], p[i, 2]
        v = walk_nearest_vertex(px, py, pz, p_ref, nbr_start, nbr_ids, nearest[c], WALK_STEPS)
        nearest[c] = v
        move[c] = 0.0
        if room[c] <= 0.0:
            continue
        behind = max(depth, min(ref_height[v], MAX_LAYER_LIFT))  # how far behind the other sheet p may lie
        d2 = (p_ref[v, 0] - px) ** 2 + (p_ref[v, 1] - py) ** 2 + (p_ref[v, 2] - pz) ** 2
        s = _closest_move(p, n, i, px, py, pz, p_ref, n_ref, v, tri_start, tri_ids, tris, ring_reach[v], side, gap,
                          behind, d2, q)
        if s == 0.0 and cross_reach > 0.0 and d2 <= (cross_reach + ring_reach[v]) ** 2:
            s = _crossing_move(p, n, i, side, p_ref, n_ref, v, nbr_start, nbr_ids, tri_start, tri_ids, tris, gap,
                               cross_reach)
        if s > 0.0:
            move[c] = min(s, room[c])
            moved += 1
    return moved


@helper
def _closest_move(p, n, i, px, py, pz, p_ref, n_ref, v, tri_start, tri_ids, tris, reach, side, gap, behind, d2, q):
    """`offsets_from_sheet`'s move by the closest point q on the other sheet around its vertex v
    (p at d2 from v; reach: how far v's triangles reach from it); 0 where none, -1 where p lies gap
    on its side of q already (no ray is cast for it)."""
    far = max(gap, behind) + reach
    if d2 > far * far:
        return 0.0  # nowhere near the other surface (most of a loose top's band, most frames)
    best, t, qx, qy, qz, nx, ny, nz = closest_on_sheet(px, py, pz, p_ref, n_ref, v, tri_start, tri_ids, tris, q)
    if t < 0:
        return 0.0
    nn = math.sqrt(nx * nx + ny * ny + nz * nz)
    if nn == 0.0:
        return 0.0
    facing = (n[i, 0] * nx + n[i, 1] * ny + n[i, 2] * nz) / nn
    if facing < FACING:
        return 0.0  # the sheet turned away from the other one (a fold's far side): not over it
    h = side * ((px - qx) * nx + (py - qy) * ny + (pz - qz) * nz) / nn
    if h >= gap:
        return -1.0  # on its side by the gap already: no ray either
    if -h > behind:
        return 0.0  # another sheet far on the other side (or a sheet over it farther off: the ray's)
    if h * h < UNDER * best and best >= gap * gap:
        return 0.0  # beside the other surface (past its edge), neither over nor under it
    return (gap - h) / max(facing, LEAN)  # along side × n, to the gap past the other's tangent plane at q


@kernel
def ease_lifts(nbr_start, nbr_ids, nbr_drop, move, queue, queued):
    """Each move at least its neighbour's minus the edge's drop (LAYER_SLOPE × its length; the
    candidates' spread edges as CSR, both ways): the moves fall off along the surface as a cone,
    never below what offsets_from_sheet asked. Relaxed outwards from the moved candidates, each
    one queued again when a neighbour raises it (queue, queued: (C,) scratch), to the exact cone."""
    size = move.shape[0]
    count = 0
    for c in range(size):
        if move[c] > 0.0:
            queue[count] = c
            queued[c] = 1
            count += 1
    head, tail = 0, count % max(size, 1)
    while count > 0:
        a = queue[head]
        head = (head + 1) % size
        count -= 1
        queued[a] = 0
        for k in range(nbr_start[a], nbr_start[a + 1]):
            b = nbr_ids[k]
            m = move[a] - nbr_drop[k]
            if m > move[b]:
                move[b] = m
                if queued[b] == 0:  # at most once in the queue: it never holds more than size
                    queued[b] = 1
                    queue[tail] = b
                    tail = (tail + 1) % size
                    count += 1


@helper
def _move_to_bound(p, n, side, i, li, j, lj, bound, give_way):
    """A move of i along side × n_i that puts it within bound of j moved by lj, from the roots
    of |c + l u_i|² = bound² (u = side × n, c = p_i - p_j - lj u_j): the smallest, at least li
    (the lower root); giving way, the largest, at most li and not negative (the upper root); li
    where no move reaches it."""
    cx = p[i, 0] - p[j, 0] - side * lj * n[j, 0]
    cy = p[i, 1] - p[j, 1] - side * lj * n[j, 1]
    cz = p[i, 2] - p[j, 2] - side * lj * n[j, 2]
    cn = side * (cx * n[i, 0] + cy * n[i, 1] + cz * n[i, 2])
    disc = cn * cn - (cx * cx + cy * cy + cz * cz) + bound * bound
    if disc < 0.0:
        return li
    if give_way:
        high = -cn + math.sqrt(disc)
        return max(0.0, high) if high < li else li
    low = -cn - math.sqrt(disc)
    return low if low > li else li


@kernel
def keep_within_bounds(p, n, side, candidates, edges, limit, move, room, sweeps, give_way):
    """Where two neighbours' moves along side × n part them farther than their edge's bound
    (moves along normals that diverge pull neighbours apart), the smaller move grows until they
    are within it, as far as its room allows; giving way (after that, where the smaller one's
    room held it), the larger move shrinks until they are. An edge's bound: its maximum
    neighbour distance (limit), or its length before the moves where that is longer (the moves
    make no edge too long that was not so already). Sweeps over the edges in both orders."""
    for _ in range(sweeps):
        for r in range(2):
            for q in range(edges.shape[0]):
                k = q if r == 0 else edges.shape[0] - 1 - q
                a, b = edges[k, 0], edges[k, 1]
                if move[a] <= 0.0 and move[b] <= 0.0:
                    continue  # neither moved: the edge is as it was (most edges)
                la, lb = min(move[a], room[a]), min(move[b], room[b])
                if la <= 0.0 and lb <= 0.0:
                    continue
                i, j = candidates[a], candidates[b]
                d = math.sqrt((p[i, 0] - p[j, 0]) ** 2 + (p[i, 1] - p[j, 1]) ** 2 + (p[i, 2] - p[j, 2]) ** 2)
                bound = max(limit[k], d)
                if (la <= lb) != give_way:  # a: the smaller (or, giving way, the larger) move
                    move[a] = min(_move_to_bound(p, n, side, i, la, j, lb, bound, give_way), room[a])
                else:
                    move[b] = min(_move_to_bound(p, n, side, j, lb, i, la, bound, give_way), room[b])


@kernel
def apply_lifts(p, n, side, candidates, move, room):
    """Each candidate moved along side × its normal by its eased move, within its room."""
    for c in range(candidates.shape[0]):
        s = side * min(move[c], room[c])
        if s != 0.0:
            i = candidates[c]
            p[i, 0] += s * n[i, 0]
            p[i, 1] += s * n[i, 1]
            p[i, 2] += s * n[i, 2]


@helper
def _inside(x, y, z, body_x, wfaces, wlo, wstart, wids, wspan, wextent):
    """Inside the body as a whole: a winding number of one or more over wfaces. Where the skinned
    body folds over itself (the hip crease in a stride, an arm on the torso) a pocket reads -1: the
    skin turned inside out, outside the flesh (the acceptance's independent test agrees)."""
    return winding_number(x, y, z, body_x, wfaces, wlo, wstart, wids, wspan, wextent) > 0


@kernel
def keep_out_of_body(p, n, side, candidates, move, room, body_x, wfaces, wlo, wstart, wids, wspan, wextent):
    """The module's Decision (never into the body), after `apply_lifts`: each candidate that its
    move left inside the body as a whole (`_inside` over wfaces, the pose's grid wlo ... wextent)
    is moved back by half its move, and again, at most KEEP_OUT_HALVINGS times, then all the way;
    room is cut to the move kept. One inside before its move too (S103 left it there) is moved
    back all the way: along its normal it went deeper into another part as often as out (the
    walk's T-shirt in the crease of the arm, -0.2 -> -1.7 mm). Returns how many were held back."""
    held = 0
    for c in range(candidates.shape[0]):
        s = side * min(move[c], room[c])
        i = candidates[c]
        if s == 0.0 or not _inside(p[i, 0], p[i, 1], p[i, 2], body_x, wfaces, wlo, wstart, wids, wspan, wextent):
            continue
        bx, by, bz = p[i, 0] - s * n[i, 0], p[i, 1] - s * n[i, 1], p[i, 2] - s * n[i, 2]
        f = 0.0  # inside before it moved: back all the way
        if not _inside(bx, by, bz, body_x, wfaces, wlo, wstart, wids, wspan, wextent):
            f = 0.5
            for _ in range(KEEP_OUT_HALVINGS):
                if not _inside(bx + f * s * n[i, 0], by + f * s * n[i, 1], bz + f * s * n[i, 2], body_x, wfaces, wlo,
                               wstart, wids, wspan, wextent):
                    break
                f *= 0.5
            else:
                f = 0.0
        p[i, 0], p[i, 1], p[i, 2] = bx + f * s * n[i, 0], by + f * s * n[i, 1], bz + f * s * n[i, 2]
        room[c] = f * min(move[c], room[c])
        held += 1
    return held


def _offsets_part(args: tuple) -> int:
    return offsets_from_sheet(*args)


def _keep_out_part(args: tuple) -> int:
    return keep_out_of_body(*args)


def _halves(helper, part: Callable[[tuple], int], size: int, whole: Callable[[int, int, np.ndarray], tuple],
            q: np.ndarray, helper_q: np.ndarray) -> int:
    """part(whole(lo, hi, q)) over candidates [0, size): in two halves, the second on the helper
    thread, where a helper is given and size reaches SPLIT_CANDIDATES (each candidate's result
    depends on it alone: the same bit for bit); returns the sum of the parts' counts."""
    if helper is None or size < SPLIT_CANDIDATES:
        return part(whole(0, size, q))
    half = size // 2
    helper.submit(part, whole(half, size, helper_q))
    try:
        mine = part(whole(0, half, q))
    finally:
        theirs = helper.result()
    return mine + theirs


def _move_sheet(t: SheetTrack, s: SheetMoves, m: LayerModel, p: np.ndarray, n: np.ndarray, p_ref: np.ndarray,
                n_ref: np.ndarray, ref_height: np.ndarray, side: float, q: np.ndarray, body: tuple | None = None,
                helper=None, helper_q: np.ndarray | None = None) -> None:
    """One garment of a pair moved to its side of the other (its room already set); ref_height: the
    other's heights over the body (`offsets_from_sheet`); body: (body_x,
    winding faces, the pose's winding grid arrays), out of which no move takes a vertex (None: no body);
    helper: a thread that measures half of a large garment's candidates (`_halves`; None: all here)."""
    s.held = 0
    s.limits[0], s.limits[1] = m.gap, m.depth
    s.limits[2] = m.cross_reach if side == OVER_SIDE else 0.0  # the inner is pressed by its closest points only
    s.moved = _halves(helper, _offsets_part, len(t.candidates),
                      lambda lo, hi, scratch: (p, n, p_ref, n_ref, ref_height, t.candidates[lo:hi], s.nearest[lo:hi],
                                               t.nbr_start, t.nbr_ids, t.tri_start, t.tri_ids, t.triangles,
                                               t.ring_reach, side, s.limits, s.room[lo:hi], scratch,
                                               s.move[lo:hi]),
                      q, helper_q)
    if s.moved:
        ease_lifts(t.spread_start, t.spread_nbrs, t.spread_nbr_drop, s.move, s.queue, s.queued)
        keep_within_bounds(p, n, side, t.candidates, t.spread_edges, t.spread_limit, s.move, s.room, BOUND_SWEEPS,
                           False)
        keep_within_bounds(p, n, side, t.candidates, t.spread_edges, t.spread_limit, s.move, s.room, BOUND_SWEEPS,
                           True)
        apply_lifts(p, n, side, t.candidates, s.move, s.room)
        if body is not None:
            s.held = _halves(helper, _keep_out_part, len(t.candidates),
                             lambda lo, hi, scratch: (p, n, side, t.candidates[lo:hi], s.move[lo:hi], s.room[lo:hi],
                                                      *body), q, helper_q)


def stack_layer(m: LayerModel, s: LayerState, p_out: np.ndarray, n_out: np.ndarray, p_in: np.ndarray,
                n_in: np.ndarray, outer: SurfaceState | None = None, inner: SurfaceState | None = None,
                max_height: float = 0.0, body: tuple | None = None, helper=None) -> None:
    """Lift the outer garment's detailed positions p_out (N, 3), in place, over the inner
    garment's detailed surface (p_in, n_in) of the same frame, then press p_in, in place, under
    what is left above it (the module's Decision). n_out, n_in: the shading normals (unit, away
    from the body). outer: the outer's surface state, whose vertices are lifted along their
    reference normals (n_pn), and whose drawn heights and S106 ceilings the lifts keep to where S103
    found a body part above a vertex (a ceiling under max_height, its SurfaceSettings'); None: along
    n_out, no body near. inner: the inner's, whose vertices are pressed along their reference normals
    (n_pn) no lower than their body floors, and whose heights over those floors let an outer vertex
    that far behind it be lifted (`offsets_from_sheet`); None: no body near. body: (body_x,
    winding faces, the pose's `WindingGrid.arrays()`): no move takes a vertex into the body as a whole
    (`keep_out_of_body`; None: no body). helper: an idle thread (`services.spin.SpinWorker`: submit,
    result) that measures half of a garment's candidates where it has SPLIT_CANDIDATES or more (two
    tops); the result is the same with or without it, bit for bit."""
    lift, press = s.lift, s.press
    if outer is None:
        lift_room(m.over.candidates, lift.no_heights, lift.no_heights, lift.no_heights, 0.0, m.max_lift, lift.room)
        n_lift = n_out
    else:
        lift_room(m.over.candidates, outer.height, outer.ceiling, outer.facing, max_height, m.max_lift, lift.room)
        n_lift = outer.n_pn
    if inner is not None:  # how far the inner's drawn surface stands over its body floor
        np.subtract(inner.height, inner.body_floor, out=s.inner_height)
        np.maximum(s.inner_height, 0.0, out=s.inner_height)
    body = body if m.keep_out else None
    _move_sheet(m.over, lift, m, p_out, n_lift, p_in, n_in, s.inner_height, OVER_SIDE, s.q, body, helper, s.helper_q)
    if inner is None:
        press_room(m.under.candidates, press.no_heights, press.no_floor, m.max_lift, press.room)
        n_press = n_in
    else:
        press_room(m.under.candidates, inner.height, inner.body_floor, m.max_lift, press.room)
        n_press = inner.n_pn
    _move_sheet(m.under, press, m, p_in, n_press, p_out, n_out, s.press_ref_height, UNDER_SIDE, s.q, body, helper,
                s.helper_q)


def nearest(points: np.ndarray, targets: np.ndarray, within: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """(distance, index) of the nearest of targets to each point (setup only); within: only
    where that is within this distance (elsewhere inf and -1)."""
    pts = np.ascontiguousarray(points, dtype=np.float64)
    tgt = np.ascontiguousarray(targets, dtype=np.float64)
    index = np.full(len(pts), -1, dtype=np.int64)
    nearest_vertices(pts, tgt, index, np.ones(len(tgt), dtype=np.uint8), np.ones(len(pts), dtype=np.uint8),
                     within)
    found = index >= 0
    dist = np.full(len(pts), np.inf)
    dist[found] = np.linalg.norm(pts[found] - tgt[index[found]], axis=1)
    if np.isfinite(within):
        dist[dist > within] = np.inf  # (a brute-force search for a few points finds every one)
        index[np.isinf(dist)] = -1
    return dist, index.astype(np.int32)


def sheet_track(rest: np.ndarray, edges: np.ndarray, other_rest: np.ndarray, other_triangles: np.ndarray,
                other_edges: np.ndarray, reach: float = LAYER_REACH, limit: np.ndarray | None = None,
                also: np.ndarray | None = None) -> SheetTrack:
    """One garment's side of a pair from the two detailed meshes at rest (m): its vertices within
    reach of the other garment, and those also names (a mask, None: none); limit: its maximum
    neighbour distance per edge (None: no limit)."""
    dist, index = nearest(rest, other_rest, np.inf if also is not None and also.any() else reach)
    near = dist < reach if also is None else (dist < reach) | also
    candidates = np.flatnonzero(near).astype(np.int32)
    slot = np.full(len(rest), -1, dtype=np.int64)
    slot[candidates] = np.arange(len(candidates))
    e = np.asarray(edges, dtype=np.int64)
    keep = (slot[e[:, 0]] >= 0) & (slot[e[:, 1]] >= 0)
    spread = slot[e[keep]].astype(np.int32)
    rest_len = np.linalg.norm(rest[e[keep, 0]] - rest[e[keep, 1]], axis=1)
    drop = LAYER_SLOPE * rest_len
    limit = np.full(len(rest_len), np.inf) if limit is None else np.asarray(limit, dtype=float)[keep]
    # the spread edges both ways, by candidate (ease_lifts)
    ends = np.concatenate([spread, spread[:, ::-1]]).astype(np.int64)
    order = np.argsort(ends[:, 0], kind="stable")
    spread_start = np.zeros(len(candidates) + 1, dtype=np.int64)
    np.cumsum(np.bincount(ends[:, 0], minlength=len(candidates)), out=spread_start[1:])
    triangles = np.ascontiguousarray(other_triangles, dtype=np.int32)
    ns, ni = vertex_neighbours(len(other_rest), np.asarray(other_edges))
    ts, ti = vertex_cells(len(other_rest), triangles)
    oe = np.asarray(other_edges, dtype=np.int64)
    longest = np.zeros(len(other_rest))
    other_len = np.linalg.norm(other_rest[oe[:, 0]] - other_rest[oe[:, 1]], axis=1)
    np.maximum.at(longest, oe[:, 0], other_len)
    np.maximum.at(longest, oe[:, 1], other_len)
    return SheetTrack(candidates, index[candidates].copy(), ns, ni, ts, ti, triangles, RING_STRETCH * longest,
                      np.ascontiguousarray(spread), limit, spread_start, ends[order, 1].astype(np.int32),
                      np.concatenate([drop, drop])[order])


def layer_pair(outer: int, inner: int, outer_rest: np.ndarray, outer_triangles: np.ndarray, outer_edges: np.ndarray,
               inner_rest: np.ndarray, inner_triangles: np.ndarray, inner_edges: np.ndarray,
               reach: float = LAYER_REACH, outer_limit: np.ndarray | None = None,
               inner_limit: np.ndarray | None = None, body_rest: np.ndarray | None = None) -> LayerModel:
    """The layer model of one pair from the two garments' detailed meshes at rest (m);
    outer_limit, inner_limit: each one's maximum neighbour distance per edge (None: no limit);
    body_rest: the body at rest: the outer's vertices over the body the inner covers, and the
    inner's vertices under the outer, are candidates too (`over_covered_body`, `under_covering_body`;
    None: those within reach only)."""
    over_also = under_also = None
    if body_rest is not None:
        _, outer_body = nearest(outer_rest, body_rest)  # each outer vertex's nearest body vertex (both use it)
        over_also = over_covered_body(outer_body, inner_rest, body_rest, reach)
        under_also = under_covering_body(inner_rest, outer_body, body_rest, reach)
    over = sheet_track(outer_rest, outer_edges, inner_rest, inner_triangles, inner_edges, reach, outer_limit, over_also)
    under = sheet_track(inner_rest, inner_edges, outer_rest, outer_triangles, outer_edges, reach, inner_limit,
                        under_also)
    return LayerModel(outer, inner, over, under)


def over_covered_body(outer_body: np.ndarray, inner_rest: np.ndarray, body_rest: np.ndarray,
                      reach: float = LAYER_REACH) -> np.ndarray:
    """(No,) bool: the outer garment's rest vertices whose nearest body vertex (outer_body: its
    index in body_rest, per outer vertex) the inner garment covers (has a vertex within reach of
    it). Decision (eighty-third session): these are tested every frame however far they hang from
    the inner garment at rest. Where the body moves inside
    the outer garment, it brings the inner one with it: a striding thigh comes 5-10 cm forward
    into a skirt that hung clear of the leggings at rest, and the leggings showed through."""
    covered, _ = nearest(body_rest, inner_rest, reach)
    return np.isfinite(covered)[outer_body]


def under_covering_body(inner_rest: np.ndarray, outer_body: np.ndarray, body_rest: np.ndarray,
                        reach: float = LAYER_REACH) -> np.ndarray:
    """(Ni,) bool: the inner garment's rest vertices whose nearest body vertex lies within reach
    of the body under the outer garment (outer_body: the body vertex nearest to each outer one): the
    counterpart of `over_covered_body` for the inner's vertices pressed under the outer."""
    near, _ = nearest(body_rest, body_rest[np.unique(outer_body)], reach)
    _, body_vertex = nearest(inner_rest, body_rest)
    return np.isfinite(near)[body_vertex]


def rest_surface(model: SurfaceModel) -> np.ndarray:
    """(N, 3) a garment's detailed surface at rest (`surface.rest_surface`)."""
    return surface_at_rest(model.tess, model.cloth.rest_positions)


def layer_outfit(models: list[SurfaceModel], body_rest: np.ndarray,
                 worn_over: set[tuple[int, int]] = frozenset()) -> list[LayerModel]:
    """The layer pairs of an outfit's garments, fitted together on the body at rest (body_rest:
    (n, 3) the rest body's vertices, m): for every two garments whose rest surfaces come within
    LAYER_BAND, the one farther from the body where they do is outer, or the one worn_over names
    first (outer, inner): garments of the same depth (`cloth.coarse_layers`). In the order they are to
    be stacked (`stacking_order`): a garment is lifted over another only once that one has been
    lifted over what it is worn over (a jacket over a shirt over trousers)."""
    rest = [rest_surface(m) for m in models]
    pairs = []
    for a in range(len(models)):
        for b in range(a + 1, len(models)):
            d_ab, _ = nearest(rest[a], rest[b], LAYER_BAND)
            d_ba, _ = nearest(rest[b], rest[a], LAYER_BAND)
            in_a, in_b = d_ab < LAYER_BAND, d_ba < LAYER_BAND
            if not (in_a.any() and in_b.any()):
                continue
            off_a, _ = nearest(rest[a][in_a], body_rest)
            off_b, _ = nearest(rest[b][in_b], body_rest)
            outer, inner = (a, b) if np.median(off_a) >= np.median(off_b) else (b, a)
            if (inner, outer) in worn_over:
                outer, inner = inner, outer
            mo, mi = models[outer], models[inner]
            pair = layer_pair(outer, inner, rest[outer], mo.tess.triangles, mo.d_edges, rest[inner],
                              mi.tess.triangles, mi.d_edges, outer_limit=mo.d_max, inner_limit=mi.d_max,
                              body_rest=body_rest)
            share = {a: float(in_a.mean()), b: float(in_b.mean())}
            pair.overlap = (share[outer], share[inner])
            pairs.append(pair)
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


__all__ = ["LAYER_BAND", "LAYER_DEPTH", "LAYER_GAP", "LAYER_REACH", "LAYER_SLOPE", "SAME_DEPTH", "LayerModel",
           "LayerState", "SheetMoves", "SheetTrack", "apply_lifts", "ease_lifts", "keep_within_bounds",
           "layer_outfit", "layer_pair", "lift_room", "nearest", "offsets_from_sheet", "over_covered_body",
           "press_room", "rest_surface", "sheet_track", "stack_layer", "stacking_order", "under_covering_body"]
