"""S103's Decision out of a crease (cloth.creases): known answers on planes and on two
overlapping boxes."""

import numpy as np
import pytest

from cloth.collision import FACE_TREE_STACK, NO_FACE_TREE, BodyMesh, FaceTree, face_normals
from cloth.creases import (EXIT_AROUND_REACH, EXIT_DIRECTIONS, EXIT_FACE_REACH, EXIT_FACING, EXIT_LOWERED_NEAR,
                           EXIT_NEAR, EXIT_NEAR_ALONG, EXIT_REACH, EXIT_TURNED, NO_DIRECTIONS, leave_creases,
                           lowered_after_lift, out_along_normals, out_of_two_planes)
from cloth.topology import vertex_cells
from cloth.winding import NO_WINDING, WindingGrid
from tests.test_cloth_dynamics import box

C = 0.001  # clearance


def plane(q, n):
    n = np.asarray(n, float)
    return np.r_[q, n / np.linalg.norm(n)]


@pytest.mark.parametrize("p, a, b, expected, ok", [
    # in front of both: no move
    ((0.01, 0.01, 0), plane((0, 0, 0), (1, 0, 0)), plane((0, 0, 0), (0, 1, 0)), (0, 0, 0), True),
    # behind one plane only, the other cleared by its step
    ((-0.005, 0.002, 0), plane((0, 0, 0), (1, 0, 0)), plane((0, 0, 0), (0, 1, 0)), (0.006, 0, 0), True),
    # behind both perpendicular planes: to the crease's corner, the clearance from each
    ((-0.002, -0.003, 0), plane((0, 0, 0), (1, 0, 0)), plane((0, 0, 0), (0, 1, 0)), (0.003, 0.004, 0), True),
    # one plane absent (zero normal)
    ((0, -0.002, 0), plane((0, 0, 0), (0, 1, 0)), np.zeros(6), (0, 0.003, 0), True),
    # facing each other across a 10 mm gap: the step out of one stays clear of the other
    ((-0.002, 0, 0), plane((0, 0, 0), (1, 0, 0)), plane((0.01, 0, 0), (-1, 0, 0)), (0.003, 0, 0), True),
    # facing each other across a 1 mm gap (less than two clearances), 0.2 mm from one side: to its middle
    ((0.0002, 0, 0), plane((0, 0, 0), (1, 0, 0)), plane((0.001, 0, 0), (-1, 0, 0)), (0.0003, 0, 0), True),
    # facing each other, overlapping by 2 mm: no outside between them
    ((-0.001, 0, 0), plane((0, 0, 0), (1, 0, 0)), plane((-0.002, 0, 0), (-1, 0, 0)), (0, 0, 0), False),
])
def test_out_of_two_planes(p, a, b, expected, ok):
    mx, my, mz, found = out_of_two_planes(*p, a, b, C)
    assert found == ok
    if ok:
        np.testing.assert_allclose((mx, my, mz), expected, atol=1e-12)
        q = np.add(p, (mx, my, mz))
        gaps = [np.dot(q - pl[:3], pl[3:]) for pl in (a, b) if pl[3:].any()]
        # the clearance, or where the planes face each other across less than two, half the gap
        clear = min(C, 0.5 * sum(gaps)) if len(gaps) == 2 and np.dot(a[3:], b[3:]) < -0.5 else C
        assert min(gaps) >= clear - 1e-12


def test_narrow_tilted_gap_goes_to_its_middle():
    """Facing planes 5° off parallel, 1 mm apart at p: the exact two-clearance answer lies about
    1 cm along the gap (where it has widened to 2 mm); the Decision takes p across to the gap's
    middle instead, a fraction of a millimetre."""
    t = np.radians(5.0)
    a = plane((0, 0, 0), (1, 0, 0))
    b = plane((0.001, 0, 0), (-np.cos(t), np.sin(t), 0))  # the gap widens along +y
    p = np.array([0.0002, 0.0, 0.0])
    move = np.array(out_of_two_planes(*p, a, b, C)[:3])
    assert out_of_two_planes(*p, a, b, C)[3]
    q = p + move
    da, db = np.dot(q - a[:3], a[3:]), np.dot(q - b[:3], b[3:])
    assert da == pytest.approx(db, rel=0.01) and 0 < da < C  # (a step along n_a: off the middle by cos 5°)
    assert np.linalg.norm(move) < 0.0005
    # without the Decision (planes less than 120° apart are not taken as facing) the same gap is
    # left along its length: check that answer is indeed far, so the case tests what it claims
    exact_y = (2 * C - 0.001) / np.tan(t)  # where the gap is two clearances wide
    assert exact_y > 0.01


def two_boxes():
    """A torso box (x, z in ±5 cm, top at y = 0) and a thigh box (x -7..-1 cm, y -1..5 cm, z ±3
    cm) whose bottom centimetre is buried in it: the crease runs along x = -1 cm, y = 0."""
    tv, tt = box(half=0.05, n=8)
    tv = tv + [0.0, -0.05, 0.0]
    bv, bt = box(half=0.03, n=8)
    bv = bv + [-0.04, 0.02, 0.0]
    x = np.ascontiguousarray(np.vstack([tv, bv]))
    tris = np.vstack([tt, bt + len(tv)]).astype(np.int32)
    regions = np.r_[np.full(len(tv), 1), np.full(len(bv), 2)].astype(np.uint8)
    return x, tris, regions, BodyMesh.build(tris, len(x), regions)


def nearest_face(x, tris, p, centre_test):
    c = x[tris].mean(axis=1)
    ok = np.flatnonzero(centre_test(c))
    return int(ok[np.argmin(np.linalg.norm(c[ok] - p, axis=1))])


