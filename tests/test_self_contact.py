"""Where the skinned body cuts through itself (services.body_job.SelfContact), and the arm
clearance that keeps the retargeted arms out of the torso."""

import numpy as np
import pytest

from services.body_job import SelfContact, run_clip
from skinning.animate import BodyAnimator
from skinning.body import BODY_REGIONS
from skinning.character import configuration_to_local, local_to_configuration
from skinning.kinematics import axis_rotation
from skinning.retarget import IKSettings

REGIONS = list(BODY_REGIONS)
LEFT_ARM = [REGIONS.index("left_upper_arm"), REGIONS.index("left_forearm")]  # the arm is two regions


@pytest.fixture(scope="module")
def contact(body):
    return SelfContact(body)


def _arm_lowered(animator, degrees):
    """The rest pose with the left upper arm turned about z by `degrees` (negative: towards the body)."""
    ch, sk = animator.character, animator.body.skeleton
    q = animator.rest_configuration()
    local, root = np.empty((len(sk.names), 3, 3)), np.empty(3)
    configuration_to_local(q, ch.idx_q, local, root)
    axis_rotation(2, degrees, local[sk.index("LeftArm")])
    local_to_configuration(local, root, ch.idx_q, q)
    return animator.pose(q)


def test_the_rest_body_does_not_cut_through_itself(body, contact):
    animator = BodyAnimator(body)
    frame = animator.pose(animator.rest_configuration())
    assert contact(frame.vertices, frame.normals).tolist() == [0] * len(BODY_REGIONS)


def test_an_arm_lowered_through_the_torso_is_counted_there_and_grows_with_the_overlap(body, contact):
    animator = BodyAnimator(body, contact=None)  # the skin as linear blend skinning leaves it
    counts = [contact(*(lambda f: (f.vertices, f.normals))(_arm_lowered(animator, d))) for d in (-30, -40, -50)]
    torso = REGIONS.index("torso")
    arm = [c[LEFT_ARM].sum() for c in counts]
    # the A-pose arm (about 40 degrees out) turned 30-50 degrees in: it enters the chest's side
    for c, a in zip(counts, arm):
        assert a > 0
        assert c.sum() == a + c[torso]  # nothing else moved
    assert arm[0] < arm[1] < arm[2]
    assert counts[0][torso] < counts[1][torso] < counts[2][torso]


def test_arm_clearance_takes_the_walkers_arms_out_of_the_torso(body, mocap):
    clip = mocap / "cmu_131_01_walk_3dsmax.bvh"
    exact = run_clip(body, clip, every=2, max_frames=60, ik=IKSettings(arm_clearance_deg=0.0, hand_clearance=None),
                     self_contact=5, contact=None)
    clear = run_clip(body, clip, every=2, max_frames=60, self_contact=5, contact=None)
    assert exact.self_contact.shape == clear.self_contact.shape == (12, len(BODY_REGIONS))
    torso = REGIONS.index("torso")
    before, after = exact.self_contact.mean(axis=0), clear.self_contact.mean(axis=0)
    # the walker's left hand rests at the hip: copied exactly, the forearm is in it
    assert before[LEFT_ARM].sum() > 50 and after[LEFT_ARM].sum() < 0.2 * before[LEFT_ARM].sum()
    assert after[torso] < 0.2 * before[torso]
    assert "clothed skin inside another part" in clear.summary() and "clothed skin" not in run_clip(
        body, clip, every=2, max_frames=3).summary()
