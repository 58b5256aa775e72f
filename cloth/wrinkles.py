"""S103-S106 kernels on the detailed surface: penetration avoidance, normal force, length
displacement, surface deformation and shading normals (numba, preallocated arrays).

Each kernel is one step of SPEC.md with its formula number in a comment; `surface.py`
holds the arrays and calls them in order.
"""

from __future__ import annotations

import math

import numpy as np

from .collision import (ALL_REGIONS, behind_every_plane, deepest_plane, face_walk_distance, grid_nearest_per_part,
                        vertex_normal, walk_nearest)
from .geometry import add_face_normal, plane_barycentric, walk_nearest_vertex
from .jit import FAST_ARITHMETIC, helper, kernel
from .winding import winding_number

UNTESTED = np.inf  # signed distance of a detailed particle S103 did not test this frame


# ---------------------------------------------------------------- S103 penetration avoidance

# m: another body part is tried when its nearest vertex is at most this much farther from
# the particle than the surface found so far (a face can be nearer than its vertices)
PART_SLACK = 0.01
MAX_PART_SEEDS = 4  # other body parts remembered per coarse particle
# m: a lift ends this close to the clearance (a flat face's one step lands on either side of
# it by rounding: half of the steps on captured walk frames, each then re-tested and half of
# those searched for with doubling and bisection)
LIFT_TOLERANCE = 1e-6
PART_NEAR = 0.01  # m: a walk in another part that ended this near is where the particle's next one starts
# m: S103 walks again from a tested parent's face where a particle reads farther than the parent's reading plus
# their distance apart plus this (the readings differ by up to MAX_TIP_ALLOWANCE through `tip_allowance`)
RECHECK_SLACK = 0.002


@kernel
def other_part_seeds(x, coarse_nearest, body_x, regions, cell, grid_start, grid_ids, grid_x, grid_regions, grid_parts,
                     part, part_vertex, part_d2, seeds, seed_reach, seed_count):
    """S103's way into the other body parts near each coarse particle: the nearest vertex of
    every body part other than its nearest vertex's within one grid cell (an arm beside the
    torso under a sleeve, the other thigh). seeds (n, MAX_PART_SEEDS) int32, seed_reach (n,
    MAX_PART_SEEDS) float64 (the seed's distance), seed_count (n,) int32: written. part,
    part_vertex, part_d2: `grid_nearest_per_part` scratch."""
    for i in range(x.shape[0]):
        v = coarse_nearest[i]
        if (x[i, 0] - body_x[v, 0]) ** 2 + (x[i, 1] - body_x[v, 1]) ** 2 + (x[i, 2] - body_x[v, 2]) ** 2 > cell * cell:
            seed_count[i] = 0  # away from the body (a hem swinging free): no seeds
            continue
        n = grid_nearest_per_part(x[i, 0], x[i, 1], x[i, 2], grid_x, grid_regions, grid_parts, cell, grid_start,
                                  grid_ids, cell, regions[v], part, part_vertex, part_d2)
        n = min(n, seeds.shape[1])
        for k in range(n):
            seeds[i, k] = part_vertex[k]
            seed_reach[i, k] = math.sqrt(part_d2[k])
        seed_count[i] = n


@kernel
def other_part_distance(px, py, pz, start, face, bound, body_x, nbr_start, nbr_ids, regions, tris, tri_start, tri_ids,
                        tri_nbrs, face_n, q):
    """Signed distance from p to the body by a face walk that starts in another body part:
    from `face` (face >= 0: where such a walk ended the frame before), else from the face
    around the nearest vertex to p of the part of vertex `start` (a vertex walk within the
    part) whose plane p is least behind; there d is inf when that vertex is farther than
    bound + PART_SLACK (the part cannot be the nearest: most walks in another part end so, 78 %
    of the walk's blouse's), or -inf there when p is behind every face around that vertex, as
    it is deep inside a limb (sixtieth session: `creases.out_along_normals` asks the winding
    number there). Returns (d, n_body, closest point, the face to start from next time: -1 if
    none)."""
    if face < 0:
        vtx = walk_nearest(px, py, pz, body_x, nbr_start, nbr_ids, start, regions, regions[start])
        d2 = (body_x[vtx, 0] - px) ** 2 + (body_x[vtx, 1] - py) ** 2 + (body_x[vtx, 2] - pz) ** 2
        if d2 > (bound + PART_SLACK) ** 2:
            # -inf: p is behind every face around the part's nearest vertex, as deep in a limb
            deep = behind_every_plane(px, py, pz, body_x, tris, tri_start, tri_ids, vtx, face_n)
            return -np.inf if deep else np.inf, 0.0, 0.0, 0.0, px, py, pz, -1
        face = deepest_plane(px, py, pz, body_x, tris, tri_start, tri_ids, vtx, face_n)[1]
        if face < 0:
            return np.inf, 0.0, 0.0, 0.0, px, py, pz, -1
    return face_walk_distance(px, py, pz, body_x, tris, tri_nbrs, tri_start, tri_ids, nbr_start, nbr_ids, regions,
                              face, face_n, q)


@helper
def _detail_signed_distance(p, i, seed, x, corners, parts, groups, group_reach, n_groups, start_face, body_x, nbr_start,
                            nbr_ids, regions, tris, tri_start, tri_ids, tri_nbrs, body_face, part_face, near_vertex,
                            face_n, q):
    """Signed distance of detailed particle i (at p[i]) to the body, by a walk over the body's
    faces (`face_walk_distance`) from the face its last walk ended on (body_face[i]): the
    body and the cloth move little between two tests, so that is usually one exact closest
    point. The walk is local; when it is new (body_face[i] < 0) or its answer is farther than
    `seed` (the coarse particle's nearest body vertex, a point of the body), it starts again
    from the face around the nearest vertex to p, found by a vertex walk from `seed`, whose
    plane p is least behind. Decision (the particle's own vertex, seventy-third session): the
    nearest body vertex to p by a vertex walk from the one found the frame before (near_vertex[i],
    carried; -1: from seed) is a point of the body too, and when it is nearer than the walk's
    answer the walk starts again from it: the walk's blouse left vertex-frames deeper than 1 mm
    that S103 had read 7-12 mm outside with a body vertex 3-7 mm away, the face walk stopped on
    a local minimum (the hand, the forearm, the torso under the arm). near_vertex of length 0:
    not kept (the seed alone checks). (One call site of the walk: LLVM inlines it, and each copy
    lengthens compilation.)
    A walk ends at a local minimum of the distance: where another body part comes near (an arm
    inside a sleeve beside the torso) it can stop on the torso while p is inside the arm. So a
    walk also starts in each other part near the coarse face and the nearest surface found
    decides, as the closest point does. The parts near the face (`part_groups`): groups[:n_groups]
    (int32 (G, 3): region bit, first and end row in `parts`), one per body part; parts (int32 (K, 2))
    their seed vertices (`other_part_seeds`, and each corner's nearest vertex); group_reach (G, 3)
    per corner of the face (corners: their coarse particles, x: the coarse positions) the farthest
    its seeds of that part are from it (-inf: none). One walk per part, from its seed nearest to p,
    where the part is not ruled out by those distances, nor the part the first walk ended in
    (starting from where p's last vertex walk in the part stopped instead: walks of a step or
    two, 8 % off S103, but more particles deeper than 1 mm, 647 / 1,561 → 664 / 1,642 on the
    walk's casual outfit; fifty-sixth session); start_face >= 0 (the face where p's walk
    in another part ended the frame before, part_face[i]) replaces them while that walk ends in
    another part. A seed is a point of the body, so the part the first walk ended in is walked too
    from its seed nearest to p where that seed is nearer than the first walk's reading, and a walk
    from start_face that comes back to that part keeps its reading where nearer (eighty-sixth
    session: walks stopped on a local minimum at the armpit and the bent elbow).
    (No bound from the particle's parents in the hierarchy: a parent on a coarse edge or corner
    was measured in a neighbouring coarse face, against that face's parts, and its distance
    ruled out a part of this face that it never looked at; fifty-fifth session.)
    Returns (d, n_body, closest point, p's distance to the other parts as far as it is known:
    the nearest walked to, else the bounds that ruled them out; inf if none; whether a walk in
    another part found p behind that part's surface, inside it, whichever surface is nearest)."""
    px, py, pz = p[i, 0], p[i, 1], p[i, 2]
    f = body_face[i]
    fresh = f < 0
    d_seed = (body_x[seed, 0] - px) ** 2 + (body_x[seed, 1] - py) ** 2 + (body_x[seed, 2] - pz) ** 2
    start, d_start = seed, d_seed  # where a fresh walk starts: the nearer of the seed and p's own vertex
    if near_vertex.shape[0] > 0:
        # Decision (the particle's own vertex): p's nearest body vertex, by a walk from where it ended the frame
        # before (a step or none), is a point of the body; a walk whose answer is farther starts again from it
        v = walk_nearest(px, py, pz, body_x, nbr_start, nbr_ids, seed if near_vertex[i] < 0 else near_vertex[i],
                         regions, ALL_REGIONS)
        near_vertex[i] = v
        d_v = (body_x[v, 0] - px) ** 2 + (body_x[v, 1] - py) ** 2 + (body_x[v, 2] - pz) ** 2
        if d_v < d_start:
            start, d_start = v, d_v
    while True:
        if fresh:
            vtx = walk_nearest(px, py, pz, body_x, nbr_start, nbr_ids, start, regions, ALL_REGIONS)
            f = deepest_plane(px, py, pz, body_x, tris, tri_start, tri_ids, vtx, face_n)[1]
            if f < 0:  # no usable face around the vertex
                body_face[i] = -1
                return np.inf, 0.0, 0.0, 0.0, px, py, pz, np.inf, False
        d, nx, ny, nz, qx, qy, qz, last = face_walk_distance(px, py, pz, body_x, tris, tri_nbrs, tri_start, tri_ids,
                                                             nbr_start, nbr_ids, regions, f, face_n, q)
        if fresh or d_start >= d * d:
            body_face[i] = last
            break
        fresh = True
    walked = regions[tris[body_face[i], 0]]
    other = np.inf
    if start_face >= 0:  # where this particle's walk in another part ended the frame before
        dk, mx, my, mz, ax, ay, az, last = other_part_distance(px, py, pz, -1, start_face, np.inf, body_x,
                                                               nbr_start, nbr_ids, regions, tris, tri_start, tri_ids,
                                                               tri_nbrs, face_n, q)
        if last >= 0 and regions[tris[last, 0]] != walked:
            part_face[i] = last if abs(dk) < PART_NEAR else -1
            if abs(dk) < abs(d):
                d, nx, ny, nz, qx, qy, qz = dk, mx, my, mz, ax, ay, az
            return d, nx, ny, nz, qx, qy, qz, abs(dk), dk < 0.0
        part_face[i] = -1  # it came back to the first walk's part: look again
        if last >= 0 and abs(dk) < abs(d):
            # Decision (a nearer reading in the same part, eighty-sixth session): the first walk stopped
            # on a local minimum (the sports top's particle under the arm read 12.9 mm outside at the
            # armpit, where this walk found it 1.3 mm inside the arm); the nearer reading decides, and
            # the next frame's walk starts from where this one ended
            d, nx, ny, nz, qx, qy, qz = dk, mx, my, mz, ax, ay, az
            body_face[i] = last
    # one walk per other part, where it is not ruled out by a lower bound on p's distance to it:
    # no vertex of it was nearer than group_reach[g, c] to corner c (and a face is nearer than
    # its vertices by less than PART_SLACK). The groups are built once per coarse face
    # (`part_groups`): a particle's bookkeeping is three square roots (5-7 % of S103 against
    # going over the seeds per particle, fifty-sixth session)
    dc0 = -1.0  # p's distances to the face's corners, once a bound needs them
    dc1 = dc2 = 0.0
    behind = False
    for g in range(n_groups):
        r = groups[g, 0]
        same = r == walked
        if not same:
            if dc0 < 0.0:
                c = corners[0]
                dc0 = math.sqrt((x[c, 0] - px) ** 2 + (x[c, 1] - py) ** 2 + (x[c, 2] - pz) ** 2)
                c = corners[1]
                dc1 = math.sqrt((x[c, 0] - px) ** 2 + (x[c, 1] - py) ** 2 + (x[c, 2] - pz) ** 2)
                c = corners[2]
                dc2 = math.sqrt((x[c, 0] - px) ** 2 + (x[c, 1] - py) ** 2 + (x[c, 2] - pz) ** 2)
            bound = max(group_reach[g, 0] - PART_SLACK - dc0, group_reach[g, 1] - PART_SLACK - dc1,
                        group_reach[g, 2] - PART_SLACK - dc2)
            if bound >= abs(d):
                other = min(other, bound)
                continue
        # from its seed nearest to p (the first of equals). Decision (a seed nearer than the reading,
        # eighty-sixth session): in the part the first walk ended in, only from a seed nearer to p than
        # |d|: a seed is a point of the body, so the walk stopped on a local minimum (the blouse's
        # particle at the bent elbow read 11 mm off the forearm, 1.8 mm inside it, with a forearm
        # vertex 8 mm away)
        sk = -1 if same else parts[groups[g, 1], 0]
        dk2 = d * d if same else np.inf
        for j in range(groups[g, 1], groups[g, 2]):
            sj = parts[j, 0]
            dj2 = (body_x[sj, 0] - px) ** 2 + (body_x[sj, 1] - py) ** 2 + (body_x[sj, 2] - pz) ** 2
            if dj2 < dk2:
                dk2, sk = dj2, sj
        if sk < 0:
            continue
        dk, mx, my, mz, ax, ay, az, last = other_part_distance(px, py, pz, sk, -1, abs(d), body_x, nbr_start,
                                                               nbr_ids, regions, tris, tri_start, tri_ids, tri_nbrs,
                                                               face_n, q)
        if same:
            if last >= 0 and abs(dk) < abs(d):  # the nearer reading decides, and next frame's walk starts there
                d, nx, ny, nz, qx, qy, qz = dk, mx, my, mz, ax, ay, az
                body_face[i] = last
            continue
        other = min(other, abs(dk) if abs(dk) < np.inf else abs(d))
        if last >= 0 and regions[tris[last, 0]] != walked:
            if abs(dk) < PART_NEAR:
                part_face[i] = last  # next frame's walk in another part starts there
            behind = behind or dk < 0.0
        behind = behind or dk == -np.inf  # (a walk cut short deep inside the part)
        if abs(dk) < abs(d):
            d, nx, ny, nz, qx, qy, qz = dk, mx, my, mz, ax, ay, az
    return d, nx, ny, nz, qx, qy, qz, other, behind