def leave(x, tris, body, p, sd, body_face, part_face, first=0, d_edges=None, whole=None, wound=None):
    """leave_creases on the two boxes (d_edges: the particles' edges, spread along; None: no
    spread; whole: the faces whose winding number tells the body's outside, None: the planes
    alone decide; wound: the faces it counts, None: all); returns (count, ids, moves)."""
    ids, moves = np.zeros(len(p), dtype=np.int32), np.zeros((len(p), 3))
    edges = np.zeros((0, 2), dtype=np.int32) if d_edges is None else np.asarray(d_edges, dtype=np.int32)
    start, edge_ids = vertex_cells(len(p), edges)
    wfaces, grid = np.zeros((0, 3), dtype=np.int32), NO_WINDING
    wound = np.ones(len(tris), dtype=bool) if wound is None else np.asarray(wound, dtype=bool)
    if whole is not None:
        wfaces = np.ascontiguousarray(whole, dtype=np.int32)
        g = WindingGrid(wfaces, len(x), cell=0.01)
        g.update(x)
        grid = g.arrays()
    count = leave_creases(p, sd, body_face, part_face, x, tris, body.tri_nbrs, body.tri_start, body.tri_ids,
                          body.nbr_start, body.nbr_ids, body.regions, face_normals(x, tris), np.zeros(3), np.zeros(6),
                          np.zeros(6), C, 2, first, d_edges is not None, edges, start, edge_ids,
                          np.zeros(len(p), dtype=np.uint8), ids, moves, np.zeros((len(p), 2), dtype=np.int32), wound,
                          wfaces, *grid, whole is not None)
    return count, ids, moves


def out_along(p, n, sd, other, facing, behind, first, x, tris, grid, face_reach=0.0, tree=NO_FACE_TREE, start=None,
              d_edges=None, was_inside=None, around=NO_DIRECTIONS, lowered=None, near_along=0.0,
              around_reach=EXIT_REACH, turned=-np.inf, coarse=False):
    """out_along_normals on a body (x, tris) with its winding grid's arrays, and a face tree's
    (none: no way out through the nearest face); start: S103's walks' faces (None: none);
    d_edges: the particles' edges, spread along (None: no spread); was_inside: the frame before's
    particles found inside, updated (None: no memory); lowered: the particles lowered after a lift
    (None: none); near_along: another part this near asks a particle whatever its facing (0: the
    rule before the sixty-ninth session); turned: n_i . n_body below this asks a particle wherever the
    other parts are (-inf: the rule before the seventy-first session); coarse: the coarse vertices
    (before `first`) asked too, along ±n_i only (False: the rule before the seventy-second session).
    Returns (count, ids, moves)."""
    lowered = np.zeros(len(p), dtype=np.uint8) if lowered is None else lowered
    ids, moves = np.zeros(len(p), dtype=np.int32), np.zeros((len(p), 3))
    start = np.full(len(p), -1, dtype=np.int32) if start is None else start
    edges = np.zeros((0, 2), dtype=np.int32) if d_edges is None else np.asarray(d_edges, dtype=np.int32)
    edge_start, edge_ids = vertex_cells(len(p), edges)
    count = out_along_normals(p, n, sd, other, facing, behind, lowered, first, EXIT_NEAR, EXIT_FACING, near_along,
                              turned, EXIT_REACH, C,
                              x, tris, *grid, ids, moves, face_reach, tris, face_normals(x, tris), *tree,
                              np.zeros(FACE_TREE_STACK, dtype=np.int32), np.zeros(3), start, d_edges is not None,
                              edges, edge_start, edge_ids, np.zeros(len(p), dtype=np.uint8),
                              np.zeros(len(p), dtype=np.int32),
                              np.zeros(len(p), dtype=np.uint8) if was_inside is None else was_inside,
                              was_inside is not None, around, around_reach, coarse)
    return count, ids, moves


def inside_boxes(p):
    torso = np.all(np.abs(p - [0, -0.05, 0]) < 0.05 - 1e-9, axis=-1)
    thigh = np.all(np.abs(p - [-0.04, 0.02, 0]) < 0.03 - 1e-9, axis=-1)
    return torso | thigh


@pytest.mark.parametrize("start, expected", [
    # 3 mm into the torso, 2 mm into the thigh: to the crease, the clearance out of each
    ((-0.012, -0.003, 0.0), (-0.009, 0.001, 0.0)),
    # 3 mm into the torso, 5 mm in front of the thigh's wall (S103's nearest surface is the
    # torso's top here, but the same rule): straight up out of the torso
    ((-0.005, -0.003, 0.0), (-0.005, 0.001, 0.0)),
])
def test_a_particle_in_a_crease_goes_to_the_nearest_point_outside_both_parts(start, expected):
    x, tris, regions, body = two_boxes()
    p = np.array([start, (0.03, 0.02, 0.0)])  # the second: outside, 2 cm over the torso, left alone
    top = nearest_face(x, tris, p[0], lambda c: (np.abs(c[:, 1]) < 1e-9) & (c[:, 0] > -0.01))  # the torso's top
    wall = nearest_face(x, tris, p[0], lambda c: np.abs(c[:, 0] + 0.01) < 1e-9)  # the thigh's inner wall
    body_face = np.array([top, top], dtype=np.int32)
    part_face = np.array([wall, wall], dtype=np.int32)
    sd = np.array([0.002, 0.02])  # (S103's reading, "outside": the kernel measures again)
    p0 = p.copy()
    moved, ids, moves = leave(x, tris, body, p, sd, body_face, part_face)
    assert moved == 1 and ids[0] == 0
    np.testing.assert_allclose(p[0], expected, atol=1e-9)
    np.testing.assert_allclose(moves[0], p[0] - p0[0], atol=1e-15)
    np.testing.assert_array_equal(p[1], p0[1])
    assert not inside_boxes(p).any() and inside_boxes(p0[0])


