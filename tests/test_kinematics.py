import numpy as np
import pinocchio as pin
import pytest

from skinning.animate import BodyAnimator
from skinning.character import Character
from skinning.kinematics import rotation_between
from skinning.retarget import Retargeter, alignment_rotations
from skinning.skeleton import CMU_BONES


def random_configuration(character, rng, scale=0.4):
    q = character.neutral()
    q = pin.integrate(character.model, q, rng.normal(scale=scale, size=character.model.nv))
    return q


def test_body_loads_all_vertices_in_metres(body):
    assert body.vertices.shape == (19158, 3)
    assert body.n_visible == 13380
    assert body.triangles.shape == (2 * 13378, 3)
    assert body.triangles.max() < body.n_visible
    height = np.ptp(body.visible_vertices[:, 1])
    assert height == pytest.approx(1.666, abs=0.01)
    np.testing.assert_allclose(body.weight_values.sum(axis=1), 1.0, atol=1e-12)
    assert body.skeleton.names == CMU_BONES
    # joints from the joint cubes: the hips' cube centroid, in metres
    assert 0.0 < body.skeleton.heads[0, 1] < 0.2


def test_pinocchio_model_structure(body):
    ch = Character(body.skeleton)
    assert ch.model.nq == 7 + 4 * 30 and ch.model.nv == 6 + 3 * 30
    data = ch.model.createData()
    pin.forwardKinematics(ch.model, data, ch.neutral())
    for b, jid in enumerate(ch.joint_ids):
        np.testing.assert_allclose(data.oMi[int(jid)].translation, body.skeleton.heads[b], atol=1e-12)
        np.testing.assert_allclose(data.oMi[int(jid)].rotation, np.eye(3), atol=1e-12)


def test_numba_forward_kinematics_matches_pinocchio(body):
    ch = Character(body.skeleton)
    data = ch.model.createData()
    rng = np.random.default_rng(1)
    n = len(body.skeleton.names)
    local, root, g_rot, g_pos = np.empty((n, 3, 3)), np.empty(3), np.empty((n, 3, 3)), np.empty((n, 3))
    for _ in range(5):
        q = random_configuration(ch, rng)
        pin.forwardKinematics(ch.model, data, q)
        ch.global_pose(q, local, root, g_rot, g_pos)
        for b, jid in enumerate(ch.joint_ids):
            np.testing.assert_allclose(g_pos[b], data.oMi[int(jid)].translation, atol=1e-12)
            np.testing.assert_allclose(g_rot[b], data.oMi[int(jid)].rotation, atol=1e-12)
        # and back: configuration from local rotations reproduces q (up to quaternion sign)
        q2 = ch.configuration(local, root)
        assert np.linalg.norm(pin.difference(ch.model, q, q2)) < 1e-9


def test_rotation_between():
    a, b = np.array([0.0, -1.0, 0.0]), np.array([1.0, 0.0, 0.0])
    r = rotation_between(a, b)
    np.testing.assert_allclose(r @ a, b, atol=1e-12)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(rotation_between(a, -a) @ a, -a, atol=1e-12)


def test_alignment_maps_character_rest_onto_person_rest(body, mocap):
    from skinning.bvh import read_bvh

    header, _ = read_bvh(mocap / "cmu_131_01_walk_3dsmax.bvh")  # arms-down rest pose
    person, cs = header.skeleton, body.skeleton
    align = alignment_rotations(cs, person)
    for name in ("LeftArm", "LeftForeArm", "RightUpLeg", "RightLeg", "LeftFoot"):
        b, pb = cs.index(name), person.index(name)
        d_char = align[b] @ (cs.tails[b] - cs.heads[b])
        d_person = person.tails[pb] - person.heads[pb]
        cosang = d_char @ d_person / np.linalg.norm(d_char) / np.linalg.norm(d_person)
        assert cosang == pytest.approx(1.0, abs=1e-9), name


@pytest.fixture(scope="module")
def solver(body):
    animator = BodyAnimator(body)
    return Retargeter(animator.character, body.skeleton)  # person = character: same names


def _leg_targets(solver, q):
    data = solver.character.model.createData()
    pin.forwardKinematics(solver.character.model, data, q)
    rots, poss = np.empty((2, 3, 3)), np.empty((2, 3))
    for k, leg in enumerate(solver.legs):
        rots[k] = data.oMi[leg["jid"]].rotation
        poss[k] = data.oMi[leg["jid"]].translation
    return rots, poss


def test_ik_converges_on_reachable_targets(solver):
    ch = solver.character
    rng = np.random.default_rng(7)
    for trial in range(20):
        q_true = random_configuration(ch, rng, scale=0.35)
        rot, pos = _leg_targets(solver, q_true)
        q = q_true.copy()
        for leg in solver.legs:  # legs start from rest with a slight knee bend
            q[leg["qslice"]] = ch.neutral()[leg["qslice"]]
        pos_err, rot_err, _ = solver.solve(q, rot, pos)
        assert pos_err.max() < 1e-3, (trial, pos_err)
        assert rot_err.max() < np.deg2rad(0.5), (trial, rot_err)
        # only the legs moved
        others = np.ones(ch.model.nq, bool)
        for leg in solver.legs:
            others[leg["qslice"]] = False
        np.testing.assert_array_equal(q[others], q_true[others])


def test_ik_degrades_gracefully_on_unreachable_targets(solver):
    ch = solver.character
    q = ch.neutral()
    rot, pos = _leg_targets(solver, q)
    pos[:, 1] -= 0.3  # 30 cm below a straight leg's reach
    pos[0, 0] += 0.5
    pos_err, rot_err, iters = solver.solve(q, rot, pos)
    assert np.isfinite(q).all() and np.isfinite(pos_err).all()
    data = ch.model.createData()
    pin.forwardKinematics(ch.model, data, q)
    sk = ch.skeleton
    for k, leg in enumerate(solver.legs):
        hip = data.oMi[int(ch.joint_ids[leg["bones"][0]])].translation
        ankle = data.oMi[leg["jid"]].translation
        reach = sk.leg_length("left")
        # the leg stretches towards the target as far as it goes
        assert np.linalg.norm(ankle - hip) > 0.98 * reach
        assert pos_err[k] == pytest.approx(np.linalg.norm(pos[k] - hip) - np.linalg.norm(ankle - hip), abs=0.02)
