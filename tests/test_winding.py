"""The body's inside test as a whole (cloth.winding) and the push out of it (leave_body_union)."""

import numpy as np
import pytest
import trimesh

from cloth.collision import (FACE_TREE_STACK, UNION_HITS, UNION_REACH, BodyMesh, BodyPose, FaceTree, face_normals,
                             leave_body_union)
from cloth.fabric import fabric
from cloth.topology import boundary_loops
from cloth.winding import WindingGrid, closed_faces, lowest_bit, winding_numbers
from tests.test_cloth_dynamics import box
from tests.test_signed_distance import solid_angle_winding


def overlapping_boxes():
    """Two 40 cm boxes as one closed surface that cuts through itself (a thigh pressed into the
    belly): A around the origin, B shifted by (0.3, 0.1, 0)."""
    a = trimesh.creation.box(extents=(0.4, 0.4, 0.4))
    b = trimesh.creation.box(extents=(0.4, 0.4, 0.4))
    b.apply_translation((0.3, 0.1, 0.0))
    return np.vstack([a.vertices, b.vertices]), np.vstack([a.faces, b.faces + len(a.vertices)]).astype(np.int32)


def windings(vertices, faces, points, **grid):
    g = WindingGrid(faces, len(vertices), **grid)
    g.update(np.ascontiguousarray(vertices, dtype=np.float64))
    out = np.zeros(len(points), dtype=np.int64)
    winding_numbers(np.ascontiguousarray(points, dtype=np.float64), vertices, g.tris, *g.arrays(), out)
    return out


def test_winding_number_counts_overlapping_boxes_like_the_solid_angle():
    """0 outside, 1 in one box, 2 in both; equal to the brute-force solid-angle winding number at
    random points and at points exactly on the edges between two faces as the rays (+z) see
    them: the diagonals of the boxes' square faces, where each crossing is counted once. With
    too few columns allowed for the cell asked, the grid widens its columns and stays exact."""
    v, f = overlapping_boxes()
    pts = np.array([[-0.15, 0.0, 0.0], [0.15, 0.05, 0.0], [0.45, 0.1, 0.0], [0.0, 0.5, 0.0], [-0.3, 0.0, 0.0]])
    np.testing.assert_array_equal(windings(v, f, pts, cell=0.05), [1, 2, 1, 0, 0])
    rng = np.random.default_rng(7)
    rand = rng.uniform([-0.3, -0.3, -0.3], [0.6, 0.4, 0.3], (300, 3))
    want = np.round(solid_angle_winding(v, f, rand))
    np.testing.assert_array_equal(windings(v, f, rand, cell=0.05), want)
    np.testing.assert_array_equal(windings(v, f, rand, cell=0.05, max_columns=16), want)
    diag = np.array([[cx + t, cy + s * t, z] for cx, cy in ((0.0, 0.0), (0.3, 0.1)) for t in (-0.15, -0.05, 0.0, 0.15)
                     for s in (-1.0, 1.0) for z in (-0.25, 0.0, 0.15)])
    np.testing.assert_array_equal(windings(v, f, diag, cell=0.05), np.round(solid_angle_winding(v, f, diag)))
    # the count runs on the nearer side of a column's extent (the crossings beyond p along the
    # ray, or minus those before it), and is 0 outside the extent: points in front of, behind
    # and near the walls of the boxes (each side of each wall) read as the solid angle does
    near = np.vstack([rng.uniform([-0.3, -0.3, z - 0.02], [0.6, 0.4, z + 0.02], (100, 3))
                      for z in (-0.2, 0.2, 0.3)])
    far = np.vstack([rand + [0.0, 0.0, 0.5], rand - [0.0, 0.0, 0.5], near])
    np.testing.assert_array_equal(windings(v, f, far, cell=0.05), np.round(solid_angle_winding(v, f, far)))
    assert windings(v, f, far, cell=0.05)[: 2 * len(rand)].max() == 0


