"""Detailed particles caught where two body parts overlap (S103, Decision: out of a crease).

S103 moves a detailed particle along its normal n_i only. In a crease, where linear-blend
skinning pushes one body part into another (the thigh into the belly in a squat or a stride,
the upper arm into the chest), the cloth's normal runs along the body and no move along it
gets out (thirty-third session: of the walk's jeans misses, 1,306 of about 1,500 had no way
out along ±n_i within 5 cm). And S103's distance, the nearest surface found by its walks,
reads "outside" there: the nearest sheet is the buried part's, in front of the particle,
while the particle is behind the other part's surface (forty-sixth session: four in five of
the walk's misses).

So after S106, each particle S103 found inside, or near another body part (its walk in that
part ended within `PART_NEAR`, `part_face`), is measured again at its final position from
the two faces S103's walks ended on, one per part. It is taken as inside when it is behind
either surface, within `CREASE_DEPTH`. (Behind one and in front of the other, it was inside
by the body's winding number in 912 of 1,053 cases on the walk's casual outfit, every third
frame of 150: the surface in front of it is the other part's, buried in the first.) An
inside particle goes to the nearest point `clearance` in front of both surfaces' tangent
planes: near a crease the body's outside is the intersection of the two parts' outsides.
Where the parts overlap (the planes face each other across less than nothing) there is no
such point, and the particle stays. Where two surfaces face each other across a gap narrower
than two clearances (an arm by the torso), the particle goes to the gap's middle: the nearest
point two clearances wide lies along the gap, centimetres away for a fraction of a millimetre
(forty-seventh session: those moves left about half the long edges around moved particles on
the walk's casual outfit). Then the neighbours of each particle moved out of a crease (its
walks ended in two body parts) are measured the same way from those two faces, and moved if
inside, and theirs in turn: S103 tested few of them (the walk, first 250 frames: vertex-frames
deeper than 1 mm T-shirt 1,835 → 1,101, jeans 6,790 → 4,618, blouse 4,850 → 4,082, skirt 2,825
→ 1,473, for edge-frames too long 9,015 → 9,686, 41,010 → 45,202, 63,017 → 63,850, 19,459 →
19,833: a moved particle's edges to neighbours left behind). Spreading from a particle with one
surface as well moved the blouse's outside particles: 2,507 of the 3,216 it moved were outside.
Its height Δh is unchanged (the next frame starts from the reference surface again); only the
drawn position leaves the normal.

Decision (never from outside the body as a whole, fifty-sixth session): a particle the planes read
as inside is asked the body's winding number first (`cloth.winding`: the faces `BodyMesh.wound_faces`
names, the clothed ones and the hands, their holes capped), and where that is 0 it stays. A
tangent plane at the closest point of a skin buried in another part, or of a fold of the skinned
skin, can stand in front of an outside particle, and the way out of it led in (the walk's crouch,
jeans, frames 150-230: 180 of the 972 vertex-frames deeper than 1 mm at the end had been outside
before such a move; 17 with the check). Where a walk ended on a face the winding surface lacks
(the head) it cannot tell, and the planes decide alone. Until the fifty-ninth session that surface
was the clothed faces alone, capped at the wrists: a sleeve's particle inside the hand, whose walk
ended on the forearm by the wrist, read as outside the body and stayed in the hand (the walk's
blouse, vertex-frames deeper than 1 mm 1,421 → 1,202 with the hands counted).

Decision (out along the normal by the winding number, fifty-ninth session; `out_along_normals`):
in a crease S103's walks read the nearer sheet, a skin buried in the other part, and call a
particle outside that the body as a whole has inside (the walk's casual outfit: 1,508 of its
1,656 vertex-frames deeper than 1 mm were outside by S103's own distance), and the tangent
planes above read it the same way. So a particle near another body part whose normal leans off
the body's, or one S103 found inside, is asked the winding number at its final position, and
one inside goes along ±n_i to where the body ends nearest (within 1 cm), the clearance beyond.
Where neither way ends within 1 cm (n_i along the skin, or deep in a limb that the coarse face
cuts across), it goes out through the nearest body face instead, or on along the line to it,
within 6 cm (Decision, sixty-third session; 3 cm until the sixty-sixth, when the walk's elegant
blouse had one or two particles a frame 32-35 mm inside the left arm at the armpit, over frames
286-496, half its vertex-frames deeper than 1 mm; 4 cm until the seventy-second, when the run's
skirt and blouse had particles 40-52 mm inside the body in its first 25 frames). Its Δh is
unchanged, as above. The neighbours of each particle found inside are asked too, and theirs while
they are inside, and a particle found inside is asked again the next frame (Decisions, sixty-fourth
session: the spread and the memory): most of the walk's vertex-frames left deeper than 1 mm lay in
patches around particles the rule above asked, read outside by S103 with their normals along the
body's. Where neither the normals nor the nearest face lead out, the nearest way out along the axes
and the diagonals (EXIT_DIRECTIONS), within 3 cm (1 cm until the seventieth session), is taken
(Decision, sixty-fifth session: the around): over the walk's first 250 frames, 125 of the casual
jeans' 174 vertex-frames left deeper than 1 mm were inside by the winding number with neither way
out, most in the right thigh in the crouch, beside the belly's skin buried in it (the nearest face,
which leads into the belly), and half had a way out within 1 cm along one of 26 directions. Since
the sixty-seventh session "near another body part" is within 3 cm (EXIT_NEAR), and a particle S103
lifted that S106 lowered again by more than the clearance is asked too (Decision: lowered after a
lift): S103's walks misread both kinds as well outside. Since the seventy-second session the coarse
vertices are asked too, moved along ±n_i or (eighty-ninth session) the way around within
EXIT_REACH, and so is a particle S106 lowered to within EXIT_LOWERED_NEAR of the body by S103's
reading (Decisions, `out_along_normals`, `lowered_after_lift`).
"""