@pytest.mark.parametrize("counted, wound, moves", [
    ("both", "both", True),    # inside the body as a whole: out of the thigh as without the check
    ("torso", "both", False),  # outside it (the thigh not counted): stays where it is
    ("torso", "torso", True),  # the thigh's wall not in the winding surface, like the head: it cannot tell
])
def test_a_particle_outside_the_body_as_a_whole_stays(counted, wound, moves):
    """The planes of the crease read a particle 2 mm into the thigh and 5 mm in front of the
    torso's top as inside (behind the thigh's wall). A crease move never takes what the body as
    a whole has outside (its winding number over the counted faces is 0), where the faces the
    walks ended on are faces the winding number counts (`BodyMesh.wound_faces`); from another
    face (the head: the winding surface is capped at the neck) the planes decide alone."""
    x, tris, regions, body = two_boxes()
    p = np.array([(-0.012, 0.005, 0.0)])
    top = nearest_face(x, tris, p[0], lambda c: (np.abs(c[:, 1]) < 1e-9) & (c[:, 0] > -0.01))
    wall = nearest_face(x, tris, p[0], lambda c: np.abs(c[:, 0] + 0.01) < 1e-9)
    body_face, part_face = np.array([top], dtype=np.int32), np.array([wall], dtype=np.int32)
    p0 = p.copy()
    torso = np.arange(len(tris)) < len(tris) // 2  # (the torso's faces come first)
    moved = leave(x, tris, body, p, np.array([0.002]), body_face, part_face, whole=tris[torso] if counted == "torso"
                  else tris, wound=torso if wound == "torso" else None)[0]
    if moves:
        assert moved == 1
        np.testing.assert_allclose(p[0], (-0.009, 0.005, 0.0), atol=1e-9)
    else:
        assert moved == 0
        np.testing.assert_array_equal(p, p0)


def test_a_particle_neither_s103_nor_its_walks_find_inside_stays():
    """Untested by S103 (no face), or not near another part and read outside: not measured;
    nor is a coarse vertex (before `first`), inside or not."""
    x, tris, regions, body = two_boxes()
    p = np.array([(-0.005, -0.003, 0.0), (-0.005, -0.003, 0.0), (-0.005, -0.003, 0.0)])
    top = nearest_face(x, tris, p[0], lambda c: (np.abs(c[:, 1]) < 1e-9) & (c[:, 0] > -0.01))
    body_face = np.array([top, -1, top], dtype=np.int32)  # (the first: a coarse vertex, inside, S103 read so)
    part_face = np.array([-1, -1, -1], dtype=np.int32)
    sd = np.array([-0.003, np.inf, 0.002])
    p0 = p.copy()
    moved = leave(x, tris, body, p, sd, body_face, part_face, first=1)[0]
    assert moved == 0
    np.testing.assert_array_equal(p, p0)


@pytest.mark.parametrize("spread", [False, True])
def test_the_neighbours_of_a_moved_particle_are_measured_from_its_faces(spread):
    """A row of three: one in the crease (as above, S103 saw it), an untested neighbour 2 mm
    into the torso and 3 mm in front of the thigh's wall, and an outside one beyond it. With
    the spread, the neighbour is measured from the first one's faces and goes straight up out
    of the torso; the outside one is measured and stays. Without, only the first moves."""
    x, tris, regions, body = two_boxes()
    p = np.array([(-0.012, -0.003, 0.0), (-0.007, -0.002, 0.0), (0.0, 0.005, 0.0)])
    top = nearest_face(x, tris, p[0], lambda c: (np.abs(c[:, 1]) < 1e-9) & (c[:, 0] > -0.01))
    wall = nearest_face(x, tris, p[0], lambda c: np.abs(c[:, 0] + 0.01) < 1e-9)
    body_face = np.array([top, -1, -1], dtype=np.int32)
    part_face = np.array([wall, -1, -1], dtype=np.int32)
    sd = np.array([0.002, np.inf, np.inf])
    p0 = p.copy()
    moved, ids, moves = leave(x, tris, body, p, sd, body_face, part_face, d_edges=[(0, 1), (1, 2)] if spread else None)
    np.testing.assert_allclose(p[0], (-0.009, 0.001, 0.0), atol=1e-9)
    if spread:
        assert moved == 2 and list(ids[:2]) == [0, 1]
        np.testing.assert_allclose(p[1], (-0.007, 0.001, 0.0), atol=1e-9)
        np.testing.assert_allclose(moves[1], p[1] - p0[1], atol=1e-15)
        assert not inside_boxes(p).any()
    else:
        assert moved == 1
        np.testing.assert_array_equal(p[1], p0[1])
    np.testing.assert_array_equal(p[2], p0[2])


def test_no_spread_from_a_particle_with_one_surface():
    """A particle moved out of the torso alone (S103 walked in no other part) is no crease: its
    neighbours are not measured from its face (on the walk's blouse such walks took most of the
    outside for inside)."""
    x, tris, regions, body = two_boxes()
    p = np.array([(0.02, -0.003, 0.0), (0.025, -0.002, 0.0)])
    top = nearest_face(x, tris, p[0], lambda c: (np.abs(c[:, 1]) < 1e-9) & (c[:, 0] > 0.0))
    body_face = np.array([top, -1], dtype=np.int32)
    part_face = np.array([-1, -1], dtype=np.int32)
    sd = np.array([-0.003, np.inf])
    p0 = p.copy()
    moved, ids, moves = leave(x, tris, body, p, sd, body_face, part_face, d_edges=[(0, 1)])
    assert moved == 1 and ids[0] == 0
    np.testing.assert_allclose(p[0], (0.02, 0.001, 0.0), atol=1e-9)
    np.testing.assert_array_equal(p[1], p0[1])


