"""numba kernels of the retargeting hot path (the Jacobians themselves come from Pinocchio).

They allocate nothing: their scratch comes from the caller (`IKScratch`), built once."""

from __future__ import annotations

import numpy as np
from numba import njit


class IKScratch:
    """Preallocated scratch of the kernels below, for joints of up to n_dof degrees of freedom
    and m error rows (one leg: 6 rows)."""

    def __init__(self, n_dof: int, m: int = 6):
        self.rel = np.empty((3, 3))  # copy_rotations, pose_error, lowest_sole_point
        self.vec = np.empty(3)  # lowest_sole_point
        self.jw = np.empty((m, n_dof))  # dls_step
        self.normal = np.empty((m, m))  # dls_step: J_w J_w^T + lam I
        self.low = np.empty((m, m))  # solve_spd: its Cholesky factor
        self.rhs = np.empty(m)
        self.y = np.empty(m)
        self.z = np.empty(m)  # solve_spd: forward substitution


@njit(cache=True, nogil=True)
def mat3_mul(a, b, out):
    """out = a @ b for 3x3 matrices (out may not alias a or b)."""
    for i in range(3):
        for j in range(3):
            out[i, j] = a[i, 0] * b[0, j] + a[i, 1] * b[1, j] + a[i, 2] * b[2, j]


@njit(cache=True, nogil=True)
def mat3_tmul(a, b, out):
    """out = a.T @ b for 3x3 matrices."""
    for i in range(3):
        for j in range(3):
            out[i, j] = a[0, i] * b[0, j] + a[1, i] * b[1, j] + a[2, i] * b[2, j]


@njit(cache=True, nogil=True)
def copy_rotations(person_global, person_index, align, parents, char_global, char_local, rel):
    """Character bone rotations from the person's: G_b = R_person_b A_b (bones the person lacks keep
    their aligned rest rotation relative to the parent); local L_b = G_parent^T G_b.
    rel: (3, 3) scratch."""
    for b in range(parents.shape[0]):
        p = parents[b]
        pb = person_index[b]
        if pb >= 0:
            mat3_mul(person_global[pb], align[b], char_global[b])
        elif p >= 0:
            mat3_tmul(align[p], align[b], rel)
            mat3_mul(char_global[p], rel, char_global[b])
        else:
            char_global[b] = align[b]
        if p >= 0:
            mat3_tmul(char_global[p], char_global[b], char_local[b])
        else:
            char_local[b] = char_global[b]


@njit(cache=True, nogil=True)
def smooth_fade(x, lo, hi):
    """1 below lo, 0 above hi, a smoothstep between."""
    if x <= lo:
        return 1.0
    if x >= hi:
        return 0.0
    t = (x - lo) / (hi - lo)
    return 1.0 - t * t * (3.0 - 2.0 * t)


@njit(cache=True, nogil=True)
def clearance_need(c, vx, vy, vz, outward, min_angle, span, front, back):
    """How far (rad) to turn a point at (vx, vy, vz) from the shoulder (world) outwards about the
    chest's forward axis (c: chest rotation) so that its angle a from the chest's down axis in the
    frontal plane is at least min_angle. With the deficit d = min_angle - a > 0 it is
        w * d                 (d <= span)
        w * (2 span - d)      (span < d < 2 span; 0 beyond: an arm reaching across the body,
                               or up past the shoulder, is placed on purpose)
    and w fades from 1 to 0 as the point's forward (backward) offset goes from 1 to 1.5 times the
    torso's front (back) depth from the shoulder: a hand held in front of the body stays there."""
    dx = c[0, 0] * vx + c[1, 0] * vy + c[2, 0] * vz
    dy = c[0, 1] * vx + c[1, 1] * vy + c[2, 1] * vz
    dz = c[0, 2] * vx + c[1, 2] * vy + c[2, 2] * vz
    d = min_angle - np.arctan2(outward * dx, -dy)
    if d <= 0.0 or d >= 2.0 * span:
        return 0.0
    depth = front if dz > 0.0 else back
    return smooth_fade(abs(dz) / depth, 1.0, 1.5) * min(d, 2.0 * span - d)