@helper
def part_groups(f, face_ids, order, coarse_nearest, part_seeds, seed_reach, seed_count, regions, corners, parts,
                reach, groups, group_reach):
    """The body parts near coarse face f, for `_detail_signed_distance`: each corner's nearest
    body vertex and its other parts' seeds (`other_part_seeds`) sorted into one group per body
    part (insertion sort, in order of arrival within a part). Writes corners (3,) (the corners'
    coarse particles, in `order`), parts[:K] (seed vertex, its corner's place 0-2) and
    reach[:K] (the seed's distance from its corner), groups[:G] (region bit, first and end row
    in parts) and group_reach[:G] (per corner, the farthest of its seeds in the group; -inf:
    none). Returns G."""
    n_parts = 0
    for c in range(3):
        corner = face_ids[f, order[c]]
        corners[c] = corner
        for k in range(-1, seed_count[corner]):
            seed = coarse_nearest[corner] if k < 0 else part_seeds[corner, k]
            r = 0.0 if k < 0 else seed_reach[corner, k]
            j = n_parts
            while j > 0 and regions[parts[j - 1, 0]] > regions[seed]:
                parts[j, 0], parts[j, 1] = parts[j - 1, 0], parts[j - 1, 1]
                reach[j] = reach[j - 1]
                j -= 1
            parts[j, 0], parts[j, 1] = seed, c
            reach[j] = r
            n_parts += 1
    n_groups = 0
    for j in range(n_parts):
        r = regions[parts[j, 0]]
        if n_groups == 0 or groups[n_groups - 1, 0] != r:
            groups[n_groups, 0] = r
            groups[n_groups, 1] = j
            group_reach[n_groups, 0] = group_reach[n_groups, 1] = group_reach[n_groups, 2] = -np.inf
            n_groups += 1
        groups[n_groups - 1, 2] = j + 1
        c = parts[j, 1]
        group_reach[n_groups - 1, c] = max(group_reach[n_groups - 1, c], reach[j])
    return n_groups


# m: the most S103 counts off a distance for the body's tips (a ridge where the skin contact
# brings two skins together can stand 10 mm out of its ring)
MAX_TIP_ALLOWANCE = 0.002


# m: S103 counts nothing off for the body's tips where another body part is nearer than this
TIP_OTHER_CLEAR = 0.01


@helper
def tip_allowance(body_face, i, face_tip, tip_share, rate, other):
    """What S103 counts off particle i's distance to the body: a share of how far the corners of
    the face its walk ended on stand out of their rings (`collision.face_tip_heights`), at most
    MAX_TIP_ALLOWANCE, so that a body vertex standing out between detailed particles stays under
    the triangles between them (Decision: S103 tests particles, not triangles). Only where the
    body lies below the particle along n_i (rate = n_i . n_body >= 0: a lift) and no other body part
    is within TIP_OTHER_CLEAR (`other`, the particle's distance to them as far as S103 knows
    it): in a crease between two skins a further lift or lowering went into the other skin."""
    f = body_face[i]
    if f < 0 or other < TIP_OTHER_CLEAR or rate < 0.0:
        return 0.0
    return min(tip_share * face_tip[f], MAX_TIP_ALLOWANCE)


@kernel
def detail_signed_distance(p, i, seed, x, corners, parts, groups, group_reach, n_groups, start_face, body_x, nbr_start,
                           nbr_ids, regions, tris, tri_start, tri_ids, tri_nbrs, body_face, part_face, near_vertex,
                           face_n, q, normals, face_tip, tip_share):
    """`_detail_signed_distance` compiled once as a function, for the lifts (a few hundred
    particles a frame), where the call costs little and more inlined copies would cost
    compilation time; less `tip_allowance`, as in `avoid_penetration`."""
    d, nx, ny, nz, qx, qy, qz, other, _ = _detail_signed_distance(p, i, seed, x, corners, parts, groups, group_reach,
                                                                  n_groups, start_face, body_x, nbr_start, nbr_ids,
                                                                  regions, tris, tri_start, tri_ids, tri_nbrs,
                                                                  body_face, part_face, near_vertex, face_n, q)
    rate = normals[i, 0] * nx + normals[i, 1] * ny + normals[i, 2] * nz
    d -= tip_allowance(body_face, i, face_tip, tip_share, rate, other)
    return d, nx, ny, nz, qx, qy, qz, other


@helper
def _set_lift(p, b0, b1, b2, normals, vid, dh, dh_pen, lift):
    dh[vid] += lift - dh_pen[vid]
    dh_pen[vid] = lift
    p[vid, 0] = b0 + lift * normals[vid, 0]
    p[vid, 1] = b1 + lift * normals[vid, 1]
    p[vid, 2] = b2 + lift * normals[vid, 2]


@kernel
def _lift_out(p, vid, seed, x, corners, parts, groups, group_reach, n_groups, d, bx, by, bz, normals, dh, dh_pen,
              body_x, nbr_start, nbr_ids, regions, tris, tri_start, tri_ids, tri_nbrs, body_face, part_face,
              near_vertex, face_n, q, face_tip, tip_share, clearance, max_iterations, up_cap, down_cap, search):
    """The smallest move along n_i that puts particle vid `clearance` outside the body (S103):
    a lift of at most up_cap, or (Decision) a lowering of at most down_cap. Distances are less
    `tip_allowance`, as in `avoid_penetration`.

    Along n_i the signed distance grows at the rate n_i . n_body, so where the body faces n_i
    one step of (clearance - d) / rate reaches the surface of a locally flat body and a few
    settle a curved one. Decision: where it faces against n_i the body part lies on the
    cloth's outer side (a hand pressed on a skirt, the arm over a sleeve's underside at the
    armpit), and lifting would carry the particle through the whole part: there the same step
    lowers it (rate < 0), towards the side the coarse cloth came from. Where neither works
    (the nearest surface is a side wall, a fold) the move doubles until outside, first in the
    direction the body's normal suggests, then in the other, and is then bisected (`search`;
    off by default since the fifty-second session: `SurfaceSettings.lift_search`). A particle
    no move gets out of (caught where body parts intersect) keeps its height.
    Returns (signed distance, n_i . n_body) at the end."""
    enough = clearance - LIFT_TOLERANCE
    b0, b1, b2 = p[vid, 0], p[vid, 1], p[vid, 2]
    rate = normals[vid, 0] * bx + normals[vid, 1] * by + normals[vid, 2] * bz
    sense = 1.0 if rate >= 0.0 else -1.0
    it = 0
    while d < enough and it < max_iterations:
        if rate * sense < 0.2:
            break  # n_i runs along the body here: a linear step would overshoot
        lift = min(max(dh_pen[vid] + (clearance - d) / rate, -down_cap), up_cap)
        if (lift - dh_pen[vid]) * sense <= 0.0:
            break
        _set_lift(p, b0, b1, b2, normals, vid, dh, dh_pen, lift)
        d, bx, by, bz, qx, qy, qz, _ = detail_signed_distance(p, vid, seed, x, corners, parts, groups, group_reach,
                                                              n_groups, part_face[vid], body_x, nbr_start, nbr_ids,
                                                              regions, tris, tri_start, tri_ids, tri_nbrs, body_face,
                                                              part_face, near_vertex, face_n, q, normals, face_tip,
                                                              tip_share)
        rate = normals[vid, 0] * bx + normals[vid, 1] * by + normals[vid, 2] * bz
        it += 1
    if d >= enough:
        return d, rate
    for attempt in range(2 if search else 0):
        sgn = sense if attempt == 0 else -sense
        cap = up_cap if sgn > 0.0 else down_cap
        lo = dh_pen[vid] if (dh_pen[vid] * sgn > 0.0) else 0.0  # inside, the linear steps' last lift
        hi = lo
        step = max(clearance - d, 0.002)
        found = False
        while hi * sgn < cap:
            hi = sgn * min(hi * sgn + step, cap)
            step *= 2.0
            _set_lift(p, b0, b1, b2, normals, vid, dh, dh_pen, hi)
            d, bx, by, bz, qx, qy, qz, _ = detail_signed_distance(p, vid, seed, x, corners, parts, groups, group_reach,
                                                                  n_groups, part_face[vid], body_x, nbr_start, nbr_ids,
                                                                  regions, tris, tri_start, tri_ids, tri_nbrs,
                                                                  body_face, part_face, near_vertex, face_n, q,
                                                                  normals, face_tip, tip_share)
            if d >= enough:
                found = True
                break
            lo = hi
        if found:
            for _ in range(max_iterations + 2):  # bisect [lo inside, hi outside]
                mid = 0.5 * (lo + hi)
                _set_lift(p, b0, b1, b2, normals, vid, dh, dh_pen, mid)
                dm, mx, my, mz, qx, qy, qz, _ = detail_signed_distance(p, vid, seed, x, corners, parts, groups,
                                                                       group_reach, n_groups, part_face[vid], body_x,
                                                                       nbr_start, nbr_ids, regions, tris, tri_start,
                                                                       tri_ids, tri_nbrs, body_face, part_face,
                                                                       near_vertex, face_n, q, normals, face_tip,
                                                                       tip_share)
                if dm >= enough:
                    hi = mid
                    d, bx, by, bz = dm, mx, my, mz
                else:
                    lo = mid
            _set_lift(p, b0, b1, b2, normals, vid, dh, dh_pen, hi)
            return d, normals[vid, 0] * bx + normals[vid, 1] * by + normals[vid, 2] * bz
    _set_lift(p, b0, b1, b2, normals, vid, dh, dh_pen, 0.0)
    d, bx, by, bz, qx, qy, qz, _ = detail_signed_distance(p, vid, seed, x, corners, parts, groups, group_reach,
                                                          n_groups, part_face[vid], body_x, nbr_start, nbr_ids, regions,
                                                          tris, tri_start, tri_ids, tri_nbrs, body_face, part_face,
                                                          near_vertex, face_n, q, normals, face_tip, tip_share)
    return d, normals[vid, 0] * bx + normals[vid, 1] * by + normals[vid, 2] * bz


@helper
def nearest_corner_seed(p, vid, f, face_ids, order, coarse_nearest, body_x):
    """S103's seed for detailed particle vid of coarse face f: of its corners' nearest body
    vertices, the nearest to it (a point of the body: a walk reading p farther than it starts
    again from it, `_detail_signed_distance`). Decision (the nearest corner's seed, eighty-sixth
    session): the first corner's alone let a walk stuck on a local minimum stand: the walk's sports
    top under the right arm read 16-21 mm outside at the armpit over ten frames, its face walk and
    vertex walk both stopped on the torso's side of the armpit, where it was up to 2.7 mm inside the
    arm, and another corner's nearest vertex, on the arm, was 10-14 mm from it."""
    best, best_d2 = -1, np.inf
    for c in range(3):
        v = coarse_nearest[face_ids[f, order[c]]]
        d2 = (body_x[v, 0] - p[vid, 0]) ** 2 + (body_x[v, 1] - p[vid, 1]) ** 2 + (body_x[v, 2] - p[vid, 2]) ** 2
        if d2 < best_d2:
            best, best_d2 = v, d2
    return best