def test_closed_faces_caps_the_holes_of_the_faces_kept():
    """A box with its top face (two triangles) left out, as the body without its head: the fan
    closes the hole, the surface has no boundary left, and the winding number inside and
    outside is the whole box's."""
    box = trimesh.creation.box(extents=(0.4, 0.4, 0.4))
    top = box.triangles_center[:, 1] > 0.19
    assert top.sum() == 2
    faces = closed_faces(box.faces, ~top)
    assert len(faces) == len(box.faces) and boundary_loops(faces) == []
    pts = np.array([[0.0, 0.1, 0.0], [0.05, 0.15, -0.1], [0.0, 0.3, 0.0], [0.3, 0.0, 0.0]])
    np.testing.assert_array_equal(windings(box.vertices, faces, pts, cell=0.05), [1, 1, 0, 0])
    np.testing.assert_array_equal(closed_faces(box.faces), box.faces)


def push_out(vertices, faces, points, velocities, thickness=0.005):
    x = np.array(points, dtype=np.float64)
    v = np.array(velocities, dtype=np.float64)
    body_x = np.ascontiguousarray(vertices, dtype=np.float64)
    grid = WindingGrid(faces, len(body_x), cell=0.05)
    grid.update(body_x)
    tree = FaceTree(faces, np.arange(len(faces)), np.ones(len(body_x), dtype=np.uint8))
    tree.update(body_x)
    placed = np.ones(len(x))
    moved = leave_body_union(x, v, np.zeros_like(v), body_x, face_normals(body_x, faces), grid.tris, *grid.arrays(),
                             faces, *tree.arrays(), np.zeros(FACE_TREE_STACK, np.int32), np.zeros(UNION_HITS),
                             np.zeros(UNION_HITS, np.int32), np.zeros(UNION_HITS, np.int32), np.zeros(3), thickness,
                             np.ones(len(x), np.uint8), placed)
    return x, v, placed, moved


def test_leave_body_union_puts_a_particle_out_where_the_nearest_face_is_buried():
    """In box A, 5 cm in front of B's face x = 0.1 (buried in A and facing the particle: the ring
    test reads "outside") and 7 cm below A's top: the nearest way out of the union is up, to
    y = 0.2, and the particle lands thickness above it, its downward velocity removed and its
    sideways one kept. A particle outside both boxes, and one in both whose every way out is
    beyond UNION_REACH, stay where they are."""
    v, f = overlapping_boxes()
    assert UNION_REACH < 0.2  # the third particle's ways out are 20 cm or more
    pts = [[0.05, 0.13, 0.0], [-0.3, 0.0, 0.0], [0.2, 0.0, 0.0]]
    vel = [[0.3, -1.0, 0.0], [0.0, -1.0, 0.0], [0.0, -1.0, 0.0]]
    x, vel_out, placed, moved = push_out(v, f, pts, vel, thickness=0.005)
    assert moved == 1
    np.testing.assert_allclose(x[0], [0.05, 0.205, 0.0], atol=1e-12)
    np.testing.assert_allclose(vel_out[0], [0.3, 0.0, 0.0], atol=1e-12)
    np.testing.assert_array_equal(x[1:], pts[1:])
    np.testing.assert_array_equal(placed, [0.0, 1.0, 1.0])
    assert windings(v, f, x[:1], cell=0.05)[0] == 0


def test_leave_body_union_takes_the_exit_face_normal_where_the_axes_meet_it_at_a_slant():
    """A box turned 30 degrees about z: from a point 2 cm inside its +x face, the axis rays
    leave 2.31 (along x) and 4 cm (along y) away, but the face's plane is 2 cm along its
    normal; the particle goes there, thickness beyond."""
    box = trimesh.creation.box(extents=(0.4, 0.4, 0.4))
    c, s = np.cos(np.pi / 6), np.sin(np.pi / 6)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    verts = box.vertices @ rot.T
    n = rot @ np.array([1.0, 0.0, 0.0])
    p = 0.18 * n
    x, _, _, moved = push_out(verts, box.faces.astype(np.int32), [p], [[0.0, 0.0, 0.0]], thickness=0.005)
    assert moved == 1
    np.testing.assert_allclose(x[0], 0.205 * n, atol=1e-12)


