"""S101 coarse dynamics: asymmetric springs, drag, gravity, explicit RK4, strain limiting (numba kernels).

Every kernel writes into arrays the caller preallocated; nothing allocates per frame.
"""

from __future__ import annotations

import math

import numpy as np

from .jit import kernel


def spring_table(si, sj, rest, k_stretch, k_compress, c_stretch, c_compress):
    """Pack springs for the force kernel: pairs (s, 2) int32 and params (5, s) = rows (rest
    length, k_stretch - k_compress, k_compress, c_stretch - c_compress, c_compress).

    A row per parameter, so that `spring_magnitudes` reads each one in sequence and vectorises."""
    pairs = np.ascontiguousarray(np.stack([si, sj], axis=1), dtype=np.int32)
    params = np.ascontiguousarray(np.stack([rest, np.subtract(k_stretch, k_compress), k_compress,
                                            np.subtract(c_stretch, c_compress), c_compress]), dtype=np.float64)
    return pairs, params


def spring_scratch(n_springs: int) -> np.ndarray:
    """The (6, s) scratch of `spring_forces`: each spring's end-to-end vector, squared length,
    relative velocity along it, force magnitude."""
    return np.zeros((6, n_springs))


@kernel(fastmath=True)
def spring_geometry(x, v, pairs, work):
    """Per spring: work[0:3] = q_i - q_j, work[3] = |q_i - q_j|², work[4] = (v_i - v_j)·(q_i - q_j).

    The loads by particle index (vector gathers were no faster than scalar loads here), kept
    apart from the arithmetic, which vectorises."""
    for s in range(pairs.shape[0]):
        i = np.uint64(pairs[s, 0])  # (unsigned: no wrap-around of a negative index)
        j = np.uint64(pairs[s, 1])
        dx = x[i, 0] - x[j, 0]
        dy = x[i, 1] - x[j, 1]
        dz = x[i, 2] - x[j, 2]
        work[0, s] = dx
        work[1, s] = dy
        work[2, s] = dz
        work[3, s] = dx * dx + dy * dy + dz * dz
        work[4, s] = (v[i, 0] - v[j, 0]) * dx + (v[i, 1] - v[j, 1]) * dy + (v[i, 2] - v[j, 2]) * dz


@kernel(fastmath=True)
def spring_magnitudes(params, work):
    """work[5] = the force along q_i - q_j per unit of it, from work[3:5] (S101 springs):
    -k (|q_i - q_j| - L_ij) / |q_i - q_j|, k = k_stretch when longer than rest and k_compress
    when shorter, plus damping on the relative velocity along the spring with the same split.

    Sequential rows only: the loop vectorises, and the square root and the division, which
    take the scalar loop most of its time, run several springs at once."""
    for s in range(work.shape[1]):
        inv = 1.0 / math.sqrt(work[3, s] + 1e-30)  # coincident ends: no direction, no force
        ext = work[3, s] * inv - params[0, s]
        # branch-free choice: near rest the sign of ext is a coin toss the CPU cannot predict
        stretched = 1.0 if ext > 0.0 else 0.0
        k = params[2, s] + stretched * params[1, s]
        c = params[4, s] + stretched * params[3, s]
        rel = work[4, s] * inv
        work[5, s] = (-k * ext - c * rel) * inv


