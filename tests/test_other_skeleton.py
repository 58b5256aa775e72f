"""Motion from a skeleton other than CMU's: the walk clip rewritten as another tool would export
it (Mixamo's naming and hierarchy, centimetres) drives the character as the clip itself does."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from skinning.animate import BodyAnimator
from skinning.bvh import CMU_UNIT_M, local_pose, read_bvh
from skinning.kinematics import axis_rotation, forward_kinematics

# the rewritten skeleton: (name, the walk's bone it copies, parent). Mixamo's spine (Spine, Spine1,
# and the chest Spine2, which the shoulders hang from, for CMU's LowerBack, Spine, Spine1), no
# Neck1 or hip joints, one finger joint per hand; names under Mixamo's namespace
MIXAMO_STYLE = [("Hips", "Hips", None)]
for side, s in (("Left", "L"), ("Right", "R")):
    MIXAMO_STYLE += [(f"{side}UpLeg", f"{side}UpLeg", "Hips"), (f"{side}Leg", f"{side}Leg", f"{side}UpLeg"),
                     (f"{side}Foot", f"{side}Foot", f"{side}Leg"), (f"{side}ToeBase", f"{side}ToeBase", f"{side}Foot")]
MIXAMO_STYLE += [("Spine", "LowerBack", "Hips"), ("Spine1", "Spine", "Spine"), ("Spine2", "Spine1", "Spine1"),
                 ("Neck", "Neck", "Spine2"), ("Head", "Head", "Neck")]
for side in ("Left", "Right"):
    MIXAMO_STYLE += [(f"{side}Shoulder", f"{side}Shoulder", "Spine2"),
                     (f"{side}Arm", f"{side}Arm", f"{side}Shoulder"),
                     (f"{side}ForeArm", f"{side}ForeArm", f"{side}Arm"),
                     (f"{side}Hand", f"{side}Hand", f"{side}ForeArm"),
                     (f"{side}HandIndex1", f"{side}FingerBase", f"{side}Hand")]
# the character's bones the rewritten skeleton has no joint for: they follow their parents
NOT_CAPTURED = {"Neck1", "LeftFingerBase", "LeftHandFinger1", "LThumb", "RightFingerBase", "RightHandFinger1",
                "RThumb"}


def zyx_degrees(r: np.ndarray) -> tuple[float, float, float]:
    """Angles (z, y, x) of R = Rz Ry Rx: a BVH joint's `Zrotation Yrotation Xrotation`."""
    return (np.degrees(np.arctan2(r[1, 0], r[0, 0])), np.degrees(np.arcsin(-np.clip(r[2, 0], -1, 1))),
            np.degrees(np.arctan2(r[2, 1], r[2, 2])))


def rewrite(header, rows: np.ndarray, path, root_offset=(0.0, 0.0, 0.0), absolute: bool = True) -> None:
    """The walk's frames `rows` as a Mixamo-style BVH: each joint's global rotation the walk's
    bone's, positions in centimetres. root_offset (m): the root's OFFSET;
    absolute: its position channels give its place (Blender's reading), else its place less the
    offset."""
    sk = header.skeleton
    names = [n for n, _, _ in MIXAMO_STYLE]
    src = {n: sk.index(b) for n, b, _ in MIXAMO_STYLE}
    heads = {n: sk.heads[i] + root_offset for n, i in src.items()}
    parent = {n: p for n, _, p in MIXAMO_STYLE}
    children = {n: [c for c, _, p in MIXAMO_STYLE if p == n] for n in names}
    cm = 100.0  # metres -> centimetres

    lines = ["HIERARCHY"]

    def joint(name: str, depth: int) -> None:
        pad = "  " * depth
        off = heads[name] - (heads[parent[name]] if parent[name] else 0.0)
        lines.append(f"{pad}{'ROOT' if parent[name] is None else 'JOINT'} mixamorig:{name}")
        lines.append(pad + "{")
        lines.append(f"{pad}  OFFSET {off[0] * cm:.10f} {off[1] * cm:.10f} {off[2] * cm:.10f}")
        lines.append(f"{pad}  CHANNELS {'6 Xposition Yposition Zposition ' if parent[name] is None else '3 '}"
                     "Zrotation Yrotation Xrotation")
        for c in children[name]:
            joint(c, depth + 1)
        if not children[name]:
            end = sk.tails[src[name]] - sk.heads[src[name]]
            lines.extend([f"{pad}  End Site", pad + "  {", f"{pad}    OFFSET {end[0] * cm:.10f} {end[1] * cm:.10f} "
                          f"{end[2] * cm:.10f}", pad + "  }"])
        lines.append(pad + "}")

    joint("Hips", 0)
    lines += ["MOTION", f"Frames: {len(rows)}", f"Frame Time: {header.frame_time:.10f}"]
    n = len(sk.names)
    g_rot, g_pos = np.empty((n, 3, 3)), np.empty((n, 3))
    for values in rows:
        rot, root = local_pose(header, values)
        forward_kinematics(sk.parents, sk.offsets, root, rot, g_rot, g_pos)
        glob = {name: g_rot[src[name]] for name in names}
        out = list((g_pos[sk.index("Hips")] - (0.0 if absolute else np.asarray(root_offset))) * cm)
        for name in names:
            local = glob[name] if parent[name] is None else glob[parent[name]].T @ glob[name]
            out += zyx_degrees(local)
        lines.append(" ".join(f"{v:.10f}" for v in out))
    path.write_text("\n".join(lines) + "\n")