def test_leave_body_union_takes_a_diagonal_where_every_axis_goes_round_a_limb():
    """A 30 cm cube turned so that a face's normal is n = (1, 1, 1)/sqrt(3), the particle 4 mm
    inside that face, and three thin rods (6 mm square) from 3 mm beyond it along +x, +y and +z
    for 20 cm, overlapping the cube: every axis ray from the particle stays inside the body
    beyond UNION_REACH (along -x, -y, -z through the cube), so no axis offers a way out, nor a
    slit. The diagonal n does, 4 mm away: the particle lands thickness beyond the face."""
    n = np.ones(3) / np.sqrt(3.0)
    cube = trimesh.creation.box(extents=(0.3, 0.3, 0.3))
    cube.apply_transform(trimesh.geometry.align_vectors([1.0, 0.0, 0.0], n))
    cube.apply_translation(-(0.15 - 0.004) * n)  # its face 4 mm along n from the origin
    parts = [cube]
    for axis in range(3):
        extents = np.full(3, 0.006)
        extents[axis] = 0.2
        rod = trimesh.creation.box(extents=extents)
        shift = np.zeros(3)
        shift[axis] = 0.003 + 0.1
        rod.apply_translation(shift)
        parts.append(rod)
    verts = np.vstack([m.vertices for m in parts])
    faces = np.vstack([m.faces + sum(len(o.vertices) for o in parts[:k]) for k, m in enumerate(parts)]).astype(np.int32)
    t = np.linspace(0.0, UNION_REACH + 0.005, 200)[:, None]
    for axis in np.vstack([np.eye(3), -np.eye(3)]):  # every axis: inside all the way
        assert windings(verts, faces, t * axis, cell=0.05).min() >= 1
    x, _, placed, moved = push_out(verts, faces, [[0.0, 0.0, 0.0]], [[0.0, 0.0, 0.0]], thickness=0.005)
    assert moved == 1 and placed[0] == 0.0
    np.testing.assert_allclose(x[0], 0.009 * n, atol=2e-5)  # 4 mm out (bisected to 4 µm), then thickness
    assert windings(verts, faces, x, cell=0.05)[0] == 0