from __future__ import annotations

import math

import numpy as np

from .collision import DIAGONALS, face_walk_distance, march_exit, outside_at, tree_nearest_face
from .jit import helper, kernel
from .winding import winding_number

CREASE_DEPTH = 0.03  # m: deeper behind a surface than this, the walk's face is as likely a limb's far side: left
FACING = -0.5  # n_a . n_b below this: the two surfaces face each other (more than 120° apart)
# m: a way out farther than this is not taken (the particle stays where S106 put it). A lower cap
# trades depth for fewer long edges, differently per garment (forty-seventh session, walk, first
# 250 frames: at 1 cm the casual outfit's edges too long fall by a fifth, the blouse's vertex-frames
# deeper than 1 mm double; docs/history.md)
CREASE_MOVE = 0.03
# m: `out_along_normals` looks at a particle whose walks found another body part this near (S103's `other`)
# where its normal leans off the body's by more than EXIT_FACING (S103's `facing`, n_i . n_body, below it),
# and moves it at most EXIT_REACH along ±n_i (EXIT_NEAR 1 cm until the sixty-seventh session: on the run the
# silk blouse's biggest class of vertex-frames deeper than 1 mm, 106 of 148, were read 9-35 mm outside by S103,
# another part 1-4 cm away, and never asked; at 3 cm 59 are left, for 0.02-0.03 ms a garment-frame)
EXIT_NEAR = 0.03
EXIT_FACING = 0.9
# m: another body part this near (S103's `other`) and `out_along_normals` asks the particle whatever its normal's
# facing (sixty-ninth session: most of the walk's vertex-frames left deeper than 1 mm had been read 6-10 mm
# outside by S103 from a face of a sheet buried in the same part, normal along the body's, another part within
# 1 cm; asking them took the casual outfit's 175 to 81 and the elegant's 183 to 143, for 0.5 ms a garment-frame).
# 2 cm since the eighty-ninth session: 39 of the jumping jacks' and walk's vertex-frames left deeper than 1 mm had
# been read outside with another part 10-25 mm away and the normal along the body's, never asked (the knees and
# hips in the crouches); at 2 cm the jumping jacks' 123 became 88 (three outfits), for about 0.03 ms a
# garment-frame (the walk's casual outfit)
EXIT_NEAR_ALONG = 0.02
# n_i . n_body below this and `out_along_normals` asks the particle wherever the other parts are (seventy-first
# session: the walk's blouse left 58 vertex-frames deeper than 1 mm that S103 had read 3-40 mm outside, no other
# part found, many with the normal facing into the body)
EXIT_TURNED = 0.0
EXIT_REACH = 0.01
# m: `lowered_after_lift` names a particle S106 lowered to less than this from the body by S103's reading
# (seventy-second session: S103's walks read the blouse's such particles 2-3 mm farther out than they were)
EXIT_LOWERED_NEAR = 0.002
# m: where no way out along ±n_i lies within EXIT_REACH, `out_along_normals` takes the way out through the
# nearest body face, or on along the line to it, within this (3 cm, CREASE_MOVE, until the sixty-sixth session:
# the walk's blouse left 32-35 mm inside the arm at the armpit, under a coarse face that cuts across it; 4 cm until
# the seventy-second: the run's skirt and blouse left particles 40-52 mm inside the body in its first 25 frames,
# under coarse faces that cut across it, 31 of the run's 59 vertex-frames deeper than 1 mm)
EXIT_FACE_REACH = 0.06
# m: how far `out_along_normals` looks along each of EXIT_DIRECTIONS (EXIT_REACH until the seventieth session:
# most of the walk's jeans vertex-frames left deeper than 1 mm were 5-20 mm deep in a crease between the thighs,
# the way out 1-3 cm away)
EXIT_AROUND_REACH = 0.03
# where neither way ends within reach, `out_along_normals` looks for the way out along each of these (unit: the
# axes, the diagonals of the cube's edges and its corners), within EXIT_AROUND_REACH, and takes the nearest
EXIT_DIRECTIONS = np.ascontiguousarray(np.concatenate([np.eye(3), -np.eye(3), DIAGONALS]))
NO_DIRECTIONS = np.zeros((0, 3))