@pytest.mark.parametrize("sense", [1.0, -1.0])
def test_a_particle_inside_by_the_winding_number_goes_out_along_its_normal(sense):
    """`out_along_normals` on the two boxes: a particle S103 read as outside near another part,
    its normal leaning off the body's, that the winding number puts inside goes out along ±n_i
    to where the body ends nearest, the clearance beyond, and so does one S103 read as outside,
    not near another part and its normal facing the body's, but behind another part's surface
    by its walk there (`behind`), and one read 2 cm outside with another part within EXIT_NEAR
    (2.5 cm); the others stay: one whose normal faces the body (S103's lifts are right there),
    the same not behind another part, one outside, one untested, one with no way out within
    reach, one whose other part is farther than EXIT_NEAR, and a coarse vertex (before `first`)."""
    x, tris, regions, body = two_boxes()
    g = WindingGrid(tris, len(x), cell=0.01)
    g.update(x)
    side = np.array([sense, 0.0, 0.0])  # across the thigh's inner wall (x = -1 cm), either way round
    up = (0.0, 1.0, 0.0)
    cases = [  # (position, normal, S103's sd, other, facing, behind)
        ((-0.012, 0.005, 0.02), side, 0.002, 0.004, 0.0, 0),    # 0: as 1, but a coarse vertex: stays
        ((-0.012, 0.005, 0.0), side, 0.002, 0.004, 0.0, 0),     # 1: in the thigh, 2 mm from its inner wall: out
        ((-0.030, 0.047, 0.0), up, -0.003, np.inf, 1.0, 0),     # 2: found inside by S103, 3 mm under the top: out
        ((-0.012, 0.005, 0.01), side, 0.002, 0.004, 0.95, 0),   # 3: as 1, its normal facing the body's: stays
        ((0.005, 0.005, 0.0), side, 0.01, 0.004, 0.0, 0),       # 4: outside: stays
        ((-0.012, 0.005, -0.01), side, np.inf, 0.004, 0.0, 0),  # 5: as 1, untested by S103: stays
        ((-0.040, 0.020, 0.0), up, 0.002, 0.004, 0.0, 0),       # 6: 3 cm from a way out along ±n: stays
        ((-0.012, 0.005, -0.02), side, 0.002, 0.02, 0.95, 0),   # 7: as 3, no other part near: stays
        ((-0.012, 0.005, 0.015), side, 0.002, 0.02, 0.95, 1),   # 8: as 7, but behind another part's surface: out
        ((-0.012, 0.005, -0.015), side, 0.02, 0.025, 0.0, 0),   # 9: as 1, read 2 cm out, another part 2.5 cm: out
        ((-0.012, 0.005, 0.005), side, 0.02, 0.035, 0.0, 0),    # 10: as 9, the other part 3.5 cm away: stays
    ]
    p = np.array([c[0] for c in cases])
    n = np.array([c[1] for c in cases])
    sd, other, facing = (np.array([c[k] for c in cases]) for k in (2, 3, 4))
    behind = np.array([c[5] for c in cases], dtype=np.uint8)
    assert EXIT_FACING < 0.95 and 0.025 < EXIT_NEAR < 0.035 and 0.003 < EXIT_REACH < 0.03
    p0 = p.copy()
    moved, ids, moves = out_along(p, n, sd, other, facing, behind, 1, x, tris, g.arrays())
    assert moved == 4 and list(ids[:4]) == [1, 2, 8, 9]
    out = [1, 2, 8, 9]
    np.testing.assert_allclose(moves[:4], p[out] - p0[out], atol=1e-15)
    np.testing.assert_allclose(p[1], (-0.01 + C, 0.005, 0.0), atol=1e-5)  # (the exit to 10 bisections of 4 mm)
    np.testing.assert_allclose(p[2], (-0.03, 0.05 + C, 0.0), atol=1e-5)
    np.testing.assert_allclose(p[8], (-0.01 + C, 0.005, 0.015), atol=1e-5)
    np.testing.assert_allclose(p[9], (-0.01 + C, 0.005, -0.015), atol=1e-5)
    np.testing.assert_array_equal(p[3:8], p0[3:8])
    np.testing.assert_array_equal(p[10], p0[10])
    np.testing.assert_array_equal(p[0], p0[0])
    assert inside_boxes(p0[out]).all() and not inside_boxes(p[out]).any() and inside_boxes(p[[3, 7, 10]]).all()


def test_a_particle_with_no_way_out_along_its_normal_goes_out_through_the_nearest_face():
    """`out_along_normals`' way out through the nearest face (Decision): on the two boxes, a
    particle inside the thigh whose normal runs along it, so that neither way along ±n_i ends
    within EXIT_REACH, goes out through the face nearest to it, to its closest point and the
    clearance beyond; one whose nearest face is the thigh's bottom, buried in the torso, goes on
    along the same line through the torso to where the body ends; with no face tree every one
    stays (one with no face within the reach: the next test)."""
    x, tris, regions, body = two_boxes()
    g = WindingGrid(tris, len(x), cell=0.01)
    g.update(x)
    tree = FaceTree(tris, np.arange(len(tris)), body.regions)
    tree.update(x)
    along = (0.0, 0.0, 1.0)  # along the thigh (its ends at z = ±3 cm): no way out within 1 cm either way
    cases = [  # positions, each found inside by S103 (sd < 0)
        (-0.060, 0.020, 0.0),  # 0: 1 cm inside the thigh's outer wall (x = -7 cm): out through it, along -x
        (-0.040, 0.043, 0.0),  # 1: 7 mm under the thigh's top (y = 5 cm): out along +y
        (-0.048, -0.004, 0.0),  # 2: in both, 2 mm inside the torso's side (x = -5 cm), buried in the thigh:
        #                        on along -x through the thigh to its outer wall, 2.2 cm
    ]
    p = np.array(cases)
    n = np.array([along] * len(cases))
    sd, other, facing = np.full(len(p), -0.005), np.full(len(p), np.inf), np.ones(len(p))
    behind = np.zeros(len(p), dtype=np.uint8)
    assert inside_boxes(p).all() and EXIT_REACH < 0.02 and 0.022 + C < EXIT_FACE_REACH

    def run(face_reach, arrays, start):
        q = p.copy()
        moved, ids, moves = out_along(q, n, sd, other, facing, behind, 0, x, tris, g.arrays(), face_reach, arrays,
                                      start)
        np.testing.assert_allclose(moves[:moved], q[ids[:moved]] - p[ids[:moved]], atol=1e-15)
        return q, list(ids[:moved])

    anywhere = np.full(len(p), -1, dtype=np.int32)
    q, ids = run(EXIT_FACE_REACH, tree.arrays(), anywhere)
    # the search for the nearest face gives the same from a face near the particle (S103's walk's)
    near = np.array([nearest_face(x, tris, c, lambda m: np.ones(len(m), bool)) for c in p], dtype=np.int32)
    q_near, ids_near = run(EXIT_FACE_REACH, tree.arrays(), near)
    assert ids_near == ids and (q_near == q).all()
    assert ids == [0, 1, 2]
    np.testing.assert_allclose(q[0], (-0.07 - C, 0.02, 0.0), atol=1e-12)
    np.testing.assert_allclose(q[1], (-0.04, 0.05 + C, 0.0), atol=1e-12)
    np.testing.assert_allclose(q[2], (-0.07 - C, -0.004, 0.0), atol=2e-5)  # (the march's bisections of 15 mm)
    assert not inside_boxes(q).any()
    q_off, ids_off = run(0.0, tree.arrays(), anywhere)  # off, and with no tree: every one stays
    assert ids_off == [] and (q_off == p).all()
    q_off, ids_off = run(EXIT_FACE_REACH, NO_FACE_TREE, anywhere)
    assert ids_off == [] and (q_off == p).all()


