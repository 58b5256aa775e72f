"""Small numba kernels for rotations and forward kinematics over bone arrays."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def axis_rotation(axis: int, degrees: float, out: np.ndarray) -> None:
    """Rotation matrix about x (0), y (1) or z (2) by an angle in degrees, written into out (3, 3)."""
    a = np.deg2rad(degrees)
    c = np.cos(a)
    s = np.sin(a)
    for i in range(3):
        for j in range(3):
            out[i, j] = 0.0
    if axis == 0:
        out[0, 0] = 1.0
        out[1, 1] = c
        out[1, 2] = -s
        out[2, 1] = s
        out[2, 2] = c
    elif axis == 1:
        out[1, 1] = 1.0
        out[0, 0] = c
        out[0, 2] = s
        out[2, 0] = -s
        out[2, 2] = c
    else:
        out[2, 2] = 1.0
        out[0, 0] = c
        out[0, 1] = -s
        out[1, 0] = s
        out[1, 1] = c


@njit(cache=True, nogil=True)
def channels_to_local(values, chan_joint, chan_kind, unit, rot_out, pos_out):
    """BVH channel values of one frame -> local rotation per joint and root translation.

    Rotation channels compose in the order the file lists them (R = R_first R_second ...),
    whatever that order is. chan_kind: 0..2 = X/Y/Z position, 3..5 = X/Y/Z rotation.
    rot_out (n, 3, 3) is overwritten; pos_out (3,) receives position channels times unit.
    Each rotation is applied in place: R @ R_axis mixes only R's two columns across the axis
    (the same sums as the full product, whose other terms are exact zeros), nothing allocated.
    """
    n = rot_out.shape[0]
    for j in range(n):
        for a in range(3):
            for b in range(3):
                rot_out[j, a, b] = 1.0 if a == b else 0.0
    pos_out[:] = 0.0
    for c in range(values.shape[0]):
        j = chan_joint[c]
        k = chan_kind[c]
        if k < 3:
            pos_out[k] = values[c] * unit
        else:
            # R_axis (see axis_rotation): [p, p] = [q, q] = cos, [p, q] = -sin, [q, p] = sin,
            # with p, q the two axes after this one in cyclic order
            p = (k - 2) % 3
            q = (k - 1) % 3
            angle = np.deg2rad(values[c])
            co = np.cos(angle)
            si = np.sin(angle)
            for a in range(3):
                rp = rot_out[j, a, p]
                rq = rot_out[j, a, q]
                rot_out[j, a, p] = rp * co + rq * si
                rot_out[j, a, q] = rq * co - rp * si


@njit(cache=True, nogil=True)
def forward_kinematics(parents, offsets, root_position, local_rot, global_rot, global_pos):
    """Global rotation and joint position of every bone (parents listed before children).

    The root's joint sits at offsets[0] + root_position; every other joint at its parent's
    position plus the parent's global rotation applied to its offset.
    """
    n = parents.shape[0]
    for j in range(n):
        p = parents[j]
        if p < 0:
            global_rot[j] = local_rot[j]
            for a in range(3):
                global_pos[j, a] = offsets[j, a] + root_position[a]
        else:
            for a in range(3):
                s = global_pos[p, a]
                for m in range(3):
                    s += global_rot[p, a, m] * offsets[j, m]
                global_pos[j, a] = s
                for b in range(3):
                    t = 0.0
                    for m in range(3):
                        t += global_rot[p, a, m] * local_rot[j, m, b]
                    global_rot[j, a, b] = t


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation taking direction a onto direction b (identity if either is ~0)."""
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na < 1e-9 or nb < 1e-9:
        return np.eye(3)
    a = a / na
    b = b / nb
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    s = np.linalg.norm(v)
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        # opposite: half-turn about any axis perpendicular to a
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx * ((1 - c) / (s * s))


@njit(cache=True, nogil=True)
def matrix_to_quaternion_xyzw(r, out):
    """Rotation matrix -> unit quaternion (x, y, z, w), Pinocchio's storage order."""
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    if tr > 0.0:
        s = np.sqrt(tr + 1.0) * 2.0
        out[3] = 0.25 * s
        out[0] = (r[2, 1] - r[1, 2]) / s
        out[1] = (r[0, 2] - r[2, 0]) / s
        out[2] = (r[1, 0] - r[0, 1]) / s
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2.0
        out[3] = (r[2, 1] - r[1, 2]) / s
        out[0] = 0.25 * s
        out[1] = (r[0, 1] + r[1, 0]) / s
        out[2] = (r[0, 2] + r[2, 0]) / s
    elif r[1, 1] > r[2, 2]:
        s = np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2.0
        out[3] = (r[0, 2] - r[2, 0]) / s
        out[0] = (r[0, 1] + r[1, 0]) / s
        out[1] = 0.25 * s
        out[2] = (r[1, 2] + r[2, 1]) / s
    else:
        s = np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2.0
        out[3] = (r[1, 0] - r[0, 1]) / s
        out[0] = (r[0, 2] + r[2, 0]) / s
        out[1] = (r[1, 2] + r[2, 1]) / s
        out[2] = 0.25 * s
    norm = np.sqrt(out[0] ** 2 + out[1] ** 2 + out[2] ** 2 + out[3] ** 2)
    for k in range(4):
        out[k] /= norm