@helper
def _plane_gap(px, py, pz, qx, qy, qz, nx, ny, nz, clearance):
    """How far p must move along n to stand `clearance` in front of the plane (q, n); <= 0: it does."""
    return clearance - ((px - qx) * nx + (py - qy) * ny + (pz - qz) * nz)


@helper
def out_of_two_planes(px, py, pz, a, b, clearance):
    """The smallest move (dx, dy, dz) that puts p `clearance` in front of both planes a and b
    (each (qx, qy, qz, nx, ny, nz), unit normals): the projection onto the intersection of
    their two half-spaces, and True; False where there is none (the planes face each other).
    Decision: where the planes face each other (n_a . n_b < FACING) across a gap at p narrower
    than two clearances, the clearance is what the gap leaves: p goes to the gap's middle.
    A plane with a zero normal is absent."""
    ga = gb = -1.0
    has_a = a[3] * a[3] + a[4] * a[4] + a[5] * a[5] > 0.0
    has_b = b[3] * b[3] + b[4] * b[4] + b[5] * b[5] > 0.0
    if has_a:
        ga = _plane_gap(px, py, pz, a[0], a[1], a[2], a[3], a[4], a[5], clearance)
    if has_b:
        gb = _plane_gap(px, py, pz, b[0], b[1], b[2], b[3], b[4], b[5], clearance)
    if ga <= 0.0 and gb <= 0.0:
        return 0.0, 0.0, 0.0, True
    k = a[3] * b[3] + a[4] * b[4] + a[5] * b[5]
    if has_a and has_b and k < FACING and ga + gb > 0.0:
        # the surfaces face each other across a gap narrower than two clearances at p (an arm by the
        # torso): to its middle, not to the far place where the gap widens to two clearances (that
        # move runs along the gap, centimetres for a fraction of a millimetre, and left the moved
        # particle's edges long). Where they overlap at p (no gap), the way out is where the overlap
        # ends, as below.
        c = clearance - 0.5 * (ga + gb)
        if c > 0.0:
            ga -= clearance - c
            gb -= clearance - c
            if ga <= 0.0 and gb <= 0.0:
                return 0.0, 0.0, 0.0, True
    # one plane's step alone, if it also clears the other (along n_a, b's gap falls by k ga)
    if ga > 0.0 and gb - k * ga <= 0.0:
        return ga * a[3], ga * a[4], ga * a[5], True
    if gb > 0.0 and ga - k * gb <= 0.0:
        return gb * b[3], gb * b[4], gb * b[5], True
    # both on their planes: move = α n_a + β n_b with α + k β = ga, k α + β = gb
    det = 1.0 - k * k
    if det < 1e-12:
        return 0.0, 0.0, 0.0, False  # (parallel planes are cleared by one step above; these face each other)
    alpha = (ga - k * gb) / det
    beta = (gb - k * ga) / det
    return (alpha * a[3] + beta * b[3], alpha * a[4] + beta * b[4], alpha * a[5] + beta * b[5],
            alpha >= 0.0 and beta >= 0.0)