@njit(cache=True, nogil=True)
def keep_arm_clear(char_global, char_local, parents, chest, subtree, arm_rest, fore_rest, outward, min_angle,
                   span, front, back, turn, rel):
    """Abduct an arm that hangs closer to the torso than `min_angle` (rad).

    Seen from the shoulder in the chest's frame (x lateral, y up, z forward at rest), the elbow
    and the wrist each make an angle a = atan2(outward * d_x, -d_y) with the chest's down axis in
    the frontal plane (positive away from the body). The whole arm (the bones in `subtree`: the
    upper arm, its forearm, then the rest) turns about the chest's forward axis by the larger
    `clearance_need` of the two points; a turn about that axis raises both angles by exactly the
    turn, and the turn is continuous in the pose. Globals of the subtree and the upper arm's local
    rotation are updated; the elbow and wrist keep their copied local angles. Returns the turn
    (rad). arm_rest, fore_rest: rest bone vectors (tail - head) of the upper arm and forearm;
    front, back: the torso's depth in front of and behind the shoulder joint (m).
    turn, rel: (3, 3) scratch."""
    c = char_global[chest]
    g = char_global[subtree[0]]
    f = char_global[subtree[1]]
    ex = g[0, 0] * arm_rest[0] + g[0, 1] * arm_rest[1] + g[0, 2] * arm_rest[2]
    ey = g[1, 0] * arm_rest[0] + g[1, 1] * arm_rest[1] + g[1, 2] * arm_rest[2]
    ez = g[2, 0] * arm_rest[0] + g[2, 1] * arm_rest[1] + g[2, 2] * arm_rest[2]
    wx = ex + f[0, 0] * fore_rest[0] + f[0, 1] * fore_rest[1] + f[0, 2] * fore_rest[2]
    wy = ey + f[1, 0] * fore_rest[0] + f[1, 1] * fore_rest[1] + f[1, 2] * fore_rest[2]
    wz = ez + f[2, 0] * fore_rest[0] + f[2, 1] * fore_rest[1] + f[2, 2] * fore_rest[2]
    delta = max(clearance_need(c, ex, ey, ez, outward, min_angle, span, front, back),
                clearance_need(c, wx, wy, wz, outward, min_angle, span, front, back))
    if delta == 0.0:
        return 0.0
    # turn = C Rz(outward * delta) C^T: a rotation about the chest's forward axis, in world
    s, k = np.sin(outward * delta), np.cos(outward * delta)
    for i in range(3):
        for j in range(3):
            turn[i, j] = (c[i, 0] * (k * c[j, 0] - s * c[j, 1]) + c[i, 1] * (s * c[j, 0] + k * c[j, 1])
                          + c[i, 2] * c[j, 2])
    for b in subtree:
        mat3_mul(turn, char_global[b], rel)
        char_global[b] = rel
    arm = subtree[0]
    mat3_tmul(char_global[parents[arm]], char_global[arm], char_local[arm])
    return delta


@njit(cache=True, nogil=True)
def rotation_log(r, out, at):
    """Axis-angle vector of a rotation matrix (log map), robust near 0 and pi, into out[at:at + 3]."""
    c = 0.5 * (r[0, 0] + r[1, 1] + r[2, 2] - 1.0)
    c = min(1.0, max(-1.0, c))
    theta = np.arccos(c)
    vx = r[2, 1] - r[1, 2]
    vy = r[0, 2] - r[2, 0]
    vz = r[1, 0] - r[0, 1]
    if theta < 1e-6:
        f = 0.5
    elif theta > np.pi - 1e-4:
        # near a half-turn: axis from the diagonal
        ax = np.sqrt(max(0.0, (r[0, 0] - c) / (1.0 - c)))
        ay = np.sqrt(max(0.0, (r[1, 1] - c) / (1.0 - c)))
        az = np.sqrt(max(0.0, (r[2, 2] - c) / (1.0 - c)))
        if vx < 0:
            ax = -ax
        if vy < 0:
            ay = -ay
        if vz < 0:
            az = -az
        out[at] = ax * theta
        out[at + 1] = ay * theta
        out[at + 2] = az * theta
        return
    else:
        f = 0.5 * theta / np.sin(theta)
    out[at] = f * vx
    out[at + 1] = f * vy
    out[at + 2] = f * vz


