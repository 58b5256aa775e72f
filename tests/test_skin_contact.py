"""Skin contact (skinning/contact.py): where the skinned body cuts through itself, the two skins
meet halfway."""

import numpy as np
import pytest
import trimesh

from services.body_job import SelfContact
from skinning.animate import BodyAnimator
from skinning.character import configuration_to_local, local_to_configuration
from skinning.contact import ContactSettings, SkinContact, _cell_hash, build_face_grid, face_boxes
from skinning.kinematics import axis_rotation
from skinning.source import BVHSource
from tests.signed_distance import SignedDistance


def two_boxes(overlap: float):
    """Two 20 cm cubes side by side along x, the second cutting `overlap` into the first; at rest
    the second stood 40 cm away. Returns (rest, posed, triangles, which box per vertex)."""
    box = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    for _ in range(3):
        box = box.subdivide()
    v, f = np.asarray(box.vertices), np.asarray(box.faces)
    shift = np.array([0.2 - overlap, 0.0, 0.0])
    posed = np.vstack([v, v + shift])
    rest = np.vstack([v, v + shift + [0.4, 0.0, 0.0]])
    tris = np.vstack([f, f + len(v)])
    return rest, posed, tris, np.repeat([0, 1], len(v))


@pytest.mark.parametrize("gap", [0.0, 0.003])
def test_overlapping_boxes_meet_on_the_midplane_a_gap_apart(gap):
    rest, posed, tris, which = two_boxes(0.02)
    x = posed.copy()
    contact = SkinContact(rest, tris, ContactSettings(gap=gap))
    moved = contact(x)
    # the faces that cut into each other: A's at x = 0.1, B's at x = 0.08; away from their rims
    # every vertex normal is the face's, and each ray leaves the other box after 2 cm: each goes
    # back 1 cm and the gap into its own box
    inner = (np.abs(posed[:, 1]) < 0.09) & (np.abs(posed[:, 2]) < 0.09)
    face_a = inner & (which == 0) & np.isclose(posed[:, 0], 0.1)
    face_b = inner & (which == 1) & np.isclose(posed[:, 0], 0.08)
    assert face_a.sum() > 20 and face_b.sum() > 20
    np.testing.assert_allclose(x[face_a, 0], 0.09 - gap, atol=1e-9)
    np.testing.assert_allclose(x[face_b, 0], 0.09 + gap, atol=1e-9)
    np.testing.assert_array_equal(x[face_a | face_b, 1:], posed[face_a | face_b, 1:])
    # beyond the lens's 2 cm rims and the smoothing's two rings of 2.5 cm edges nothing moves
    near = ((which == 0) & (posed[:, 0] > 0.08 - 0.05 - 1e-9)) | ((which == 1) & (posed[:, 0] < 0.1 + 0.05 + 1e-9))
    np.testing.assert_array_equal(x[~near], posed[~near])
    assert moved == np.count_nonzero(np.any(x != posed, axis=1))


def test_a_lens_met_halfway_already_is_not_moved_again():
    """Facing sheets meet on the midplane in the first round: the later rounds find no lens left."""
    rest, posed, tris, _ = two_boxes(0.02)
    once, thrice = posed.copy(), posed.copy()
    SkinContact(rest, tris, ContactSettings(rounds=1))(once)
    SkinContact(rest, tris, ContactSettings(rounds=3))(thrice)
    np.testing.assert_array_equal(thrice, once)


def test_later_rounds_take_out_what_halfway_left_of_a_slanted_lens():
    """A box turned 30 degrees about z cuts 2 cm into another: the sheets' normals are not
    opposite, so halfway along each normal leaves the turned box's corner edge inside the other
    box (the independent signed distance); the later rounds measure what is left and take it out."""
    box = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    for _ in range(3):
        box = box.subdivide()
    v, f = np.asarray(box.vertices), np.asarray(box.faces)
    c, s = np.cos(np.radians(30.0)), np.sin(np.radians(30.0))
    turned = v @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T
    turned[:, 0] += 0.1 - turned[:, 0].min() - 0.02
    posed = np.vstack([v, turned])
    rest = np.vstack([v, turned + [0.4, 0.0, 0.0]])
    tris = np.vstack([f, f + len(v)])
    a_mesh = SignedDistance(f, len(v))
    depth = {}
    for rounds in (1, 3):
        x = posed.copy()
        SkinContact(rest, tris, ContactSettings(rounds=rounds))(x)
        depth[rounds] = (a_mesh(x[:len(v)], x[len(v):]).min(), a_mesh(x[len(v):], x[:len(v)]).min())
    assert depth[1][0] < -0.0005  # the turned box 0.85 mm inside the other after one round
    assert min(depth[3]) > 0.0  # 0.16 mm out after three; the first box's skin 3.3 mm out of the turned one