@helper
def _out_of_crease(p, i, fa, fb, body_x, tris, tri_nbrs, tri_start, tri_ids, nbr_start, nbr_ids, regions, face_n,
                   q, plane_a, plane_b, clearance, rounds, wound, wfaces, wlo, wstart, wids, wspan, wextent, whole):
    """Measure particle i from body faces fa and fb (fb -1: none) and move it out of the body
    if it is inside, up to `rounds` times (`leave_creases`); whole: not if it is outside the
    body as a whole (its winding number over wfaces, the grid wlo ... wextent, is 0) while the
    faces its walks ended on are among those wfaces has (`wound`). Returns (moved, fa, fb):
    the faces the walks ended on (fb -1 where its walk came back to fa's part)."""
    p0, p1, p2 = p[i, 0], p[i, 1], p[i, 2]
    for r in range(rounds):
        px, py, pz = p[i, 0], p[i, 1], p[i, 2]
        da, nx, ny, nz, qx, qy, qz, fa = face_walk_distance(px, py, pz, body_x, tris, tri_nbrs, tri_start,
                                                             tri_ids, nbr_start, nbr_ids, regions, fa, face_n, q)
        plane_a[0], plane_a[1], plane_a[2], plane_a[3], plane_a[4], plane_a[5] = qx, qy, qz, nx, ny, nz
        db = np.inf
        for a in range(6):
            plane_b[a] = 0.0
        if fb >= 0:
            db, nx, ny, nz, qx, qy, qz, fb = face_walk_distance(px, py, pz, body_x, tris, tri_nbrs, tri_start,
                                                                 tri_ids, nbr_start, nbr_ids, regions, fb, face_n, q)
            if regions[tris[fb, 0]] == regions[tris[fa, 0]]:
                db, fb = np.inf, -1  # it came back to the first walk's part: one surface
            else:
                plane_b[0], plane_b[1], plane_b[2], plane_b[3], plane_b[4], plane_b[5] = qx, qy, qz, nx, ny, nz
        if not (-CREASE_DEPTH < min(da, db) < 0.0):
            break  # outside both (S103's clearance is its own), or too deep to trust
        if whole and r == 0 and wound[fa] and (fb < 0 or wound[fb]) and \
                winding_number(px, py, pz, body_x, wfaces, wlo, wstart, wids, wspan, wextent) == 0:
            break  # behind a tangent plane but outside the body: the way out would lead in (module)
        mx, my, mz, ok = out_of_two_planes(px, py, pz, plane_a, plane_b, clearance)
        if not ok or mx * mx + my * my + mz * mz > CREASE_MOVE * CREASE_MOVE:
            break
        p[i, 0] = px + mx
        p[i, 1] = py + my
        p[i, 2] = pz + mz
    return p[i, 0] != p0 or p[i, 1] != p1 or p[i, 2] != p2, fa, fb


@helper
def _list_move(p, i, p0, p1, p2, fa, fb, k, ids, moves, faces):
    ids[k] = i
    moves[k, 0], moves[k, 1], moves[k, 2] = p[i, 0] - p0, p[i, 1] - p1, p[i, 2] - p2
    faces[k, 0], faces[k, 1] = fa, fb
    return k + 1