@kernel
def avoid_penetration(p, normals, dh, dh_pen, sd, facing, other, behind, face_ids, order, parents, ctrl, x,
                      coarse_nearest, find_parts, part_seeds, seed_reach, seed_count, corners, parts, reach, groups,
                      group_reach, body_x, nbr_start, nbr_ids, regions, tris, tri_start, tri_ids, tri_nbrs, body_face,
                      part_face, near_vertex, face_n, q, face_tip, tip_share, clearance, margin, face_margin,
                      max_iterations, max_lift, max_height, search, heights, recheck):
    """S103: raise each detailed particle that is inside the body (or closer than `clearance`)
    along its normal n_i by the smallest Δh_penetration that puts it `clearance` outside:
    p_i = p_smoothed,i + (Δh_last_frame,i + Δh_penetration,i) n_i.

    Hierarchical: a coarse face none of whose corners (the coarse particles) is within
    `face_margin` of the body is skipped; inside a face the lattice is visited top-down
    (`order`), and a finer particle is tested only if one of its coarser parents was within
    `margin`, or within `face_margin` for a parent that is a corner (Decision: a coarse face
    whose corners stand a little off a convex body part can cut into it between them, S101
    testing vertices only, so its first subdivision is tested from further out). Decision (the
    bulge): a face's corners count as near from `face_margin` plus as far as its PN patch bulges
    towards the body (`bulge_towards_body`, from its control points ctrl (T, 10, 3) of this
    frame): where the coarse normals lean towards the body, as on a sleeve whose arm has come
    through it between coarse particles, the patch dips into the body from corners 1-1.6 cm off
    it (the walk's blouse at the armpit). Decision (the Lipschitz reach): a finer particle is
    tested too where every tested parent lies within the clearance plus its distance from the
    particle (the distance to the body changes no faster than the position, so only then can the
    particle be within the clearance): a body part narrower than the lattice (a finger, a
    vertex standing out) can come through between parents all farther than `margin`. Decision
    (the heights' reach, seventy-second session; `heights` False: off): a face's corners count as
    near from as far again as the largest |Δh| among its particles (`face_height`): the heights
    carried from the frame before stand the particles off the PN patch along n_i, which can take
    them into another body part over the cloth (the walk's blouse: particles raised 10-20 mm
    earlier, 1-6 mm inside the arm, their face's corners farther than the margin, never tested).
    The Lipschitz reach counts a particle's |Δh| too (eighty-fifth session): one left untested gets
    S106's floor of 0, and can end |Δh| from where its parents' readings bound it (a particle S103
    had lowered 22 mm under the arm came back up to the PN patch, 3 mm inside the arm).
    p, dh: positions and heights, updated in place; dh_pen: Δh_penetration (out, negative where
    a body part on the cloth's outer side lowered the particle, see `_lift_out`); sd: signed
    distance of each tested particle after lifting (UNTESTED otherwise); facing: n_i . n_body
    at its closest body point (< 0: the body lies above it, along n_i); other: each tested
    particle's distance to the other body parts as far as S103 knows it (inf: none near; out);
    behind (N,) uint8: 1 where a walk of its first test in another body part found the particle
    behind that part's surface (out; its distance is the nearer surface's, which may be its own
    part's, outside: a skin buried in the other part; `creases.out_along_normals` asks the
    winding number there);
    part_seeds, seed_reach, seed_count: each coarse particle's other body parts
    (`other_part_seeds`), whose walks the particles of its faces take too (x: the coarse
    positions; find_parts False: none are); corners (3,) int32, parts (K, 2) int32, reach (K,),
    groups (K, 3) int32, group_reach (K, 3), K = 3 (MAX_PART_SEEDS + 1): scratch (`part_groups`);
    body_face: the body face each particle's last distance walk ended on (-1: none yet),
    and part_face the face its last walk in another body part ended on, both carried between
    frames; near_vertex (N,) int32: each particle's nearest body vertex by its last vertex walk
    (-1: none yet; carried between frames; length 0: not kept, see `_detail_signed_distance`).
    face_tip, tip_share: where the body lies below it, a particle's distance counts tip_share x
    face_tip of the face its walk ended on less
    (`tip_allowance`; Decision: a body vertex standing out of its ring would come through the
    detailed triangles between particles that are only the clearance away from the faces
    around it).
    Decision (the Lipschitz check, seventy-third session; `recheck` False: off): the distance to the
    body changes no faster than the position, so a particle that reads farther from the body than
    a tested parent's reading plus their distance apart (plus RECHECK_SLACK) was read from a walk
    that stopped on a local minimum; it walks again from the face the parent's walk ended on, and
    the nearer reading decides (the walk's 496 frames, with the particle's own vertex below:
    vertex-frames deeper than 1 mm, casual outfit 11 → 6, sport 15 → 9, elegant 22 → 22).
    Along n_i the signed distance grows at the rate n_i . n_body, so one move of
    (clearance - d) / (n_i . n_body) reaches the surface of a locally flat body (see
    `_lift_out` for the other cases; search: its doubling and bisection where the linear steps
    fail). A coarse vertex's particle the lifts leave within the clearance goes back to its coarse
    particle where it reads farther out there (`_back_to_coarse`). Returns the number of particles
    tested."""
    n = p.shape[0]
    n_coarse = coarse_nearest.shape[0]
    face_margin = max(face_margin, margin)  # (never narrower than the test inside a face)
    for i in range(n):
        sd[i] = UNTESTED
        dh_pen[i] = 0.0
        other[i] = np.inf
        behind[i] = 0
    tested = 0
    for f in range(face_ids.shape[0]):
        near = False
        n_groups = 0  # the body parts near the face's corners: their nearest vertices, and the other parts'
        if find_parts:
            n_groups = part_groups(f, face_ids, order, coarse_nearest, part_seeds, seed_reach, seed_count, regions,
                                   corners, parts, reach, groups, group_reach)
        corner_margin = face_margin
        for k in range(order.shape[0]):
            loc = order[k]
            vid = face_ids[f, loc]
            # the Lipschitz check's candidate among its tested parents: the least reach (reading plus
            # distance from the particle plus RECHECK_SLACK), and the face that parent's walk ended on
            recheck_reach, recheck_face = np.inf, -1
            if parents[loc, 0] >= 0:
                if k == 3:  # (the corners come first in order, and are tested whatever their distance)
                    corner_margin = face_margin + bulge_towards_body(ctrl, f, face_ids, order, normals, facing)
                    if heights:
                        corner_margin += face_height(dh, f, face_ids)
                    for c in range(3):
                        if sd[face_ids[f, order[c]]] < corner_margin:
                            near = True
                if not near:
                    break  # no corner near the body: skip the face
                hit = False
                bound = 0  # tested parents, and of those, the ones that leave room for it inside
                room = 0
                # (the heights' reach: untested, S106 may take it back to the PN patch, |Δh| away)
                shift = abs(dh[vid]) if heights else 0.0
                for m in range(3):
                    par = parents[loc, m]
                    if par < 0:
                        continue
                    pid = face_ids[f, par]
                    if sd[pid] < (corner_margin if parents[par, 0] < 0 else margin):
                        hit = True
                    if sd[pid] != UNTESTED:
                        # Decision (the Lipschitz reach): the distance to the body changes no faster
                        # than the position, so the particle can be within the clearance only if
                        # each parent is within the clearance plus its distance from it
                        gx, gy, gz = p[vid, 0] - p[pid, 0], p[vid, 1] - p[pid, 1], p[vid, 2] - p[pid, 2]
                        g = math.sqrt(gx * gx + gy * gy + gz * gz)
                        bound += 1
                        if sd[pid] < clearance + g + shift:
                            room += 1
                        # (the Lipschitz check below: the first parent of least reach)
                        reach_p = abs(sd[pid]) + g + RECHECK_SLACK
                        if body_face[pid] >= 0 and reach_p < recheck_reach:
                            recheck_reach, recheck_face = reach_p, body_face[pid]
                if bound > 0 and room == bound:
                    hit = True
                if not hit:
                    continue
            if sd[vid] == UNTESTED:
                tested += 1
                seed = coarse_nearest[vid] if vid < n_coarse else nearest_corner_seed(p, vid, f, face_ids, order,
                                                                                      coarse_nearest, body_x)
                d = np.inf
                kept = -1
                for attempt in range(2 if recheck else 1):
                    # (a walk in another part starts where its own ended the frame before, if it ended near)
                    dk, mx, my, mz, _, _, _, ok, ik = _detail_signed_distance(
                        p, vid, seed, x, corners, parts, groups, group_reach, n_groups, part_face[vid], body_x,
                        nbr_start, nbr_ids, regions, tris, tri_start, tri_ids, tri_nbrs, body_face, part_face,
                        near_vertex, face_n, q)
                    if abs(dk) < abs(d) or attempt == 0:
                        d, bx, by, bz, other[vid], inside_part = dk, mx, my, mz, ok, ik
                        kept = body_face[vid]
                    # Decision (the Lipschitz check): the distance to the body changes no faster than the
                    # position, so a reading farther than a tested parent's plus their distance apart is a
                    # walk stopped on a local minimum: walk again from the face the nearest such parent's ended
                    # on (the parent of least reach, found above: the first of the parents it exceeds)
                    if attempt > 0 or abs(d) <= recheck_reach or recheck_face == body_face[vid]:
                        break
                    body_face[vid] = recheck_face
                body_face[vid] = kept
                behind[vid] = inside_part
                rate = normals[vid, 0] * bx + normals[vid, 1] * by + normals[vid, 2] * bz
                d -= tip_allowance(body_face, vid, face_tip, tip_share, rate, other[vid])
                if d < clearance - LIFT_TOLERANCE:
                    # |Δh| never exceeds max_height
                    up = max(0.0, min(max_lift, max_height - dh[vid]))
                    down = max(0.0, min(max_lift, max_height + dh[vid]))
                    d, rate = _lift_out(p, vid, seed, x, corners, parts, groups, group_reach, n_groups, d, bx, by, bz,
                                        normals, dh, dh_pen, body_x, nbr_start, nbr_ids, regions, tris, tri_start,
                                        tri_ids, tri_nbrs, body_face, part_face, near_vertex, face_n, q, face_tip,
                                        tip_share, clearance, max_iterations, up, down, search)
                    if vid < n_coarse and d < clearance - LIFT_TOLERANCE and dh[vid] != 0.0:
                        d, rate = _back_to_coarse(p, vid, seed, x, corners, parts, groups, group_reach, n_groups, d,
                                                  rate, normals, dh, dh_pen, body_x, nbr_start, nbr_ids, regions, tris,
                                                  tri_start, tri_ids, tri_nbrs, body_face, part_face, near_vertex,
                                                  face_n, q, face_tip, tip_share)
                sd[vid] = d
                facing[vid] = rate
    return tested


@kernel
def _back_to_coarse(p, vid, seed, x, corners, parts, groups, group_reach, n_groups, d, rate, normals, dh, dh_pen,
                    body_x, nbr_start, nbr_ids, regions, tris, tri_start, tri_ids, tri_nbrs, body_face, part_face,
                    near_vertex, face_n, q, face_tip, tip_share):
    """Decision (back to where S101 put it, eighty-eighth session): a coarse vertex's particle that no
    move along n_i gets out of the body goes back to its coarse particle (Δh = 0: the PN patch passes
    through its corners), which S101's collision left outside the body, where it reads farther out
    there. Its heights carried from earlier frames had stood it off the coarse particle along a
    normal that now runs along the body (the jumping jacks' blouse at the right elbow: coarse vertex
    21, 20 mm up its normal, 2-6 mm inside the forearm folding onto the upper arm, n_i . n_body
    0.0-0.2, over 30 frames). Returns (signed distance, n_i . n_body) where it ends."""
    h = dh[vid]
    p0, p1, p2 = p[vid, 0], p[vid, 1], p[vid, 2]
    p[vid, 0] -= h * normals[vid, 0]
    p[vid, 1] -= h * normals[vid, 1]
    p[vid, 2] -= h * normals[vid, 2]
    d0, bx, by, bz, _, _, _, _ = detail_signed_distance(p, vid, seed, x, corners, parts, groups, group_reach, n_groups,
                                                        part_face[vid], body_x, nbr_start, nbr_ids, regions, tris,
                                                        tri_start, tri_ids, tri_nbrs, body_face, part_face,
                                                        near_vertex, face_n, q, normals, face_tip, tip_share)
    if d0 <= d:  # no farther out there: it stays where the lifts left it
        p[vid, 0], p[vid, 1], p[vid, 2] = p0, p1, p2
        return d, rate
    dh_pen[vid] -= h
    dh[vid] = 0.0
    return d0, normals[vid, 0] * bx + normals[vid, 1] * by + normals[vid, 2] * bz


@helper
def face_height(dh, f, face_ids):
    """The largest |Δh| among coarse face f's detailed particles (m): how far S103's positions of
    them stand off the PN patch along their normals at most."""
    h = 0.0
    for k in range(face_ids.shape[1]):
        h = max(h, abs(dh[face_ids[f, k]]))
    return h


@helper
def bulge_towards_body(ctrl, f, face_ids, order, normals, facing):
    """How far coarse face f's PN patch can stand nearer the body than the plane of its corners
    (m, >= 0): its control points' largest offset from that plane towards the body (the patch
    lies in their convex hull). Towards the body is along -n_i where its corners face the body
    (facing > 0: the body below them), along n_i where the body lies over them (facing < 0);
    facing, normals: S103's, at the corners (tested)."""
    ax, ay, az = ctrl[f, 0, 0], ctrl[f, 0, 1], ctrl[f, 0, 2]
    e1x, e1y, e1z = ctrl[f, 1, 0] - ax, ctrl[f, 1, 1] - ay, ctrl[f, 1, 2] - az
    e2x, e2y, e2z = ctrl[f, 2, 0] - ax, ctrl[f, 2, 1] - ay, ctrl[f, 2, 2] - az
    nx, ny, nz = e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x
    length = math.sqrt(nx * nx + ny * ny + nz * nz)
    if length == 0.0:
        return 0.0
    nx, ny, nz = nx / length, ny / length, nz / length
    # which side of the plane the body lies on: the corners' facing, by how their normals lean on it
    w = 0.0
    for c in range(3):
        v = face_ids[f, order[c]]
        w += facing[v] * (normals[v, 0] * nx + normals[v, 1] * ny + normals[v, 2] * nz)
    towards = -1.0 if w > 0.0 else 1.0
    bulge = 0.0
    for k in range(3, 10):
        off = towards * ((ctrl[f, k, 0] - ax) * nx + (ctrl[f, k, 1] - ay) * ny + (ctrl[f, k, 2] - az) * nz)
        if w == 0.0:
            off = abs(off)
        bulge = max(bulge, off)
    return bulge