def test_far_side_of_the_own_part_and_the_rest_pose_are_left_alone():
    rest, posed, tris, _ = two_boxes(0.02)
    # boxes apart (a 1 cm gap): every ray leaves through its own box's far side, 20 cm away
    apart = posed.copy()
    apart[len(posed) // 2:, 0] += 0.03
    x = apart.copy()
    assert SkinContact(rest, tris)(x) == 0
    np.testing.assert_array_equal(x, apart)
    # the rest pose itself, even with the boxes touching there: nothing was farther at rest
    x = posed.copy()
    assert SkinContact(posed, tris)(x) == 0


def test_settings_are_validated():
    with pytest.raises(ValueError, match="ContactSettings.reach"):
        ContactSettings(reach=0.0)
    for gap in (-0.001, ContactSettings().reach):
        with pytest.raises(ValueError, match="ContactSettings.gap"):
            ContactSettings(gap=gap)
    assert ContactSettings().gap == 0.003
    for rounds in (0, 1.5):
        with pytest.raises(ValueError, match="ContactSettings.rounds"):
            ContactSettings(rounds=rounds)


def test_face_grid_lists_each_face_in_the_cells_of_its_box_in_face_order():
    """The rays' face grid, against a brute-force bucketing: each face in every hashed cell its
    bounding box overlaps, once per cell, a cell's faces in face order; ids grown when short."""
    rest, posed, tris, _ = two_boxes(0.05)
    tris = tris.astype(np.int64)
    m, cell, mask = len(tris), 0.02, (1 << 6) - 1  # a small table: many cells share a slot
    corners = np.empty((m, 9))
    lo, hi = np.empty((m, 3), np.int32), np.empty((m, 3), np.int32)
    start, counts = np.zeros(mask + 2, np.int32), np.zeros(mask + 1, np.int32)
    ids = np.zeros(8, np.int32)  # too short: build_face_grid says how many it needs
    face_boxes(posed, tris, 1.0 / cell, mask, corners, lo, hi, counts)
    need = build_face_grid(lo, hi, mask, start, ids, counts)
    assert need > len(ids)
    ids = np.zeros(need, np.int32)
    face_boxes(posed, tris, 1.0 / cell, mask, corners, lo, hi, counts)
    assert build_face_grid(lo, hi, mask, start, ids, counts) == need
    expected = [[] for _ in range(mask + 1)]
    for t, (a, b, c) in enumerate(tris):
        box_lo = np.floor(posed[[a, b, c]].min(axis=0) / cell).astype(int)
        box_hi = np.floor(posed[[a, b, c]].max(axis=0) / cell).astype(int)
        np.testing.assert_array_equal(lo[t], box_lo)
        np.testing.assert_array_equal(hi[t], box_hi)
        np.testing.assert_array_equal(corners[t], posed[[a, b, c]].ravel())
        for i in range(box_lo[0], box_hi[0] + 1):
            for j in range(box_lo[1], box_hi[1] + 1):
                for k in range(box_lo[2], box_hi[2] + 1):
                    expected[_cell_hash(i, j, k, mask)].append(t)
    assert need == sum(len(e) for e in expected)
    for h in range(mask + 1):
        assert list(ids[start[h]:start[h + 1]]) == expected[h]


THIGH, KNEE = -80.0, 110.0


def test_bent_knee_and_raised_thigh_skins_meet(body):
    sk = body.skeleton
    plain = BodyAnimator(body, contact=None)
    fixed = BodyAnimator(body)
    q = plain.rest_configuration()
    local, root = np.empty((len(sk.names), 3, 3)), np.empty(3)
    configuration_to_local(q, plain.character.idx_q, local, root)
    # a high step: the left thigh raised into the belly, the knee bent
    axis_rotation(0, THIGH, local[sk.index("LeftUpLeg")])
    axis_rotation(0, KNEE, local[sk.index("LeftLeg")])
    local_to_configuration(local, root, plain.character.idx_q, q)
    inside = SelfContact(body)  # the winding number of the capped clothed skin: independent
    before = plain.pose(q)
    inside_before = inside.inside(before.vertices, before.normals)
    after = fixed.pose(q)
    inside_after = inside.inside(after.vertices, after.normals)
    assert fixed.contact.moved > 30
    assert len(inside_before) > 40  # 68 when written
    assert len(inside_after) < 0.25 * len(inside_before)  # 11
    # the right leg, nowhere near, is untouched
    right = body.weight_bones[: body.n_visible, 0] == sk.index("RightLeg")
    np.testing.assert_array_equal(after.vertices[: body.n_visible][right], before.vertices[: body.n_visible][right])


def test_later_rounds_halve_what_the_walks_crouch_leaves_inside(body, mocap):
    """The walk's crouch (frames 184-192 at 60 Hz): the right arm bent against the thigh, the knees
    bent. Clothed skin more than 2 mm inside another part (SelfContact, the independent winding
    number) after one round of the skin contact, and after the default three: 241 and 112 vertices
    over the five frames when written."""
    inside = SelfContact(body)
    counts = {}
    for rounds in (1, ContactSettings().rounds):
        with BVHSource(mocap / "cmu_131_01_walk_3dsmax.bvh", every=2, max_frames=194) as source:
            animator = BodyAnimator(body, source.skeleton, contact=ContactSettings(rounds=rounds))
            counts[rounds] = sum(len(inside.inside(f.vertices, f.normals)) for f in
                                 (animator(fr.local_rot, fr.root_position) for fr in source
                                  if fr.index >= 184 and fr.index % 2 == 0))
    assert ContactSettings().rounds == 3
    assert counts[1] > 150
    assert counts[3] < 0.6 * counts[1]