@kernel
def leave_creases(p, sd, body_face, part_face, body_x, tris, tri_nbrs, tri_start, tri_ids, nbr_start, nbr_ids, regions,
                  face_n, q, plane_a, plane_b, clearance, rounds, first, spread, d_edges, edge_start, edge_ids, seen,
                  ids, moves, faces, wound, wfaces, wlo, wstart, wids, wspan, wextent, whole):
    """Move each detailed particle that is inside the body near a crease out of it (module
    docstring). p: final positions, moved in place; sd, body_face, part_face: S103's (its
    signed distances, UNTESTED = inf where it did not test, and the faces its walks ended on);
    plane_a, plane_b (6,): scratch. Each particle is measured and moved up to `rounds` times
    (a curved crease: the planes of the first closest points are an approximation). Particles
    before `first` (the coarse vertices, placed by S101) are left alone.
    spread: a moved particle's detailed neighbours (d_edges; edge_start, edge_ids: CSR of each
    particle's edges) are measured too, from the faces its walks ended on in two body parts,
    and so on from each one moved: S103 did not test many of them, and one left inside beside a
    moved particle left their edge long. seen (N,) uint8: scratch.
    whole: a particle outside the body as a whole is not moved, where its walks ended on faces
    the winding number counts (wound: `BodyMesh.wound_faces`; wfaces: `BodyMesh.winding_faces`;
    wlo ... wextent: the pose's `WindingGrid.arrays()`); False: the planes alone decide.
    Returns the number of particles moved, k; ids[:k] (int32) are they, moves[:k] (k, 3) how
    far each went, faces[:k] (k, 2) int32 the faces its walks ended on."""
    for i in range(p.shape[0]):
        seen[i] = 1 if i < first else 0
    moved = 0
    for i in range(first, p.shape[0]):
        if body_face[i] < 0 or not (part_face[i] >= 0 or sd[i] < 0.0):
            continue
        seen[i] = 1
        p0, p1, p2 = p[i, 0], p[i, 1], p[i, 2]
        out, fa, fb = _out_of_crease(p, i, body_face[i], part_face[i], body_x, tris, tri_nbrs, tri_start, tri_ids,
                                     nbr_start, nbr_ids, regions, face_n, q, plane_a, plane_b, clearance, rounds,
                                     wound, wfaces, wlo, wstart, wids, wspan, wextent, whole)
        if out:
            moved = _list_move(p, i, p0, p1, p2, fa, fb, moved, ids, moves, faces)
    if not spread:
        return moved
    k = 0
    while k < moved:  # (the list grows as neighbours are moved: a flood over the inside particles)
        i = ids[k]
        if faces[k, 1] < 0:  # one surface, no crease: a neighbour's walk from it misread the outside
            k += 1
            continue
        for m in range(edge_start[i], edge_start[i + 1]):
            e = edge_ids[m]
            j = d_edges[e, 0] + d_edges[e, 1] - i
            if seen[j]:
                continue
            seen[j] = 1
            p0, p1, p2 = p[j, 0], p[j, 1], p[j, 2]
            out, fa, fb = _out_of_crease(p, j, faces[k, 0], faces[k, 1], body_x, tris, tri_nbrs, tri_start, tri_ids,
                                         nbr_start, nbr_ids, regions, face_n, q, plane_a, plane_b, clearance, rounds,
                                         wound, wfaces, wlo, wstart, wids, wspan, wextent, whole)
            if out:
                moved = _list_move(p, j, p0, p1, p2, fa, fb, moved, ids, moves, faces)
        k += 1
    return moved


@helper
def _out_through_nearest_face(px, py, pz, start, reach, clearance, body_x, wfaces, wlo, wstart, wids, wspan, wextent,
                              tris, face_n, box, child, tfirst, count, order, parent, leaf, stack, q):
    """`out_along_normals`' way out through the nearest face p is behind (or less than the
    clearance in front of), within reach: (how far, unit direction); inf where there is none.
    To the face's closest point and the clearance beyond if that is outside the body as a
    whole; else (a face buried in another part) on along the same line to where the body ends,
    by winding numbers, the clearance beyond if that is outside too. start: a body face near p,
    where the tree's search starts (-1: at its root; the same answer)."""
    f, d2, _, _ = tree_nearest_face(px, py, pz, body_x, tris, face_n, box, child, tfirst, count, order, parent, leaf,
                                    start, -1, stack, reach * reach, clearance, q)
    if f < 0:
        return np.inf, 0.0, 0.0, 0.0
    d = math.sqrt(d2)
    if d > 1e-9:
        ux, uy, uz = (q[0] - px) / d, (q[1] - py) / d, (q[2] - pz) / d
    else:  # on the face: out along its normal
        ux, uy, uz = face_n[f, 0], face_n[f, 1], face_n[f, 2]
    if d + clearance <= reach and outside_at(px, py, pz, ux, uy, uz, d + clearance, body_x, wfaces, wlo, wstart, wids,
                                             wspan, wextent):
        return d + clearance, ux, uy, uz
    t = march_exit(px, py, pz, ux, uy, uz, reach, body_x, wfaces, wlo, wstart, wids, wspan, wextent)
    if t == np.inf:
        return np.inf, 0.0, 0.0, 0.0
    return _beyond_exit(px, py, pz, ux, uy, uz, t, clearance, reach, body_x, wfaces, wlo, wstart, wids, wspan,
                        wextent), ux, uy, uz


@helper
def _beyond_exit(px, py, pz, ux, uy, uz, t, clearance, limit, body_x, wfaces, wlo, wstart, wids, wspan, wextent):
    """How far along u a particle whose way out along u ends t from p goes: the clearance beyond
    the exit, if that is outside too and within limit, else the exit itself."""
    if t + clearance <= limit and outside_at(px, py, pz, ux, uy, uz, t + clearance, body_x, wfaces, wlo, wstart, wids,
                                             wspan, wextent):
        return t + clearance
    return t