# the body's tips against the detailed triangles (Decision, `cover_body_tips`)
MIN_COVERED_TIP = 0.0005  # m: a body vertex standing out of its ring by less is covered by S103's particles alone
COVER_FACING = 0.5  # the skin faces out through the triangle: n_v . n_triangle at least this
MAX_COVER_POKE = 0.005  # m: a vertex farther in front of the triangle is not under it (another body part over it)
COVER_SLACK = 0.001  # m: the triangle's plane and the tangent plane at its particle differ by less there
COVER_REACH = 0.0015  # m: a vertex deeper under its triangle leaves S106 the floor S103 gave (it comes down less)
COVER_WALK_STEPS = 4  # steps over the detailed edges from a particle to the one nearest the vertex
# where the vertex lies over none of the triangles around the particle nearest it (their normals lean), the
# one it misses least is taken while it lies no farther outside that one's edges than this (barycentric)
COVER_OUTSIDE = 0.25


@helper
def _over_vertex(p, normals, d_tri_start, d_tri_ids, d_tris, i, vx, vy, vz):
    """Of the detailed triangles around particle i, the one whose projection along its normal
    holds the point v, or else the one it misses least: (triangle, how far outside its edges the
    point's projection lies in barycentric terms (0: inside), its unit normal turned to the
    particles' side); triangle -1 if none has an area."""
    best_t, best_out = -1, np.inf
    bx = by = bz = 0.0
    for k in range(d_tri_start[i], d_tri_start[i + 1]):
        t = d_tri_ids[k]
        a, b, c = d_tris[t, 0], d_tris[t, 1], d_tris[t, 2]
        v, w, ok = plane_barycentric(p, a, b, c, vx, vy, vz)
        if not ok:
            continue
        out = max(0.0, -v, -w, v + w - 1.0)
        if out >= best_out:
            continue
        e0x, e0y, e0z = p[b, 0] - p[a, 0], p[b, 1] - p[a, 1], p[b, 2] - p[a, 2]
        e1x, e1y, e1z = p[c, 0] - p[a, 0], p[c, 1] - p[a, 1], p[c, 2] - p[a, 2]
        nx, ny, nz = e0y * e1z - e0z * e1y, e0z * e1x - e0x * e1z, e0x * e1y - e0y * e1x
        length = math.sqrt(nx * nx + ny * ny + nz * nz)
        side = 0.0
        for m in range(3):
            q = d_tris[t, m]
            side += normals[q, 0] * nx + normals[q, 1] * ny + normals[q, 2] * nz
        if side < 0.0:
            length = -length
        best_t, best_out = t, out
        bx, by, bz = nx / length, ny / length, nz / length
        if out == 0.0:
            break
    return best_t, best_out, bx, by, bz


@kernel
def cover_body_tips(p, normals, dh, dh_pen, lifted, floor, ceiling, body_floor, sd, facing, other, body_face, part_face,
                    near_vertex, body_x, tris, tri_nbrs, tri_start, tri_ids, nbr_start, nbr_ids, regions, face_n, q,
                    vertex_tip, d_tris, d_tri_start, d_tri_ids, d_nbr_start, d_nbr_ids, owner, owned, clearance,
                    max_height, wfaces, wlo, wstart, wids, wspan, wextent, use_winding):
    """Decision (the body's tips against the detailed triangles; S103 tests particles, not
    triangles): a body vertex standing out of its ring (vertex_tip, `collision.face_tip_heights`)
    can come through the detailed triangle between particles that S103 put the clearance off the
    faces around it, or that S106 brought down towards the body as far as their own distances
    allow: skin seen through tight cloth, at the knees and thighs. Each such vertex that is a
    tested particle's nearest body vertex (near_vertex, S103's own vertex) is looked for under the
    detailed triangles around the particle nearest to it (walking there over the detailed edges
    from the first such particle, at most COVER_WALK_STEPS steps, `geometry.walk_nearest_vertex`;
    or the one of those triangles it misses least, by at most COVER_OUTSIDE, where their normals
    lean). Where the skin faces out through that triangle (n_v . n_t >= COVER_FACING) and the
    vertex lies at most MAX_COVER_POKE in front of its plane or less than COVER_REACH behind it
    (s, its height over the plane), the plane is kept the clearance over it: each corner rises
    along its normal by
    (s + clearance) / (n_i . n_t) where that is positive, and S106 may bring it down by no more
    than -(s + clearance) / (n_i . n_t) after (floor, body_floor: `penetration_floor`'s, raised;
    ceiling not below the floor). Only where S103 tested all three corners with the body below
    them (facing >= 0), and where a corner to be raised has another body part within
    TIP_OTHER_CLEAR, only if it still reads the clearance or more outside by a face walk from
    where its walk in the other part ended (part_face), else from its own (body_face: S103's
    walks in the other parts came back to its own, or a bound ruled them out). In a crease a lift
    goes into the other skin; at the seam between two parts, as at the knee, the other part is
    the same skin going on, and the specks showed there: `tip_allowance`'s rule, no other part
    within 1 cm, left the knees as they were. And a raised corner must lie outside the body as a
    whole (its winding number 0; use_winding, the pose's winding grid over wfaces): where the
    skinned skin overlaps itself, as the thigh in the belly in a squat, a corner S103 read outside
    its own part rose into the other (the jumping jacks' squats). Δh stays within max_height; the lifts count in Δh,
    Δh_penetration and `lifted` (sd is left as S103 read it). owner (n_body,) int32: -1 on entry
    and on return; owned (n_body,) int32 scratch; q (3,) scratch. Returns the number of vertices
    covered by a lift."""
    n_owned = 0
    for i in range(p.shape[0]):  # each tip that is a tested particle's nearest body vertex, once
        if sd[i] == UNTESTED:
            continue
        v = near_vertex[i]
        if v < 0 or owner[v] >= 0 or vertex_tip[v] < MIN_COVERED_TIP:
            continue
        owner[v] = i
        owned[n_owned] = v
        n_owned += 1
    covered = 0
    for m in range(n_owned):
        v = owned[m]
        i = owner[v]
        owner[v] = -1
        vx, vy, vz = body_x[v, 0], body_x[v, 1], body_x[v, 2]
        # (its height over the tangent plane at its nearest particle: most lie deep under it, or far over)
        s = (vx - p[i, 0]) * normals[i, 0] + (vy - p[i, 1]) * normals[i, 1] + (vz - p[i, 2]) * normals[i, 2]
        if s < -COVER_REACH - COVER_SLACK or s > MAX_COVER_POKE + COVER_SLACK:
            continue
        i = walk_nearest_vertex(vx, vy, vz, p, d_nbr_start, d_nbr_ids, i, COVER_WALK_STEPS)
        t, out, nx, ny, nz = _over_vertex(p, normals, d_tri_start, d_tri_ids, d_tris, i, vx, vy, vz)
        if t < 0 or out > COVER_OUTSIDE:
            continue
        a = d_tris[t, 0]
        s = (vx - p[a, 0]) * nx + (vy - p[a, 1]) * ny + (vz - p[a, 2]) * nz  # the vertex's height over the plane
        if s <= -COVER_REACH or s > MAX_COVER_POKE:
            continue
        bx, by, bz = vertex_normal(tri_start, tri_ids, face_n, v)
        if bx * nx + by * ny + bz * nz < COVER_FACING:
            continue  # the skin does not face out through this triangle
        need = s + clearance  # > 0: the plane rises by this; <= 0: it may come down by -need, no more
        usable = True
        for c in range(3):
            j = d_tris[t, c]
            rate = normals[j, 0] * nx + normals[j, 1] * ny + normals[j, 2] * nz
            if sd[j] == UNTESTED or facing[j] < 0.0 or rate < COVER_FACING:
                usable = False
                break
            if need <= LIFT_TOLERANCE:
                continue
            lift = max(0.0, min(need / rate, max_height - dh[j]))
            rx, ry, rz = p[j, 0] + lift * normals[j, 0], p[j, 1] + lift * normals[j, 1], p[j, 2] + lift * normals[j, 2]
            # the raised corner stays outside the body as a whole (where the skinned skin overlaps itself, as the
            # thigh in the belly in a squat, a corner S103 read outside its own part can rise into the other)
            if use_winding and winding_number(rx, ry, rz, body_x, wfaces, wlo, wstart, wids, wspan, wextent) != 0:
                usable = False
                break
            if other[j] < TIP_OTHER_CLEAR:  # another part near: the raised corner must stay the clearance out of it
                start = part_face[j] if part_face[j] >= 0 else body_face[j]
                if start < 0 or face_walk_distance(rx, ry, rz, body_x, tris, tri_nbrs, tri_start, tri_ids, nbr_start,
                                                   nbr_ids, regions, start, face_n, q)[0] < clearance:
                    usable = False
                    break
        if not usable:
            continue
        for c in range(3):
            j = d_tris[t, c]
            rate = normals[j, 0] * nx + normals[j, 1] * ny + normals[j, 2] * nz
            if need > LIFT_TOLERANCE:
                lift = min(need / rate, max_height - dh[j])
                if lift > 0.0:
                    dh[j] += lift
                    dh_pen[j] += lift
                    lifted[j] = dh[j]
                    p[j, 0] += lift * normals[j, 0]
                    p[j, 1] += lift * normals[j, 1]
                    p[j, 2] += lift * normals[j, 2]
            low = dh[j] - max(0.0, -need) / rate  # S106 may bring the corner down this far, no further
            floor[j] = max(floor[j], low)
            body_floor[j] = max(body_floor[j], low)
            ceiling[j] = max(ceiling[j], floor[j])
        if need > LIFT_TOLERANCE:
            covered += 1
    return covered


# ---------------------------------------------------------------- S104 normal force

@helper
def transfer_curve(c, exponent):
    """S104 step 2's mapping of c = cos θ to a transfer rate: max(c, 0)^exponent (exponent 1:
    the patent's plain cosine)."""
    if c <= 0.0:
        return 0.0
    # the presets' exponents without a call to pow (the rate is computed for every detailed particle)
    if exponent == 1.0:
        return c
    if exponent == 2.0:
        return c * c
    if exponent == 0.5:
        return math.sqrt(c)
    return c ** exponent


@kernel(fastmath=FAST_ARITHMETIC)
def chain_segments(p, chain_ids, seg):
    """seg[:, q] = p[chain_ids[q + 1]] - p[chain_ids[q]] for every position q of the chains
    (across two chains' boundary: unused). The loads by particle index, apart from the
    arithmetic of `chain_rates`, which vectorises (as the S101 springs do)."""
    i = chain_ids[0]
    x0, y0, z0 = p[i, 0], p[i, 1], p[i, 2]
    for q in range(chain_ids.shape[0] - 1):
        j = np.uint64(chain_ids[q + 1])  # (unsigned: no wrap-around of a negative index)
        x1, y1, z1 = p[j, 0], p[j, 1], p[j, 2]
        seg[0, q] = x1 - x0
        seg[1, q] = y1 - y0
        seg[2, q] = z1 - z0
        x0, y0, z0 = x1, y1, z1


@kernel(fastmath=FAST_ARITHMETIC)
def chain_rates(seg, exponent, rates):
    """S104 step 2 at every inner position q of a chain: the mapped
    c_q = (p_q - p_{q-1}).(p_{q+1} - p_q) / (|p_q - p_{q-1}| |p_{q+1} - p_q|), max(c, 0)^exponent
    (`transfer_curve`), 1 where a segment has no length. In float32, whose reciprocal square
    root the loop runs eight or sixteen at a time: a transfer weight needs no more than its
    seven digits, and the scalar square roots and divisions in float64 were two thirds of
    the elastic forces' time. rates[0] and the chains' ends: unused."""
    sx, sy, sz = seg[0], seg[1], seg[2]
    for q in range(1, rates.shape[0]):
        ax, ay, az = sx[q - 1], sy[q - 1], sz[q - 1]
        bx, by, bz = sx[q], sy[q], sz[q]
        ll = (ax * ax + ay * ay + az * az) * (bx * bx + by * by + bz * bz)
        c = min(max(ax * bx + ay * by + az * bz, np.float32(0.0)) / math.sqrt(ll), np.float32(1.0))
        rates[q] = c if ll > np.float32(0.0) else np.float32(1.0)
    # the presets' exponents without a call to pow (1: the patent's plain cosine)
    if exponent == 2.0:
        for q in range(rates.shape[0]):
            rates[q] = rates[q] * rates[q]
    elif exponent == 0.5:
        for q in range(rates.shape[0]):
            rates[q] = math.sqrt(rates[q])
    elif exponent != 1.0:
        for q in range(rates.shape[0]):
            rates[q] = transfer_curve(rates[q], exponent)


