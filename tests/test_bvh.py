import re
import time

import numpy as np
import pytest

from skinning.bvh import BVHError, BVHReader, read_bvh, local_pose
from skinning.kinematics import axis_rotation, channels_to_local, forward_kinematics
from skinning.skeleton import CMU_BONES
from skinning.source import BVHSource

EXPECTED = {"cmu_13_29_jumping_jacks": 4593, "cmu_131_01_walk_3dsmax": 994, "cmu_npybvh_example_75f": 75}

SMALL = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
  JOINT LeftUpLeg
  {
    OFFSET 1 -1 0
    CHANNELS 3 Xrotation Yrotation Zrotation
    JOINT LeftLeg
    {
      OFFSET 0 -4 0
      CHANNELS 3 Zrotation Xrotation Yrotation
      JOINT LeftFoot
      {
        OFFSET 0 -4 0
        CHANNELS 3 Zrotation Yrotation Xrotation
        End Site
        {
          OFFSET 0 0 1
        }
      }
    }
  }
  JOINT RightUpLeg
  {
    OFFSET -1 -1 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    JOINT RightLeg
    {
      OFFSET 0 -4 0
      CHANNELS 3 Zrotation Yrotation Xrotation
      JOINT RightFoot
      {
        OFFSET 0 -4 0
        CHANNELS 3 Zrotation Yrotation Xrotation
        End Site
        {
          OFFSET 0 0 1
        }
      }
    }
  }
  JOINT LowerBack
  {
    OFFSET 0 1 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    JOINT Spine
    {
      OFFSET 0 2 0
      CHANNELS 3 Zrotation Yrotation Xrotation
      JOINT Spine1
      {
        OFFSET 0 2 0
        CHANNELS 3 Zrotation Yrotation Xrotation
        JOINT Neck
        {
          OFFSET 0 1 0
          CHANNELS 3 Zrotation Yrotation Xrotation
          JOINT Neck1
          {
            OFFSET 0 1 0
            CHANNELS 3 Zrotation Yrotation Xrotation
            JOINT Head
            {
              OFFSET 0 1 0
              CHANNELS 3 Zrotation Yrotation Xrotation
              End Site
              {
                OFFSET 0 1 0
              }
            }
          }
        }
        JOINT LeftShoulder
        {
          OFFSET 1 0 0
          CHANNELS 3 Zrotation Yrotation Xrotation
          JOINT LeftArm
          {
            OFFSET 1 0 0
            CHANNELS 3 Zrotation Yrotation Xrotation
            JOINT LeftForeArm
            {
              OFFSET 3 0 0
              CHANNELS 3 Zrotation Yrotation Xrotation
              JOINT LeftHand
              {
                OFFSET 3 0 0
                CHANNELS 3 Zrotation Yrotation Xrotation
                End Site
                {
                  OFFSET 1 0 0
                }
              }
            }
          }
        }
        JOINT RightShoulder
        {
          OFFSET -1 0 0
          CHANNELS 3 Zrotation Yrotation Xrotation
          JOINT RightArm
          {
            OFFSET -1 0 0
            CHANNELS 3 Zrotation Yrotation Xrotation
            JOINT RightForeArm
            {
              OFFSET -3 0 0
              CHANNELS 3 Zrotation Yrotation Xrotation
              JOINT RightHand
              {
                OFFSET -3 0 0
                CHANNELS 3 Zrotation Yrotation Xrotation
                End Site
                {
                  OFFSET -1 0 0
                }
              }
            }
          }
        }
      }
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.01
"""
N_CHANNELS = 6 + 3 * 20  # 21 joints
FIRST_ROW = SMALL.count("\n") + 1  # line number of the first motion row


def _row(value=0.0, n=N_CHANNELS):
    return " ".join([str(value)] * n) + "\n"


def write(tmp_path, text, name="clip.bvh"):
    p = tmp_path / name
    p.write_text(text)
    return p


@pytest.mark.parametrize("clip", sorted(EXPECTED))
def test_every_shipped_clip_parses(mocap, clip):
    header, motion = read_bvh(mocap / f"{clip}.bvh")
    assert motion.shape == (EXPECTED[clip], 96)
    assert header.n_frames == EXPECTED[clip]
    assert header.skeleton.names == CMU_BONES  # 31 joints, canonical names, file order
    assert header.n_channels == 96
    assert header.frame_time == pytest.approx(1 / 120, rel=1e-3)
    assert np.isfinite(motion).all()


def test_3dsmax_names_are_mapped_by_position(mocap):
    header, _ = read_bvh(mocap / "cmu_131_01_walk_3dsmax.bvh")
    mapping = dict(zip(header.source_names, header.skeleton.names))
    # the same name means different joints in the two schemes
    assert mapping["LeftShoulder"] == "LeftArm"
    assert mapping["LeftCollar"] == "LeftShoulder"
    assert mapping["Neck"] == "Neck1"
    assert mapping["lowerneck"] == "Neck"
    assert mapping["LFingers"] == "LeftHandFinger1"


def test_finger_aliases(mocap):
    header, _ = read_bvh(mocap / "cmu_13_29_jumping_jacks.bvh")
    assert "LeftHandIndex1" in header.source_names
    assert "LeftHandFinger1" in header.skeleton.names


def test_units_convert_to_metres(mocap):
    header, _ = read_bvh(mocap / "cmu_131_01_walk_3dsmax.bvh")
    knee = header.skeleton.index("LeftLeg")
    # OFFSET 2.49329 -6.85026 0 (CMU units) -> metres with 0.056444 m per unit
    np.testing.assert_allclose(header.skeleton.offsets[knee], np.array([2.49329, -6.85026, 0]) * 0.056444)


def test_small_file_without_optional_joints(tmp_path):
    p = write(tmp_path, SMALL + _row() + _row(1.0))
    header, motion = read_bvh(p, unit=1.0)
    assert motion.shape == (2, N_CHANNELS)
    assert "LHipJoint" not in header.skeleton.names


def test_rotation_order_is_respected(tmp_path):
    # LeftUpLeg lists X Y Z: R = Rx(90) Ry(90) Rz(0); LeftLeg lists Z X Y: R = Rz(90) Rx(90) Ry(0)
    values = np.zeros(N_CHANNELS)
    values[6:9] = [90, 90, 0]
    values[9:12] = [90, 90, 0]
    p = write(tmp_path, SMALL + " ".join(map(str, values)) + "\n" + _row())
    header, motion = read_bvh(p, unit=1.0)
    rot, _ = local_pose(header, motion[0])
    rx = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])
    ry = np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    rz = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    np.testing.assert_allclose(rot[header.skeleton.index("LeftUpLeg")], rx @ ry, atol=1e-12)
    np.testing.assert_allclose(rot[header.skeleton.index("LeftLeg")], rz @ rx, atol=1e-12)


def test_channels_compose_as_the_product_of_axis_rotations():
    # every order of the three rotation channels, random angles: the in-place composition is
    # the product R_first R_second R_third of the axis rotations (to rounding: numpy's matrix
    # product may sum in another order), and a rotation
    rng = np.random.default_rng(3)
    orders = [(0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)]
    chan_joint = np.repeat(np.arange(len(orders)), 3).astype(np.int64)
    chan_kind = np.array([3 + a for order in orders for a in order], dtype=np.int64)
    values = rng.uniform(-180.0, 180.0, len(chan_kind))
    rot, pos = np.empty((len(orders), 3, 3)), np.empty(3)
    channels_to_local(values, chan_joint, chan_kind, 1.0, rot, pos)
    r = np.empty((3, 3))
    for j, order in enumerate(orders):
        expected = np.eye(3)
        for c, axis in enumerate(order):
            axis_rotation(axis, values[3 * j + c], r)
            expected = expected @ r
        np.testing.assert_allclose(rot[j], expected, rtol=0, atol=1e-15)
        np.testing.assert_allclose(rot[j] @ rot[j].T, np.eye(3), atol=1e-14)


def test_forward_kinematics_against_offsets(tmp_path):
    values = np.zeros(N_CHANNELS)
    values[:3] = [1.0, 9.0, 2.0]
    values[6] = 90.0  # LeftUpLeg Xrotation +90: the leg below it (-y) swings to -z
    p = write(tmp_path, SMALL + " ".join(map(str, values)) + "\n" + _row())
    header, motion = read_bvh(p, unit=1.0)
    sk = header.skeleton
    rot, root = local_pose(header, motion[0])
    n = len(sk.names)
    g_rot, g_pos = np.empty((n, 3, 3)), np.empty((n, 3))
    forward_kinematics(sk.parents, sk.offsets, root, rot, g_rot, g_pos)
    np.testing.assert_allclose(g_pos[sk.index("Hips")], [1, 9, 2])
    np.testing.assert_allclose(g_pos[sk.index("LeftUpLeg")], [2, 8, 2])
    np.testing.assert_allclose(g_pos[sk.index("LeftLeg")], [2, 8, -2], atol=1e-12)
    np.testing.assert_allclose(g_pos[sk.index("LeftFoot")], [2, 8, -6], atol=1e-12)
    np.testing.assert_allclose(g_pos[sk.index("RightFoot")], [0, 0, 2], atol=1e-12)
    np.testing.assert_allclose(g_pos[sk.index("LeftHand")], [9, 14, 2], atol=1e-12)


@pytest.mark.parametrize("body_text, rows, problem, line", [
    (SMALL, _row(), "truncated motion: file ends after 1 of 2 frames", FIRST_ROW),
    (SMALL, _row() + _row(0.0, N_CHANNELS - 1), "expected 66 channel values, got 65", FIRST_ROW + 1),
    (SMALL, _row() + _row().replace("0.0", "nan", 1), "channel 0 is not finite", FIRST_ROW + 1),
    (SMALL, _row() + _row().replace("0.0", "abc", 1), "value is not a number: 'abc'", FIRST_ROW + 1),
    (SMALL, _row() + _row() + _row(), "more motion rows than 'Frames: 2'", FIRST_ROW + 2),
    (SMALL.replace("JOINT LeftFoot", "JOINT Tail"), "", "not the CMU skeleton (joints 'Tail') and no joint maps "
     "onto LeftFoot, which the retargeting needs: name them in clip.bones.toml", None),
    (SMALL.replace("JOINT LeftLeg", "JOINT Hips"), "", "joint 'Hips' appears twice (as 'Hips')",
     SMALL[:SMALL.index("JOINT LeftLeg")].count("\n") + 1),
    (SMALL.replace("CHANNELS 3 Xrotation Yrotation Zrotation", "CHANNELS 4 Xrotation Yrotation Zrotation"), "",
     "CHANNELS declares 4 but 'JOINT' is not a channel name", 10),
    (SMALL.replace("Frame Time: 0.01", "Frame Time: -1"), "", "Frame Time: must be a positive number", FIRST_ROW - 1),
    (SMALL.replace("OFFSET 1 -1 0", "OFFSET 1 -1"), "", "OFFSET of LeftUpLeg is not a number: 'CHANNELS'", 9),
    (SMALL.replace("MOTION", "MOTON"), "", "no MOTION section", None),
])
def test_malformed_files_name_file_line_and_problem(tmp_path, body_text, rows, problem, line):
    p = write(tmp_path, body_text + rows)
    with pytest.raises(BVHError) as info:
        read_bvh(p)
    err = info.value
    assert problem in str(err)
    assert str(p) in str(err)
    if line is not None:
        assert err.line == line, str(err)


def test_wrong_parent_is_rejected(tmp_path):
    # swap two names so LeftHand sits directly under LeftArm
    text = SMALL.replace("JOINT LeftForeArm", "JOINT TMP").replace("JOINT LeftHand", "JOINT LeftForeArm") \
        .replace("JOINT TMP", "JOINT LeftHand")
    with pytest.raises(BVHError, match="'LeftHand' is a child of 'LeftArm', expected 'LeftForeArm'"):
        read_bvh(write(tmp_path, text + _row() + _row()))


def test_streaming_reads_frames_before_the_end(tmp_path):
    """Frames come one at a time: the first frame is served before a truncation is noticed."""
    p = write(tmp_path, SMALL + _row(1.5))
    with BVHReader(p) as reader:
        rows = reader.rows()
        assert next(rows)[0] == 1.5
        with pytest.raises(BVHError, match="truncated"):
            next(rows)


def test_source_every_and_loop(mocap):
    path = mocap / "cmu_npybvh_example_75f.bvh"
    with BVHSource(path, every=2) as src:
        frames = list(src)
    assert len(frames) == 38
    assert src.frame_time == pytest.approx(2 / 120, rel=1e-3)
    assert frames[-1].time == pytest.approx(37 * src.frame_time)
    with BVHSource(path, loop=True, max_frames=200) as src:
        frames = list(src)
    assert len(frames) == 200 and frames[-1].index == 199
    np.testing.assert_array_equal(frames[75].local_rot, frames[0].local_rot)  # wrapped around
    assert [f.index for f in frames if f.jump] == [75, 150]  # where the motion jumps back to its start
    # a clip whose first frame is its converter's T-pose loops back to the frame after it
    with BVHSource(path, every=2, loop=True, loop_from=1, max_frames=80) as src:
        frames = list(src)
    assert [f.index for f in frames if f.jump] == [38, 75]  # 38 frames, then 37 a loop
    np.testing.assert_array_equal(frames[38].local_rot, frames[1].local_rot)
    np.testing.assert_array_equal(frames[75].root_position, frames[1].root_position)
    assert [f.index for f in frames] == list(range(80))
    with BVHSource(path, every=2, loop=True, loop_from=38, max_frames=80) as src:
        assert len(list(src)) == 38  # nothing left to loop over: the clip plays once
    with pytest.raises(ValueError, match="loop_from"):
        BVHSource(path, loop_from=-1)


def test_realtime_pacing_waits_for_the_clip_rate(mocap):
    with BVHSource(mocap / "cmu_npybvh_example_75f.bvh", pace="realtime", max_frames=13) as src:
        t0 = time.perf_counter()
        n = sum(1 for _ in src)
        elapsed = time.perf_counter() - t0
    assert n == 13
    assert elapsed >= 12 / 120 * 0.95  # never ahead of the clock


def test_realtime_pacing_spreads_frames_after_a_pause(mocap):
    """A consumer that pauses (a slow first frame, a stall) gets the next frame at once and the
    ones after on the clip's schedule again, not a burst of late frames; a short lag is caught up."""
    with BVHSource(mocap / "cmu_npybvh_example_75f.bvh", pace="realtime", every=2, max_frames=12) as src:
        stamps = []
        for frame in src:
            stamps.append(time.perf_counter())
            if frame.index == 1:
                time.sleep(0.3)  # well beyond max_lag (one frame)
    gaps = np.diff(stamps)
    ft = src.frame_time  # 1/60 s
    assert gaps[1] >= 0.3  # the pause itself
    # after it, frames come on schedule: a burst would deliver them back to back (gaps ≈ 0)
    assert np.all(gaps[2:] > 0.5 * ft), gaps
    assert stamps[-1] - stamps[2] >= (len(stamps) - 3) * ft * 0.95


def test_realtime_pacing_has_no_burst_after_a_slow_first_frame(mocap):
    """A slow first frame (the ingest's first retarget and announcement, tens of ms) is not
    made up by a burst: the frames after it keep the clip's spacing, or the first few would
    queue up at the cloth service and come out late."""
    with BVHSource(mocap / "cmu_npybvh_example_75f.bvh", pace="realtime", every=2, max_frames=8) as src:
        stamps = []
        for frame in src:
            stamps.append(time.perf_counter())
            if frame.index == 0:
                time.sleep(0.06)  # 3.6 frames at 60 Hz
    gaps = np.diff(stamps)
    assert np.all(gaps[1:] > 0.5 * src.frame_time), gaps


MIXAMO = """HIERARCHY
ROOT mixamorig:Hips
{
  OFFSET 0 100 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
  JOINT mixamorig:LeftUpLeg
  {
    OFFSET 10 -5 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    JOINT mixamorig:LeftLeg
    {
      OFFSET 0 -45 0
      CHANNELS 3 Zrotation Yrotation Xrotation
      JOINT mixamorig:LeftFoot
      {
        OFFSET 0 -45 0
        CHANNELS 3 Zrotation Yrotation Xrotation
        End Site
        {
          OFFSET 0 0 10
        }
      }
    }
  }
  JOINT mixamorig:RightUpLeg
  {
    OFFSET -10 -5 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    JOINT mixamorig:RightLeg
    {
      OFFSET 0 -45 0
      CHANNELS 3 Zrotation Yrotation Xrotation
      JOINT mixamorig:RightFoot
      {
        OFFSET 0 -45 0
        CHANNELS 3 Zrotation Yrotation Xrotation
        End Site
        {
          OFFSET 0 0 10
        }
      }
    }
  }
  JOINT mixamorig:Spine
  {
    OFFSET 0 13 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    JOINT mixamorig:Spine2
    {
      OFFSET 0 30 0
      CHANNELS 3 Zrotation Yrotation Xrotation
      JOINT mixamorig:Neck
      {
        OFFSET 0 10 0
        CHANNELS 3 Zrotation Yrotation Xrotation
        End Site
        {
          OFFSET 0 10 0
        }
      }
      JOINT mixamorig:LeftShoulder
      {
        OFFSET 6 6 0
        CHANNELS 3 Zrotation Yrotation Xrotation
        End Site
        {
          OFFSET 10 0 0
        }
      }
      JOINT mixamorig:RightShoulder
      {
        OFFSET -6 6 0
        CHANNELS 3 Zrotation Yrotation Xrotation
        End Site
        {
          OFFSET -10 0 0
        }
      }
    }
  }
}
MOTION
Frames: 1
Frame Time: 0.0333333
""" + " ".join(["0"] * (6 + 3 * 11)) + "\n"


def test_a_skeleton_of_another_tool_is_read_by_its_bone_names(tmp_path, mocap):
    """A Mixamo-style file (namespace prefix, no LowerBack or hip joints, a Spine2 with three
    children): not the CMU skeleton, kept as it is, each joint named as the character's bones
    go by (the prefix left off), the spine by its place: the joint the shoulders hang from is the
    chest (Spine1), the one below it Spine; a bone with several children and no main one ends at
    their heads' mean."""
    header, _ = read_bvh(write(tmp_path, MIXAMO), unit=0.01)
    sk = header.skeleton
    assert not header.cmu
    assert sk.names == ("Hips", "LeftUpLeg", "LeftLeg", "LeftFoot", "RightUpLeg", "RightLeg", "RightFoot",
                        "Spine", "Spine1", "Neck", "LeftShoulder", "RightShoulder")
    np.testing.assert_allclose(sk.heads[sk.index("LeftFoot")], [0.10, 0.05, 0.0], atol=1e-12)
    # the chest (Spine2 in the file) ends at the neck, as CMU's; the hips, without CMU's LowerBack,
    # at their three children's mean (two hip joints 5 cm lower, to the sides, the spine 13 cm higher)
    np.testing.assert_allclose(sk.tails[sk.index("Spine1")], [0.0, 1.53, 0.0], atol=1e-12)
    np.testing.assert_allclose(sk.tails[sk.index("Hips")], [0.0, 1.01, 0.0], atol=1e-12)
    # a map that names a joint of the spine itself is followed as it is
    (tmp_path / "named.bones.toml").write_text('[bones]\n"mixamorig:Spine" = "LowerBack"\n')
    assert read_bvh(write(tmp_path, MIXAMO, "named.bvh"))[0].skeleton.names[7:9] == ("LowerBack", "Spine2")
    with BVHReader(mocap / "cmu_131_01_walk_3dsmax.bvh") as walk:
        assert walk.header.cmu  # (the 3dsMax naming: CMU's)


def test_a_bone_name_map_beside_the_clip_names_its_joints(tmp_path):
    """walk.bvh's joints named in walk.bones.toml ([bones] its name = the CMU name); a map onto a
    bone the character lacks, or not a table of names, is refused naming the map file."""
    text = MIXAMO.replace("mixamorig:LeftUpLeg", "thigh_l").replace("mixamorig:LeftLeg", "calf_l")
    with pytest.raises(BVHError, match="no joint maps onto LeftUpLeg, LeftLeg"):
        read_bvh(write(tmp_path, text))
    (tmp_path / "clip.bones.toml").write_text('[bones]\nthigh_l = "LeftUpLeg"\ncalf_l = "LeftLeg"\n')
    sk = read_bvh(write(tmp_path, text))[0].skeleton
    assert sk.names[:3] == ("Hips", "LeftUpLeg", "LeftLeg")
    (tmp_path / "clip.bones.toml").write_text('[bones]\nthigh_l = "Thigh"\n')
    with pytest.raises(BVHError, match=r"clip.bones.toml: \[bones\] maps onto 'Thigh', which the character has no"):
        read_bvh(write(tmp_path, text))
    (tmp_path / "clip.bones.toml").write_text('thigh_l = "LeftUpLeg"\n')
    with pytest.raises(BVHError, match=r"clip.bones.toml: expected a \[bones\] table"):
        read_bvh(write(tmp_path, text))
    # the same skeleton Z up: its legs along -Z at rest
    zup = MIXAMO.replace("OFFSET 0 -45 0", "OFFSET 0 0 -45").replace("OFFSET 10 -5 0", "OFFSET 10 0 -5") \
        .replace("OFFSET -10 -5 0", "OFFSET -10 0 -5")
    with pytest.raises(BVHError, match=r"in the rest pose 'LeftFoot' is not below 'LeftUpLeg' along Y \(the hip to "
                                       r"the ankle: \[0.0, 0.0, -90.0\] file units\): BVH motion is read Y up"):
        read_bvh(write(tmp_path, zup, "zup.bvh"))
    # a rig mapped wholly onto CMU names is still its own skeleton (its hierarchy is not CMU's)
    (tmp_path / "mapped.bones.toml").write_text("[bones]\n" + "\n".join(
        f'"{n}" = "{n.split(":")[1]}"' for n in re.findall(r"(mixamorig:\w+)", MIXAMO) if "Spine2" not in n)
        + '\n"mixamorig:Spine2" = "Spine1"\n')
    header = read_bvh(write(tmp_path, MIXAMO, "mapped.bvh"))[0]
    assert not header.cmu and header.skeleton.names[7:9] == ("Spine", "Spine1")
    # a leg whose knee does not hang from its hip
    text = MIXAMO.replace("mixamorig:LeftLeg", "TMP").replace("mixamorig:RightLeg", "mixamorig:LeftLeg") \
        .replace("TMP", "mixamorig:RightLeg")
    with pytest.raises(BVHError, match="joint 'LeftLeg' does not descend from 'LeftUpLeg'"):
        read_bvh(write(tmp_path, text, "other.bvh"))
