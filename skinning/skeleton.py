"""Skeletons as arrays: bone names, parent indices and rest joint positions.

The canonical bone set is the 31-bone CMU skeleton (MakeHuman's `cmu_mb` rig
and the MotionBuilder-friendly CMU BVH release share it). Bones are kept in
the BVH file order, which lists every parent before its children.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CMU_BONES: tuple[str, ...] = (
    "Hips",
    "LHipJoint", "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase",
    "RHipJoint", "RightUpLeg", "RightLeg", "RightFoot", "RightToeBase",
    "LowerBack", "Spine", "Spine1", "Neck", "Neck1", "Head",
    "LeftShoulder", "LeftArm", "LeftForeArm", "LeftHand", "LeftFingerBase", "LeftHandFinger1", "LThumb",
    "RightShoulder", "RightArm", "RightForeArm", "RightHand", "RightFingerBase", "RightHandFinger1", "RThumb",
)
CMU_PARENTS: dict[str, str | None] = {
    "Hips": None,
    "LHipJoint": "Hips", "LeftUpLeg": "LHipJoint", "LeftLeg": "LeftUpLeg", "LeftFoot": "LeftLeg",
    "LeftToeBase": "LeftFoot",
    "RHipJoint": "Hips", "RightUpLeg": "RHipJoint", "RightLeg": "RightUpLeg", "RightFoot": "RightLeg",
    "RightToeBase": "RightFoot",
    "LowerBack": "Hips", "Spine": "LowerBack", "Spine1": "Spine", "Neck": "Spine1", "Neck1": "Neck",
    "Head": "Neck1",
    "LeftShoulder": "Spine1", "LeftArm": "LeftShoulder", "LeftForeArm": "LeftArm", "LeftHand": "LeftForeArm",
    "LeftFingerBase": "LeftHand", "LeftHandFinger1": "LeftFingerBase", "LThumb": "LeftHand",
    "RightShoulder": "Spine1", "RightArm": "RightShoulder", "RightForeArm": "RightArm",
    "RightHand": "RightForeArm", "RightFingerBase": "RightHand", "RightHandFinger1": "RightFingerBase",
    "RThumb": "RightHand",
}
# The child whose joint is the far end of a bone that has several children.
MAIN_CHILD: dict[str, str] = {"Hips": "LowerBack", "Spine1": "Neck", "LeftHand": "LeftFingerBase",
                              "RightHand": "RightFingerBase"}
LEGS = {
    "left": ("LeftUpLeg", "LeftLeg", "LeftFoot"),
    "right": ("RightUpLeg", "RightLeg", "RightFoot"),
}
# the person's bones the lower body is mapped from (pelvis and ankles, through the legs' chains)
NEEDED_BONES = ("Hips", *LEGS["left"], *LEGS["right"])


# the character's spine from the chest down: the chest is where the shoulders hang from
SPINE = ("Spine1", "Spine", "LowerBack")


def spine_by_place(names: list[str], parents: np.ndarray) -> list[str]:
    """Another skeleton's spine named by its place, not its names: the joint the shoulders (or,
    without them, the upper arms) hang from is the chest (Spine1), and the two joints below it,
    down to the pelvis, Spine and LowerBack. Mixamo's chest is its Spine2, under Spine1 and Spine:
    by name, the character's chest would turn with Mixamo's mid-spine, short of the chest's bend
    that the shoulders, copied by name, have."""
    arm = next((names.index(n) for n in ("LeftShoulder", "RightShoulder", "LeftArm", "RightArm") if n in names), -1)
    if arm < 0 or parents[arm] < 0:
        return names
    out = list(names)
    chain = []  # the chest, then down towards the pelvis
    b = int(parents[arm])
    while b >= 0 and names[b] != "Hips" and len(chain) < len(SPINE):
        chain.append(b)
        b = int(parents[b])
    if [names[b] for b in chain] == list(SPINE[:len(chain)]):
        return names
    for b, new in zip(chain, SPINE):
        for other in range(len(out)):  # (a joint of that name elsewhere gives it up)
            if out[other] == new and other not in chain:
                out[other] = names[other] + "_"
        out[b] = new
    return out


@dataclass(frozen=True)
class Skeleton:
    """Bones in parent-first order. `heads[b]` is the rest position of bone b's joint."""

    names: tuple[str, ...]
    parents: np.ndarray  # (n,) int32, -1 for the root
    heads: np.ndarray  # (n, 3) float64, metres, rest pose, world frame
    tails: np.ndarray  # (n, 3) float64, far end of each bone (main child's head or end site)

    def index(self, name: str) -> int:
        return self.names.index(name)

    @property
    def offsets(self) -> np.ndarray:
        """Rest translation of each joint from its parent's joint (root: its head)."""
        out = self.heads.copy()
        has_parent = self.parents >= 0
        out[has_parent] -= self.heads[self.parents[has_parent]]
        return out

    def leg_length(self, side: str = "left") -> float:
        up, knee, foot = (self.index(n) for n in LEGS[side])
        h = self.heads
        return float(np.linalg.norm(h[knee] - h[up]) + np.linalg.norm(h[foot] - h[knee]))


def cmu_parents() -> np.ndarray:
    return np.array([-1 if CMU_PARENTS[n] is None else CMU_BONES.index(CMU_PARENTS[n]) for n in CMU_BONES],
                    dtype=np.int32)


def bone_tails(names, parents, heads, end_sites: dict[int, np.ndarray] | None = None) -> np.ndarray:
    """Far end of each bone: the head of its main (or only) child, else the mean of its children's
    heads, else its end site, else its head."""
    tails = heads.copy()
    children: dict[int, list[int]] = {}
    for b, p in enumerate(parents):
        if p >= 0:
            children.setdefault(int(p), []).append(b)
    for b, name in enumerate(names):
        kids = children.get(b, [])
        if name in MAIN_CHILD and MAIN_CHILD[name] in names:
            tails[b] = heads[names.index(MAIN_CHILD[name])]
        elif len(kids) == 1:
            tails[b] = heads[kids[0]]
        elif kids:  # (another skeleton's: a hand over five fingers, a chest under the neck and shoulders)
            tails[b] = heads[kids].mean(axis=0)
        elif end_sites and b in end_sites:
            tails[b] = end_sites[b]
    return tails