@helper
def _interpolate_line(ids, rates, count, f1, fn, ef, weight, accumulate):
    """S104 step 3 along one chain ids[0..count-1] whose end forces are f1, fn, with its
    transfer rates (`chain_rates`):
    ef_i = f_1 + (Σ_{j=2}^{i-1} c_j + 0.5 c_i) / (Σ_{j=2}^{n-1} c_j) (f_n - f_1).
    accumulate: add weight * ef_i (face lines, averaged) instead of storing it (edges)."""
    total = 0.0
    for m in range(1, count - 1):
        total += rates[m]
    run = 0.0
    inv_total = 1.0 / total if total > 1e-12 else 0.0
    d0, d1, d2 = fn[0] - f1[0], fn[1] - f1[1], fn[2] - f1[2]
    for m in range(1, count - 1):
        if inv_total > 0.0:
            s = (run + 0.5 * rates[m]) * inv_total
        else:  # a chain folded flat everywhere transmits nothing: split evenly
            s = (m - 0.5) / (count - 2)
        run += rates[m]
        i = np.uint64(ids[m])  # (unsigned: no wrap-around of a negative index)
        if accumulate:
            ef[i, 0] += weight * (f1[0] + s * d0)
            ef[i, 1] += weight * (f1[1] + s * d1)
            ef[i, 2] += weight * (f1[2] + s * d2)
        else:
            ef[i, 0] = f1[0] + s * d0
            ef[i, 1] = f1[1] + s * d1
            ef[i, 2] = f1[2] + s * d2


@kernel
def coarse_edge_forces(x, edges, rest, k_stretch, k_compress, out):
    """S104 step 1 on each coarse edge: the elastic force of the edge at its two ends, as S101's
    springs define it (k_stretch longer than rest, k_compress shorter), taken as the reaction on
    the surroundings: a compressed edge pushes inward, along itself, at both ends.
    Every edge of the triangulation gets the fabric's structural stiffness, the diagonal of a
    split quad included (its S101 spring is a shear spring, which would make diagonals
    dominate). out (E, 2, 3): force at the edge's low and high vertex, N."""
    for e in range(edges.shape[0]):
        a, b = edges[e, 0], edges[e, 1]
        dx, dy, dz = x[b, 0] - x[a, 0], x[b, 1] - x[a, 1], x[b, 2] - x[a, 2]
        length = math.sqrt(dx * dx + dy * dy + dz * dz)
        if length == 0.0:
            for k in range(3):
                out[e, 0, k] = 0.0
                out[e, 1, k] = 0.0
            continue
        ext = length - rest[e]
        tension = (k_stretch if ext > 0.0 else k_compress) * ext  # > 0 stretched
        # the edge pulls a towards b with +tension (b - a)/length; the reaction is its negative
        fx, fy, fz = -tension * dx / length, -tension * dy / length, -tension * dz / length
        out[e, 0, 0], out[e, 0, 1], out[e, 0, 2] = fx, fy, fz
        out[e, 1, 0], out[e, 1, 1], out[e, 1, 2] = -fx, -fy, -fz


@kernel(fastmath=FAST_ARITHMETIC)
def elastic_forces(p, coarse_force, edge_force, edge_ids, line_start, chain_ids, exponent, seg, rates, f1, fn, ef):
    """S104 steps 1-4: elastic force ef_i of every detailed particle.

    Coarse-vertex particles take the coarse elastic force (coarse_force, reaction sign);
    particles on a coarse edge interpolate between the edge's end forces with the transfer
    rates (step 3); face-interior particles (numbered after the edges' particles)
    interpolate the same way along the lattice lines through them (line_start; chain_ids:
    the Tessellation's), from the edge values at the lines' ends, and average the three
    directions (step 4: a triangle's lattice has three grid directions).
    seg (3, Q) float32, rates (Q,) float32 (Q = len(chain_ids)), f1 (3,), fn (3,): scratch."""
    chain_segments(p, chain_ids, seg)
    chain_rates(seg, exponent, rates)
    n_coarse = coarse_force.shape[0]
    for i in range(n_coarse):
        for a in range(3):
            ef[i, a] = coarse_force[i, a]
    L1 = edge_ids.shape[1]
    for e in range(edge_ids.shape[0]):
        o = e * L1
        _interpolate_line(chain_ids[o:o + L1], rates[o:o + L1], L1, edge_force[e, 0], edge_force[e, 1], ef, 1.0,
                          False)
    for i in range(n_coarse + edge_ids.shape[0] * (L1 - 2), ef.shape[0]):
        for a in range(3):
            ef[i, a] = 0.0
    third = 1.0 / 3.0
    lines = edge_ids.shape[0] * L1  # where the face lines start in chain_ids
    for k in range(line_start.shape[0] - 1):
        o, count = lines + line_start[k], line_start[k + 1] - line_start[k]
        ids = chain_ids[o:o + count]
        for a in range(3):
            f1[a] = ef[ids[0], a]
            fn[a] = ef[ids[count - 1], a]
        _interpolate_line(ids, rates[o:o + count], count, f1, fn, ef, third, True)


@kernel(fastmath=FAST_ARITHMETIC)
def normal_force(p, ef, edges, vf):
    """S104 step 5: vf_i = Σ_j (p_i - p_j)/|p_i - p_j| . ef_j over the detailed neighbours j.
    vf > 0: pushed by its surroundings (relief grows); vf < 0: pulled (the surface flattens).
    Summed over the detailed edges (i, j), each giving its two terms: one square root per
    edge instead of one per neighbour pair, and that one a float32 reciprocal square root (a
    direction to seven digits; the float64 square root and division were an eighth of the
    time)."""
    for i in range(vf.shape[0]):
        vf[i] = 0.0
    for e in range(edges.shape[0]):
        i, j = np.uint64(edges[e, 0]), np.uint64(edges[e, 1])  # (unsigned: no wrap-around of a negative index)
        dx, dy, dz = p[i, 0] - p[j, 0], p[i, 1] - p[j, 1], p[i, 2] - p[j, 2]
        d2 = dx * dx + dy * dy + dz * dz
        if d2 > 1e-30:  # (an edge under 1e-15 m has no direction in float32: as coincident ends)
            inv = np.float32(1.0) / math.sqrt(np.float32(d2))
            vf[i] += (dx * ef[j, 0] + dy * ef[j, 1] + dz * ef[j, 2]) * inv
            vf[j] -= (dx * ef[i, 0] + dy * ef[i, 1] + dz * ef[i, 2]) * inv


# ---------------------------------------------------------------- S105 length displacement

@kernel
def length_displacement(p, p_smoothed, edge_ids, edge_rest, coarse_tris, owner_face, owner_weights, edge_required,
                        edge_deficit, vertex_required, vertex_compressed, required):
    """S105: per coarse edge ΔLE_required,e = L_rest,e - L_e (L_e: the detailed arc length along
    it; > 0 when compressed); per coarse vertex the mean over its compressed edges (Decision,
    below); then interpolated linearly along the edges and inside the faces (plain
    interpolation: for values linear along the edges this is the barycentric interpolation of
    the corner values, used here); the particles on an edge that is long enough take none.
    Decision, the per-vertex mean: over the edges with ΔLE_required > 0 only (0 where there
    are none). Cloth buckles across a compressed direction while it is tense along the other
    (a tension field), so an over-long edge must neither cancel its neighbour's requirement
    nor dilute it. With the signed mean over every edge, 92-97 % of the detailed particles on
    the walk clip's compressed T-shirt edges had no requirement left, and old wrinkles stayed
    as isolated bumps; S106's flat rule takes down what is over-long.
    edge_deficit: written, L_rest,e minus the arc length of the reference surface (p_smoothed)
    along the edge: > 0 where the coarse cloth itself is short along it, whatever the heights.
    vertex_compressed (n_coarse,): scratch, the compressed edges at each coarse vertex."""
    n_coarse = vertex_required.shape[0]
    for v in range(n_coarse):
        vertex_required[v] = 0.0
        vertex_compressed[v] = 0.0
    L1 = edge_ids.shape[1]
    for e in range(edge_ids.shape[0]):
        length = 0.0
        reference = 0.0
        for m in range(L1 - 1):
            a, b = edge_ids[e, m], edge_ids[e, m + 1]
            length += math.sqrt((p[b, 0] - p[a, 0]) ** 2 + (p[b, 1] - p[a, 1]) ** 2 + (p[b, 2] - p[a, 2]) ** 2)
            reference += math.sqrt((p_smoothed[b, 0] - p_smoothed[a, 0]) ** 2
                                   + (p_smoothed[b, 1] - p_smoothed[a, 1]) ** 2
                                   + (p_smoothed[b, 2] - p_smoothed[a, 2]) ** 2)
        dl = edge_rest[e] - length
        edge_required[e] = dl
        edge_deficit[e] = edge_rest[e] - reference
        if dl > 0.0:
            for end in (edge_ids[e, 0], edge_ids[e, L1 - 1]):
                vertex_required[end] += dl
                vertex_compressed[end] += 1.0
    for v in range(n_coarse):
        if vertex_compressed[v] > 0.0:
            vertex_required[v] /= vertex_compressed[v]
    for i in range(p.shape[0]):
        t = owner_face[i]
        required[i] = (owner_weights[i, 0] * vertex_required[coarse_tris[t, 0]]
                       + owner_weights[i, 1] * vertex_required[coarse_tris[t, 1]]
                       + owner_weights[i, 2] * vertex_required[coarse_tris[t, 2]])
    for e in range(edge_ids.shape[0]):
        if edge_required[e] <= 0.0:  # long enough: its particles take no requirement from its ends
            for m in range(1, L1 - 1):
                required[edge_ids[e, m]] = 0.0


# ---------------------------------------------------------------- S106 surface deformation

@kernel
def deformation_heights(vf, dh, required, edges, n_coarse, k_out, dt, expected, out):
    """S106 steps 1-4: Δh_deformation per detailed particle.

    1. ΔL_expected,i = Σ_j ±k_out |vf_i - vf_j|, + when (vf_i - vf_j)(Δh_i - Δh_j) >= 0.
    2. Δh_length,i from ΔL_required,i / ΔL_expected,i when their product is > 0, else 0.
    3. Δh_out-plane_force,i = k_out vf_i Δt.
    4. The smaller in magnitude (the force term is a clamp).
    Units (Decision): k_out is a speed per unit normal force (m/(N·s)), so ΔL_expected is the
    rate at which the surface around i lengthens when every particle moves at k_out vf, and
    ΔL_required / ΔL_expected is the time that takes; Δh_length is the height reached moving
    at k_out vf_i for that time, and the clamp limits it to one frame's motion. Coarse-vertex
    particles keep Δh_deformation = 0: S101 has placed them.
    Step 1 is summed over the detailed edges (i, j): the term is the same seen from i and from
    j (both factors change sign). expected: (N,) scratch."""
    for i in range(vf.shape[0]):
        expected[i] = 0.0
    for e in range(edges.shape[0]):
        i, j = edges[e, 0], edges[e, 1]
        dv = vf[i] - vf[j]
        term = k_out * abs(dv)
        if dv * (dh[i] - dh[j]) < 0.0:
            term = -term
        expected[i] += term
        expected[j] += term
    for i in range(vf.shape[0]):
        if i < n_coarse:
            out[i] = 0.0
            continue
        speed = k_out * vf[i]
        if required[i] * expected[i] > 0.0:
            h_length = speed * (required[i] / expected[i])
        else:
            h_length = 0.0
        h_force = speed * dt
        out[i] = h_length if abs(h_length) < abs(h_force) else h_force


@helper
def _scaled_height(dh, dh_def, floor, vf, k_out, dt, ceiling, i, s):
    """Particle i's height with its S106 step scaled by s, through the force clamp (step 4)
    and the floor and ceiling of step 5, as they will apply."""
    limit = abs(k_out * vf[i] * dt)
    step = min(limit, max(-limit, s * dh_def[i]))
    return max(floor[i], min(dh[i] + step, ceiling[i]))


@helper
def _lower_within(p_smoothed, n_pn, i, j, h, floor_i, qx, qy, qz, seg_max, allowance):
    """Particle i's height h, lowered (never below floor_i) until it is within the limit of its
    neighbour j, standing at q, as S106 step 5 brings the higher end of an over-long edge down
    (`_limit_edge`): seg_max, or where the reference surface alone parts them farther, that
    length with seg_max² - rest² on top."""
    lim2 = _limit2(p_smoothed, i, j, seg_max, allowance)
    dx = p_smoothed[i, 0] + h * n_pn[i, 0] - qx
    dy = p_smoothed[i, 1] + h * n_pn[i, 1] - qy
    dz = p_smoothed[i, 2] + h * n_pn[i, 2] - qz
    if dx * dx + dy * dy + dz * dz <= lim2:
        return h
    t = _height_at_distance(p_smoothed, n_pn, i, qx, qy, qz, math.sqrt(lim2), h)[0]
    return max(floor_i, min(h, t))