@njit(cache=True, nogil=True)
def pose_error(target_rot, target_pos, rot, pos, out, rel):
    """6-vector [target_pos - pos, log(target_rot rot^T)] in world axes. rel: (3, 3) scratch."""
    for a in range(3):
        out[a] = target_pos[a] - pos[a]
    for i in range(3):
        for j in range(3):
            rel[i, j] = target_rot[i, 0] * rot[j, 0] + target_rot[i, 1] * rot[j, 1] + target_rot[i, 2] * rot[j, 2]
    rotation_log(rel, out, 3)


@njit(cache=True, nogil=True)
def weighted_cost(error, weights):
    s = 0.0
    for i in range(error.shape[0]):
        s += (error[i] * weights[i]) ** 2
    return s


@njit(cache=True, nogil=True)
def solve_spd(a, b, out, low, y):
    """Solve a x = b for a small symmetric positive definite a (Cholesky, no pivoting).
    low (n, n), y (n,): scratch (the lower triangle of low is written before it is read)."""
    n = a.shape[0]
    for i in range(n):
        for j in range(i + 1):
            s = a[i, j]
            for k in range(j):
                s -= low[i, k] * low[j, k]
            if i == j:
                low[i, i] = np.sqrt(max(s, 1e-300))
            else:
                low[i, j] = s / low[j, j]
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= low[i, k] * y[k]
        y[i] = s / low[i, i]
    for i in range(n - 1, -1, -1):
        s = y[i]
        for k in range(i + 1, n):
            s -= low[k, i] * out[k]
        out[i] = s / low[i, i]


@njit(cache=True, nogil=True)
def dls_step(jac, error, weights, lam, posture, posture_gain, max_step, out, jw, a, low, rhs, y, z):
    """Damped least-squares step with a null-space pull towards a posture.

    J_w = W J, e_w = W e, J+ = J_w^T (J_w J_w^T + lam I)^-1;
    dq = J+ e_w + k (posture - J+ J_w posture), scaled so no component exceeds max_step.
    jw (m, n), a, low (m, m), rhs, y, z (m,): scratch (`IKScratch`).
    """
    m, n = jac.shape
    for i in range(m):
        for j in range(n):
            jw[i, j] = jac[i, j] * weights[i]
    for i in range(m):
        for k in range(m):
            s = 0.0
            for j in range(n):
                s += jw[i, j] * jw[k, j]
            a[i, k] = s
        a[i, i] += lam
    # right-hand side: e_w - k J_w posture, so dq = J+ (e_w - k J_w p) + k p
    for i in range(m):
        s = 0.0
        for j in range(n):
            s += jw[i, j] * posture[j]
        rhs[i] = error[i] * weights[i] - posture_gain * s
    solve_spd(a, rhs, y, low, z)
    biggest = 0.0
    for j in range(n):
        s = posture_gain * posture[j]
        for i in range(m):
            s += jw[i, j] * y[i]
        out[j] = s
        biggest = max(biggest, abs(s))
    if biggest > max_step:
        for j in range(n):
            out[j] *= max_step / biggest


@njit(cache=True, nogil=True)
def lowest_sole_point(points, on_toe, foot_rot, foot_pos, foot_head, toe_local, toe_head, toe_rot, toe_pos):
    """Lowest world height of the sole points when the foot joint is at (foot_rot, foot_pos) and the
    toe joint rotates by toe_local relative to the foot (points are rest positions).
    toe_rot (3, 3), toe_pos (3,): scratch."""
    mat3_mul(foot_rot, toe_local, toe_rot)
    for a in range(3):
        toe_pos[a] = foot_pos[a]
        for m in range(3):
            toe_pos[a] += foot_rot[a, m] * (toe_head[m] - foot_head[m])
    lowest = np.inf
    for i in range(points.shape[0]):
        if on_toe[i]:
            y = toe_pos[1]
            for m in range(3):
                y += toe_rot[1, m] * (points[i, m] - toe_head[m])
        else:
            y = foot_pos[1]
            for m in range(3):
                y += foot_rot[1, m] * (points[i, m] - foot_head[m])
        lowest = min(lowest, y)
    return lowest