@helper
def _exit_body(p, n, i, reach, clearance, body_x, wfaces, wlo, wstart, wids, wspan, wextent, face_reach, tris, face_n,
               box, child, tfirst, count, order, parent, leaf, stack, q, start_face, ids, moves, moved, around,
               around_reach):
    """`out_along_normals` for particle i: if the body's winding number puts it inside, out along
    ±n_i, else through the nearest face (within reach, face_reach), else along the nearest way out
    among the directions `around` (within around_reach). Returns (inside, the new length of the moved list
    ids, moves)."""
    px, py, pz = p[i, 0], p[i, 1], p[i, 2]
    if winding_number(px, py, pz, body_x, wfaces, wlo, wstart, wids, wspan, wextent) <= 0:
        return False, moved
    best, sense = np.inf, 0.0
    for sgn in (1.0, -1.0):
        t = march_exit(px, py, pz, sgn * n[i, 0], sgn * n[i, 1], sgn * n[i, 2], min(best, reach), body_x, wfaces,
                       wlo, wstart, wids, wspan, wextent)
        if t < best:
            best, sense = t, sgn
    ux, uy, uz = sense * n[i, 0], sense * n[i, 1], sense * n[i, 2]
    t = np.inf
    if best < np.inf:
        t = _beyond_exit(px, py, pz, ux, uy, uz, best, clearance, np.inf, body_x, wfaces, wlo, wstart, wids, wspan,
                         wextent)
    elif face_reach > 0.0:
        t, ux, uy, uz = _out_through_nearest_face(px, py, pz, start_face, face_reach, clearance, body_x, wfaces, wlo,
                                                  wstart, wids, wspan, wextent, tris, face_n, box, child, tfirst,
                                                  count, order, parent, leaf, stack, q)
    if t == np.inf and around.shape[0] > 0:
        for d in range(around.shape[0]):
            s = march_exit(px, py, pz, around[d, 0], around[d, 1], around[d, 2], min(best, around_reach), body_x,
                           wfaces, wlo, wstart, wids, wspan, wextent)
            if s < best:
                best, ux, uy, uz = s, around[d, 0], around[d, 1], around[d, 2]
        if best < np.inf:
            t = _beyond_exit(px, py, pz, ux, uy, uz, best, clearance, np.inf, body_x, wfaces, wlo, wstart, wids, wspan,
                             wextent)
    if t == np.inf:
        return True, moved
    moves[moved, 0], moves[moved, 1], moves[moved, 2] = t * ux, t * uy, t * uz
    for a in range(3):
        p[i, a] += moves[moved, a]
    ids[moved] = i
    return True, moved + 1