@helper
def _arc_at_scale(p_smoothed, n_pn, dh, dh_def, floor, vf, k_out, dt, ceiling, edge_ids, edge_seg_max, allowance, e,
                  s, heights):
    """Detailed arc length along coarse edge e with its interior particles' steps scaled by s,
    and each one then brought down where it would stand farther than its limit from its
    neighbour along the edge (the rule of step 5, one pass from each end: where the ends,
    coarse vertices, stay at their height, a tall step makes a cliff beside them that step 5
    takes back). heights (L + 1,): written, the heights along the edge."""
    L = edge_ids.shape[1] - 1
    for m in range(L + 1):
        b = edge_ids[e, m]
        heights[m] = dh[b] if m == 0 or m == L else _scaled_height(dh, dh_def, floor, vf, k_out, dt, ceiling, b, s)
    for m in range(1, L):  # from the first end: each particle within reach of the one before
        a, b = edge_ids[e, m - 1], edge_ids[e, m]
        if heights[m] > heights[m - 1]:
            heights[m] = _lower_within(p_smoothed, n_pn, b, a, heights[m], floor[b],
                                       p_smoothed[a, 0] + heights[m - 1] * n_pn[a, 0],
                                       p_smoothed[a, 1] + heights[m - 1] * n_pn[a, 1],
                                       p_smoothed[a, 2] + heights[m - 1] * n_pn[a, 2], edge_seg_max[e, m - 1],
                                       allowance)
    length = 0.0
    for m in range(L - 1, -1, -1):  # from the other end, measuring as it goes
        a, b = edge_ids[e, m], edge_ids[e, m + 1]
        bx = p_smoothed[b, 0] + heights[m + 1] * n_pn[b, 0]
        by = p_smoothed[b, 1] + heights[m + 1] * n_pn[b, 1]
        bz = p_smoothed[b, 2] + heights[m + 1] * n_pn[b, 2]
        if m > 0 and heights[m] > heights[m + 1]:
            heights[m] = _lower_within(p_smoothed, n_pn, a, b, heights[m], floor[a], bx, by, bz,
                                       edge_seg_max[e, m], allowance)
        dx = p_smoothed[a, 0] + heights[m] * n_pn[a, 0] - bx
        dy = p_smoothed[a, 1] + heights[m] * n_pn[a, 1] - by
        dz = p_smoothed[a, 2] + heights[m] * n_pn[a, 2] - bz
        length += math.sqrt(dx * dx + dy * dy + dz * dz)
    return length


@kernel
def match_required_length(p_smoothed, n_pn, dh, dh_def, floor, vf, k_out, dt, ceiling, edge_ids, edge_required,
                          edge_rest, edge_seg_max, allowance, face_ids, face_edges, interior_local, max_scale,
                          tolerance, iterations, edge_scale, heights):
    """S106 step 2, how far (Decision): on each compressed coarse edge (ΔLE_required > 0) the
    steps of steps 1-4 are scaled by one factor s so that the detailed arc length along the
    edge after them is its rest length.

    Step 1's ΔL_expected counts all of two neighbours' relative motion as length, as if the
    edge between them stood upright; on a gentle wrinkle the surface lengthens by about the
    sine of its slope times that, so the step was short of the deficit. The arc length of the
    stepped surface is measured instead: secant steps on s from s = 0 (S105's L_e) and s = 1
    (the patent's step), false position (Illinois) once a factor is beyond it, until it is
    within `tolerance` (a fraction of the rest length) or after `iterations` arc evaluations,
    each particle's step through the force clamp, the floor and the ceiling as they will
    apply, s kept in [0, max_scale]. Decision: the particles along the edge are then brought
    down where step 5's maximum neighbour distance will bring them down (edge_seg_max (E, L):
    d_max of each segment along each coarse edge; allowance: see `apply_constraints`), and the
    arc measured after that: otherwise, on an edge compressed by a third or more, the step's
    tall first particle beside a coarse vertex lost most of its height to step 5 and the edge
    its length (a run clip recovered 0.65-0.7 of the deficit); measured this way, s grows
    until the heights ramp up from both ends.
    Face interiors take the mean factor of their face's compressed edges; elsewhere the steps
    are unchanged. edge_scale (E,): written, s per coarse edge (-1: not compressed); heights
    (L + 1,): scratch."""
    L1 = edge_ids.shape[1]
    for e in range(edge_ids.shape[0]):
        edge_scale[e] = -1.0
        if edge_required[e] <= 0.0:
            continue
        target = edge_rest[e]
        # s_lo: a factor known short of the target (0: S105's L_e); s_hi: one known beyond it
        s_lo, a_lo = 0.0, edge_rest[e] - edge_required[e]
        s_hi, a_hi = -1.0, 0.0
        side = 0
        s1 = 1.0
        a1 = _arc_at_scale(p_smoothed, n_pn, dh, dh_def, floor, vf, k_out, dt, ceiling, edge_ids, edge_seg_max,
                           allowance, e, s1, heights)
        for _ in range(iterations - 1):
            if abs(a1 - target) <= tolerance * target:
                break
            if a1 < target:
                if s_hi < 0.0:  # not bracketed yet: the secant through the last two factors, ahead
                    s2 = max_scale if a1 <= a_lo else min(max_scale, s1 + (target - a1) * (s1 - s_lo) / (a1 - a_lo))
                if side < 0:  # (Illinois: the end kept twice counts half as far off)
                    a_hi = target + 0.5 * (a_hi - target)
                s_lo, a_lo, side = s1, a1, -1
            else:
                if side > 0:
                    a_lo = target + 0.5 * (a_lo - target)
                s_hi, a_hi, side = s1, a1, 1
            if s_hi >= 0.0:  # bracketed (step 5's cut makes the length flat in places): false position
                s2 = s_lo + (target - a_lo) * (s_hi - s_lo) / (a_hi - a_lo)
            if s2 == s1:
                break
            s1 = s2
            a1 = _arc_at_scale(p_smoothed, n_pn, dh, dh_def, floor, vf, k_out, dt, ceiling, edge_ids, edge_seg_max,
                               allowance, e, s1, heights)
        edge_scale[e] = s1
        for m in range(1, L1 - 1):  # (heights: those of the last evaluation, at s1)
            i = edge_ids[e, m]
            dh_def[i] = heights[m] - dh[i]
    for f in range(face_ids.shape[0]):
        total = 0.0
        count = 0
        for k in range(3):
            s = edge_scale[face_edges[f, k]]
            if s >= 0.0:
                total += s
                count += 1
        if count > 0:
            s = total / count
            for k in range(interior_local.shape[0]):
                i = face_ids[f, interior_local[k]]
                dh_def[i] = _scaled_height(dh, dh_def, floor, vf, k_out, dt, ceiling, i, s) - dh[i]


@kernel
def apply_constraints(p_smoothed, n_pn, dh, floor, ceiling, face_ids, face_edges, edge_required, edge_deficit,
                      coarse_edge_ids, interior_local, d_edges, d_max, allowance, edge_start, edge_ids, passes,
                      max_height, flat_edge, moved, stamp, start_h, widen, fold, p):
    """S106 steps 5-6: constraints on Δh, then p_i = p_smoothed,i + Δh_i n_i.

    floor_i <= Δh_i <= ceiling_i (floor: 0, or the height S103 needs to keep it out of the
    body; ceiling: max_height, which bounds what S103 lifts pile up where the coarse cloth is
    deep in the body, or lower under a body part above, see `penetration_floor`); in a coarse
    face all of whose edges are stretched (ΔLE_required < 0) the interior is flat (Δh = floor).
    Decision: so are the particles on a coarse edge (coarse_edge_ids) all of whose faces are
    such faces — the edge is inside the stretched region, and keeping its particles' heights
    left a bump on every edge between flattened faces — unless the coarse cloth is short along
    it (edge_deficit > 0): then the wrinkles there are what made its faces look stretched.
    flat_edge (E,) uint8: scratch.
    Neighbours no farther apart than d_max (per detailed edge): the higher one comes down
    towards its floor, and if that is not enough the lower one goes up (`passes` rounds).
    Decision (across the normals): where neither move can bring them within the limit — the
    edge runs across both normals, as on the top of a fold over a curved limb, where raised
    particles stand farther apart than on the reference surface — both come down together,
    by one factor on their heights above their floors (`_common_factor`): on the walk's jeans
    these were most of the edges left too long with neither end at a bound.
    Decision (stretched edges): where the reference surface alone already parts an edge's ends
    beyond d_max (the coarse cloth is stretched past the ratio there), no height can meet the
    limit; the heights may then part them as far as on the edge at rest,
    |p_i - p_j|² <= |p_s,i - p_s,j|² + d_max² - rest² (allowance = 1 - 1/ratio², so
    d_max² - rest² = allowance d_max²). Demanding the reference length instead would ask the
    whole stretched region for one height; the rounds chased that and left the edges too long.
    Decision (widen): a wrinkle on a compressed coarse edge keeps its height and widens into a
    fold — the lower end, off that edge, rises to d_max from it (at most to max_height) and
    carries the fold on to its own neighbours; the patent's step raises the particles along
    the edge alone, and bringing them down to their unraised neighbours took back nearly all of
    the length the step gave. Particles held flat by the stretched-face rule are not raised, nor
    are coarse vertices (S103 skips a face whose corners are away from the body: a raised
    corner hid the face's interior from it).
    The first round visits every edge; a later one only the edges around the particles the
    round before moved (edge_start, edge_ids: CSR of each particle's detailed edges), as the
    others are as that round left them; a particle back at the height it had when the round
    first moved it is dropped from the list (where an edge's two limits conflict, the rounds
    move a particle up for one edge and down for the next, round after round, to the same
    end). moved (2, N) int32, stamp (N,) int32, start_h (N,): scratch; fold (N,) uint8:
    scratch (1: in a fold, 2: held flat)."""
    for i in range(dh.shape[0]):
        dh[i] = max(floor[i], min(dh[i], ceiling[i]))
        stamp[i] = -1
        fold[i] = 0
    for e in range(flat_edge.shape[0]):
        flat_edge[e] = 1 if edge_deficit[e] <= 0.0 else 0
    for f in range(face_ids.shape[0]):
        if (edge_required[face_edges[f, 0]] < 0.0 and edge_required[face_edges[f, 1]] < 0.0
                and edge_required[face_edges[f, 2]] < 0.0):
            for k in range(interior_local.shape[0]):
                vid = face_ids[f, interior_local[k]]
                dh[vid] = floor[vid]
                fold[vid] = 2
        else:
            for k in range(3):
                flat_edge[face_edges[f, k]] = 0
    for e in range(flat_edge.shape[0]):
        if flat_edge[e]:
            for m in range(1, coarse_edge_ids.shape[1] - 1):
                vid = coarse_edge_ids[e, m]
                dh[vid] = floor[vid]
                fold[vid] = 2
    if widen:
        L = coarse_edge_ids.shape[1] - 1
        for e in range(edge_required.shape[0]):
            fold[coarse_edge_ids[e, 0]] = 2  # coarse vertices: S101 placed them, and S103 skips a
            fold[coarse_edge_ids[e, L]] = 2  # face by its corners' distance, so a fold lifts none
            if edge_required[e] > 0.0:
                for m in range(1, L):
                    fold[coarse_edge_ids[e, m]] = 1
    offset_along_normals(p_smoothed, n_pn, dh, p)
    count = 0
    for e in range(d_edges.shape[0]):  # the first round: every edge
        count = _limit_edge(e, 0, count, p_smoothed, n_pn, dh, floor, ceiling, d_edges, d_max, allowance, moved,
                            stamp, start_h, fold, max_height, p)
    for r in range(1, passes):  # a later round: the edges around a particle moved in the round before
        last_count, count = _keep_changed(moved[(r - 1) % 2], count, dh, start_h), 0
        for k in range(last_count):
            v = moved[(r - 1) % 2, k]
            for m in range(np.uint64(edge_start[v]), np.uint64(edge_start[v + 1])):
                count = _limit_edge(edge_ids[m], r, count, p_smoothed, n_pn, dh, floor, ceiling, d_edges, d_max,
                                    allowance, moved, stamp, start_h, fold, max_height, p)


@helper
def _keep_changed(listed, count, dh, start_h):
    """Compact a round's list of moved particles to those whose height differs from the one
    they had when first moved in that round; returns the new length."""
    kept = 0
    for k in range(count):
        v = listed[k]
        if dh[v] != start_h[v]:
            listed[kept] = v
            kept += 1
    return kept


@helper
def _dist2(p, i, j):
    return (p[i, 0] - p[j, 0]) ** 2 + (p[i, 1] - p[j, 1]) ** 2 + (p[i, 2] - p[j, 2]) ** 2


@helper
def _limit2(p_smoothed, i, j, d_max, allowance):
    """S106 step 5's squared limit on the distance of neighbours i and j: d_max², or (Decision)
    where the reference surface alone parts them beyond d_max, as far as on the edge at rest
    beyond that (d_max² - rest² = allowance d_max²)."""
    lim2 = d_max * d_max
    ref2 = _dist2(p_smoothed, i, j)
    return ref2 + allowance * lim2 if ref2 > lim2 else lim2