@pytest.mark.parametrize("face_reach", [0.04, EXIT_FACE_REACH])
def test_the_way_out_through_the_nearest_face_looks_as_far_as_its_reach(face_reach):
    """`out_along_normals`' way out through the nearest face within 6 cm (Decision, seventy-second
    session): in a box 12 cm across (a thigh a coarse face cuts across), a particle 5 cm under its
    top, its normal along the box and 6 cm from its ends, found inside by S103, goes out through the
    top, the clearance beyond, within EXIT_FACE_REACH, and stays within 4 cm (the reach before)."""
    bx, bt = box(half=0.06, n=8)
    x = np.ascontiguousarray(bx)
    tris = bt.astype(np.int32)
    body = BodyMesh.build(tris, len(x), np.ones(len(x), dtype=np.uint8))
    g = WindingGrid(tris, len(x), cell=0.01)
    g.update(x)
    tree = FaceTree(tris, np.arange(len(tris)), body.regions)
    tree.update(x)
    p = np.array([(0.0, 0.01, 0.0)])
    n = np.array([(0.0, 0.0, 1.0)])
    sd, other, facing = np.full(1, -0.05), np.full(1, np.inf), np.ones(1)
    behind = np.zeros(1, dtype=np.uint8)
    assert 0.04 < 0.05 + C < EXIT_FACE_REACH
    moved, ids, moves = out_along(p, n, sd, other, facing, behind, 0, x, tris, g.arrays(), face_reach, tree.arrays(),
                                  around=EXIT_DIRECTIONS, around_reach=EXIT_AROUND_REACH)
    if face_reach > 0.05 + C:
        assert moved == 1
        np.testing.assert_allclose(p[0], (0.0, 0.06 + C, 0.0), atol=1e-12)
    else:
        assert moved == 0
        np.testing.assert_array_equal(p[0], (0.0, 0.01, 0.0))


@pytest.mark.parametrize("spread", [True, False])
def test_the_neighbours_of_a_particle_inside_are_asked_too(spread):
    """`out_along_normals`' spread (Decision): a chain of particles across the thigh, S103 read
    each as outside with its normal along the body's (not asked), but the first one leaning off
    it (asked): with the spread, the winding number finds the first inside, then its neighbour,
    and so on along the chain while they are inside: each goes out along ±n_i; the chain's last
    one, outside the thigh, is asked and stays, and so does a particle beyond it (not asked: its
    neighbour was outside), inside the thigh but not on the chain, and a coarse vertex (before
    `first`) beside the first. Without the spread only the first moves."""
    x, tris, regions, body = two_boxes()
    g = WindingGrid(tris, len(x), cell=0.01)
    g.update(x)
    side = (1.0, 0.0, 0.0)  # across the thigh's inner wall (x = -1 cm)
    cases = [  # (position, facing): S103's sd 2 mm, other part 4 mm away, normal along +x
        ((-0.012, 0.005, 0.005), 0.0),   # 0: a coarse vertex, leaning off the body: stays
        ((-0.012, 0.005, 0.0), 0.0),     # 1: leaning off the body: asked, out through the inner wall
        ((-0.013, 0.010, 0.0), 0.95),    # 2: its neighbour: out
        ((-0.014, 0.015, 0.0), 0.95),    # 3: and its neighbour: out
        ((-0.013, 0.055, 0.0), 0.95),    # 4: above the thigh's top: outside, stays
        ((-0.013, 0.060, 0.0), 0.95),    # 5: beyond it: outside, never asked
        ((-0.012, 0.005, -0.01), 0.95),  # 6: inside the thigh, not on the chain: not asked
    ]
    p = np.array([c[0] for c in cases])
    n = np.array([side] * len(cases))
    facing = np.array([c[1] for c in cases])
    sd, other = np.full(len(p), 0.002), np.full(len(p), 0.004)
    behind = np.zeros(len(p), dtype=np.uint8)
    assert facing[2:].min() > EXIT_FACING and inside_boxes(p[[0, 1, 2, 3, 6]]).all() and not inside_boxes(p[4:6]).any()
    p0 = p.copy()
    moved, ids, moves = out_along(p, n, sd, other, facing, behind, 1, x, tris, g.arrays(),
                                  d_edges=[(0, 1), (1, 2), (2, 3), (3, 4), (4, 5)] if spread else None)
    out = [1, 2, 3] if spread else [1]
    assert list(ids[:moved]) == out
    np.testing.assert_allclose(moves[:moved], p[out] - p0[out], atol=1e-15)
    for i in out:
        np.testing.assert_allclose(p[i], (-0.01 + C, p0[i, 1], p0[i, 2]), atol=1e-5)
    rest = [i for i in range(len(p)) if i not in out]
    np.testing.assert_array_equal(p[rest], p0[rest])
    assert not inside_boxes(p[out]).any()


def chain_across_the_thigh():
    """Particles on the thigh's inner wall side, each read outside by S103 (2 mm) with another part
    4 mm away and its normal along +x (across the wall at x = -1 cm): 0 and 1 inside the thigh
    (0 with its normal leaning off the body's: asked), 2 outside it, above the thigh's top."""
    p = np.array([(-0.012, 0.005, 0.0), (-0.013, 0.010, 0.0), (-0.013, 0.055, 0.0)])
    n = np.tile((1.0, 0.0, 0.0), (len(p), 1))
    facing = np.array([0.0, 0.95, 0.95])
    return p, n, np.full(len(p), 0.002), np.full(len(p), 0.004), facing, np.zeros(len(p), dtype=np.uint8)


