"""The character's skeleton as a Pinocchio model, and its pose as arrays.

Joint frames have identity orientation in the rest pose (world axes) and sit at
the bones' heads, so a bone's global rotation is directly the rotation it applies
to the rest mesh. The root (Hips) is a free-flyer whose configuration is its world
pose; every other bone is a spherical joint whose configuration is the bone's
rotation relative to its parent.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
from numba import njit

from .kinematics import forward_kinematics, matrix_to_quaternion_xyzw
from .skeleton import Skeleton


def build_model(skeleton: Skeleton) -> tuple[pin.Model, np.ndarray]:
    """pin.Model with a free-flyer root and spherical joints; returns (model, joint_id per bone)."""
    model = pin.Model()
    model.name = "character"
    joint_ids = np.zeros(len(skeleton.names), dtype=np.int64)
    for b, name in enumerate(skeleton.names):
        p = int(skeleton.parents[b])
        if p < 0:
            jid = model.addJoint(0, pin.JointModelFreeFlyer(), pin.SE3.Identity(), name)
        else:
            placement = pin.SE3(np.eye(3), skeleton.heads[b] - skeleton.heads[p])
            jid = model.addJoint(int(joint_ids[p]), pin.JointModelSpherical(), placement, name)
        # nominal inertia so dynamics-based algorithms stay well defined
        model.appendBodyToJoint(jid, pin.Inertia.FromSphere(1.0, 0.05), pin.SE3.Identity())
        model.addJointFrame(jid)
        joint_ids[b] = jid
    return model, joint_ids


@njit(cache=True, nogil=True)
def local_to_configuration(local_rot, root_position, idx_q, q):
    """Local bone rotations + root position -> Pinocchio configuration q (in place)."""
    q[0] = root_position[0]
    q[1] = root_position[1]
    q[2] = root_position[2]
    for b in range(local_rot.shape[0]):
        matrix_to_quaternion_xyzw(local_rot[b], q[idx_q[b]: idx_q[b] + 4])


@njit(cache=True, nogil=True)
def quaternion_to_matrix(x, y, z, w, out):
    out[0, 0] = 1 - 2 * (y * y + z * z)
    out[0, 1] = 2 * (x * y - z * w)
    out[0, 2] = 2 * (x * z + y * w)
    out[1, 0] = 2 * (x * y + z * w)
    out[1, 1] = 1 - 2 * (x * x + z * z)
    out[1, 2] = 2 * (y * z - x * w)
    out[2, 0] = 2 * (x * z - y * w)
    out[2, 1] = 2 * (y * z + x * w)
    out[2, 2] = 1 - 2 * (x * x + y * y)


@njit(cache=True, nogil=True)
def configuration_to_local(q, idx_q, local_rot, root_position):
    """Pinocchio configuration -> local bone rotations (n, 3, 3) and root position (3,)."""
    for a in range(3):
        root_position[a] = q[a]
    for b in range(local_rot.shape[0]):
        i = idx_q[b]
        x, y, z, w = q[i], q[i + 1], q[i + 2], q[i + 3]
        n = np.sqrt(x * x + y * y + z * z + w * w)
        quaternion_to_matrix(x / n, y / n, z / n, w / n, local_rot[b])


class Character:
    """What does not change about the character: skeleton, Pinocchio model, index maps."""

    def __init__(self, skeleton: Skeleton):
        self.skeleton = skeleton
        self.model, self.joint_ids = build_model(skeleton)
        self.idx_q = np.array([self.model.joints[int(j)].idx_q for j in self.joint_ids], dtype=np.int64)
        # quaternion part of the free-flyer starts 3 entries after its translation
        self.idx_q[0] += 3
        self.idx_v = np.array([self.model.joints[int(j)].idx_v for j in self.joint_ids], dtype=np.int64)
        self.offsets = skeleton.offsets
        self.offsets[0] = 0.0  # the free-flyer carries the root's world position itself

    def neutral(self) -> np.ndarray:
        """Rest configuration with the root at its rest head position."""
        q = pin.neutral(self.model)
        q[:3] = self.skeleton.heads[0]
        return q

    def configuration(self, local_rot: np.ndarray, root_position: np.ndarray, q: np.ndarray | None = None):
        q = np.empty(self.model.nq) if q is None else q
        local_to_configuration(local_rot, root_position, self.idx_q, q)
        return q

    def global_pose(self, q: np.ndarray, local_rot: np.ndarray, root_position: np.ndarray,
                    global_rot: np.ndarray, global_pos: np.ndarray) -> None:
        """Forward kinematics of configuration q into preallocated global arrays (numba, no pin)."""
        configuration_to_local(q, self.idx_q, local_rot, root_position)
        forward_kinematics(self.skeleton.parents, self.offsets, root_position, local_rot, global_rot, global_pos)