@helper
def _limit_edge(e, r, count, p_smoothed, n_pn, dh, floor, ceiling, d_edges, d_max, allowance, moved, stamp, start_h,
                fold, max_height, p):
    """S106 step 5 on detailed edge e in round r: if its ends are farther apart than its limit
    (d_max[e], or on an edge the reference surface stretches beyond it, see apply_constraints),
    the lower one rises if the higher is in a fold and it is not (it joins the fold); then if
    still too far, the higher one comes down towards its floor, if that is not enough the lower
    one goes up, and if neither reaches, both come down by one factor. A particle whose height
    changed is listed once per round in moved[r % 2] (stamp: the round it was listed in; one
    held at its floor by an edge no height can shorten is not, or every later round would
    revisit it for nothing); returns the new length of that list."""
    i, j = np.uint64(d_edges[e, 0]), np.uint64(d_edges[e, 1])  # (unsigned: no wrap-around of a negative index)
    d2 = _dist2(p, i, j)
    if d2 <= d_max[e] * d_max[e]:
        return count  # (most edges: the limit's reference length is not needed)
    lim2 = _limit2(p_smoothed, i, j, d_max[e], allowance)
    if d2 <= lim2:
        return count
    lim = math.sqrt(lim2)
    hi, lo = (i, j) if dh[i] >= dh[j] else (j, i)
    if fold[hi] == 1 and fold[lo] == 0:  # widen the fold: the lower end rises with it
        t = _height_at_distance(p_smoothed, n_pn, lo, p[hi, 0], p[hi, 1], p[hi, 2], lim, dh[lo])[0]
        if t > dh[lo] and dh[lo] < ceiling[lo]:  # (a round may have raised lo beyond the bound)
            count = _move(p_smoothed, n_pn, dh, p, lo, min(t, ceiling[lo]), r, moved, stamp, start_h, count)
            fold[lo] = 1
            if _dist2(p, i, j) <= lim * lim * (1.0 + 1e-9):  # the root, up to rounding
                return count
    # lower hi along its normal: |p_s,hi + t n_hi - p_lo| = lim, the root nearest dh[hi]
    t, exact = _height_at_distance(p_smoothed, n_pn, hi, p[lo, 0], p[lo, 1], p[lo, 2], lim, dh[hi])
    done = exact and t >= floor[hi]
    if not done:
        t = max(floor[hi], min(t, dh[hi]))
    if t != dh[hi]:
        count = _move(p_smoothed, n_pn, dh, p, hi, t, r, moved, stamp, start_h, count)
    if done:
        return count
    t = _height_at_distance(p_smoothed, n_pn, lo, p[hi, 0], p[hi, 1], p[hi, 2], lim, dh[lo])[0]
    if ceiling[lo] < max_height:  # beyond the 3 cm bound if need be, never into a body part above
        t = min(t, ceiling[lo])
    if t > dh[lo]:
        count = _move(p_smoothed, n_pn, dh, p, lo, t, r, moved, stamp, start_h, count)
    if _dist2(p, i, j) > lim * lim * (1.0 + 1e-9):
        # neither end alone reaches: the edge runs across both normals (on a fold's top over a
        # curved limb the raised particles stand farther apart than on the reference surface):
        # both come down together, by one factor on their heights above their floors
        s = _common_factor(p_smoothed, n_pn, dh, floor, hi, lo, lim * lim)
        if s < 1.0:
            count = _move(p_smoothed, n_pn, dh, p, hi, floor[hi] + s * (dh[hi] - floor[hi]), r, moved, stamp,
                          start_h, count)
            count = _move(p_smoothed, n_pn, dh, p, lo, floor[lo] + s * (dh[lo] - floor[lo]), r, moved, stamp,
                          start_h, count)
    return count


@helper
def _common_factor(p_smoothed, n_pn, dh, floor, i, j, lim2):
    """The largest s in [0, 1] with |q_i - q_j|² <= lim2, q_k = p_s,k + (floor_k + s (Δh_k - floor_k)) n_k:
    particles i and j brought down towards their floors by one factor (S106 step 5, Decision);
    1 where even their floors stand farther apart (no common factor helps), or i and j are not
    above their floors."""
    a2 = b1 = c2 = 0.0
    for k in range(3):
        qa = p_smoothed[i, k] + floor[i] * n_pn[i, k] - p_smoothed[j, k] - floor[j] * n_pn[j, k]
        qb = (dh[i] - floor[i]) * n_pn[i, k] - (dh[j] - floor[j]) * n_pn[j, k]
        a2 += qb * qb
        b1 += qa * qb
        c2 += qa * qa
    c2 -= lim2
    if c2 > 0.0 or a2 <= 0.0:
        return 1.0
    # a2 s² + 2 b1 s + c2 = 0, c2 <= 0: one root >= 0
    return min(1.0, max(0.0, (-b1 + math.sqrt(b1 * b1 - a2 * c2)) / a2))


@kernel
def offset_along_normals(p_smoothed, n_pn, dh, p):
    """p_i = p_smoothed,i + Δh_i n_i (S102 step 4, S106 step 6)."""
    for i in range(dh.shape[0]):
        for a in range(3):
            p[i, a] = p_smoothed[i, a] + dh[i] * n_pn[i, a]


@helper
def _set_height(p_smoothed, n_pn, dh, p, i, h):
    dh[i] = h
    for a in range(3):
        p[i, a] = p_smoothed[i, a] + h * n_pn[i, a]


@helper
def _move(p_smoothed, n_pn, dh, p, i, h, r, moved, stamp, start_h, count):
    """Particle i to height h in round r, listed in moved[r % 2] with the height it had
    (start_h) unless it already is this round (stamp); returns the list's new length."""
    if stamp[i] != r:
        stamp[i] = r
        start_h[i] = dh[i]
        moved[r % 2, count] = i
        count += 1
    _set_height(p_smoothed, n_pn, dh, p, i, h)
    return count


@helper
def _height_at_distance(p_smoothed, n_pn, i, qx, qy, qz, lim, current):
    """The height t of particle i along its normal with |p_s,i + t n_i - q| = lim, the root
    nearest `current`, and True; if none exists (q is farther than lim from the whole normal
    line), the height nearest to q (the closest approach), and False."""
    ax = p_smoothed[i, 0] - qx
    ay = p_smoothed[i, 1] - qy
    az = p_smoothed[i, 2] - qz
    an = ax * n_pn[i, 0] + ay * n_pn[i, 1] + az * n_pn[i, 2]
    disc = an * an - (ax * ax + ay * ay + az * az) + lim * lim
    if disc < 0.0:
        return -an, False
    r = math.sqrt(disc)
    t1, t2 = -an - r, -an + r
    return (t1 if abs(t1 - current) < abs(t2 - current) else t2), True


@kernel(fastmath=FAST_ARITHMETIC)
def shading_normals(p, triangles, n_pn, dh, h_normal, n_deform, out):
    """S106 step 7: n_i = normalize(α n_deform + (1 - α) n_pnt), α = min(1, Δh_i / h_normal);
    n_deform: area-weighted normals of the deformed detailed mesh.

    A particle with Δh <= 0 (α = 0) takes n_pnt (unit already), so n_deform is summed only over
    the triangles with a raised corner: every triangle around a raised particle is one."""
    for i in range(p.shape[0]):
        n_deform[i, 0] = 0.0
        n_deform[i, 1] = 0.0
        n_deform[i, 2] = 0.0
    for t in range(triangles.shape[0]):
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        if dh[a] > 0.0 or dh[b] > 0.0 or dh[c] > 0.0:
            add_face_normal(p, triangles, t, n_deform)
    for i in range(p.shape[0]):
        if dh[i] <= 0.0:
            out[i, 0] = n_pn[i, 0]
            out[i, 1] = n_pn[i, 1]
            out[i, 2] = n_pn[i, 2]
            continue
        alpha = 1.0 if dh[i] >= h_normal else dh[i] / h_normal
        m = math.sqrt(n_deform[i, 0] ** 2 + n_deform[i, 1] ** 2 + n_deform[i, 2] ** 2)
        m = alpha / m if m > 0.0 else 0.0
        x = m * n_deform[i, 0] + (1.0 - alpha) * n_pn[i, 0]
        y = m * n_deform[i, 1] + (1.0 - alpha) * n_pn[i, 1]
        z = m * n_deform[i, 2] + (1.0 - alpha) * n_pn[i, 2]
        m = math.sqrt(x * x + y * y + z * z)
        m = 1.0 / m if m > 0.0 else 0.0
        out[i, 0] = x * m
        out[i, 1] = y * m
        out[i, 2] = z * m


# ---------------------------------------------------------------- S106: folds across the compression


def fold_lines(lattice: np.ndarray, level: int) -> tuple[np.ndarray, np.ndarray]:
    """Where each lattice point of a face lies on the fold lines from each of its edges (AB, BC,
    CA) to the opposite corner: the line from the corner through the point meets the edge
    between two of the edge's lattice points. Returns src (3, P, 2) int32, their local indices,
    and weight (3, P, 2) float64: the second one's share, and the taper 1 - depth / L (depth:
    lattice steps from the edge). Only the face's interior points lie on fold lines (taper 0
    elsewhere): a coarse edge's particles keep the heights S106 gave them for its length."""
    L = level
    local = {(int(b), int(c)): k for k, (b, c) in enumerate(lattice)}
    P = len(lattice)
    src = np.zeros((3, P, 2), dtype=np.int32)
    weight = np.zeros((3, P, 2))
    # lattice point m steps along each edge from its first corner (AB from A, BC from B, CA from A)
    edge_point = (lambda m: (m, 0), lambda m: (L - m, m), lambda m: (0, m))
    for k, (b, c) in enumerate(lattice):
        a = L - b - c
        if a == 0 or b == 0 or c == 0:
            continue  # on a coarse edge: its heights are its own wrinkles' (S106), folds run inside faces
        # per edge: the point's depth from it, and its position along it as seen from the opposite corner
        for s, (depth, along, rest) in enumerate(((c, b, a + b), (a, c, b + c), (b, c, a + c))):
            u = L * along / rest
            lo = min(int(math.floor(u + 1e-9)), L - 1)
            src[s, k] = (local[edge_point[s](lo)], local[edge_point[s](lo + 1)])
            weight[s, k] = (u - lo, 1.0 - depth / L)
    return src, weight


