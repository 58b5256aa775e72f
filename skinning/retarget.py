"""Map a person's motion onto the character (the patent's try-on prototype, SPEC.md).

* Upper body and arms: the person's joint rotations are copied, expressed relative
  to each skeleton's rest orientation. Rest poses differ (BVH T-pose or arms-down,
  MakeHuman A-pose), so each limb bone gets an alignment rotation A_b that poses the
  character like the person's zero-rotation pose (computed down the hierarchy, a
  minimal swing per bone, so an elbow straightens about its own hinge without
  spurious twist). The character's bone b then has global rotation R_person_b(t) A_b.
* Lower body: the pelvis position (scaled by the ratio of leg lengths) and
  orientation, and both ankles' positions and orientations, become targets; the
  legs (hip, knee, ankle: 9 DOF each) are solved by damped least squares
  (Levenberg-Marquardt, per-leg step acceptance) on the Pinocchio Jacobians of the
  ankle joints, warm-started from the previous frame, with the copied leg angles as
  a null-space posture prior. The pelvis position is that of the hip-joint centre:
  the skeletons' root joints sit at different heights above the hips (11 cm on the
  CMU skeleton, 2.4 cm on MakeHuman's), and mapping the root would change leg reach.
* Floor: positions are scaled about the person's floor (`person_floor_y`, 0 for
  CMU captures), which becomes the character's floor y = 0. Feet are proportioned
  differently (the character's toes rest on the floor, the CMU toe joints 2-3 cm
  above it), so an ankle target is raised when the character's sole would go below
  the floor; the IK residual is reported against the raised target, and the raise
  itself in `floor_lift`.
* Arm clearance: the character is broader than most captured people, so an arm
  copied hanging straight down passes through its torso and hips. An arm whose
  elbow or wrist is closer to the chest's down axis than
  `IKSettings.arm_clearance_deg` (in the frontal plane) is turned outwards about
  the chest's forward axis, elbow and wrist angles kept; the turn fades out when
  the hand is held in front of or behind the torso (its depth is measured on the
  body: `torso_depth`), or reaches across the body (`keep_arm_clear`). The turn is
  reported per arm in `arm_turn`; 0 degrees copies the arms exactly.
* Hand clearance: a hand still inside the torso or a leg once the body is skinned (a hand
  resting on the hip) turns its arm out further about the same axis (`hands.HandClearance`,
  applied by `animate.BodyAnimator`; the turn is added to `arm_turn`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

from .character import Character
from .hands import HandSettings
from .ik_kernels import (IKScratch, copy_rotations, dls_step, keep_arm_clear, lowest_sole_point, pose_error,
                         weighted_cost)
from .kinematics import forward_kinematics, rotation_between
from .skeleton import LEGS, NEEDED_BONES, Skeleton

# Bones whose rest direction is a matter of proportion, not of pose: no alignment.
STRUCTURAL_BONES = {"Hips", "LHipJoint", "RHipJoint", "LowerBack", "Spine", "Spine1", "Neck", "Neck1", "Head",
                    "LeftShoulder", "RightShoulder"}
TOES = {"left": "LeftToeBase", "right": "RightToeBase"}
ARMS = ("LeftArm", "RightArm")
# an elbow or wrist up to this far inside the clearance angle is turned out by all of the
# deficit; the turn then shrinks to 0 at twice this (an arm reaching across the body)
ARM_SPAN_DEG = 30.0
DEFAULT_TORSO_DEPTH = (0.12, 0.08)  # m in front of / behind the shoulder joints, without a body


def alignment_rotations(character: Skeleton, person: Skeleton) -> np.ndarray:
    """A_b (n, 3, 3): the character's bone rotations that reproduce the person's rest pose."""
    n = len(character.names)
    align = np.tile(np.eye(3), (n, 1, 1))
    for b, name in enumerate(character.names):
        p = int(character.parents[b])
        parent_rot = align[p] if p >= 0 else np.eye(3)
        if name in STRUCTURAL_BONES or name not in person.names:
            align[b] = parent_rot
            continue
        pb = person.index(name)
        d_char = parent_rot @ (character.tails[b] - character.heads[b])
        d_person = person.tails[pb] - person.heads[pb]
        align[b] = rotation_between(d_char, d_person) @ parent_rot
    return align


def sole_points(vertices: np.ndarray, weight_bones: np.ndarray, weight_values: np.ndarray, n_visible: int,
                skeleton: Skeleton, side: str, height: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Rest positions of the visible vertices within `height` of the foot's lowest point that
    follow the foot or toe bone, and whether each follows the toe."""
    foot, toe = skeleton.index(LEGS[side][-1]), skeleton.index(TOES[side])
    vis = np.arange(n_visible)
    dominant = weight_bones[vis, np.argmax(weight_values[vis], axis=1)]
    on_foot = (dominant == foot) | (dominant == toe)
    lowest = vertices[vis[on_foot], 1].min()
    pick = vis[on_foot & (vertices[vis, 1] < lowest + height)]
    return vertices[pick].copy(), dominant[pick] == toe


