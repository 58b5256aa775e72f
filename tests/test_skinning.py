import numpy as np

from skinning.animate import BodyAnimator
from skinning.skin import (MeshNormals, SkinWeights, linear_blend_skinning, skin_matrices, vertex_faces,
                           vertex_normals_at)


def test_rest_pose_reproduces_rest_mesh(body):
    animator = BodyAnimator(body)
    frame = animator.pose(animator.rest_configuration())
    np.testing.assert_allclose(frame.vertices, body.vertices + animator.world_offset, atol=1e-12)
    assert abs(frame.vertices[: body.n_visible, 1].min()) < 1e-12  # soles on the floor y = 0


def test_the_visible_skin_alone_is_the_whole_bodys_visible_part_bit_for_bit(body):
    """helpers=False (the ingest, which publishes the visible skin): the helper vertices are not
    skinned, and the visible ones are what the whole body's skinning gives them, contact and all."""
    whole, visible = BodyAnimator(body), BodyAnimator(body, helpers=False)
    q = whole.rest_configuration()
    rng = np.random.default_rng(5)
    for joint in range(2, len(q) // 4):  # (spherical joints' quaternions after the free flyer)
        i = 7 + 4 * (joint - 2)
        if i + 4 <= len(q):
            turn = rng.normal(size=4) * [0.2, 0.2, 0.2, 0.0] + [0.0, 0.0, 0.0, 1.0]
            q[i:i + 4] = turn / np.linalg.norm(turn)
    a, b = whole.pose(q).vertices, visible.pose(q).vertices
    assert a.shape == body.vertices.shape and b.shape == (body.n_visible, 3)
    np.testing.assert_array_equal(b, a[: body.n_visible])


def test_single_bone_vertex_moves_rigidly(body):
    rng = np.random.default_rng(3)
    n_bones = len(body.skeleton.names)
    rot = np.empty((n_bones, 3, 3))
    for b in range(n_bones):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        rot[b] = q * np.sign(np.linalg.det(q))
    pos = rng.normal(size=(n_bones, 3))
    mats = np.empty((n_bones, 3, 4))
    skin_matrices(rot, pos, body.skeleton.heads, mats)
    out = np.empty_like(body.vertices)
    w = SkinWeights.from_padded(body.weight_bones, body.weight_values)
    linear_blend_skinning(body.vertices, w.start, w.bones, w.weights, mats, out)
    rigid = np.flatnonzero(body.weight_values.max(axis=1) == 1.0)
    assert len(rigid) > 1000
    bone = body.weight_bones[rigid, body.weight_values[rigid].argmax(axis=1)]
    expected = np.einsum("vij,vj->vi", rot[bone], body.vertices[rigid] - body.skeleton.heads[bone]) + pos[bone]
    np.testing.assert_allclose(out[rigid], expected, atol=1e-12)
    # distances between vertices on the same bone are preserved exactly
    same = rigid[bone == bone[0]]
    d_rest = np.linalg.norm(body.vertices[same[0]] - body.vertices[same[1:]], axis=1)
    d_posed = np.linalg.norm(out[same[0]] - out[same[1:]], axis=1)
    np.testing.assert_allclose(d_posed, d_rest, atol=1e-12)


def test_vertex_normals_of_a_cube_point_outward():
    v = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=float)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], dtype=np.int32)
    n = MeshNormals(tris, len(v))(v, np.empty_like(v))
    outward = v - 0.5
    assert (np.einsum("ij,ij->i", n, outward) > 0).all()
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0)


def test_normals_at_some_vertices_match_the_whole_mesh_normals_bit_for_bit():
    """The skin contact's normals of its clothed vertices only: the whole mesh's there, to the bit,
    and the other rows untouched."""
    rng = np.random.default_rng(3)
    v = rng.normal(size=(40, 3))
    tris = rng.integers(0, 40, size=(60, 3)).astype(np.int64)
    tris = tris[(tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 0] != tris[:, 2])]
    whole = MeshNormals(tris, len(v))(v, np.empty_like(v))
    start, faces = vertex_faces(tris, len(v))
    some = np.arange(0, 40, 3)
    out = np.full_like(v, 7.0)
    vertex_normals_at(v, tris, start, faces, np.empty((len(tris), 3)), some, out)
    assert out[some].tobytes() == whole[some].tobytes()
    rest = np.setdiff1d(np.arange(40), some)
    assert (out[rest] == 7.0).all()


def test_normals_of_a_flat_grid_are_exact():
    xs, zs = np.meshgrid(np.arange(4.0), np.arange(3.0))
    v = np.stack([xs.ravel(), np.zeros(xs.size), zs.ravel()], axis=1)
    tris = []
    for r in range(2):
        for c in range(3):
            a = r * 4 + c
            tris += [(a, a + 4, a + 1), (a + 1, a + 4, a + 5)]
    n = MeshNormals(np.array(tris), len(v))(v, np.empty_like(v))
    np.testing.assert_allclose(n, np.tile([0.0, 1.0, 0.0], (len(v), 1)), atol=1e-15)


def test_body_regions_and_clothed_faces_follow_the_dominant_bones(body):
    """A face is left out of the clothed faces exactly when all three corners are dominated by
    a bone of the head, the hands or the toes; a vertex's region is its dominant bone's limb."""
    from skinning.body import BODY_REGIONS, body_clothed_faces, body_regions

    names = body.skeleton.names
    vis = np.arange(body.n_visible)
    dominant = np.array(names)[body.weight_bones[vis, np.argmax(body.weight_values[vis], axis=1)]]
    bare = np.isin(dominant, ["Head", "LeftHand", "LeftFingerBase", "LeftHandFinger1", "LThumb", "RightHand",
                              "RightFingerBase", "RightHandFinger1", "RThumb", "LeftToeBase", "RightToeBase"])
    clothed = body_clothed_faces(body)
    np.testing.assert_array_equal(clothed, ~bare[body.triangles].all(axis=1))
    assert 0.2 < clothed.mean() < 0.5  # the head, hands and toes are most of MakeHuman's triangles
    spine = (dominant[body.triangles] == "Spine").all(axis=1)
    assert spine.any() and clothed[spine].all()
    regions = body_regions(body)
    assert (regions[dominant == "LeftUpLeg"] == BODY_REGIONS["left_thigh"]).all()
    assert (regions[dominant == "RightLeg"] == BODY_REGIONS["right_lower_leg"]).all()
    assert (regions[dominant == "Spine"] == BODY_REGIONS["torso"]).all()
    # the arms split at the elbow, the hand with the forearm; region bits past uint8
    assert (regions[dominant == "LeftArm"] == BODY_REGIONS["left_upper_arm"]).all()
    assert (regions[np.isin(dominant, ["RightForeArm", "RightHand"])] == BODY_REGIONS["right_forearm"]).all()
    assert regions.dtype == np.uint16 and BODY_REGIONS["right_forearm"] > 255
    # the legs split at the ankle too, the toes with the foot
    assert (regions[np.isin(dominant, ["LeftFoot", "LeftToeBase"])] == BODY_REGIONS["left_foot"]).all()
    assert (regions[dominant == "RightFoot"] == BODY_REGIONS["right_foot"]).all()
    assert np.count_nonzero(dominant == "RightFoot") > 100
    assert (regions[dominant == "LeftLeg"] == BODY_REGIONS["left_lower_leg"]).all()
