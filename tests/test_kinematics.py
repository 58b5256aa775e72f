import re

import numpy as np
import pinocchio as pin
import pytest

from skinning.animate import BodyAnimator
from skinning.character import Character
from skinning.kinematics import rotation_between
from skinning.retarget import IKSettings, Retargeter, alignment_rotations
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


def _frontal_angles(rt, side="Left"):
    """Elbow's and wrist's angle (deg) from the chest's down axis in its frontal plane, seen from
    the shoulder (positive: away from the body), and their forward offset (m), after
    Retargeter.copied_pose."""
    cs = rt.character.skeleton
    chest = rt._char_global[cs.index("Spine1")]
    shoulder = rt._fk_pos[cs.index(f"{side}Arm")]
    out = 1.0 if side == "Left" else -1.0
    res = []
    for joint in (f"{side}ForeArm", f"{side}Hand"):
        d = chest.T @ (rt._fk_pos[cs.index(joint)] - shoulder)
        res.append((np.degrees(np.arctan2(out * d[0], -d[1])), d[2]))
    return res


@pytest.fixture(scope="module")
def walker(body, mocap):
    from skinning.bvh import read_bvh

    header, _ = read_bvh(mocap / "cmu_131_01_walk_3dsmax.bvh")  # arms-down rest pose
    return header.skeleton


def _person_pose(person, arm_rot=None, side="Left", fore_rot=None):
    local = np.tile(np.eye(3), (len(person.names), 1, 1))
    if arm_rot is not None:
        local[person.index(f"{side}Arm")] = arm_rot
    if fore_rot is not None:
        local[person.index(f"{side}ForeArm")] = fore_rot
    return local, np.array([0.0, 0.95 / 0.056444, 0.0])


def _about(axis, deg):
    from skinning.kinematics import axis_rotation

    r = np.empty((3, 3))
    axis_rotation(axis, deg, r)
    return r


def _retargeters(body, person):
    ch = BodyAnimator(body).character
    torso = (0.15, 0.1)
    return (Retargeter(ch, person, ik=IKSettings(arm_clearance_deg=0.0), torso=torso),
            Retargeter(ch, person, ik=IKSettings(arm_clearance_deg=10.0), torso=torso))


def test_torso_depth_is_measured_on_the_body(body):
    from skinning.body import BODY_REGIONS, body_regions
    from skinning.retarget import torso_depth

    front, back = torso_depth(body.vertices, body_regions(body), BODY_REGIONS["torso"], body.skeleton)
    # the MakeHuman body: chest and belly 10-20 cm in front of the shoulder joints, back and seat 5-15 cm behind
    assert 0.10 < front < 0.20 and 0.05 < back < 0.15


def test_arm_clearance_abducts_a_hanging_arm_to_the_set_angle(body, walker):
    exact, clear = _retargeters(body, walker)
    local, root = _person_pose(walker)
    exact.copied_pose(local, root)
    before = _frontal_angles(exact)
    assert min(a for a, _ in before) < 8.0  # the person's arm hangs closer to the body than 10 degrees
    assert exact._arm_turn.max() == 0.0
    clear.copied_pose(local, root)
    after = _frontal_angles(clear)
    # the arm hangs in the frontal plane: the nearer of elbow and wrist ends exactly at 10 degrees
    assert min(a for a, _ in after) == pytest.approx(10.0, abs=1e-6)
    turn = np.degrees(clear._arm_turn[0])
    for (a0, _), (a1, _) in zip(before, after):
        assert a1 - a0 == pytest.approx(turn, abs=1e-6)  # a turn about the forward axis
    ch = clear.character
    cs = ch.skeleton
    for name in ("LeftForeArm", "LeftHand", "RightForeArm", "RightHand"):  # elbow and wrist keep their angles
        np.testing.assert_allclose(clear._char_local[cs.index(name)], exact._char_local[cs.index(name)], atol=1e-12)
    for name in ("Spine1", "LeftShoulder", "Neck", "LeftUpLeg"):  # nothing else moves
        np.testing.assert_allclose(clear._char_global[cs.index(name)], exact._char_global[cs.index(name)], atol=1e-12)
    # mirror image: the right arm turns the other way by the same amount
    assert min(a for a, _ in _frontal_angles(clear, "Right")) == pytest.approx(10.0, abs=1e-6)