def fold_quads(triangles: np.ndarray, faces: np.ndarray, coarse_edges: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The coarse quads' halves, for folds that run straight across a quad. A quad ABCD split
    along a diagonal is two triangles; each has a corner O off the diagonal, the next corner N
    and the previous P in its winding, and O' (the other half's O) across the diagonal. In the
    unit square O = (0, 0), P = (1, 0), N = (0, 1), O' = (1, 1), a lattice point of weights
    (w_O, w_N, w_P) lies at (r, s) = (w_P, w_N). The quad's four edges in that frame: e0 = OP
    (s = 0, along r from O), e1 = NO' (s = 1, along r from N), e2 = ON (r = 0, along s from O),
    e3 = PO' (r = 1, along s from P), and the diagonal e4 = NP (along r from N).

    Returns groups (G, 2) int32: the triangles drawn together (a quad's halves; a triangle
    that is no half of a quad alone, -1 second); corner (T,) int8: each triangle's O (0-2;
    -1 for a lone triangle); edges (T, 5) int32: e0-e4 as coarse edges (rows of coarse_edges,
    sorted pairs); flip (T, 5) uint8: 1 where the edge's parameter runs from its high vertex to
    its low one (the reverse of Tessellation.edge_ids' rows)."""
    tris = np.asarray(triangles)
    edge_of = {(int(a), int(b)): e for e, (a, b) in enumerate(coarse_edges)}
    tri_of = {frozenset(map(int, t)): k for k, t in enumerate(tris)}
    T = len(tris)
    corner = np.full(T, -1, dtype=np.int8)
    edges = np.full((T, 5), -1, dtype=np.int32)
    flip = np.zeros((T, 5), dtype=np.uint8)
    partner = np.full(T, -1, dtype=np.int64)
    for f in np.asarray(faces):
        if len(f) < 4 or f[3] < 0:
            continue
        a, b, c, d = map(int, f)
        for one, two in (((a, b, c), (a, c, d)), ((a, b, d), (b, c, d))):
            k1, k2 = tri_of.get(frozenset(one)), tri_of.get(frozenset(two))
            if k1 is not None and k2 is not None:
                partner[k1], partner[k2] = k2, k1
                break
    for k in np.flatnonzero(partner >= 0):
        other = set(map(int, tris[partner[k]]))
        t = [int(v) for v in tris[k]]
        o = next(i for i in range(3) if t[i] not in other)
        O, N, P = t[o], t[(o + 1) % 3], t[(o + 2) % 3]
        O2 = next(v for v in other if v not in t)
        corner[k] = o
        for j, (u, v) in enumerate(((O, P), (N, O2), (O, N), (P, O2), (N, P))):
            edges[k, j] = edge_of[(min(u, v), max(u, v))]
            flip[k, j] = u > v
    groups = [(k, partner[k]) for k in range(T) if partner[k] < 0 or k < partner[k]]
    return np.array(groups, dtype=np.int32).reshape(-1, 2), corner, edges, flip


def quad_lattice(lattice: np.ndarray, level: int) -> tuple[np.ndarray, np.ndarray]:
    """For each choice of a face's corner O (0, 1, 2; `fold_quads`): the lattice points a fold
    across the quad draws, those off the edges ON and OP (the face's interior and the
    diagonal's inner points), and their (r, s) in lattice steps. Returns points (3, Q) int32
    local indices and rs (3, Q, 2) int32."""
    L = level
    b, c = np.asarray(lattice).T.astype(np.int64)
    w = np.stack([L - b - c, b, c])  # weights of corners 0, 1, 2, in lattice steps
    points, rs = [], []
    for o in range(3):
        r, s = w[(o + 2) % 3], w[(o + 1) % 3]
        k = np.flatnonzero((r > 0) & (s > 0))
        points.append(k)
        rs.append(np.stack([r[k], s[k]], axis=1))
    return np.array(points, dtype=np.int32), np.array(rs, dtype=np.int32)


@helper
def _edge_wrinkles(dh, floor, edge_ids, edge_required, wrinkle, peak):
    """Each compressed coarse edge's wrinkle (heights above the floors) along it, low vertex to
    high, and its largest; zeros on the others."""
    for e in range(edge_ids.shape[0]):
        top = 0.0
        if edge_required[e] > 0.0:
            for m in range(edge_ids.shape[1]):
                v = edge_ids[e, m]
                w = max(dh[v] - floor[v], 0.0)
                wrinkle[e, m] = w
                top = max(top, w)
        else:
            for m in range(edge_ids.shape[1]):
                wrinkle[e, m] = 0.0
        peak[e] = top


@helper
def _draw_fold(dh, floor, ceiling, vid, fold, height, raised, count):
    """Particle vid drawn at floor + fold (never above its ceiling, never below what it has),
    listed in raised the first time it rises above Δh; returns the list's new length."""
    h = min(floor[vid] + fold, ceiling[vid])
    if h > height[vid]:
        if height[vid] <= dh[vid]:
            raised[count] = vid
            count += 1
        height[vid] = h
    return count


@helper
def _corner_folds(dh, floor, ceiling, face_ids, f, s, interior_local, fold_src, fold_weight, height, raised, count):
    """Face f's interior drawn with the fold of its edge s (0: AB, 1: BC, 2: CA) running to the
    opposite corner (`fold_lines`)."""
    for q in range(interior_local.shape[0]):
        k = interior_local[q]
        v0, v1 = face_ids[f, fold_src[s, k, 0]], face_ids[f, fold_src[s, k, 1]]
        w = fold_weight[s, k, 0]
        wrinkle = (1.0 - w) * (dh[v0] - floor[v0]) + w * (dh[v1] - floor[v1])
        if wrinkle > 0.0:
            count = _draw_fold(dh, floor, ceiling, face_ids[f, k], fold_weight[s, k, 1] * wrinkle, height, raised,
                               count)
    return count


@helper
def _quad_folds(dh, floor, ceiling, face_ids, f, wrinkle, peak, corner, quad_edges, quad_flip, quad_points, quad_rs,
                diagonal_too, height, raised, count):
    """Half f of a quad drawn with the folds of the quad's compressed edges straight across it:
    at (r, s), (1 - s) W0(r) + s W1(r) from the edges along r, (1 - r) W2(s) + r W3(s) from
    those along s (`fold_quads`' frame), the larger of the two; the diagonal's particles
    (r + s = L) only where diagonal_too."""
    e0, e1, e2, e3 = quad_edges[f, 0], quad_edges[f, 1], quad_edges[f, 2], quad_edges[f, 3]
    along_r, along_s = peak[e0] > 0.0 or peak[e1] > 0.0, peak[e2] > 0.0 or peak[e3] > 0.0
    if not (along_r or along_s):
        return count
    o = corner[f]
    L = wrinkle.shape[1] - 1
    inv = 1.0 / L
    f0, f1, f2, f3 = quad_flip[f, 0], quad_flip[f, 1], quad_flip[f, 2], quad_flip[f, 3]
    for q in range(quad_points.shape[1]):
        r, s = quad_rs[o, q, 0], quad_rs[o, q, 1]
        if r + s == L and not diagonal_too:
            continue
        fold = 0.0
        if along_r:  # the edges s = 0 and s = 1, at r
            fold = ((L - s) * wrinkle[e0, L - r if f0 else r] + s * wrinkle[e1, L - r if f1 else r]) * inv
        if along_s:
            fold = max(fold, ((L - r) * wrinkle[e2, L - s if f2 else s] + r * wrinkle[e3, L - s if f3 else s]) * inv)
        if fold > 0.0:
            count = _draw_fold(dh, floor, ceiling, face_ids[f, quad_points[o, q]], fold, height, raised, count)
    return count


@helper
def _diagonal_folds(dh, floor, ceiling, face_ids, f, wrinkle, corner, quad_edges, quad_flip, quad_points, quad_rs,
                    height, raised, count):
    """Half f of a quad drawn with the fold of its compressed diagonal NP, compressed along
    itself: straight across it, parallel to the quad's other diagonal OO'. The line through
    (r, s) meets the diagonal t = (r - s + L) / 2 steps from N, (L - r - s) / 2 from it, and
    runs on to the edge ON or OP, min(t, L - t) from it: drawn at the diagonal's wrinkle at t
    (halfway between two of its particles where t is not whole) times the taper 1 - depth /
    min(t, L - t), which is r / t or s / (L - t)."""
    e, flip = quad_edges[f, 4], quad_flip[f, 4]
    o = corner[f]
    L = wrinkle.shape[1] - 1
    for q in range(quad_points.shape[1]):
        r, s = quad_rs[o, q, 0], quad_rs[o, q, 1]
        t2 = r - s + L  # twice t
        if r + s == L:
            continue  # on the diagonal: its own particles
        lo, hi = t2 // 2, (t2 + 1) // 2
        w = 0.5 * (wrinkle[e, L - lo if flip else lo] + wrinkle[e, L - hi if flip else hi])
        if w > 0.0:
            taper = 2.0 * r / t2 if t2 <= L else 2.0 * s / (2 * L - t2)
            count = _draw_fold(dh, floor, ceiling, face_ids[f, quad_points[o, q]], taper * w, height, raised, count)
    return count


@kernel
def fold_across(p_smoothed, n_pn, dh, floor, ceiling, face_ids, face_edges, edge_ids, edge_required, interior_local,
                fold_src, fold_weight, groups, corner, quad_edges, quad_flip, quad_points, quad_rs, d_edges, d_max,
                d_edge_start, d_edge_ids, allowance, wrinkle, peak, raised, height, p):
    """Decision (folds across the compression, S106 step 6 as drawn): S106 raises the particles
    along a compressed coarse edge (ΔLE_required > 0), which gives the edge its length back, but
    its wrinkle stays a bump a few particles wide on that edge, where cloth buckles into a fold
    running across the compression. Each such edge's wrinkle heights above their floors are
    carried across its faces, a particle drawn at least floor + fold, never above its S106
    ceiling (a body part above or beside it), never lower than its Δh:

    * in a coarse quad (`fold_quads`), straight across to the opposite edge, blended linearly
      with that edge's wrinkle at the same place (a quad's two parallel compressed edges join
      into folds that run from one to the other; one alone tapers to nothing at the other), the
      folds of the two directions drawn to the larger; the diagonal's inner particles are drawn
      too, unless the diagonal is compressed itself: then they keep S106's heights, and its
      wrinkle runs straight across it, parallel to the other diagonal (`_diagonal_folds`);
    * in a lone triangle, along the lines towards the opposite corner (`fold_lines`), tapering
      to nothing there.

    The particles on the coarse edges, but for a quad's uncompressed diagonal (so every
    compressed edge's arc length, S105's measure), the coarse vertices and the carried Δh (next
    frame's Δh_last_frame) are unchanged: only the drawn surface takes the folds. Where a fold
    parts two neighbours beyond S106 step 5's limit (d_max, allowance: `apply_constraints`') it
    is taken off them. wrinkle (E, L + 1), peak (E,), raised (2, at least two faces' lattice
    points): scratch; height (N,): the drawn heights, written; p: written where raised."""
    for i in range(dh.shape[0]):
        height[i] = dh[i]
    _edge_wrinkles(dh, floor, edge_ids, edge_required, wrinkle, peak)
    for g in range(groups.shape[0]):
        count = 0
        for h in range(2):
            f = groups[g, h]
            if f < 0:
                continue
            o = corner[f]
            if o < 0:
                for s in range(3):
                    if peak[face_edges[f, s]] > 0.0:  # compressed, with a wrinkle
                        count = _corner_folds(dh, floor, ceiling, face_ids, f, s, interior_local, fold_src,
                                              fold_weight, height, raised[0], count)
                continue
            compressed = edge_required[quad_edges[f, 4]] > 0.0  # the diagonal
            count = _quad_folds(dh, floor, ceiling, face_ids, f, wrinkle, peak, corner, quad_edges, quad_flip,
                                quad_points, quad_rs, not compressed, height, raised[0], count)
            if compressed and peak[quad_edges[f, 4]] > 0.0:
                count = _diagonal_folds(dh, floor, ceiling, face_ids, f, wrinkle, corner, quad_edges, quad_flip,
                                        quad_points, quad_rs, height, raised[0], count)
        if count > 0:
            _settle_fold(p_smoothed, n_pn, dh, raised[0], count, d_edges, d_max, d_edge_start, d_edge_ids, allowance,
                         raised[1], height, p)


@helper
def _too_far(p_smoothed, p, d_max, allowance, e, i, j):
    """Whether neighbours i and j (detailed edge e) are farther apart than S106 step 5's limit
    (d_max or more: `_limit2`)."""
    d2, lim = _dist2(p, i, j), d_max[e]
    return d2 > lim * lim and d2 > _limit2(p_smoothed, i, j, lim, allowance)


@helper
def _settle_fold(p_smoothed, n_pn, dh, raised, count, d_edges, d_max, d_edge_start, d_edge_ids, allowance, back,
                 height, p):
    """The raised particles of one face or quad drawn, and taken back to their Δh where they
    part a neighbour beyond S106 step 5's limit: the folds bound height steps, not distances,
    and a fold beside a steep wrinkle of S106 can part them. A raised particle's neighbours
    lie in its face or quad (those on its outer edges are never raised). Every raised
    particle's edges are checked once; after that only the edges of those taken back (listed
    in back), until none is left too long (each particle goes back once, so this ends; an edge
    left too long was so before the folds)."""
    for q in range(count):
        vid = raised[q]
        for a in range(3):
            p[vid, a] = p_smoothed[vid, a] + height[vid] * n_pn[vid, a]
    n_back = 0
    for q in range(count):
        i = np.uint64(raised[q])  # (unsigned: no wrap-around of a negative index)
        if height[i] <= dh[i]:
            continue
        for k in range(np.uint64(d_edge_start[i]), np.uint64(d_edge_start[i + np.uint64(1)])):
            e = np.uint64(d_edge_ids[k])
            j = np.uint64(d_edges[e, 0]) + np.uint64(d_edges[e, 1]) - i
            if not _too_far(p_smoothed, p, d_max, allowance, e, i, j):
                continue
            _set_height(p_smoothed, n_pn, height, p, i, dh[i])
            back[n_back] = i
            n_back += 1
            if height[j] > dh[j]:
                _set_height(p_smoothed, n_pn, height, p, j, dh[j])
                back[n_back] = j
                n_back += 1
            break
    q = 0
    while q < n_back:  # a particle taken back moved away from its raised neighbours
        c = np.uint64(back[q])
        q += 1
        for k in range(np.uint64(d_edge_start[c]), np.uint64(d_edge_start[c + np.uint64(1)])):
            e = np.uint64(d_edge_ids[k])
            j = np.uint64(d_edges[e, 0]) + np.uint64(d_edges[e, 1]) - c
            if height[j] <= dh[j] or not _too_far(p_smoothed, p, d_max, allowance, e, c, j):
                continue
            _set_height(p_smoothed, n_pn, height, p, j, dh[j])
            back[n_back] = j
            n_back += 1


@kernel
def penetration_floor(dh, sd, facing, other, dh_pen, clearance, untested_reach, max_height, floor, ceiling,
                      body_floor):
    """The lowest and highest heights S106 may give each particle without undoing S103.

    An untested particle: from the reference surface (0) to max_height. A tested one whose
    body lies below it (facing >= 0) may come down by its distance beyond the clearance, never
    below 0; Decision: one whose body lies above it (a body part on the cloth's outer side,
    facing < 0) may rise only by that distance, and comes back up to the reference surface as
    far as that allows (where S103 lowered it, it stays). Decision: where S103 measured
    another body part near the particle (other: its distance, before S103 moved it by
    dh_pen), the particle may rise by no more than that distance beyond the clearance either:
    in the gap between the torso and an arm resting on the cloth a wrinkle would rise into
    the arm.

    body_floor: the lowest height the body allows, below the reference surface too (for the
    layering's press, cloth.layers): a tested particle whose body lies below it, its distance
    beyond the clearance down from its height (every body point lies at least that distance
    away, so no point that near comes closer than the clearance); an untested one,
    untested_reach down (none of its parents came within S103's contact margin); one with a
    body part above it, its floor."""
    for i in range(dh.shape[0]):
        if sd[i] == UNTESTED:
            floor[i] = 0.0
            ceiling[i] = max_height
            body_floor[i] = dh[i] - untested_reach
        elif facing[i] >= 0.0:
            body_floor[i] = dh[i] - max(0.0, sd[i] - clearance)
            floor[i] = max(0.0, body_floor[i])
            ceiling[i] = max_height
            gap = other[i] - abs(dh_pen[i]) - clearance  # a ball this wide around p is outside the other parts
            if gap < max_height:
                ceiling[i] = max(floor[i], min(max_height, dh[i] + max(0.0, gap)))
        else:
            ceiling[i] = min(max_height, dh[i] + max(0.0, sd[i] - clearance))
            floor[i] = min(0.0, ceiling[i])
            body_floor[i] = floor[i]