@kernel
def out_along_normals(p, n, sd, other, facing, behind, lowered, first, near, lean, near_along, turned, reach, clearance,
                      body_x, wfaces, wlo, wstart, wids, wspan, wextent, ids, moves, face_reach, tris, face_n, box,
                      child, tfirst, count, order, parent, leaf, stack, q, body_face, spread, d_edges, edge_start,
                      edge_ids, seen, inside, was_inside, memory, around, around_reach, coarse):
    """Decision (out along the normal by the winding number, fifty-ninth session): a detailed
    particle S103 tested near another body part (its walks found one within `near`, `other`) with
    its normal leaning off the body's (`facing` below `lean`), or found inside, or (sixtieth
    session) found behind another part's surface by its walk there (`behind`, though a nearer
    surface called it outside), that the body's winding number puts inside at its final
    position goes out along ±n_i to where the body ends
    nearest, `clearance` beyond it (found by winding numbers, `collision.march_exit`, within
    `reach`; where the point `clearance` beyond is inside again, the exit itself). In a crease
    S103's walks read the nearer sheet, a skin buried in the other part, and call the particle
    outside (the walk's casual outfit: 1,508 of its 1,656 vertex-frames deeper than 1 mm), and
    the crease planes read it the same way; the winding number is not misled (module).
    Decision (through the nearest face, sixty-third session): where neither way along ±n_i ends
    within `reach` (n_i runs along the skin, or the particle lies deep in a limb that its coarse
    face cuts across, as under the arm of a loose sleeve), the particle goes out through the
    nearest body face it is behind (the face tree's, among the clothed faces), to that face's
    closest point and `clearance` beyond, if that is outside the body as a whole; else on along
    the line to it, to where the body ends (a face buried in another part); either within
    `face_reach` (0: not at all). Of the walk's vertex-frames deeper than 1 mm that this rule
    asked and left inside, most had no way out along ±n_i within reach (sixty-third session).
    Decision (spread, sixty-fourth session): the detailed neighbours of each particle found
    inside are asked too, and theirs in turn while they are inside (spread; d_edges, edge_start,
    edge_ids: the detailed edges and each particle's, CSR): of the walk's vertex-frames left
    deeper than 1 mm, most had been read outside by S103 near another part with the normal
    along the body's, and were never asked, in a patch around particles that were.
    Decision (memory, sixty-fourth session): a particle found inside the frame before is asked
    again (was_inside (N,) uint8, carried between frames: written with this frame's, memory
    False: not read), whatever S103 reads of it: its Δh is unchanged, so it starts the frame where
    it was before the move out, and the readings that named it flicker from frame to frame.
    Decision (around, sixty-fifth session): where neither way along ±n_i nor the nearest face leads out, the
    particle goes out along the nearest way among the directions `around` (EXIT_DIRECTIONS; (0, 3): none),
    within `around_reach`: in the walk's crouch, the jeans' particles inside the thigh beside the belly's skin
    buried in it, whose nearest face leads into the belly, and n_i along the thigh. Its reach is
    EXIT_AROUND_REACH (3 cm; EXIT_REACH, 1 cm, until the seventieth session): the walk's jeans were left
    5-20 mm deep in the crease between the thighs as they pass, the crease's mouth 1-3 cm away.
    Decision (lowered after a lift, sixty-seventh session): a particle S103 lifted this frame that
    S106 then lowered by more than the clearance (`lowered`, from `lowered_after_lift`) is asked
    too: after a lift S103's walk can stop on a face the particle projects into while a nearer
    surface lies beside it, and read it farther out than it is (the run's silk blouse: 12-27 mm
    where it was 8-13 mm), and S106's floor follows that reading back into the body.
    Decision (another part within a centimetre, sixty-ninth session): a particle S103 tested with
    another part nearer than `near_along` is asked whatever its normal's facing: at the walk's
    hip S103's walk stops on a face of a sheet folded into the same part (the thigh's skin
    buried under the belly's) and reads the particle 6-10 mm outside, its normal along that face's,
    where it is 1-6 mm inside; the other part's nearness is the sign of such a fold. Within 2 cm
    since the eighty-ninth session (EXIT_NEAR_ALONG; 1 cm before): in the jumping jacks' crouches
    most of the vertex-frames left deeper than 1 mm that no rule asked had another part 10-25 mm
    away (knees, hips).
    Decision (turned in, seventy-first session): a particle S103 tested whose normal faces into the
    body (`facing` below `turned`) is asked wherever the other parts are: the walk's blouse left 58
    vertex-frames deeper than 1 mm that S103 had read 3-40 mm outside with no other part found, many
    with n_i turned against the skin's, a sign the walk stopped on a face the particle is behind.
    p: final positions, moved in place; n (N, 3): the normals n_i; sd, other, facing, behind: S103's
    (sd UNTESTED = inf where it did not test); lowered (N,) uint8: 1 where a particle is to be asked
    whatever S103 read; particles before `first` (the coarse vertices) are left alone, or with
    `coarse` asked as the others are but moved only along ±n_i or the way around within `reach`
    (Decision, the coarse vertices, seventy-second session: S101 keeps the coarse particle itself
    out of the body, but the lift S103 gave it along n_i, carried from frame to frame, can take it
    into another part: on the walk's leggings 18 of 26 vertex-frames deeper than 1 mm were coarse
    vertices 4-12 mm above their particle, between the thighs, S103 reading 2-5 mm outside them by
    the other thigh's buried skin. Along ±n_i it stays on its normal, where S102 and S103 put it.
    Eighty-ninth session: where no way along ±n_i leads out, the way around within `reach` too, never
    through the nearest face: in the jumping jacks' armpits, hips and knees most coarse vertices
    left deeper than 1 mm had the way around 1-7 mm away, their normals along the skin).
    wfaces, wlo ... wextent: the pose's winding grid; tris, face_n: the body's faces and this
    pose's face normals; box ... leaf: the pose's `FaceTree.arrays()` (tfirst its `first`),
    stack (FACE_TREE_STACK,) int32 and q (3,): scratch; body_face: the face each particle's S103
    walk ended on (-1: none), where the tree's search for the nearest face starts; seen (N,) uint8,
    inside (N,) int32: scratch (the particles asked, and those found inside). Returns the number
    of particles moved, k; ids[:k] (int32) are they, moves[:k] (k, 3) how far each went."""
    moved = 0
    n_inside = 0
    coarse_around = min(around_reach, reach)  # (a coarse vertex's way around looks no farther than ±n_i)
    if spread:
        for i in range(p.shape[0]):
            seen[i] = 0
    for i in range(0 if coarse else first, p.shape[0]):
        # (a winding number for every particle near another part was 0.7 ms a garment-frame on the walk's
        # casual outfit, 2,000 particles; those leaning off the body are 250 of them, and two thirds of the
        # ones inside)
        if not ((memory and was_inside[i]) or lowered[i]
                or (sd[i] != np.inf and ((other[i] < near and facing[i] < lean) or other[i] < near_along
                                         or facing[i] < turned or sd[i] < 0.0 or behind[i]))):
            continue
        seen[i] = 1
        off = i >= first  # (a coarse vertex: along ±n_i, or the way around within reach)
        found, moved = _exit_body(p, n, i, reach, clearance, body_x, wfaces, wlo, wstart, wids, wspan, wextent,
                                  face_reach if off else 0.0, tris, face_n, box, child, tfirst, count, order, parent,
                                  leaf, stack, q, body_face[i], ids, moves, moved, around,
                                  around_reach if off else coarse_around)
        if found:
            inside[n_inside] = i
            n_inside += 1
    k = 0
    while spread and k < n_inside:  # (the list grows as neighbours are found inside: a flood over them)
        i = inside[k]
        for m in range(edge_start[i], edge_start[i + 1]):
            e = edge_ids[m]
            j = d_edges[e, 0] + d_edges[e, 1] - i
            if (j < first and not coarse) or seen[j]:
                continue
            seen[j] = 1
            off = j >= first
            found, moved = _exit_body(p, n, j, reach, clearance, body_x, wfaces, wlo, wstart, wids, wspan, wextent,
                                      face_reach if off else 0.0, tris, face_n, box, child, tfirst, count, order,
                                      parent, leaf, stack, q, body_face[j] if body_face[j] >= 0 else body_face[i],
                                      ids, moves, moved, around, around_reach if off else coarse_around)
            if found:
                inside[n_inside] = j
                n_inside += 1
        k += 1
    for i in range(was_inside.shape[0]):
        was_inside[i] = 0
    for k in range(n_inside):
        was_inside[inside[k]] = 1
    return moved