def test_arm_clearance_turns_a_forearm_that_crosses_into_the_hips(body, walker):
    exact, clear = _retargeters(body, walker)
    # upper arm hanging 20 degrees out, elbow bent 45 degrees inwards: the wrist is inside the angle
    local, root = _person_pose(walker, _about(2, 20.0), fore_rot=_about(2, -45.0))
    exact.copied_pose(local, root)
    (elbow, _), (wrist, _) = _frontal_angles(exact)
    assert elbow > 10.0 and wrist < 10.0
    clear.copied_pose(local, root)
    assert np.degrees(clear._arm_turn[0]) == pytest.approx(10.0 - wrist, abs=1e-6)
    assert _frontal_angles(clear)[1][0] == pytest.approx(10.0, abs=1e-6)


def test_arm_clearance_leaves_raised_open_and_forward_arms_as_copied(body, walker):
    exact, clear = _retargeters(body, walker)
    ch = clear.character
    arm = ch.skeleton.index("LeftArm")
    poses = [
        (_about(0, -90.0), None),  # raised forward to the horizontal (the hanging arm's tip moves to +z)
        (_about(2, 35.0), None),  # abducted 35 degrees
        (_about(2, 20.0) @ _about(0, -20.0), _about(0, -100.0)),  # forearm raised: the hand well in front of the belly
        (_about(2, 20.0) @ _about(0, -150.0), None),  # raised forward past the shoulder, slightly across the head
    ]
    for arm_rot, fore_rot in poses:
        local, root = _person_pose(walker, arm_rot, fore_rot=fore_rot)
        q0 = exact.copied_pose(local, root).copy()
        q1 = clear.copied_pose(local, root)
        assert clear._arm_turn[0] == 0.0
        np.testing.assert_array_equal(q1[ch.idx_q[arm]: ch.idx_q[arm] + 4], q0[ch.idx_q[arm]: ch.idx_q[arm] + 4])


def test_arm_clearance_fades_continuously_as_the_arm_swings_forward(body, walker):
    _, clear = _retargeters(body, walker)
    turns, ahead = [], []
    for deg in np.arange(0.0, 90.5, 0.5):
        clear.copied_pose(*_person_pose(walker, _about(0, -deg)))
        turns.append(np.degrees(clear._arm_turn[0]))
        ahead.append(min(dz for _, dz in _frontal_angles(clear)))
    turns, ahead = np.array(turns), np.array(ahead)
    assert turns[0] > 2.0 and turns[-1] == 0.0
    assert np.abs(np.diff(turns)).max() < 0.5  # no jump from one half-degree to the next
    assert turns[ahead >= 1.5 * clear.torso[0]].max() == 0.0  # elbow and wrist in front of the body: as copied
    assert turns[ahead <= clear.torso[0]].min() > 2.0


@pytest.mark.parametrize("kwargs, says", [
    ({"max_iterations": 0}, "IKSettings.max_iterations must be an integer >= 1, got 0"),
    ({"damping": 0.0}, "IKSettings.damping must be > 0 and finite, got 0.0"),
    ({"max_step": float("nan")}, "IKSettings.max_step must be > 0 and finite, got nan"),
    ({"posture_gain": 1.5}, "IKSettings.posture_gain must be in [0, 1], got 1.5"),
    ({"arm_clearance_deg": 90.0}, "IKSettings.arm_clearance_deg must be in [0, 90), got 90.0"),
])
def test_ik_settings_name_a_value_out_of_range(kwargs, says):
    with pytest.raises(ValueError, match=re.escape(says)):
        IKSettings(**kwargs)
    IKSettings(arm_clearance_deg=0.0, hand_clearance=None)  # values in range are taken