def test_a_particle_found_inside_is_asked_again_the_next_frame():
    """`out_along_normals`' memory (Decision): a particle the winding number found inside is asked
    again the next frame, though S103's reading no longer names it (its normal now along the
    body's), and goes out again; without the memory it stays. Its record is the frame's: one
    found outside is dropped, one not asked (and not inside) is not kept."""
    x, tris, regions, body = two_boxes()
    g = WindingGrid(tris, len(x), cell=0.01)
    g.update(x)
    p, n, sd, other, facing, behind = chain_across_the_thigh()
    p0 = p.copy()
    was_inside = np.zeros(len(p), dtype=np.uint8)
    moved, ids, _ = out_along(p, n, sd, other, facing, behind, 0, x, tris, g.arrays(), was_inside=was_inside)
    assert list(ids[:moved]) == [0] and list(was_inside) == [1, 0, 0]
    facing[0] = 0.95  # the next frame: back where it was (Δh unchanged), its normal along the body's
    for memory in (True, False):
        p = p0.copy()
        moved, ids, _ = out_along(p, n, sd, other, facing, behind, 0, x, tris, g.arrays(),
                                  was_inside=was_inside.copy() if memory else None)
        assert list(ids[:moved]) == ([0] if memory else [])
        np.testing.assert_allclose(p[0], (-0.01 + C, 0.005, 0.0) if memory else p0[0], atol=1e-5)
    p = p0.copy()
    p[0] = (-0.005, 0.005, 0.0)  # a frame later it lies outside the body: asked, and dropped from the record
    moved, ids, _ = out_along(p, n, sd, other, facing, behind, 0, x, tris, g.arrays(), was_inside=was_inside)
    assert moved == 0 and not was_inside.any()


@pytest.mark.parametrize("near", [-np.inf, EXIT_LOWERED_NEAR])
def test_a_particle_s106_lowered_near_the_body_by_s103s_reading_is_named(near):
    """`lowered_after_lift`'s lowered near the body (Decision): S103 read each particle 5 mm from the
    body and did not lift it; S106 lowered the first by 4 mm (1 mm left by that reading, within
    EXIT_LOWERED_NEAR: named), the second by 2 mm (3 mm left: not), raised the third by 6 mm (not),
    and lowered the fourth, untested (sd inf), by 2 cm (not). With the rule off (-inf) none is named,
    though S106 lowered the first by less and a fifth, read 1 mm out, by 3 mm, past the body by that
    reading."""
    dh_pen = np.zeros(5)
    lifted = np.full(5, 0.006)
    height = np.array([0.002, 0.004, 0.012, -0.014, 0.003])
    sd = np.array([0.005, 0.005, 0.005, np.inf, 0.001])
    lowered = np.zeros(5, dtype=np.uint8)
    assert 0.001 < EXIT_LOWERED_NEAR < 0.003
    lowered_after_lift(dh_pen, lifted, height, C, lowered, sd, near, np.inf)
    assert list(lowered) == ([1, 0, 0, 0, 1] if near > 0.0 else [0, 0, 0, 0, 0])


@pytest.mark.parametrize("raised_by", [np.inf, C])
def test_a_particle_s103_lowered_that_s106_raised_again_is_named(raised_by):
    """`lowered_after_lift`'s raised after a lowering (Decision): S103 lowered the first three
    particles by 2 cm (a body part on the cloth's outer side); S106 raised the first back to the
    reference surface (named), the second by 0.5 mm (within the clearance: not) and lowered the third
    further (not); the fourth S103 lifted and S106 raised further (not: not lowered). Off (inf): none."""
    dh_pen = np.array([-0.02, -0.02, -0.02, 0.005])
    lifted = np.array([-0.02, -0.02, -0.02, 0.005])
    height = np.array([0.0, -0.0195, -0.025, 0.01])
    sd = np.full(4, 0.01)  # (read well off the body after the move: no other rule names them)
    lowered = np.zeros(4, dtype=np.uint8)
    lowered_after_lift(dh_pen, lifted, height, C, lowered, sd, EXIT_LOWERED_NEAR, raised_by)
    assert list(lowered) == ([1, 0, 0, 0] if raised_by == C else [0, 0, 0, 0])


def test_a_particle_lowered_after_a_lift_is_asked_whatever_s103_read():
    """`out_along_normals`' lowered after a lift (Decision): `lowered_after_lift` names the
    particles S103 lifted this frame that S106 brought more than the clearance below S103's
    height, and only those; such a particle, read well outside by S103 (1 cm: its walk stopped on
    a face it projects into) with its normal facing the body's and no other part near, which the
    winding number puts inside, goes out along n_i; unnamed, it stays."""
    dh_pen = np.array([0.02, 0.02, 0.02, 0.0, -0.004])
    lifted = np.array([0.02, 0.02, 0.02, 0.01, 0.0])
    height = np.array([0.004, 0.0195, 0.02, 0.0, -0.01])  # 0: 16 mm down; 1: 0.5 mm down; 2: as lifted
    lowered = np.zeros(len(dh_pen), dtype=np.uint8)
    far = np.full(len(dh_pen), 0.05)  # S103's readings, all farther than any move here
    lowered_after_lift(dh_pen, lifted, height, C, lowered, far, EXIT_LOWERED_NEAR, np.inf)
    assert list(lowered) == [1, 0, 0, 0, 0]  # (3: not lifted; 4: lowered by S103, not lifted)
    lowered_after_lift(dh_pen, lifted, height, np.inf, lowered, far, EXIT_LOWERED_NEAR, np.inf)  # (exit_lowered False)
    assert not lowered.any()
    x, tris, regions, body = two_boxes()
    g = WindingGrid(tris, len(x), cell=0.01)
    g.update(x)
    p = np.array([(-0.03, 0.047, 0.0), (-0.03, 0.047, 0.01)])  # 3 mm under the thigh's top, n_i up
    n = np.tile((0.0, 1.0, 0.0), (2, 1))
    sd, other, facing = np.full(2, 0.01), np.full(2, np.inf), np.full(2, 1.0)
    behind = np.zeros(2, dtype=np.uint8)
    p0 = p.copy()
    for named in ([0, 0], [1, 0]):
        p = p0.copy()
        moved, ids, _ = out_along(p, n, sd, other, facing, behind, 0, x, tris, g.arrays(),
                                  lowered=np.array(named, dtype=np.uint8))
        assert list(ids[:moved]) == ([0] if named[0] else [])
        np.testing.assert_allclose(p[0], (-0.03, 0.05 + C, 0.0) if named[0] else p0[0], atol=1e-5)
        np.testing.assert_array_equal(p[1], p0[1])
    assert inside_boxes(p0).all() and not inside_boxes(p[:1]).any()