@kernel
def lowered_after_lift(dh_pen, lifted, height, by, lowered, sd, near, raised_by):
    """`out_along_normals`' particles lowered after a lift: 1 where S103 lifted the particle this
    frame (dh_pen > 0) and its drawn height (S106's, folds included) ends more than `by` below the
    height S103 left it at (lifted), else 0. Decision (lowered near the body, seventy-second
    session): 1 too where S106 lowered a particle S103 tested to less than `near` (EXIT_LOWERED_NEAR;
    -inf: none) from the body by S103's reading (sd less how far it came down): the walk's blouse left
    22 vertex-frames deeper than 1 mm that S103 had read 2-12 mm out and S106 then lowered by 1-4 mm,
    1-2 mm short of the body by that reading, where they ended 1-2 mm inside it (the reading
    2-3 mm long there). Decision (raised after a lowering, seventy-third session): 1 too where S103
    lowered the particle (dh_pen < 0: a body part on the cloth's outer side) and S106 raised it again
    by more than `raised_by` (inf: none): S103's reading was taken where the particle no longer is
    (the walk's skirt under the left hand: lowered 18-24 mm, brought back to the reference surface,
    5-12 mm inside the thigh, never asked)."""
    for i in range(dh_pen.shape[0]):
        down = lifted[i] - height[i]
        lowered[i] = 1 if ((dh_pen[i] > 0.0 and down > by) or (down > 0.0 and sd[i] - down < near)
                           or (dh_pen[i] < 0.0 and -down > raised_by)) else 0


__all__ = ["EXIT_AROUND_REACH", "EXIT_DIRECTIONS", "EXIT_FACE_REACH", "EXIT_FACING", "EXIT_LOWERED_NEAR", "EXIT_NEAR",
           "EXIT_NEAR_ALONG", "EXIT_REACH", "EXIT_TURNED", "NO_DIRECTIONS", "leave_creases", "lowered_after_lift",
           "out_along_normals", "out_of_two_planes"]