@kernel(fastmath=True)
def spring_forces(x, v, pairs, params, work, force):
    """Add every spring's force to `force` (S101 springs).

    f_i = -k (|q_i - q_j| - L_ij) (q_i - q_j)/|q_i - q_j|, with k = k_stretch when the spring is
    longer than rest and k_compress when shorter (the patent's two stiffnesses), plus damping
    along the spring on the relative velocity, with the same stretch/compress split (v: world
    velocities, see `accelerations`).
    pairs, params: see `spring_table`; work: (6, s) scratch (`spring_scratch`). Three passes:
    gather, vectorised arithmetic, scatter (a fifth less time than one loop doing all three:
    13.7 → 10.7 µs for 1,809 springs on the AMD EPYC)."""
    spring_geometry(x, v, pairs, work)
    spring_magnitudes(params, work)
    for s in range(pairs.shape[0]):
        i = np.uint64(pairs[s, 0])
        j = np.uint64(pairs[s, 1])
        m = work[5, s]
        fx = m * work[0, s]
        fy = m * work[1, s]
        fz = m * work[2, s]
        force[i, 0] += fx
        force[i, 1] += fy
        force[i, 2] += fz
        force[j, 0] -= fx
        force[j, 1] -= fy
        force[j, 2] -= fz


@kernel
def accelerations(x, v, carried, world, inv_mass, drag, normals, gravity_y, pairs, params, spring_work, out):
    """a = (springs + air drag + gravity) / m.

    v is relative to the frame body following carries (`collision.follow_body`), carried the
    carried part of the body's velocity. Decision: the spring damping acts on the relative
    world velocity, v + carried (written to `world`, (n, 3) scratch): two neighbours carried
    with different weights are not parting because their v differ (on the run clip's sprint
    that damping held the blouse's loose hem back against the body's 6 m/s).
    Air drag acts on the velocity across the cloth: f = -drag_i (v·n_i) n_i, drag_i = air_drag ·
    area_i (N·s/m), n_i the particle normal of this frame (a sheet moving along itself feels
    little air); on v, the velocity relative to the carried frame: the air near the body moves
    with it, the more the nearer (its boundary layer)."""
    for i in range(x.shape[0]):
        for k in range(3):
            world[i, k] = v[i, k] + carried[i, k]
    for i in range(x.shape[0]):
        d = drag[i] * (v[i, 0] * normals[i, 0] + v[i, 1] * normals[i, 1] + v[i, 2] * normals[i, 2])
        out[i, 0] = -d * normals[i, 0]
        out[i, 1] = -d * normals[i, 1]
        out[i, 2] = -d * normals[i, 2]
    spring_forces(x, world, pairs, params, spring_work, out)
    for i in range(x.shape[0]):
        w = inv_mass[i]
        out[i, 0] *= w
        out[i, 1] = out[i, 1] * w + (gravity_y if w > 0.0 else 0.0)  # inv_mass 0: gripped, kinematic
        out[i, 2] *= w


@kernel
def _axpy(out, base, h, d):
    for i in range(out.shape[0]):
        for k in range(3):
            out[i, k] = base[i, k] + h * d[i, k]


@kernel
def rk4_substep(x, v, carried, dt, inv_mass, drag, normals, gravity_y, pairs, params, spring_work, work):
    """One classical 4th-order Runge-Kutta step of dx/dt = v, dv/dt = a(x, v) (S101 integrator).
    carried: the part of the body's velocity body following transports at each particle
    (`accelerations`).

    spring_work: see `spring_forces`; work: (9, n, 3) scratch: a1..a4, v2..v4, a position
    buffer and the world velocities."""
    a1, a2, a3, a4 = work[0], work[1], work[2], work[3]
    v2, v3, v4 = work[4], work[5], work[6]
    xt = work[7]
    h = 0.5 * dt
    accelerations(x, v, carried, work[8], inv_mass, drag, normals, gravity_y, pairs, params, spring_work, a1)
    _axpy(xt, x, h, v)
    _axpy(v2, v, h, a1)
    accelerations(xt, v2, carried, work[8], inv_mass, drag, normals, gravity_y, pairs, params, spring_work, a2)
    _axpy(xt, x, h, v2)
    _axpy(v3, v, h, a2)
    accelerations(xt, v3, carried, work[8], inv_mass, drag, normals, gravity_y, pairs, params, spring_work, a3)
    _axpy(xt, x, dt, v3)
    _axpy(v4, v, dt, a3)
    accelerations(xt, v4, carried, work[8], inv_mass, drag, normals, gravity_y, pairs, params, spring_work, a4)
    s = dt / 6.0
    for i in range(x.shape[0]):
        for k in range(3):
            x[i, k] += s * (v[i, k] + 2.0 * v2[i, k] + 2.0 * v3[i, k] + v4[i, k])
            v[i, k] += s * (a1[i, k] + 2.0 * a2[i, k] + 2.0 * a3[i, k] + a4[i, k])