@pytest.mark.parametrize("near_along", [0.0, 0.01, EXIT_NEAR_ALONG])
def test_a_particle_read_outside_with_another_part_within_2_cm_is_asked_whatever_its_normal(near_along):
    """`out_along_normals`' another part within a centimetre (Decision; 2 cm since the eighty-ninth
    session): on the two boxes, a particle in the thigh 2 mm from its inner wall, read 2 mm outside by
    S103 with its normal facing the body's (0.95, above EXIT_FACING), goes out across the wall, the
    clearance beyond, when another part that near asks it: at 4 mm under the rule of the sixty-ninth
    session (1 cm) and EXIT_NEAR_ALONG, at 15 mm under EXIT_NEAR_ALONG only; neither is asked under
    the rule before (0). The same particle with the other part 2.5 cm away stays whatever the rule."""
    x, tris, regions, body = two_boxes()
    g = WindingGrid(tris, len(x), cell=0.01)
    g.update(x)
    p = np.array([(-0.012, 0.005, 0.01), (-0.012, 0.005, 0.0), (-0.012, 0.005, -0.01)])
    n = np.tile((1.0, 0.0, 0.0), (3, 1))
    sd, other, facing = np.full(3, 0.002), np.array([0.004, 0.015, 0.025]), np.full(3, 0.95)
    behind = np.zeros(3, dtype=np.uint8)
    assert EXIT_FACING < 0.95 and 0.015 < EXIT_NEAR_ALONG < 0.025 and inside_boxes(p).all()
    p0 = p.copy()
    moved, ids, moves = out_along(p, n, sd, other, facing, behind, 0, x, tris, g.arrays(), near_along=near_along)
    asked = [k for k in range(3) if other[k] < near_along]
    assert moved == len(asked) and list(ids[:moved]) == asked
    for m, k in enumerate(asked):
        np.testing.assert_allclose(p[k], (-0.01 + C, 0.005, p0[k, 2]), atol=1e-5)
        np.testing.assert_allclose(moves[m], p[k] - p0[k], atol=1e-15)
        assert not inside_boxes(p[k:k + 1]).any()
    for k in set(range(3)) - set(asked):
        np.testing.assert_array_equal(p[k], p0[k])
    assert asked == {0.0: [], 0.01: [0], EXIT_NEAR_ALONG: [0, 1]}[near_along]


@pytest.mark.parametrize("turned", [-np.inf, EXIT_TURNED])
def test_a_particle_whose_normal_faces_into_the_body_is_asked_wherever_the_other_parts_are(turned):
    """`out_along_normals`' turned in (Decision): on the two boxes, a particle in the thigh 2 mm
    from its inner wall, read 2 mm outside by S103 with no other part found and its normal facing
    into the body (n_i . n_body -0.5, below EXIT_TURNED), goes out across the wall, the clearance
    beyond, when a turned normal asks it (EXIT_TURNED), and stays under the rule before (-inf);
    the same particle with its normal leaning off the body's but not turned (0.5) stays either way."""
    x, tris, regions, body = two_boxes()
    g = WindingGrid(tris, len(x), cell=0.01)
    g.update(x)
    p = np.array([(-0.012, 0.005, 0.01), (-0.012, 0.005, -0.01)])
    n = np.tile((1.0, 0.0, 0.0), (2, 1))
    sd, other, facing = np.full(2, 0.002), np.full(2, np.inf), np.array([-0.5, 0.5])
    behind = np.zeros(2, dtype=np.uint8)
    assert -0.5 < EXIT_TURNED < 0.5 < EXIT_FACING and inside_boxes(p).all()
    p0 = p.copy()
    moved, ids, moves = out_along(p, n, sd, other, facing, behind, 0, x, tris, g.arrays(), near_along=EXIT_NEAR_ALONG,
                                  turned=turned)
    if turned > -np.inf:
        assert moved == 1 and ids[0] == 0
        np.testing.assert_allclose(p[0], (-0.01 + C, 0.005, 0.01), atol=1e-5)
        np.testing.assert_allclose(moves[0], p[0] - p0[0], atol=1e-15)
        assert not inside_boxes(p[:1]).any()
    else:
        assert moved == 0
        np.testing.assert_array_equal(p[0], p0[0])
    np.testing.assert_array_equal(p[1], p0[1])