def test_zyx_degrees_round_trip():
    r, a = np.eye(3), np.empty((3, 3))
    for axis, deg in ((2, 40.0), (1, -25.0), (0, 70.0)):
        axis_rotation(axis, deg, a)
        r = r @ a
    np.testing.assert_allclose(zyx_degrees(r), (40.0, -25.0, 70.0))


@pytest.mark.parametrize("root", ["zero offset", "offset, absolute channels", "offset, relative channels"])
def test_a_skeleton_of_another_tool_drives_the_character_as_the_clip_does(body, mocap, tmp_path, root):
    """The walk rewritten with Mixamo's names and hierarchy (its spine Spine, Spine1, Spine2, no
    Neck1 or hip joints, one finger joint a hand) in centimetres: every character bone the
    rewritten skeleton has a joint for turns as it does from the walk itself (the rotations are
    copied globally, by name, the spine by its place: Mixamo's Spine2, which the shoulders hang
    from, is the chest), the legs' IK reaches the same ankles and the pelvis lands at the same
    place (the person's size cancels in the legs' length ratio); the bones it has no joint for
    (Neck1, the fingers) follow their parents. With the root's rest place as its OFFSET, its
    position channels read either as its place (Blender's export) or as its place less the offset
    give the same."""
    header, motion = read_bvh(mocap / "cmu_131_01_walk_3dsmax.bvh")
    rows = motion[1:121:6]  # 20 frames of the walk, 0.05 s apart
    other_path = tmp_path / "walk_mixamo.bvh"
    hips = (0.0, 0.0, 0.0) if root == "zero offset" else (0.01, 0.93, -0.02)
    rewrite(header, rows, other_path, hips, absolute="absolute" in root)
    other, other_rows = read_bvh(other_path)
    assert not other.cmu and other.skeleton.names[9:13] == ("LowerBack", "Spine", "Spine1", "Neck")
    assert np.allclose(other.root_shift, np.array(hips) * CMU_UNIT_M * 100 if "absolute" in root else 0.0)

    runs = []
    for h, frames in ((header, rows), (other, other_rows)):
        animator = BodyAnimator(body, h.skeleton, contact=None, normals=False, helpers=False)
        model, data = animator.character.model, animator.character.model.createData()
        out = []
        for values in frames:
            rot, root = local_pose(h, values)
            q = animator.retargeter(rot, root).q.copy()
            pin.forwardKinematics(model, data, q)
            out.append((q[:3].copy(), np.array([data.oMi[int(j)].rotation for j in animator.character.joint_ids])))
        runs.append(out)
    names = body.skeleton.names
    compared = [b for b, n in enumerate(names) if n not in NOT_CAPTURED]
    assert len(compared) == len(names) - len(NOT_CAPTURED)
    for (root_a, rot_a), (root_b, rot_b) in zip(*runs):
        np.testing.assert_allclose(root_b, root_a, atol=1e-6)
        np.testing.assert_allclose(rot_b[compared], rot_a[compared], atol=1e-6)
    # (what is compared moves: the walk's hips travel, its knees bend)
    assert np.linalg.norm(runs[0][-1][0] - runs[0][0][0]) > 0.1
    knee = names.index("LeftLeg")
    assert not np.allclose(runs[0][0][1][knee], runs[0][10][1][knee], atol=0.05)


def test_tryon_body_runs_a_clip_of_another_skeleton_and_says_what_it_leaves_unmoved(mocap, tmp_path, capsys):
    from services.cli import main

    header, motion = read_bvh(mocap / "cmu_131_01_walk_3dsmax.bvh")
    clip = tmp_path / "walk_mixamo.bvh"
    rewrite(header, motion[:8], clip)
    assert main(["body", "--clip", str(clip), "--no-png", "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert ("clip walk_mixamo.bvh is not the CMU skeleton: its joints named as the character's bones drive 24 of "
            "the character's 31 bones; of those a CMU clip moves, Neck1 follows its parent (name the joint for it "
            "in walk_mixamo.bones.toml)") in out
    assert "walk_mixamo: 8 frames" in out and "NaN frames 0" in out