@kernel
def limit_stretch(x, v, carried, inv_mass, si, sj, rest, n_springs, max_strain):
    """Strain limiting (Provot 1995) on the first n_springs springs (the structural ones).

    One Gauss-Seidel pass: a spring longer than (1 + max_strain) * rest has its ends pulled
    together to that length, split by inverse mass, and loses the part of its ends' relative
    velocity that separates them (an inextensible thread does not bounce back; the world
    velocities v + carried, see `accelerations`). Explicit
    springs soft enough for a few substeps would otherwise let loose cloth sag and flutter
    far beyond what woven fabric allows."""
    for s in range(n_springs):
        i = np.uint64(si[s])  # (unsigned: no wrap-around of a negative index)
        j = np.uint64(sj[s])
        wi = inv_mass[i]
        wj = inv_mass[j]
        w = wi + wj
        if w == 0.0:
            continue
        dx = x[i, 0] - x[j, 0]
        dy = x[i, 1] - x[j, 1]
        dz = x[i, 2] - x[j, 2]
        length = math.sqrt(dx * dx + dy * dy + dz * dz)
        limit = (1.0 + max_strain) * rest[s]
        if length <= limit:
            continue
        dx /= length
        dy /= length
        dz /= length
        corr = (length - limit) / w
        x[i, 0] -= wi * corr * dx
        x[i, 1] -= wi * corr * dy
        x[i, 2] -= wi * corr * dz
        x[j, 0] += wj * corr * dx
        x[j, 1] += wj * corr * dy
        x[j, 2] += wj * corr * dz
        sep = ((v[i, 0] + carried[i, 0] - v[j, 0] - carried[j, 0]) * dx
               + (v[i, 1] + carried[i, 1] - v[j, 1] - carried[j, 1]) * dy
               + (v[i, 2] + carried[i, 2] - v[j, 2] - carried[j, 2]) * dz)
        if sep > 0.0:
            imp = sep / w
            v[i, 0] -= wi * imp * dx
            v[i, 1] -= wi * imp * dy
            v[i, 2] -= wi * imp * dz
            v[j, 0] += wj * imp * dx
            v[j, 1] += wj * imp * dy
            v[j, 2] += wj * imp * dz


# The step's bound takes every spring under tension at this multiple of its fabric's strain
# limit: the limit is enforced after each substep, so within one a spring can pass it.
TENSION_STRAIN_ALLOWANCE = 2.0
# A dense eigenvalue solve up to this many particles (0.05 s at 320, about 1 s at 1000);
# above it Gershgorin's bound, which can only ask for more substeps.
EXACT_EIGEN_PARTICLES = 1200


def rk4_stability_radius(damping_ratio: float) -> float:
    """|z| = |λ dt| where RK4 stops being stable for a mode of damping ratio ζ, along the ray
    z = |z| (-ζ + i sqrt(1 - ζ²)): the first point where |R(z)| = 1, with RK4's amplification
    R(z) = 1 + z + z²/2 + z³/6 + z⁴/24. 2√2 for ζ = 0 (the imaginary axis), 2.96 at
    ζ = 0.15, 2.62 at ζ = 0.5, 2.785 at ζ = 1 (the real axis)."""
    zeta = min(max(float(damping_ratio), 0.0), 1.0)
    ray = complex(-zeta, math.sqrt(1.0 - zeta * zeta))

    def outside(r: float) -> bool:
        z = r * ray
        return abs(1.0 + z * (1.0 + z * (0.5 + z * (1.0 / 6.0 + z / 24.0)))) > 1.0 + 1e-12

    step = 0.005  # |R| < 1 near the origin on every ray into the left half-plane: walk out, then bisect
    r = step
    while not outside(r):
        r += step
    lo, hi = r - step, r
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if outside(mid) else (mid, hi)
    return lo