def test_leave_body_union_goes_into_a_slit_narrower_than_thickness_only_where_there_is_no_wider_way_out():
    """Box A around the origin and box B 2 mm beyond its +x face (two skins pressed together):
    from 3 cm inside A's +x face, with every other way out of A beyond UNION_REACH, the only way
    out is the 2 mm slit, narrower than thickness (5 mm): the particle goes to its middle, outside
    both. 7 cm below A's top as well, the way up, 7 cm but wide, is taken instead of the slit."""
    a = trimesh.creation.box(extents=(0.4, 0.4, 0.4))
    b = trimesh.creation.box(extents=(0.4, 0.4, 0.4))
    b.apply_translation((0.402, 0.0, 0.0))
    v = np.vstack([a.vertices, b.vertices])
    f = np.vstack([a.faces, b.faces + len(a.vertices)]).astype(np.int32)
    pts = [[0.17, 0.0, 0.0], [0.17, 0.13, 0.0]]
    x, vel, placed, moved = push_out(v, f, pts, [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], thickness=0.005)
    assert moved == 2
    np.testing.assert_allclose(x[0], [0.201, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(x[1], [0.17, 0.205, 0.0], atol=1e-12)
    np.testing.assert_array_equal(windings(v, f, x, cell=0.05), [0, 0])
    np.testing.assert_allclose(vel, [[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]], atol=1e-12)  # outward speed kept


QUAD_IN_A = np.array([[0.04, 0.13, -0.01], [0.04, 0.13, 0.01], [0.06, 0.13, 0.01], [0.06, 0.13, -0.01]])


def quad_in_overlapping_boxes(union_passes, **settings):
    """A 2 cm cotton quad at rest at QUAD_IN_A, inside box A of the overlapping boxes (finely
    meshed), 5 cm in front of B's buried face x = 0.1 and 7 cm below A's top: (sim, verts).
    settings: more SimSettings."""
    from cloth.coarsen import CoarseMesh
    from cloth.garment import Garment
    from cloth.model import SimSettings, build_cloth_model
    from cloth.sim import ClothSim

    va, ta = box(0.2, 8)
    verts = np.vstack([va, va + [0.3, 0.1, 0.0]])
    tris = np.vstack([ta, ta + len(va)]).astype(np.int32)
    quad = np.array([[0, 1, 2, 3]], np.int32)
    model = build_cloth_model(Garment("quad", QUAD_IN_A, quad, np.arange(4)), fabric("cotton"),
                              SimSettings(union_passes=union_passes, **settings), QUAD_IN_A,
                              CoarseMesh(QUAD_IN_A, quad, np.zeros(0, np.int32), np.zeros((0, 3))))
    sim = ClothSim(model, BodyMesh.build(tris, len(verts)), verts)
    sim.state.x[:] = QUAD_IN_A
    sim.state.v[:] = 0.0
    return sim, verts


@pytest.mark.parametrize("union_passes", [0, 1])
def test_cloth_sim_union_pass_puts_a_quad_out_of_overlapping_boxes(union_passes):
    """A 2 cm cotton quad at rest inside box A of the overlapping boxes (finely meshed), 5 cm in
    front of B's buried face x = 0.1 and 7 cm below A's top: the contact pass's ring tests read
    it as outside and leave it. With SimSettings.union_passes it ends thickness (3 mm) above
    A's top, every corner counted once; without, it stays. A shared body pose without the
    winding grid is refused with a message."""
    sim, verts = quad_in_overlapping_boxes(union_passes)
    sim.settle_contacts(sim.pose)
    want = QUAD_IN_A.copy()
    if union_passes:
        want[:, 1] = 0.2 + sim.model.fabric.thickness
    np.testing.assert_allclose(sim.state.x, want, atol=1e-12)
    assert sim.stats.union_pushes == 4 * union_passes
    if union_passes:
        bare = BodyPose(sim.body)
        bare.update(verts)
        with pytest.raises(ValueError, match="union_passes needs a body pose"):
            sim.settle_contacts(bare)


def test_second_union_pass_tests_only_what_moved_since_the_first():
    """union_passes = 2: the first union pass puts the quad out of the overlapping boxes and
    tests every particle; the last one tests only the particles that moved more than
    FINAL_RECHECK x thickness since (none here: the quad lies flat and unstretched on A's top),
    and the quad ends where the first pass put it (`ClothSim.union_tested`). Then with corner 3
    6 cm above A's top (no slide pass): the first union pass puts the other three out and
    leaves it, the held strain-limiting passes pull it down towards them, and the last union
    pass tests that one particle alone; none ends inside."""
    sim, _ = quad_in_overlapping_boxes(2)
    top = 0.2 + sim.model.fabric.thickness
    sim.settle_contacts(sim.pose)
    np.testing.assert_array_equal(sim.union_tested, [4, 0])
    np.testing.assert_allclose(sim.state.x[:, 1], top, atol=1e-12)
    assert sim.stats.union_pushes == 4

    sim, verts = quad_in_overlapping_boxes(2, slide_passes=0)
    sim.state.x[3, 1] = 0.26
    sim.settle_contacts(sim.pose)
    np.testing.assert_array_equal(sim.union_tested, [4, 1])
    assert sim.stats.union_pushes == 3
    x = sim.state.x
    np.testing.assert_allclose(x[:3, 1], top, atol=1e-12)
    assert top < x[3, 1] < 0.26 - 0.01  # pulled down, still above the others
    np.testing.assert_array_equal(windings(verts, sim.body.triangles, x), 0)


def test_leave_body_union_goes_straight_out_through_the_nearest_face():
    """A sphere of 10 cm (an icosphere of 1,280 faces: a limb's curve), the particle 3 cm inside
    its surface in a direction that is neither an axis nor between axes: the nearest way out
    is through the nearest face, to its closest point (by trimesh), and the particle lands
    thickness beyond it along the way it left, its inward velocity removed. An axis ray leaves
    the sphere through another face, whose plane is farther."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    faces = sphere.faces.astype(np.int32)
    d = np.array([0.31, 0.52, 0.80])
    d /= np.linalg.norm(d)
    p = 0.07 * d
    on_faces = trimesh.triangles.closest_point(sphere.triangles, np.repeat([p], len(faces), axis=0))
    q = on_faces[np.argmin(np.linalg.norm(on_faces - p, axis=1))]
    out = (q - p) / np.linalg.norm(q - p)
    x, vel, placed, moved = push_out(sphere.vertices, faces, [p], [-out], thickness=0.005)
    assert moved == 1 and placed[0] == 0.0
    np.testing.assert_allclose(x[0], q + 0.005 * out, atol=1e-9)
    np.testing.assert_allclose(vel[0], 0.0, atol=1e-12)
    assert windings(sphere.vertices, faces, x, cell=0.05)[0] == 0


def test_the_collision_body_keeps_each_foot_with_its_lower_leg_for_the_coarse_cloth_only(body):
    """The cloth service's collision body: S101 walks a lower leg and its foot as one region (a
    trouser leg covers both: the regions of the coarse cloth are the lower leg's bit there), while
    S103 tells them apart (`BodyMesh.parts`), as the upper arm and the forearm: in a squat the
    flexed ankle folds the top of the foot into the shin under the hem, where a walk over the shin
    stops outside it."""
    from services.cloth_job import collision_body
    from skinning.body import BODY_REGIONS, body_regions

    mesh = collision_body(body)
    regions = body_regions(body)[mesh.vertex_order]
    for side in ("left", "right"):
        foot, leg = BODY_REGIONS[f"{side}_foot"], BODY_REGIONS[f"{side}_lower_leg"]
        on_foot = regions == foot
        assert on_foot.sum() > 500
        assert (mesh.parts[on_foot] == foot).all() and (mesh.regions[on_foot] == leg).all()
        assert (mesh.parts[regions == leg] == leg).all() and (mesh.regions[regions == leg] == leg).all()
    # the coarse cloth's regions: the lower legs', the thighs', the torso's and the upper arms' bits only
    assert set(np.unique(mesh.regions).tolist()) == {1, 2, 4, 8, 16, 32, 64}
    assert set(np.unique(mesh.parts).tolist()) == set(BODY_REGIONS.values())


def test_the_cloth_winding_number_counts_the_whole_hands(body):
    """The collision body's winding surface keeps the whole hands (`BodyMesh.wound_faces`,
    WRIST_REACH None): within 3 cm of the hands' skin, fingers and thumbs included, it says inside
    exactly where the independent test does (tests/signed_distance.py, over the whole skin), where
    the clothed faces alone, capped at the wrists, said outside inside the hand, and the hands
    capped 6 cm from the wrist (the rule before) said outside inside the fingers."""
    from services.cloth_job import WRIST_REACH, collision_body
    from skinning.body import ARM_LIMBS, LEG_LIMBS, body_clothed_faces, body_hand_faces, body_regions
    from tests.signed_distance import SignedDistance

    assert WRIST_REACH is None
    mesh = collision_body(body)
    skin = np.asarray(body.vertices[: body.n_visible], dtype=np.float64)
    x = mesh.internal(body.vertices)
    hand, clothed = body_hand_faces(body), body_clothed_faces(body)
    hand_skin = skin[np.unique(body.triangles[hand])]
    rng = np.random.default_rng(7)
    points = rng.uniform(hand_skin.min(axis=0) - 0.03, hand_skin.max(axis=0) + 0.03, size=(200000, 3))
    near = np.zeros(len(points), dtype=bool)
    for chunk in np.array_split(np.arange(len(points)), 20):
        near[chunk] = ((points[chunk, None, :] - hand_skin[None, ::4, :]) ** 2).sum(axis=2).min(axis=1) < 0.03**2
    points = points[near]
    expected = SignedDistance(body.triangles, body.n_visible).winding_numbers(skin, points) >= 1
    got = windings(x, mesh.winding_faces, points) >= 1
    clothed_only = windings(x, closed_faces(mesh.triangles, mesh.clothed_faces), points) >= 1
    before = BodyMesh.build(body.triangles, body.n_visible, body_regions(body), clothed, body.vertices,
                            limbs=ARM_LIMBS + LEG_LIMBS, wound_faces=clothed | body_hand_faces(body, 0.06))
    to_6cm = windings(before.internal(body.vertices), before.winding_faces, points) >= 1
    in_hand = expected & ~clothed_only  # inside the hand (the clothed skin's cap is flat at the wrist)
    in_fingers = expected & ~to_6cm
    assert in_hand.sum() > 1000 and in_fingers.sum() > 300
    np.testing.assert_array_equal(got, expected)
    assert mesh.wound_faces.sum() == clothed.sum() + hand.sum()


def reference_columns(x, tris, lo):
    """The winding grid's columns built the plain way (face order in each column), from the grid
    corner, counts and side the kernel chose: start, ids, span (each entry's face's box: low and
    high along the ray, then across it; exact, where the grid's is widened to single precision), extent."""
    u0, v0, nu, nv, cell = lo[0], lo[1], int(lo[2]), int(lo[3]), lo[4]
    col = np.minimum(((x[:, :2] - [u0, v0]) * (1.0 / cell)).astype(np.int64), [nu - 1, nv - 1])
    lists = [[] for _ in range(nu * nv)]
    for t, f in enumerate(tris):
        for i in range(col[f, 0].min(), col[f, 0].max() + 1):
            for k in range(col[f, 1].min(), col[f, 1].max() + 1):
                lists[i * nv + k].append(t)
    start = np.concatenate([[0], np.cumsum([len(c) for c in lists])])
    ids = np.array([t for c in lists for t in c], dtype=np.int64)
    z = x[tris, 2]
    span = np.stack([x[tris, a].min(axis=1)[ids] if low else x[tris, a].max(axis=1)[ids]
                     for a in (2, 0, 1) for low in (True, False)], axis=1)  # along the ray, then across it
    extent = np.array([[z[c].min(), z[c].max()] if c else [np.inf, -np.inf] for c in lists])
    return start, ids, span, extent


@pytest.mark.parametrize("cell", [0.02, 0.004])
def test_the_winding_grid_holds_each_face_in_every_column_its_box_covers(body, cell):
    """The grid's build writes a face within 2 x 2 columns (nearly all of the body's at 2 cm)
    without a loop, and larger ones (all at 4 mm, and the caps' long fans) with one: either way
    each column lists exactly the faces whose box across the ray overlaps it, in face order, with
    their boxes and the column's extent along the ray, on the body at rest and turned about
    every axis; the overlapping boxes (faces 40 cm across in 5 cm columns) too."""
    from services.cloth_job import collision_body

    def turn(axis, degrees):
        c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
        i, j = [k for k in range(3) if k != axis]
        r = np.eye(3)
        r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
        return r

    mesh = collision_body(body)
    rest = mesh.internal(body.vertices)
    poses = [rest] + [rest @ turn(axis, degrees).T for axis, degrees in ((0, 30), (1, 45), (2, 60))]
    faces = mesh.winding_faces
    v, f = overlapping_boxes()
    for x, tris, side in [(np.ascontiguousarray(p), faces, cell) for p in poses] + [(v, f, 0.05)]:
        g = WindingGrid(tris, len(x), cell=side)
        g.update(np.ascontiguousarray(x, dtype=np.float64))
        lo, start, ids, span, extent = g.arrays()
        n = int(lo[2] * lo[3])
        want = reference_columns(x, np.asarray(tris), lo)
        np.testing.assert_array_equal(start[: n + 1], want[0])
        np.testing.assert_array_equal(ids[: start[n]], want[1])
        # each entry's box (single precision) holds its face's, and is hardly wider
        box = span[:, : start[n]].T.astype(np.float64)  # (one row per box side)
        assert span.dtype == np.float32
        assert (box[:, 0::2] <= want[2][:, 0::2]).all() and (box[:, 1::2] >= want[2][:, 1::2]).all()
        np.testing.assert_allclose(box, want[2], rtol=0, atol=1e-5)
        full = np.diff(want[0]) > 0  # a column's extent along the ray: its entries', so it holds its faces'
        assert (extent[:n][full, 0] <= want[3][full, 0]).all() and (extent[:n][full, 1] >= want[3][full, 1]).all()
        np.testing.assert_allclose(extent[:n][full], want[3][full], rtol=0, atol=1e-5)
        np.testing.assert_array_equal(extent[:n][~full], want[3][~full])
        sizes = np.diff(want[0])
        if tris is faces and side == 0.02:
            assert start[n] > 2 * len(tris) and sizes.max() > 30  # most faces in several columns


def test_winding_numbers_are_the_same_whatever_the_columns_hold(body):
    """Near the skin, where most queries are, the winding number skips a column's faces by their
    entries (span along the ray, box across it) and crosses only those left, 64 entries at a
    time: the same answer from 2 cm columns (~23 faces), 4 mm ones (a few) and 40 cm ones (more
    than 64 entries, several rounds of the mask), and the brute-force solid angle's on a sample;
    the same 500 m from the origin."""
    from services.cloth_job import collision_body

    mesh = collision_body(body)
    x = np.ascontiguousarray(mesh.internal(body.vertices), dtype=np.float64)
    faces = mesh.winding_faces
    used = np.unique(faces)
    rng = np.random.default_rng(11)
    corners = x[used[rng.choice(len(used), 4000)]]
    points = corners + rng.normal(scale=0.004, size=corners.shape)  # within a few mm of the skin
    wide = WindingGrid(faces, len(x), cell=0.4)
    wide.update(x)
    lo, start = wide.arrays()[:2]
    assert np.diff(start[: int(lo[2] * lo[3]) + 1]).max() > 3 * 64
    got = {cell: windings(x, faces, points, cell=cell) for cell in (0.02, 0.004, 0.4)}
    assert 500 < (got[0.02] >= 1).sum() < 3500
    np.testing.assert_array_equal(got[0.004], got[0.02])
    np.testing.assert_array_equal(got[0.4], got[0.02])
    np.testing.assert_array_equal(got[0.02][:150], np.round(solid_angle_winding(x, faces, points[:150])))
    # far from the origin too, where single precision's steps are wider than the box's fixed slack
    far = np.array([400.0, 0.0, -300.0])
    np.testing.assert_array_equal(windings(x + far, faces, points + far), got[0.02])


def test_lowest_bit_finds_the_lowest_set_bit_of_every_word():
    """The winding number's mask is read from its lowest set bit up (de Bruijn's multiply): every
    position 0-63, with any higher bits set or not."""
    rng = np.random.default_rng(3)
    for k in range(64):
        low = np.uint64(1) << np.uint64(k)
        for high in (0, int(rng.integers(0, 2**63)), 2**64 - 1):
            word = (np.uint64(high) & ~(low - np.uint64(1))) | low  # bits below k cleared, bit k set
            assert lowest_bit(word) == k


def column_winding(x, tris, grid, p):
    """The winding number of p as `winding_number` counts it, but crossing every face of p's
    column (no entry skipped by its box)."""
    from cloth.winding import U, V, W, ray_crossing

    lo, start, ids, span, extent = grid.arrays()
    i, k = np.floor((p[U] - lo[0]) / lo[4]), np.floor((p[V] - lo[1]) / lo[4])
    if i < 0 or k < 0 or i >= lo[2] or k >= lo[3]:
        return 0
    c = int(i) * int(lo[3]) + int(k)
    if p[W] >= extent[c, 1] or p[W] < extent[c, 0]:
        return 0
    beyond = 2.0 * p[W] >= extent[c, 0] + extent[c, 1]
    w = 0
    for e in range(start[c], start[c + 1]):
        h, s = ray_crossing(x, tris, ids[e], p[U], p[V], U, V, W)
        if beyond and h > p[W]:
            w += s
        elif not beyond and h < p[W]:
            w -= s
    return w


def test_the_box_tests_skip_only_faces_the_ray_cannot_cross(body):
    """The winding number skips a column's entries by their single-precision boxes, compared with p
    rounded to single precision: the same count as crossing every face of the column, near the
    skin and at points on the boxes' bounds, within a float64 step of them, where that rounding
    meets the bound (the boxes are widened by more than it)."""
    from cloth.winding import U, V, W
    from services.cloth_job import collision_body

    mesh = collision_body(body)
    x = np.ascontiguousarray(mesh.internal(body.vertices), dtype=np.float64)
    faces = mesh.winding_faces
    g = WindingGrid(faces, len(x))
    g.update(x)
    lo, start, ids, span, extent = g.arrays()
    rng = np.random.default_rng(5)
    used = np.unique(faces)
    points = list(x[used[rng.choice(len(used), 1500)]] + rng.normal(scale=0.004, size=(1500, 3)))
    for e in rng.choice(int(start[int(lo[2] * lo[3])]), 1500):
        w_lo, w_hi, u_lo, u_hi, v_lo, v_hi = (float(b) for b in span[:, e])
        p = np.zeros(3)
        p[U] = rng.choice([u_lo, u_hi, np.nextafter(u_lo, -np.inf), np.nextafter(u_hi, np.inf), (u_lo + u_hi) / 2])
        p[V] = rng.choice([v_lo, v_hi, np.nextafter(v_lo, -np.inf), np.nextafter(v_hi, np.inf), (v_lo + v_hi) / 2])
        p[W] = rng.choice([w_lo, w_hi, np.nextafter(w_lo, -np.inf), np.nextafter(w_hi, np.inf), (w_lo + w_hi) / 2])
        points.append(p)
    points = np.array(points)
    out = np.zeros(len(points), dtype=np.int64)
    winding_numbers(points, x, g.tris, *g.arrays(), out)
    want = np.array([column_winding(x, g.tris, g, p) for p in points])
    np.testing.assert_array_equal(out, want)
    assert (want[:1500] >= 1).sum() > 200  # some near-skin points inside
