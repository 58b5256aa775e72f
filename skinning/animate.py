"""Per-frame body: retarget a person's pose, pose the character, skin and shade it.

`BodyAnimator` owns every per-frame array (allocated once); each call overwrites them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .body import BODY_REGIONS, Body, body_regions
from .character import Character
from .contact import ContactSettings, SkinContact
from .hands import HandClearance, axis_angle_matrix
from .kinematics import matrix_to_quaternion_xyzw
from .retarget import IKSettings, Retargeter, RetargetFrame, sole_points, torso_depth
from .skeleton import Skeleton
from .skin import MeshNormals, SkinWeights, linear_blend_skinning, skin_matrices


@dataclass
class BodyFrame:
    vertices: np.ndarray  # (n, 3) all skinned vertices (helpers included), metres, world
    normals: np.ndarray | None  # (n_visible, 3) unit normals of the visible skin (None: not computed)
    joint_rotations: np.ndarray  # (bones, 3, 3) global
    joint_positions: np.ndarray  # (bones, 3) global
    retarget: RetargetFrame | None


STAGES = ("ik", "skinning", "hands", "contact", "normals")


class BodyAnimator:
    """Retarget + skin, one frame at a time. `stage_seconds` holds the last frame's stage times."""

    def __init__(self, body: Body, person: Skeleton | None = None, ik: IKSettings | None = None,
                 person_floor_y: float = 0.0, normals: bool = True,
                 contact: ContactSettings | None = ContactSettings(), helpers: bool = True):
        """normals: compute the skin's vertex normals each frame (False: a service that publishes
        the body for displays that compute their own; BodyFrame.normals is then None).
        helpers: skin the helper vertices after the visible skin too (garments are fitted to
        them); False: BodyFrame.vertices holds the visible skin only (a third fewer vertices to
        skin; what a service publishing the body needs).
        contact: where the skinned body cuts through itself, bring the skin to a contact surface
        (`SkinContact`); None: the skin as linear blend skinning leaves it.
        With a person, `ik.hand_clearance` turns a retargeted arm out where its hand sinks into the
        torso or a leg (`HandClearance`)."""
        self.body = body
        self.character = Character(body.skeleton)
        self.retargeter = None
        if person is not None:
            soles = [sole_points(body.vertices, body.weight_bones, body.weight_values, body.n_visible,
                                 body.skeleton, side) for side in ("left", "right")]
            torso = torso_depth(body.vertices, body_regions(body), BODY_REGIONS["torso"], body.skeleton)
            self.retargeter = Retargeter(self.character, person, soles, person_floor_y, ik, torso)
        n_bones = len(body.skeleton.names)
        self._local = np.empty((n_bones, 3, 3))
        self._root = np.empty(3)
        self._matrices = np.empty((n_bones, 3, 4))
        self._weights = SkinWeights.from_padded(body.weight_bones, body.weight_values)
        self._normals = MeshNormals(body.triangles, body.n_visible)
        self.contact = SkinContact.for_body(body, contact) if contact is not None else None
        hands = self.retargeter.ik.hand_clearance if self.retargeter is not None else None
        self.hands = HandClearance.for_body(body, hands) if hands is not None else None
        self._turn = np.empty((3, 3))
        self._arm = np.empty((3, 3))
        self._axis = np.empty(3)
        self.stage_seconds = np.zeros(len(STAGES))
        self._n_skinned = len(body.vertices) if helpers else body.n_visible
        self.frame = BodyFrame(
            vertices=np.empty((self._n_skinned, 3)),
            normals=np.empty((body.n_visible, 3)) if normals else None,
            joint_rotations=np.empty((n_bones, 3, 3)),
            joint_positions=np.empty((n_bones, 3)),
            retarget=None,
        )

    @property
    def world_offset(self) -> np.ndarray:
        """Translation that puts the rest body on the floor y = 0."""
        return np.array([0.0, -self.body.floor_y, 0.0])

    def rest_configuration(self) -> np.ndarray:
        q = self.character.neutral()
        q[:3] += self.world_offset
        return q

    def _skin(self, q: np.ndarray) -> None:
        f = self.frame
        self.character.global_pose(q, self._local, self._root, f.joint_rotations, f.joint_positions)
        skin_matrices(f.joint_rotations, f.joint_positions, self.body.skeleton.heads, self._matrices)
        w = self._weights
        linear_blend_skinning(self.body.vertices[: self._n_skinned], w.start, w.bones, w.weights, self._matrices,
                              f.vertices)

    def _clear_hands(self, q: np.ndarray, arm_turn: np.ndarray) -> bool:
        """Turn out (in q) each arm whose hand the skinned frame has inside the torso or a leg;
        the turn is added to arm_turn. True if an arm turned."""
        f = self.frame
        moved = False
        for hand in self.hands.hands:
            arm = hand["arm"]
            axis = np.multiply(f.joint_rotations[hand["chest"], :, 2], hand["outward"], out=self._axis)
            angle = self.hands.turn(hand, f.vertices, f.joint_rotations, f.joint_positions[arm], axis)
            if angle == 0.0:
                continue
            # the arm's global rotation turned about the world axis, then back to its local rotation
            axis_angle_matrix(axis, angle, self._turn)
            np.matmul(self._turn, f.joint_rotations[arm], out=self._arm)
            np.matmul(f.joint_rotations[hand["parent"]].T, self._arm, out=self._turn)
            i = self.character.idx_q[arm]
            matrix_to_quaternion_xyzw(self._turn, q[i: i + 4])
            arm_turn[hand["slot"]] += angle
            moved = True
        return moved

    def pose(self, q: np.ndarray, contact: bool = True) -> BodyFrame:
        """Skin the body in configuration q (Pinocchio layout); contact=False: without the skin
        contact even if the animator has one."""
        t0 = time.perf_counter()
        self._skin(q)
        t1 = time.perf_counter()
        self.stage_seconds[1] = t1 - t0
        self.stage_seconds[2] = 0.0
        self._finish(contact, t1)
        return self.frame

    def _finish(self, contact: bool, t1: float) -> None:
        f = self.frame
        if contact and self.contact is not None:
            self.contact(f.vertices)
        t2 = time.perf_counter()
        if f.normals is not None:
            self._normals(f.vertices, f.normals)
        self.stage_seconds[3] = t2 - t1
        self.stage_seconds[4] = time.perf_counter() - t2

    def __call__(self, local_rot: np.ndarray, root_position: np.ndarray) -> BodyFrame:
        """Retarget one frame of the person's motion and skin the character."""
        if self.retargeter is None:
            raise RuntimeError("BodyAnimator was built without a person skeleton")
        t0 = time.perf_counter()
        result = self.retargeter(local_rot, root_position)
        t1 = time.perf_counter()
        self._skin(result.q)
        t2 = time.perf_counter()
        if self.hands is not None and self._clear_hands(result.q, result.arm_turn):
            self._skin(result.q)  # the turned arm: skinned again
        t3 = time.perf_counter()
        self._finish(True, t3)
        self.stage_seconds[:3] = t1 - t0, t2 - t1, t3 - t2
        self.frame.retarget = result
        return self.frame