def stiffness_eigenvalue(x: np.ndarray, inv_mass: np.ndarray, si: np.ndarray, sj: np.ndarray,
                         k_stretch: np.ndarray, strain: float) -> float:
    """ω_max²: the largest eigenvalue of M⁻¹K, with every spring at its stretch stiffness k and
    under tension at `strain`. A spring's block of K is k (d dᵀ + g (I - d dᵀ)), g = strain /
    (1 + strain): along it k, across it the geometric stiffness T / l of the tension
    T = k × strain × rest at length (1 + strain) × rest. Exact (a symmetric eigenvalue solve of
    M^-1/2 K M^-1/2) up to EXACT_EIGEN_PARTICLES; above, Gershgorin's upper bound."""
    n = len(inv_mass)
    d = x[si] - x[sj]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    g = strain / (1.0 + strain)
    block = k_stretch[:, None, None] * ((1.0 - g) * d[:, :, None] * d[:, None, :] + g * np.eye(3))
    w = np.sqrt(inv_mass)
    if n > EXACT_EIGEN_PARTICLES:
        rows = np.zeros((n, 3))
        row_abs = np.abs(block).sum(axis=2)
        np.add.at(rows, si, row_abs * (inv_mass[si] + w[si] * w[sj])[:, None])
        np.add.at(rows, sj, row_abs * (inv_mass[sj] + w[si] * w[sj])[:, None])
        return float(rows.max())
    ii = 3 * si[:, None] + np.arange(3)
    jj = 3 * sj[:, None] + np.arange(3)
    a = np.zeros((3 * n, 3 * n))
    np.add.at(a, (ii[:, :, None], ii[:, None, :]), block * inv_mass[si, None, None])
    np.add.at(a, (jj[:, :, None], jj[:, None, :]), block * inv_mass[sj, None, None])
    off = block * -(w[si] * w[sj])[:, None, None]
    np.add.at(a, (ii[:, :, None], jj[:, None, :]), off)
    np.add.at(a, (jj[:, :, None], ii[:, None, :]), off)
    return float(np.linalg.eigvalsh(a)[-1])


def stable_time_step(x: np.ndarray, inv_mass: np.ndarray, si: np.ndarray, sj: np.ndarray, k_stretch: np.ndarray,
                     max_strain: float = 0.0, damping_ratio: float = 0.0, margin: float = 0.99) -> float:
    """Largest RK4 step that keeps the linearised springs stable, with a margin.

    ω_max from `stiffness_eigenvalue`: every spring at its stretch stiffness (the stiff side of
    the asymmetric springs) and under tension at TENSION_STRAIN_ALLOWANCE × `max_strain`, so the
    bound holds for cloth stretched to its limit everywhere at once. The step keeps ω_max dt
    within `margin` of RK4's stability radius for the fabric's damping ratio, and never past
    its undamped one (2√2): the spring damping (2ζ sqrt(k m) per spring) puts the highest mode
    only near the ζ ray, and the tension's share across a spring is undamped. margin 0.99:
    ω_max dt <= 2.80 for the presets (ζ 0.1-0.2), where RK4 alone still damps an undamped mode
    by 7 % a step."""
    lam = stiffness_eigenvalue(x, inv_mass, si, sj, k_stretch, TENSION_STRAIN_ALLOWANCE * max_strain)
    limit = min(2.0 * math.sqrt(2.0), rk4_stability_radius(damping_ratio))
    return margin * limit / math.sqrt(lam)