def torso_depth(vertices: np.ndarray, regions: np.ndarray, torso_region: int,
                skeleton: Skeleton) -> tuple[float, float]:
    """How far (m) the rest torso reaches in front of and behind the shoulder joints, between the
    hip joints' and the shoulders' heights. regions: (n_visible,) region of each visible vertex."""
    shoulder = 0.5 * (skeleton.heads[skeleton.index(ARMS[0])] + skeleton.heads[skeleton.index(ARMS[1])])
    hips = 0.5 * (skeleton.heads[skeleton.index("LeftUpLeg")] + skeleton.heads[skeleton.index("RightUpLeg")])
    x = vertices[: len(regions)]
    band = (regions == torso_region) & (x[:, 1] > hips[1]) & (x[:, 1] < shoulder[1])
    if not band.any():
        raise ValueError("torso_depth: no torso vertex between the hips and the shoulders")
    return float(x[band, 2].max() - shoulder[2]), float(shoulder[2] - x[band, 2].min())


@dataclass
class IKSettings:
    max_iterations: int = 20
    position_tolerance: float = 1e-4  # m
    rotation_tolerance: float = 1e-3  # rad
    damping: float = 1e-4  # initial Levenberg-Marquardt damping (weighted units)
    rotation_weight: float = 0.3  # m per rad: trades ankle orientation against position
    posture_gain: float = 0.2  # pull of the copied leg angles in the null space, per iteration
    max_step: float = 0.5  # rad per joint coordinate per iteration
    # Forward flexion added to the knees' posture prior: a straight copied knee does not say
    # which way to bend when the ankle target comes closer; a knee bends forward.
    knee_bias_deg: float = 8.0
    # Smallest angle between a hanging upper arm and the chest's down axis (frontal plane); see
    # the module. 0: copy the arms exactly.
    arm_clearance_deg: float = 10.0
    # A hand the pose sinks into the torso or a leg turns out with its arm, once the body is skinned
    # (`hands.HandClearance`, applied by `BodyAnimator`); None: the hands stay where the arms put them.
    hand_clearance: HandSettings | None = field(default_factory=HandSettings)

    def __post_init__(self):
        if isinstance(self.max_iterations, bool) or not isinstance(self.max_iterations, int) or self.max_iterations < 1:
            raise ValueError(f"IKSettings.max_iterations must be an integer >= 1, got {self.max_iterations!r}")
        for key in ("position_tolerance", "rotation_tolerance", "damping", "rotation_weight", "max_step"):
            if not 0 < getattr(self, key) < np.inf:
                raise ValueError(f"IKSettings.{key} must be > 0 and finite, got {getattr(self, key)!r}")
        if not 0 <= self.posture_gain <= 1:
            raise ValueError(f"IKSettings.posture_gain must be in [0, 1], got {self.posture_gain!r}")
        if not -90 < self.knee_bias_deg < 90:
            raise ValueError(f"IKSettings.knee_bias_deg must be in (-90, 90), got {self.knee_bias_deg!r}")
        if not 0 <= self.arm_clearance_deg < 90:
            raise ValueError(f"IKSettings.arm_clearance_deg must be in [0, 90), got {self.arm_clearance_deg!r}")