@pytest.mark.parametrize("coarse", [False, True])
def test_a_coarse_vertex_inside_goes_out_along_its_normal_or_the_way_around_within_exit_reach(coarse):
    """`out_along_normals`' coarse vertices (Decision): on the two boxes, with the coarse ones
    asked, a coarse vertex in the thigh 2 mm from its inner wall, its normal across the wall and
    leaning off the body's, goes out along it, the clearance beyond, and so does one the spread
    reaches from a detailed neighbour inside. A coarse vertex whose normal runs along the thigh (no
    way out along ±n_i within EXIT_REACH) goes out the way around where that is within EXIT_REACH
    (eighty-ninth session: +x, 2 mm), and stays where it is farther (-x, 1.4 cm), where a detailed
    particle beside it goes out the way around. Under the rule before, only the detailed particles
    move."""
    x, tris, regions, body = two_boxes()
    g = WindingGrid(tris, len(x), cell=0.01)
    g.update(x)
    side, along = (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)
    cases = [  # (position, normal, S103's sd, facing): the first four coarse vertices, other part 4 mm away
        ((-0.012, 0.005, 0.01), side, 0.002, 0.0),     # 0: leaning off the body: asked, out across the wall
        ((-0.056, 0.020, 0.0), along, -0.005, 1.0),    # 1: found inside by S103, the way around 1.4 cm: stays
        ((-0.013, 0.010, -0.01), side, 0.002, 0.95),   # 2: facing the body's normal: reached by the spread from 4
        ((-0.012, 0.005, 0.0), along, 0.002, 0.0),     # 3: no way along ±n_i, the way around 2 mm: out across it
        ((-0.012, 0.005, -0.01), side, 0.002, 0.0),    # 4: a detailed particle leaning off the body: out
        ((-0.056, 0.020, 0.01), along, -0.005, 1.0),   # 5: as 1, a detailed particle: out the way around
    ]
    p = np.array([c[0] for c in cases])
    n = np.array([c[1] for c in cases])
    sd, facing = np.array([c[2] for c in cases]), np.array([c[3] for c in cases])
    other, behind = np.full(len(p), 0.004), np.zeros(len(p), dtype=np.uint8)
    assert inside_boxes(p).all() and 0.002 < EXIT_REACH < 0.014 < EXIT_AROUND_REACH and 0.95 > EXIT_FACING
    p0 = p.copy()
    moved, ids, moves = out_along(p, n, sd, other, facing, behind, 4, x, tris, g.arrays(), d_edges=[(2, 4)],
                                  around=EXIT_DIRECTIONS, around_reach=EXIT_AROUND_REACH, coarse=coarse)
    out = [0, 3, 4, 5, 2] if coarse else [4, 5]
    assert list(ids[:moved]) == out
    np.testing.assert_allclose(moves[:moved], p[out] - p0[out], atol=1e-15)
    np.testing.assert_allclose(p[4], (-0.01 + C, 0.005, -0.01), atol=1e-5)
    np.testing.assert_allclose(p[5], (-0.07 - C, 0.020, 0.01), atol=1e-5)
    np.testing.assert_array_equal(p[1], p0[1])
    if coarse:
        np.testing.assert_allclose(p[0], (-0.01 + C, 0.005, 0.01), atol=1e-5)
        np.testing.assert_allclose(p[2], (-0.01 + C, 0.010, -0.01), atol=1e-5)
        np.testing.assert_allclose(p[3], (-0.01 + C, 0.005, 0.0), atol=1e-5)
        # along ±n_i where that leads out: those coarse moves are parallel to their normals
        for k, i in enumerate(ids[:moved]):
            if i in (0, 2):
                np.testing.assert_allclose(np.cross(moves[k], n[i]), 0.0, atol=1e-15)
        assert not inside_boxes(p[[0, 2, 3, 4, 5]]).any()
    else:
        np.testing.assert_array_equal(p[[0, 2, 3]], p0[[0, 2, 3]])


@pytest.mark.parametrize("around_reach", [EXIT_REACH, EXIT_AROUND_REACH])
def test_the_way_around_looks_as_far_as_its_reach(around_reach):
    """`out_along_normals`' way around (Decision, its 3 cm reach): on the two boxes, a particle
    1.4 cm inside the thigh's outer wall, its normal along the thigh (whose ends lie 3 cm away),
    goes out along -x, the clearance beyond, within EXIT_AROUND_REACH, and stays within EXIT_REACH."""
    x, tris, regions, body = two_boxes()
    g = WindingGrid(tris, len(x), cell=0.01)
    g.update(x)
    p = np.array([(-0.056, 0.020, 0.0)])
    n = np.array([(0.0, 0.0, 1.0)])
    sd, other, facing = np.full(1, -0.005), np.full(1, np.inf), np.ones(1)
    behind = np.zeros(1, dtype=np.uint8)
    assert inside_boxes(p).all() and EXIT_REACH < 0.014 < EXIT_AROUND_REACH
    q = p.copy()
    moved, ids, _ = out_along(q, n, sd, other, facing, behind, 0, x, tris, g.arrays(), around=EXIT_DIRECTIONS,
                              around_reach=around_reach)
    if around_reach > 0.014:
        assert moved == 1 and ids[0] == 0
        np.testing.assert_allclose(q[0], (-0.07 - C, 0.02, 0.0), atol=2e-5)
        assert not inside_boxes(q).any()
    else:
        assert moved == 0 and (q == p).all()


def test_a_particle_with_no_way_out_along_its_normal_or_a_face_goes_out_along_the_nearest_direction():
    """`out_along_normals`' way around (Decision): on the two boxes, with no face tree to go through,
    a particle inside the thigh whose normal runs along it goes out along the nearest of
    EXIT_DIRECTIONS that ends within EXIT_REACH, the clearance beyond; one with none within reach
    stays, and without the directions every one stays."""
    x, tris, regions, body = two_boxes()
    g = WindingGrid(tris, len(x), cell=0.01)
    g.update(x)
    cases = [
        (-0.063, 0.020, 0.0),  # 0: 7 mm inside the thigh's outer wall (x = -7 cm): out along -x
        (-0.040, 0.043, 0.0),  # 1: 7 mm under the thigh's top (y = 5 cm): out along +y
        (0.000, -0.050, 0.0),  # 2: the torso's middle, 5 cm from every wall: stays
    ]
    p = np.array(cases)
    n = np.array([(0.0, 0.0, 1.0)] * len(cases))  # along the thigh: its ends 3 cm away
    sd, other, facing = np.full(len(p), -0.005), np.full(len(p), np.inf), np.ones(len(p))
    behind = np.zeros(len(p), dtype=np.uint8)
    assert inside_boxes(p).all() and EXIT_REACH < 0.02
    q = p.copy()
    moved, ids, moves = out_along(q, n, sd, other, facing, behind, 0, x, tris, g.arrays(), around=EXIT_DIRECTIONS)
    assert list(ids[:moved]) == [0, 1]
    np.testing.assert_allclose(q[0], (-0.07 - C, 0.02, 0.0), atol=2e-5)
    np.testing.assert_allclose(q[1], (-0.04, 0.05 + C, 0.0), atol=2e-5)
    np.testing.assert_array_equal(q[2], p[2])
    assert not inside_boxes(q[:2]).any()
    q = p.copy()
    moved, _, _ = out_along(q, n, sd, other, facing, behind, 0, x, tris, g.arrays())
    assert moved == 0 and (q == p).all()