@dataclass
class RetargetFrame:
    q: np.ndarray  # Pinocchio configuration of the character (owned by the retargeter, overwritten)
    ankle_position_error: np.ndarray  # (2,) m, left/right, against the ankle targets
    ankle_rotation_error: np.ndarray  # (2,) rad
    floor_lift: np.ndarray  # (2,) m the ankle targets were raised to keep the soles above the floor
    arm_turn: np.ndarray  # (2,) rad left/right arm turned outwards for clearance
    iterations: int


def missing_bones(names) -> list[str]:
    """The bones of NEEDED_BONES a person's skeleton (its bone names) lacks."""
    return [n for n in NEEDED_BONES if n not in names]


class Retargeter:
    """Per-session retargeting state: alignment, scale, last IK solution."""

    def __init__(self, character: Character, person: Skeleton, soles=None, person_floor_y: float = 0.0,
                 ik: IKSettings | None = None, torso: tuple[float, float] = DEFAULT_TORSO_DEPTH):
        """soles: per leg `sole_points` (None: no floor); torso: `torso_depth` of the body."""
        self.character = character
        self.person = person
        self.ik = ik or IKSettings()
        cs = character.skeleton
        missing = missing_bones(person.names)
        if missing:
            raise ValueError(f"person skeleton lacks {missing}")
        self.align = alignment_rotations(cs, person)
        self.scale = (cs.leg_length("left") + cs.leg_length("right")) / (
            person.leg_length("left") + person.leg_length("right"))
        self.person_floor_y = person_floor_y
        # person bone index for every character bone (-1: not captured)
        self.person_index = np.array([person.names.index(n) if n in person.names else -1 for n in cs.names],
                                     dtype=np.int64)
        model = character.model
        self.data = model.createData()
        self.legs = []
        for side in ("left", "right"):
            bones = [cs.index(n) for n in LEGS[side]]
            v0 = int(character.idx_v[bones[0]])
            assert list(character.idx_v[bones]) == [v0, v0 + 3, v0 + 6], "leg joints must be consecutive"
            self.legs.append(dict(bones=bones, cols=slice(v0, v0 + 9), jid=int(character.joint_ids[bones[-1]]),
                                  person_foot=person.index(LEGS[side][-1]), toe=cs.index(TOES[side]),
                                  qslice=slice(int(character.idx_q[bones[0]]), int(character.idx_q[bones[-1]]) + 4)))
        self.soles = soles  # per leg (points, on_toe) or None
        n = len(cs.names)
        self._person_offsets = person.offsets  # a derived property: computed once, not per frame
        self._person_rot = np.empty((len(person.names), 3, 3))
        self._person_pos = np.empty((len(person.names), 3))
        self._char_global = np.empty((n, 3, 3))
        self._char_local = np.empty((n, 3, 3))
        self._fk_rot = np.empty((n, 3, 3))
        self._fk_pos = np.empty((n, 3))
        self._knees = [cs.index(LEGS[side][1]) for side in ("left", "right")]
        c, sn = np.cos(np.deg2rad(self.ik.knee_bias_deg)), np.sin(np.deg2rad(self.ik.knee_bias_deg))
        # rotation about the knee joint's x axis (world x at rest): positive moves the shin backward
        self._knee_bias = np.array([[1.0, 0.0, 0.0], [0.0, c, -sn], [0.0, sn, c]])
        self._person_hips = (person.index("LeftUpLeg"), person.index("RightUpLeg"))
        self._char_hips = (cs.index("LeftUpLeg"), cs.index("RightUpLeg"))
        self._q = np.empty(model.nq)
        self._q_prior = np.empty(model.nq)
        self._q_try = np.empty(model.nq)
        self._q_last: np.ndarray | None = None
        self._dv = np.zeros(model.nv)
        self._weights = np.array([1, 1, 1, self.ik.rotation_weight, self.ik.rotation_weight,
                                  self.ik.rotation_weight], dtype=float)
        self._step = np.empty(9)
        self._jac = np.empty((2, 6, 9))
        self._scratch = IKScratch(9)
        self._err = np.empty((2, 6))
        self._err_try = np.empty((2, 6))
        self.target_rot = np.empty((2, 3, 3))
        self.target_pos = np.empty((2, 3))
        self._lift = np.zeros(2)
        self.torso = torso
        self._arm_turn = np.zeros(2)
        self._turn = np.empty((3, 3))
        self.arms = []
        for slot, name in enumerate(ARMS):
            if name not in cs.names:
                continue
            arm = cs.index(name)
            children = [b for b in range(n) if cs.parents[b] == arm]
            if len(children) != 1:
                continue
            fore = children[0]
            subtree = [arm, fore] + [b for b in range(n) if b not in (arm, fore) and self._descends(cs.parents, b, arm)]
            self.arms.append(dict(slot=slot, chest=int(cs.parents[cs.parents[arm]]),
                                  subtree=np.array(subtree, dtype=np.int64),
                                  arm_rest=cs.tails[arm] - cs.heads[arm], fore_rest=cs.tails[fore] - cs.heads[fore],
                                  outward=float(np.sign(cs.heads[arm, 0]))))

    @staticmethod
    def _descends(parents: np.ndarray, b: int, ancestor: int) -> bool:
        while b >= 0:
            if b == ancestor:
                return True
            b = int(parents[b])
        return False

    def reset(self) -> None:
        self._q_last = None

    def map_point(self, p: np.ndarray) -> np.ndarray:
        """A point of the person's space (metres) -> the character's world (floor at y = 0)."""
        out = p * self.scale
        out[1] = (p[1] - self.person_floor_y) * self.scale
        return out

    def copied_pose(self, person_local: np.ndarray, person_root: np.ndarray) -> np.ndarray:
        """The character configuration with every rotation copied (the IK prior)."""
        forward_kinematics(self.person.parents, self._person_offsets, person_root, person_local,
                           self._person_rot, self._person_pos)
        cs = self.character.skeleton
        copy_rotations(self._person_rot, self.person_index, self.align, cs.parents, self._char_global,
                       self._char_local, self._scratch.rel)
        self._arm_turn[:] = 0.0
        if self.ik.arm_clearance_deg > 0.0:
            for a in self.arms:
                self._arm_turn[a["slot"]] = keep_arm_clear(
                    self._char_global, self._char_local, cs.parents, a["chest"], a["subtree"], a["arm_rest"],
                    a["fore_rest"], a["outward"], np.deg2rad(self.ik.arm_clearance_deg), np.deg2rad(ARM_SPAN_DEG),
                    self.torso[0], self.torso[1], self._turn, self._scratch.rel)
        for knee in self._knees:  # only the IK's posture prior; the solved knee follows the targets
            self._char_local[knee] = self._char_local[knee] @ self._knee_bias
        # place the root so that the hip-joint centre lands on the mapped person's hip centre
        forward_kinematics(cs.parents, self.character.offsets, np.zeros(3), self._char_local,
                           self._fk_rot, self._fk_pos)
        hips_person = 0.5 * (self._person_pos[self._person_hips[0]] + self._person_pos[self._person_hips[1]])
        hips_char = 0.5 * (self._fk_pos[self._char_hips[0]] + self._fk_pos[self._char_hips[1]])
        root = self.map_point(hips_person) - hips_char
        return self.character.configuration(self._char_local, root, self._q_prior)

    def ankle_targets(self) -> None:
        """Ankle targets (self.target_rot/pos): the person's ankle pose, raised above the floor if needed."""
        cs = self.character.skeleton
        for k, leg in enumerate(self.legs):
            foot = leg["bones"][-1]
            self.target_rot[k] = self._char_global[foot]
            self.target_pos[k] = self.map_point(self._person_pos[leg["person_foot"]])
            self._lift[k] = 0.0
            if self.soles is not None:
                points, on_toe = self.soles[k]
                lowest = lowest_sole_point(points, on_toe, self.target_rot[k], self.target_pos[k], cs.heads[foot],
                                           self._char_local[leg["toe"]], cs.heads[leg["toe"]], self._scratch.rel,
                                           self._scratch.vec)
                if lowest < 0.0:
                    self._lift[k] = -lowest
                    self.target_pos[k, 1] -= lowest

    def _errors(self, q: np.ndarray, out: np.ndarray) -> None:
        """Forward kinematics + Jacobians at q; ankle error per leg."""
        pin.computeJointJacobians(self.character.model, self.data, q)
        for k, leg in enumerate(self.legs):
            oMi = self.data.oMi[leg["jid"]]
            pose_error(self.target_rot[k], self.target_pos[k], oMi.rotation, oMi.translation, out[k],
                       self._scratch.rel)

    def _jacobian(self, k: int) -> None:
        leg = self.legs[k]
        self._jac[k] = pin.getJointJacobian(self.character.model, self.data, leg["jid"],
                                            pin.LOCAL_WORLD_ALIGNED)[:, leg["cols"]]

    def solve_legs(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """Levenberg-Marquardt on both legs towards the ankle targets; only leg joints of q move."""
        model, ik, w = self.character.model, self.ik, self._weights
        err, err_try = self._err, self._err_try
        self._errors(q, err)
        cost = [weighted_cost(err[k], w) for k in range(2)]
        for k in range(2):
            self._jacobian(k)
        lam = [ik.damping, ik.damping]
        q_try = self._q_try
        q_try[:] = q
        it = 0
        while it < ik.max_iterations:
            active = [not (np.linalg.norm(err[k, :3]) < ik.position_tolerance
                           and np.linalg.norm(err[k, 3:]) < ik.rotation_tolerance) for k in range(2)]
            if not any(active):
                break
            it += 1
            posture = pin.difference(model, q, self._q_prior)
            dv = self._dv
            dv[:] = 0.0
            sc = self._scratch
            for k, leg in enumerate(self.legs):
                if active[k]:
                    dls_step(self._jac[k], err[k], w, lam[k], posture[leg["cols"]], ik.posture_gain,
                             ik.max_step, self._step, sc.jw, sc.normal, sc.low, sc.rhs, sc.y, sc.z)
                    dv[leg["cols"]] = self._step
            q_try[:] = pin.integrate(model, q, dv)
            self._errors(q_try, err_try)
            rejected = False
            for k, leg in enumerate(self.legs):
                if not active[k]:
                    continue
                new_cost = weighted_cost(err_try[k], w)
                if new_cost <= cost[k]:
                    q[leg["qslice"]] = q_try[leg["qslice"]]
                    err[k] = err_try[k]
                    cost[k] = new_cost
                    lam[k] = max(lam[k] / 3.0, 1e-9)
                    self._jacobian(k)  # data holds this leg at its accepted configuration
                else:
                    lam[k] = lam[k] * 4.0 + 1e-6
                    rejected = True
            if rejected:  # data holds a rejected leg: recompute at the accepted configuration
                self._errors(q, err)
                for k in range(2):
                    self._jacobian(k)
        return np.linalg.norm(err[:, :3], axis=1), np.linalg.norm(err[:, 3:], axis=1), it

    def solve(self, q: np.ndarray, target_rot: np.ndarray, target_pos: np.ndarray,
              prior: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, int]:
        """Solve both legs towards given ankle targets ((2, 3, 3), (2, 3): left, right) from q,
        which is updated in place; `prior` is the null-space posture (default: q itself)."""
        self.target_rot[:] = target_rot
        self.target_pos[:] = target_pos
        self._q_prior[:] = q if prior is None else prior
        return self.solve_legs(q)

    def __call__(self, person_local: np.ndarray, person_root: np.ndarray) -> RetargetFrame:
        prior = self.copied_pose(person_local, person_root)
        self.ankle_targets()
        q = self._q
        q[:] = prior
        if self._q_last is not None:
            # warm start: last frame's leg angles, this frame's root and upper body
            for leg in self.legs:
                q[leg["qslice"]] = self._q_last[leg["qslice"]]
        else:
            self._q_last = np.empty_like(q)
        pos_err, rot_err, iters = self.solve_legs(q)
        self._q_last[:] = q
        return RetargetFrame(q=q, ankle_position_error=pos_err, ankle_rotation_error=rot_err,
                             floor_lift=self._lift.copy(), arm_turn=self._arm_turn.copy(), iterations=iters)
