"""S101 kernels on cases whose answers are known."""

import dataclasses
import math
import re

import numpy as np
import pytest

from cloth.collision import (FACE_TREE_STACK, PART_SLOTS, BodyMesh, BodyPose, FaceTree, VertexGrid, attach_to_body,
                             collide_particles, face_normals, follow_body, part_seeds, part_slots, resolve_contacts,
                             tree_nearest_face)
from cloth import dynamics
from cloth.dynamics import limit_stretch, rk4_substep, spring_forces, spring_scratch, spring_table, stable_time_step
from cloth.fabric import FabricError, fabric, fabric_from_table, load_fabrics
from cloth.model import SimSettings
from cloth.sim import REGION_RADIUS, mark_moved, particle_regions

REFINE_RADIUS = 0.08  # the contact pass's nearest-face query where it is on (SimSettings.nearest_face_radius)

G = 9.81


def springs(pairs, rest, ks, kc, cs=0.0, cc=0.0):
    s = len(pairs)
    p = np.asarray(pairs, dtype=np.int32)
    return spring_table(p[:, 0], p[:, 1], np.full(s, rest, float), np.full(s, ks, float), np.full(s, kc, float),
                        np.full(s, cs, float), np.full(s, cc, float))


def run_rk4(x, v, inv_mass, spring_args, dt, steps, gravity=0.0, drag=None, normals=None):
    n = len(x)
    drag = np.zeros(n) if drag is None else drag
    normals = np.zeros((n, 3)) if normals is None else normals
    work = np.zeros((9, n, 3))
    spring_work = spring_scratch(len(spring_args[0]))
    for _ in range(steps):
        rk4_substep(x, v, np.zeros((n, 3)), dt, inv_mass, drag, normals, -gravity, *spring_args, spring_work, work)


def test_hanging_spring_settles_at_analytic_extension():
    m, k, rest = 0.01, 50.0, 0.1
    x = np.array([[0.0, 0.0, 0.0], [0.0, -rest, 0.0]])
    v = np.zeros_like(x)
    inv_mass = np.array([0.0, 1.0 / m])  # the top particle is held
    c = 2 * 0.5 * math.sqrt(k * m)  # half-critical damping: settles quickly
    args = springs([(0, 1)], rest, k, k * 0.01, c, c)
    run_rk4(x, v, inv_mass, args, 1e-3, 3000, gravity=G)
    extension = -x[1, 1] - rest
    assert extension == pytest.approx(m * G / k, rel=1e-6)
    assert x[0, 1] == 0.0


def test_stretch_and_compression_forces_have_the_configured_ratio():
    ks, kc, rest, d = 400.0, 10.0, 0.05, 0.004
    x_long = np.array([[0.0, 0.0, 0.0], [rest + d, 0.0, 0.0]])
    x_short = np.array([[0.0, 0.0, 0.0], [rest - d, 0.0, 0.0]])
    args = springs([(0, 1)], rest, ks, kc)
    forces = []
    for x in (x_long, x_short):
        f = np.zeros_like(x)
        spring_forces(x, np.zeros_like(x), *args, spring_scratch(1), f)
        forces.append(f)
    f_long, f_short = forces
    assert f_long[1, 0] == pytest.approx(-ks * d)  # pulled back towards particle 0
    assert f_short[1, 0] == pytest.approx(kc * d)  # pushed away, weakly
    assert abs(f_long[1, 0] / f_short[1, 0]) == pytest.approx(ks / kc)
    np.testing.assert_allclose(f_long[0], -f_long[1])  # action = reaction


def oscillator_error(dt: float) -> float:
    """Phase-space error of an undamped particle on a symmetric spring after 1 s vs the exact solution.

    sqrt(dx² + (dv/omega)²) is the size of the complex error, free of the cancellations a
    position-only error has at particular times."""
    m, k, rest, a = 0.02, 20.0, 0.1, 0.01
    x = np.array([[0.0, 0.0, 0.0], [rest + a, 0.0, 0.0]])
    v = np.zeros_like(x)
    inv_mass = np.array([0.0, 1.0 / m])
    args = springs([(0, 1)], rest, k, k)
    steps = int(round(1.0 / dt))
    run_rk4(x, v, inv_mass, args, dt, steps)
    w = math.sqrt(k / m)
    t = steps * dt
    dx = x[1, 0] - (rest + a * math.cos(w * t))
    dv = v[1, 0] - (-a * w * math.sin(w * t))
    return math.hypot(dx, dv / w)


def test_rk4_is_fourth_order_on_a_linear_oscillator():
    e1, e2 = oscillator_error(0.02), oscillator_error(0.01)  # omega*dt = 0.63, 0.32: far above round-off
    order = math.log2(e1 / e2)
    assert 3.7 < order < 4.3, order


def test_stable_time_step_matches_a_single_spring():
    # one free particle on a held spring: omega = sqrt(k/m); undamped, RK4's limit is 2√2/omega
    x = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    k, m = 30.0, 0.01
    dt = stable_time_step(x, np.array([0.0, 1.0 / m]), np.array([0], np.int32), np.array([1], np.int32),
                          np.array([k]))
    assert dt == pytest.approx(0.99 * 2.0 * math.sqrt(2.0) / math.sqrt(k / m), rel=1e-9)


def test_stable_time_step_counts_the_tension_across_springs():
    """A free particle on two held springs, along x (k1) and y (k2), both under tension at
    twice the strain limit: K = k1 (xxᵀ + g (I - xxᵀ)) + k2 (yyᵀ + g (I - yyᵀ)), g = 2ε / (1 + 2ε),
    so ω_max² = (k1 + g k2) / m for k1 > k2 (along x); a heavier damping ratio than 0.3
    shortens the step to its own stability radius."""
    x = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]])
    k1, k2, m, eps = 30.0, 10.0, 0.01, 0.05
    inv_mass = np.array([1.0 / m, 0.0, 0.0])
    args = (x, inv_mass, np.array([0, 0], np.int32), np.array([1, 2], np.int32), np.array([k1, k2]))
    g = dynamics.TENSION_STRAIN_ALLOWANCE * eps / (1.0 + dynamics.TENSION_STRAIN_ALLOWANCE * eps)
    omega = math.sqrt((k1 + g * k2) / m)
    assert dynamics.stiffness_eigenvalue(*args, dynamics.TENSION_STRAIN_ALLOWANCE * eps) == pytest.approx(
        omega ** 2, rel=1e-12)
    assert stable_time_step(*args, eps, 0.15) == pytest.approx(0.99 * 2.0 * math.sqrt(2.0) / omega, rel=1e-9)
    assert stable_time_step(*args, eps, 0.5) == pytest.approx(0.99 * dynamics.rk4_stability_radius(0.5) / omega)
    assert dynamics.rk4_stability_radius(0.5) < 2.7


def test_gershgorin_bounds_the_exact_eigenvalue(monkeypatch):
    """Past EXACT_EIGEN_PARTICLES the bound is Gershgorin's: exact for two equal free masses on
    a spring (ω² = 2k/m), never below the exact eigenvalue on a random sheet."""
    two = (np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]]), np.array([50.0, 50.0]), np.array([0], np.int32),
           np.array([1], np.int32), np.array([30.0]))
    rng = np.random.default_rng(3)
    grid = np.stack(np.meshgrid(np.arange(6.0), np.arange(6.0), indexing="ij"), -1).reshape(-1, 2) * 0.05
    pts = np.column_stack([grid, rng.normal(0.0, 0.01, len(grid))])
    pairs = np.array([(i, j) for i in range(36) for j in range(i + 1, 36)
                      if np.linalg.norm(grid[i] - grid[j]) < 0.08], np.int32)
    sheet = (pts, rng.uniform(20.0, 80.0, 36), pairs[:, 0].copy(), pairs[:, 1].copy(),
             rng.uniform(10.0, 60.0, len(pairs)))
    exact = [dynamics.stiffness_eigenvalue(*case, 0.1) for case in (two, sheet)]
    monkeypatch.setattr(dynamics, "EXACT_EIGEN_PARTICLES", 0)
    bound = [dynamics.stiffness_eigenvalue(*case, 0.1) for case in (two, sheet)]
    assert exact[0] == pytest.approx(2 * 30.0 * 50.0) and bound[0] == pytest.approx(exact[0])
    assert exact[1] < bound[1] < 2.5 * exact[1]


def test_rk4_stability_radius_is_where_the_amplification_reaches_one():
    # undamped: the imaginary axis, |R(iy)|² = 1 - y⁶/72 + y⁸/576 = 1 at y = 2√2
    assert dynamics.rk4_stability_radius(0.0) == pytest.approx(2.0 * math.sqrt(2.0), rel=1e-9)
    # critically damped: the real axis, R(-r) = 1 at the real root of r³ - 4r² + 12r - 24
    real = [r.real for r in np.roots([1.0, -4.0, 12.0, -24.0]) if abs(r.imag) < 1e-9]
    assert dynamics.rk4_stability_radius(1.0) == pytest.approx(real[0], rel=1e-9)
    for zeta in (0.1, 0.15, 0.2, 0.5):
        r = dynamics.rk4_stability_radius(zeta)
        z = r * complex(-zeta, math.sqrt(1 - zeta * zeta))
        assert abs(1 + z + z * z / 2 + z ** 3 / 6 + z ** 4 / 24) == pytest.approx(1.0, abs=1e-9)


def spring_amplitude_after(dt_omega: float, zeta: float, steps: int = 400) -> float:
    """A particle on a held spring (damping ratio zeta), started 1 cm long and stepped at
    omega dt = dt_omega: its phase-space amplitude after `steps` RK4 steps."""
    m, k, rest, a = 0.01, 30.0, 0.1, 0.01
    x = np.array([[0.0, 0.0, 0.0], [rest + a, 0.0, 0.0]])
    v = np.zeros_like(x)
    c = 2.0 * zeta * math.sqrt(k * m)
    w = math.sqrt(k / m)
    run_rk4(x, v, np.array([0.0, 1.0 / m]), springs([(0, 1)], rest, k, k, c, c), dt_omega / w, steps)
    return math.hypot(x[1, 0] - rest, v[1, 0] / w)


def test_rk4_is_stable_at_the_step_and_not_past_its_limit():
    """The step's claim on one spring. At the presets' damping (0.15) and at the step
    `stable_time_step` gives (omega dt = 0.99 x 2√2 = 2.80) the oscillation decays; past RK4's
    limit for that damping (2.96) it grows. Undamped, RK4's own dissipation still takes it down
    at 2.80, while at 2.9 (past 2√2) it grows. Heavily damped (0.5) it decays at 0.99 of that
    damping's radius (2.60) and grows at 2.7."""
    step = 0.99 * 2.0 * math.sqrt(2.0)
    assert spring_amplitude_after(step, 0.15) < 0.01 * 1e-3
    assert spring_amplitude_after(3.05, 0.15) > 0.01 * 10
    assert spring_amplitude_after(step, 0.0) < 0.01 * 1e-3
    assert spring_amplitude_after(2.9, 0.0) > 0.01 * 1.5
    assert spring_amplitude_after(0.99 * dynamics.rk4_stability_radius(0.5), 0.5) < 0.01 * 1e-3
    assert spring_amplitude_after(2.7, 0.5) > 0.01 * 3  # (that ray runs close along the region's edge: slow)


def uv_sphere(radius=0.5, n_lat=24, n_lon=48):
    verts = [[0.0, radius, 0.0]]
    for i in range(1, n_lat):
        th = math.pi * i / n_lat
        for j in range(n_lon):
            ph = 2 * math.pi * j / n_lon
            verts.append([radius * math.sin(th) * math.cos(ph), radius * math.cos(th),
                          radius * math.sin(th) * math.sin(ph)])
    verts.append([0.0, -radius, 0.0])
    tris = []
    for j in range(n_lon):
        tris.append([0, 1 + (j + 1) % n_lon, 1 + j])
    for i in range(n_lat - 2):
        for j in range(n_lon):
            a = 1 + i * n_lon + j
            b = 1 + i * n_lon + (j + 1) % n_lon
            c = a + n_lon
            d = b + n_lon
            tris += [[a, b, d], [a, d, c]]
    last = len(verts) - 1
    base = 1 + (n_lat - 2) * n_lon
    for j in range(n_lon):
        tris.append([last, base + j, base + (j + 1) % n_lon])
    return np.array(verts), np.array(tris, dtype=np.int32)


def box(half=0.3, n=8):
    """A closed box made of n×n quads per side (outward triangles)."""
    verts, tris, index = [], [], {}

    def vid(p):
        key = tuple(np.round(p, 9))
        if key not in index:
            index[key] = len(verts)
            verts.append(p)
        return index[key]

    g = np.linspace(-half, half, n + 1)
    for axis in range(3):
        for sign in (-1.0, 1.0):
            u_ax, v_ax = [a for a in range(3) if a != axis]
            for i in range(n):
                for j in range(n):
                    quad = []
                    for di, dj in ((0, 0), (1, 0), (1, 1), (0, 1)):
                        p = np.zeros(3)
                        p[axis] = sign * half
                        p[u_ax] = g[i + di]
                        p[v_ax] = g[j + dj]
                        quad.append(vid(p))
                    a, b, c, d = quad
                    t1, t2 = [a, b, c], [a, c, d]
                    # orient outward
                    pa, pb, pc = (np.array(verts[q]) for q in t1)
                    if np.dot(np.cross(pb - pa, pc - pa), pa) < 0:
                        t1, t2 = t1[::-1], t2[::-1]
                    tris += [t1, t2]
    return np.array(verts), np.array(tris, dtype=np.int32)


def no_parts(n):
    """part_nearest for particles near one body part only (collide_particles walks from nearest)."""
    return np.full((n, PART_SLOTS), -1, np.int32)


def collide_once(points, verts, tris, thickness):
    mesh = BodyMesh.build(tris, len(verts))
    x = np.array(points, dtype=float)
    v = np.zeros_like(x)
    nearest = np.zeros(len(x), dtype=np.int32)  # start the walk anywhere: it must find its way
    contact = np.zeros(len(x), dtype=np.uint8)
    masks = np.full(len(x), 255, dtype=np.uint8)
    free = np.zeros(len(x), dtype=np.uint8)
    collide_particles(x, v, verts, np.zeros_like(x), mesh.nbr_start, mesh.nbr_ids, mesh.triangles, mesh.tri_start,
                      mesh.tri_ids, mesh.regions, masks, nearest, no_parts(len(x)), thickness, 0.5, contact, free,
                      face_normals(verts, tris), np.zeros_like(x), np.full(len(x), -np.inf))
    return x, contact


def test_collision_skips_a_particle_far_in_front_of_the_faces_of_its_last_test():
    """Box of half-width 0.3 m, thickness 3 mm. A particle 3 cm above the top face is tested
    (clear = 0.03 m). Moved 5 mm down it is still more than 2 thicknesses + 5 mm in front:
    not tested (its nearest vertex, set elsewhere on purpose, stays). Moved inside the box, it
    is tested again, its walk finds the top, and it is pushed out to thickness above it."""
    verts, tris = box(0.3)
    mesh = BodyMesh.build(tris, len(verts))
    x = np.array([[0.01, 0.33, 0.02]])
    v = np.zeros_like(x)
    nearest = np.zeros(1, np.int32)
    contact = np.zeros(1, np.uint8)
    tested_at, clear = np.zeros_like(x), np.full(1, -np.inf)
    args = (verts, np.zeros_like(x), mesh.nbr_start, mesh.nbr_ids, mesh.triangles, mesh.tri_start, mesh.tri_ids,
            mesh.regions, np.full(1, 255, np.uint8), nearest, no_parts(1), 0.003, 0.0, contact, np.zeros(1, np.uint8),
            face_normals(verts, tris), tested_at, clear)

    def collide():
        collide_particles(x, v, *args)

    collide()
    assert clear[0] == pytest.approx(0.03)
    np.testing.assert_array_equal(tested_at[0], x[0])
    far = int(np.argmin(verts[:, 1]))  # a bottom vertex
    nearest[0] = far
    x[0, 1] = 0.325
    collide()
    assert nearest[0] == far and contact[0] == 0  # skipped
    np.testing.assert_array_equal(x[0], [0.01, 0.325, 0.02])
    x[0, 1] = 0.29
    collide()
    assert nearest[0] != far and verts[nearest[0], 1] == pytest.approx(0.3)
    assert contact[0] == 1
    np.testing.assert_allclose(x[0], [0.01, 0.303, 0.02], atol=1e-12)


def test_air_drag_acts_across_the_cloth_only():
    """A particle whose cloth faces up (n = +Y) falls from rest while moving sideways at 1 m/s:
    the drag -d (v·n) n gives the falling plate v_y(t) = -(g m / d)(1 - exp(-d t / m)) and leaves
    the motion along the sheet alone."""
    m, d, T = 0.002, 0.01, 0.5
    x = np.zeros((1, 3))
    v = np.array([[1.0, 0.0, 0.0]])
    empty = np.zeros(0, np.int32)
    args = spring_table(empty, empty, *[np.zeros(0)] * 5)
    run_rk4(x, v, np.array([1.0 / m]), args, 1e-3, int(round(T / 1e-3)), gravity=G, drag=np.array([d]),
            normals=np.array([[0.0, 1.0, 0.0]]))
    tau = m / d
    assert v[0, 1] == pytest.approx(-G * tau * (1 - math.exp(-T / tau)), rel=1e-9)
    assert x[0, 1] == pytest.approx(-G * tau * (T - tau * (1 - math.exp(-T / tau))), rel=1e-9)
    assert v[0, 0] == 1.0 and x[0, 0] == pytest.approx(T, rel=1e-12)


def test_spring_damping_and_the_strain_limit_see_world_velocities():
    """Two particles moving together at 1 m/s in the world, one carried by the body following
    (v 0, carried 1 m/s), the other not (v 1 m/s, carried 0): the damping of a spring at its rest
    length between them is zero, and the strain limit takes no velocity from its stretched ends.
    Counted by v alone they would be parting at 1 m/s: damping c x 1 m/s, and the strain limit's
    velocity change."""
    x = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    v = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    carried = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    args = springs([(0, 1)], 0.1, 100.0, 10.0, cs=0.5, cc=0.5)
    for c, want in ((carried, 0.0), (np.zeros((2, 3)), 0.5)):
        a, world = np.zeros((2, 3)), np.zeros((2, 3))
        dynamics.accelerations(x, v, c, world, np.ones(2), np.zeros(2), np.zeros((2, 3)), 0.0, *args,
                               spring_scratch(1), a)
        np.testing.assert_allclose(a, [[want, 0.0, 0.0], [-want, 0.0, 0.0]], atol=1e-12)
        np.testing.assert_allclose(world, v + c, atol=0)
    si, sj, rest = np.array([0], np.int32), np.array([1], np.int32), np.array([0.09])
    for c, want in ((carried, [0.0, 1.0]), (np.zeros((2, 3)), [0.5, 0.5])):
        xs, vs = x.copy(), v.copy()
        limit_stretch(xs, vs, c, np.ones(2), si, sj, rest, 1, 0.0)
        np.testing.assert_allclose(xs[:, 0], [0.005, 0.095], atol=1e-12)
        np.testing.assert_allclose(vs[:, 0], want, atol=1e-12)


@pytest.mark.parametrize("friction, body_vel, expected", [
    (0.5, (0.0, 0.0, 0.0), (1.5, 0.0, 0.0)),  # the slide slowed by 0.5 x the 1 m/s stopped
    (3.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),  # static: the slide stops
    (0.5, (0.0, 0.0, 1.0), (2 * (1 - 0.5 / math.sqrt(5)), 0.0, 1 - (1 - 0.5 / math.sqrt(5)))),  # relative to the body
])
def test_contact_stops_the_inward_velocity_and_friction_slows_the_slide(friction, body_vel, expected):
    """S101 collision on a box's top face (y = 0.3): a particle 1 cm inside, moving at (2, -1, 0)
    m/s, is put on the surface plus thickness; its velocity relative to the body loses the
    inward 1 m/s, and Coulomb friction takes friction x 1 m/s off the tangential part (all of
    it when that is more)."""
    verts, tris = box(0.3)
    mesh = BodyMesh.build(tris, len(verts))
    x = np.array([[0.075, 0.29, 0.0]])
    v = np.array([[2.0, -1.0, 0.0]])
    contact = np.zeros(1, np.uint8)
    collide_particles(x, v, verts, np.array([body_vel]), mesh.nbr_start, mesh.nbr_ids, mesh.triangles, mesh.tri_start,
                      mesh.tri_ids, mesh.regions, np.full(1, 255, np.uint8), np.zeros(1, np.int32), no_parts(1), 0.003,
                      friction, contact, np.zeros(1, np.uint8), face_normals(verts, tris), np.zeros_like(x),
                      np.full(1, -np.inf))
    assert contact[0] == 1
    np.testing.assert_allclose(x[0], [0.075, 0.303, 0.0], atol=1e-12)
    np.testing.assert_allclose(v[0], expected, atol=1e-12)


def test_particle_inside_a_sphere_is_pushed_out_to_its_surface():
    verts, tris = uv_sphere(0.5)
    rng = np.random.default_rng(1)
    dirs = rng.standard_normal((50, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    inside = dirs * 0.47  # 3 cm deep
    x, contact = collide_once(inside, verts, tris, thickness=0.002)
    assert contact.all()
    r = np.linalg.norm(x, axis=1)
    # faceted sphere: the faces lie between cos(half angle)·R and R from the centre
    assert np.all(r > 0.5 * math.cos(math.pi / 24) + 0.0019) and np.all(r < 0.503)
    outside = dirs * 0.6
    x2, contact2 = collide_once(outside, verts, tris, thickness=0.002)
    assert not contact2.any()
    np.testing.assert_array_equal(x2, outside)


def test_particle_inside_a_box_is_pushed_out_to_the_nearest_face():
    verts, tris = box(0.3)
    p = np.array([[0.1, 0.28, -0.05], [-0.29, 0.0, 0.12]])
    x, contact = collide_once(p, verts, tris, thickness=0.003)
    assert contact.all()
    np.testing.assert_allclose(x[0], [0.1, 0.303, -0.05], atol=1e-9)
    np.testing.assert_allclose(x[1], [-0.303, 0.0, 0.12], atol=1e-9)


def contact_grids(verts, mesh):
    """resolve_contacts' grids for the body in this pose (vertices, then faces) and the
    refinement radius of the faces' nearest-face query."""
    pose = BodyPose(mesh)
    pose.update(verts)
    return (*pose.grid.arrays(), *pose.faces.arrays(), REFINE_RADIUS, np.zeros(FACE_TREE_STACK, np.int32))


def contact_scratch(n, inv_mass=None):
    """resolve_contacts' scratch for the body parts near a particle, the particles' inverse
    masses (1 unless given), the placed-particle inverse masses it writes (index PLACED), the
    active mask (every particle, index ACTIVE) and the unsettled flags it writes."""
    inv_mass = np.ones(n) if inv_mass is None else inv_mass
    return (np.zeros(8, np.uint8), np.zeros(8, np.int32), np.zeros(8), inv_mass, np.full(n, np.nan),
            np.ones(n, np.uint8), np.full(n, 7, np.uint8))


PLACED, ACTIVE, UNSETTLED = 4, 5, 6


def resolve_against_two_parts(x, v, coarse_v, coarse_t, same_part=False, refine=REFINE_RADIUS):
    """resolve_contacts against two body parts: a finely meshed box (vertices every 2.5 mm,
    top face at z = 0, bottom at z = -0.02) and a coarse one (coarse_v, coarse_t); same_part:
    both boxes are one body part (two sheets of a fold); refine: the nearest-face query's
    radius (0: off). Returns resolve_contacts' scratch (placed inverse masses at PLACED, unsettled
    flags at UNSETTLED); the nearest vertex found must be the fine box's."""
    fine_v, fine_t = box(0.01, n=8)
    fine_v = fine_v + [0.0, 0.0, -0.01]
    verts = np.concatenate([fine_v, coarse_v])
    tris = np.concatenate([fine_t, coarse_t + len(fine_v)]).astype(np.int32)
    regions = np.r_[np.full(len(fine_v), 1), np.full(len(coarse_v), 1 if same_part else 2)].astype(np.uint8)
    mesh = BodyMesh.build(tris, len(verts), regions)
    nearest = np.zeros(1, np.int32)
    scratch = contact_scratch(len(x))
    resolve_contacts(x, v, verts, np.zeros_like(x), mesh.nbr_start, mesh.nbr_ids, mesh.triangles, mesh.tri_start,
                     mesh.tri_ids, mesh.tri_nbrs, mesh.regions, nearest, 0.003, np.zeros(1, np.uint8),
                     face_normals(verts, tris), np.zeros(3), *contact_grids(verts, mesh)[:-2], refine,
                     np.zeros(FACE_TREE_STACK, np.int32), *scratch)
    assert nearest[0] < len(fine_v)  # the nearest vertex is the fine box's
    return scratch


def test_body_face_normals_are_unit_normals_and_twice_the_areas():
    """Three faces: a 3 × 4 right triangle in the xy plane (normal +z, twice the area 12), the
    same one wound the other way (normal -z), and a degenerate one (no normal, no area)."""
    verts = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 4.0, 0.0], [6.0, 0.0, 0.0]])
    tris = np.array([[0, 1, 2], [0, 2, 1], [0, 1, 3]], np.int32)
    np.testing.assert_allclose(face_normals(verts, tris), [[0, 0, 1, 12], [0, 0, -1, 12], [0, 0, 0, 0]], atol=1e-15)


def test_behind_every_plane_is_the_deepest_planes_inside_test(body):
    """S103's test for a part ruled out by its nearest vertex (`behind_every_plane`, which stops
    at the first face p is in front of) answers as `deepest_plane`'s "behind every face around
    the vertex" does: on the body at rest, at points a few millimetres either side of the skin
    around its vertices, inside deeper, and exactly on a face's plane; and a vertex with no
    usable face around it (every area 0) is never one p is behind."""
    from cloth.collision import behind_every_plane, deepest_plane
    from services.cloth_job import collision_body

    mesh = collision_body(body)
    x = np.ascontiguousarray(mesh.internal(body.vertices), dtype=np.float64)
    fn = face_normals(x, mesh.triangles)
    rng = np.random.default_rng(7)
    vertices = rng.choice(mesh.n_vertices, 3000)
    normals = np.zeros((mesh.n_vertices, 3))
    np.add.at(normals, mesh.triangles.ravel(), np.repeat(fn[:, :3], 3, axis=0))
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    offsets = rng.choice([-0.02, -0.004, -0.001, 0.001, 0.004], size=len(vertices))
    points = x[vertices] + offsets[:, None] * normals[vertices] + rng.normal(scale=0.001, size=(len(vertices), 3))
    got, want = [], []
    for v, p in zip(vertices, points):
        got.append(behind_every_plane(p[0], p[1], p[2], x, mesh.triangles, mesh.tri_start, mesh.tri_ids, v, fn))
        d, t = deepest_plane(p[0], p[1], p[2], x, mesh.triangles, mesh.tri_start, mesh.tri_ids, v, fn)
        want.append(t >= 0 and d < 0.0)
    assert got == want and 300 < sum(got) < 2700
    # at a box's corner, on one side's plane (distance 0) and behind the other two: not behind
    # every face, as deepest_plane reads it; a little further in, behind them all
    bv, bt = box(0.1, 2)
    bmesh = BodyMesh.build(bt, len(bv))
    bx = np.ascontiguousarray(bmesh.internal(bv), dtype=np.float64)
    bfn = face_normals(bx, bmesh.triangles)
    corner = int(np.argmax(bx.sum(axis=1)))  # (0.1, 0.1, 0.1)
    for p, behind in (((0.1, 0.09, 0.09), False), ((0.0999, 0.09, 0.09), True), ((0.11, 0.09, 0.09), False)):
        assert behind_every_plane(*p, bx, bmesh.triangles, bmesh.tri_start, bmesh.tri_ids, corner, bfn) == behind
        d, t = deepest_plane(*p, bx, bmesh.triangles, bmesh.tri_start, bmesh.tri_ids, corner, bfn)
        assert (t >= 0 and d < 0.0) == behind
    v = int(vertices[0])
    flat = fn.copy()
    flat[mesh.tri_ids[mesh.tri_start[v]:mesh.tri_start[v + 1]], 3] = 0.0  # no usable face around v
    inside = x[v] - 0.01 * normals[v]
    assert not behind_every_plane(inside[0], inside[1], inside[2], x, mesh.triangles, mesh.tri_start, mesh.tri_ids,
                                  v, flat)


def test_body_regions_are_sixteen_bit_masks():
    """Region bits past the first eight (a MakeHuman forearm's is 256) are kept as they are, and
    a vertex without a region, or with a bit past the sixteenth, is refused with what is wrong."""
    verts, tris = box(0.1, 2)
    regions = np.where(verts[:, 0] < 0, 1, 256)
    mesh = BodyMesh.build(tris, len(verts), regions)
    assert mesh.regions.dtype == np.uint16
    np.testing.assert_array_equal(mesh.regions, regions)
    for bad in (0, 1 << 16):
        with pytest.raises(ValueError, match="at most 16 bits, with a bit set for every vertex"):
            BodyMesh.build(tris, len(verts), np.where(verts[:, 0] < 0, 1, bad))


def test_a_limb_is_one_region_for_the_coarse_cloth_and_two_parts_for_the_detailed_surface():
    """Three boxes in a row along x, 0.3 m apart: a torso (region 1), an upper arm (2) and a
    forearm (256), the arm's two regions one limb. The coarse cloth sees the arm as one region,
    its lowest bit (a particle over the forearm has region mask 2), the detailed surface as two
    parts; so does the vertex grid, built for both. Without the limb both see three. Limbs that
    are not region masks are refused."""
    parts = [box(0.05, 2)[0] + [0.3 * k, 0.0, 0.0] for k in range(3)]
    tris = np.vstack([box(0.05, 2)[1] + k * len(parts[0]) for k in range(3)]).astype(np.int32)
    verts = np.vstack(parts)
    regions = np.repeat([1, 2, 256], len(parts[0]))
    points = np.array([[0.6, 0.06, 0.0], [0.3, 0.06, 0.0], [0.0, 0.06, 0.0]])
    assert REGION_RADIUS < 0.3 - 0.05 - 0.06  # each point is near its own box alone
    limb = BodyMesh.build(tris, len(verts), regions, limbs=(2 | 256,))
    np.testing.assert_array_equal(limb.parts, regions)
    np.testing.assert_array_equal(limb.regions, np.repeat([1, 2, 2], len(parts[0])))
    np.testing.assert_array_equal(particle_regions(points, verts, limb), [2, 2, 1])
    grid = VertexGrid(len(verts))
    grid.update(verts, limb.regions, limb.parts)
    np.testing.assert_array_equal(grid.regions, limb.regions[grid.ids])
    np.testing.assert_array_equal(grid.detail_regions, regions[grid.ids])
    assert np.bitwise_or.reduce(grid.parts) == 3 and np.bitwise_or.reduce(grid.detail_parts) == 259
    apart = BodyMesh.build(tris, len(verts), regions)
    assert apart.parts is apart.regions
    np.testing.assert_array_equal(particle_regions(points, verts, apart), [256, 2, 1])
    with pytest.raises(ValueError, match="limbs must be region masks"):
        BodyMesh.build(tris, len(verts), regions, limbs=(0,))


def test_part_seeds_have_a_column_per_region_bit_up_to_the_highest_used():
    """A torso (1), an upper arm (2) and a forearm (256) as three boxes. With the arm one limb
    the coarse cloth's regions use bits 0 and 1, so part_nearest needs two columns, not 16;
    without it, nine (bit 8). A particle between torso and upper arm gets a seed in both
    columns, each a vertex of its part; a table too narrow for the body is refused."""
    parts = [box(0.05, 2)[0] + [0.3 * k, 0.0, 0.0] for k in range(3)]
    tris = np.vstack([box(0.05, 2)[1] + k * len(parts[0]) for k in range(3)]).astype(np.int32)
    verts = np.vstack(parts)
    regions = np.repeat([1, 2, 256], len(parts[0]))
    limb = BodyMesh.build(tris, len(verts), regions, limbs=(2 | 256,))
    apart = BodyMesh.build(tris, len(verts), regions)
    assert part_slots(limb.regions) == 2 and part_slots(apart.regions) == 9
    point = np.array([[0.15, 0.0, 0.0]])
    seeds = part_seeds(point, verts, limb.regions, np.array([3]))
    assert seeds.shape == (1, 2)
    assert limb.regions[seeds[0, 0]] == 1 and limb.regions[seeds[0, 1]] == 2
    assert part_seeds(point, verts, apart.regions, np.array([1 | 256])).shape == (1, 9)
    with pytest.raises(ValueError, match="out has 2 columns, the body's regions need 9"):
        part_seeds(point, verts, apart.regions, np.array([3]), out=np.zeros((1, 2), np.int32))


def test_vertex_grid_buckets_copy_positions_and_or_the_parts_of_each_cell():
    """Four vertices: two of part 1 in one 3 cm cell, one of part 2 in the same cell and one of
    part 4 in a cell of its own. Each bucket lists its vertices with their positions and
    region bits in the same order, and a cell's part mask is the OR of its vertices' bits."""
    verts = np.array([[0.001, 0.001, 0.001], [0.02, 0.01, 0.005], [0.015, 0.025, 0.02], [0.1, 0.0, 0.0]])
    regions = np.array([1, 1, 2, 4], np.uint8)
    grid = VertexGrid(len(verts))
    grid.update(verts, regions)
    np.testing.assert_array_equal(grid.x, verts[grid.ids])
    np.testing.assert_array_equal(grid.regions, regions[grid.ids])
    buckets = {int(c): sorted(grid.ids[grid.start[c]:grid.start[c + 1]]) for c in np.flatnonzero(np.diff(grid.start))}
    assert sorted(buckets.values()) == [[0, 1, 2], [3]]
    parts = {tuple(ids): int(grid.parts[c]) for c, ids in buckets.items()}
    assert parts == {(0, 1, 2): 3, (3,): 4}
    assert np.count_nonzero(grid.parts) == 2


def test_resolve_contacts_finds_a_face_of_another_part_nearer_than_its_vertices():
    """Above the fine box a coarse one (corners only, 2 cm wide, bottom face at z = 0.006). A
    particle 1 mm inside that bottom face is 7 mm from the fine box's nearest vertex and 13 mm
    from the coarse box's: the nearest vertex's ring says "outside", the other part's ring
    finds the face, and the particle ends thickness below it (z = 0.003)."""
    coarse_v, coarse_t = box(1.0, n=1)
    coarse_v = coarse_v * [0.01, 0.01, 0.01] + [0.0, 0.0, 0.016]
    x = np.array([[0.0005, 0.001, 0.007]])
    v = np.array([[0.0, 0.0, 1.0]])
    placed = resolve_against_two_parts(x, v, coarse_v, coarse_t)[PLACED]
    np.testing.assert_allclose(x[0], [0.0005, 0.001, 0.003], atol=1e-9)
    np.testing.assert_allclose(v[0], [0.0, 0.0, 0.0], atol=1e-12)  # into the coarse box: removed
    assert placed[0] == 0.0


@pytest.mark.parametrize("same_part", [False, True])
def test_resolve_contacts_puts_a_particle_midway_into_a_slit_narrower_than_twice_the_thickness(same_part):
    """Above the fine box a coarse one whose bottom face is 2 mm above the fine box's top (skin
    pressed against skin, as parts or as the sheets of one fold), thickness 3 mm. A particle
    1 mm inside the fine box: out of it at thickness lands it 1 mm inside the coarse box, out of
    that back 1 mm inside the fine one, for ever. The pass puts it midway into the slit
    (z = 0.001, outside both) and leaves it there, its velocity towards either side removed."""
    coarse_v, coarse_t = box(1.0, n=1)
    coarse_v = coarse_v * [0.01, 0.01, 0.01] + [0.0, 0.0, 0.012]
    x = np.array([[0.0005, 0.001, -0.001]])
    v = np.array([[0.3, 0.0, 1.0]])
    placed = resolve_against_two_parts(x, v, coarse_v, coarse_t, same_part=same_part)[PLACED]
    np.testing.assert_allclose(x[0], [0.0005, 0.001, 0.001], atol=1e-12)
    np.testing.assert_allclose(v[0], [0.3, 0.0, 0.0], atol=1e-12)
    assert placed[0] == 0.0


@pytest.mark.parametrize("tilt", [15.0, 45.0])
def test_resolve_contacts_treats_surfaces_at_an_angle_as_a_slit(tilt):
    """The coarse box of the slit test tilted about y (its bottom's normal (sin φ, 0, -cos φ):
    cos φ from opposite the fine box's top, 0.966 and 0.707, a wedge, within SLIT_COS), the
    bottom through (0, 0, 2 mm). The two surfaces are 2 mm + x tan φ apart above the particle;
    the particle 1 mm inside the fine box goes midway between them along the fine box's
    normal, z = 1 mm + x tan φ / 2, and stays (the crease solve for both planes at thickness
    would take it out along the wedge, a long way where they are near opposite)."""
    phi = np.radians(tilt)
    rot = np.array([[np.cos(phi), 0.0, -np.sin(phi)], [0.0, 1.0, 0.0], [np.sin(phi), 0.0, np.cos(phi)]])
    coarse_v, coarse_t = box(1.0, n=1)
    coarse_v = (coarse_v * 0.01) @ rot.T
    bottom = np.array([0.0, 0.0, -0.01]) @ rot.T
    np.testing.assert_allclose(bottom / 0.01, [np.sin(phi), 0.0, -np.cos(phi)], atol=1e-15)
    coarse_v = coarse_v + ([0.0, 0.0, 0.002] - bottom)
    x0 = 0.0005
    x = np.array([[x0, 0.001, -0.001]])
    placed = resolve_against_two_parts(x, np.zeros_like(x), coarse_v, coarse_t)[PLACED]
    np.testing.assert_allclose(x[0], [x0, 0.001, 0.001 + x0 * np.tan(phi) / 2], atol=1e-12)
    assert placed[0] == 0.0


def test_resolve_contacts_leaves_overlapping_facing_surfaces_to_the_last_push():
    """The same two boxes overlapping by 1 mm (the coarse box's bottom at z = -0.001, as linear
    blend skinning presses one part into another): there is no slit to go into, and the
    particle between the two surfaces (z = -0.0005) ends where the pass's last push put it,
    flagged unsettled, 3 mm in front of one of the two faces."""
    coarse_v, coarse_t = box(1.0, n=1)
    coarse_v = coarse_v * [0.01, 0.01, 0.01] + [0.0, 0.0, 0.009]
    x = np.array([[0.0005, 0.001, -0.0005]])
    scratch = resolve_against_two_parts(x, np.zeros_like(x), coarse_v, coarse_t)
    assert scratch[UNSETTLED][0] == 1
    assert min(abs(x[0, 2] - 0.003), abs(x[0, 2] - (-0.001 - 0.003))) < 1e-12, x


@pytest.mark.parametrize("refine", [0.0, REFINE_RADIUS])
def test_resolve_contacts_finds_a_nearer_face_of_the_same_part_by_the_face_tree(refine):
    """The boxes of the test above as one body part, two sheets of a fold: no other part to
    look at, and the rings of the fine box's vertices say "outside". Without the nearest-face
    query (refine = 0) the particle 1 mm inside the coarse box stays where it is; with it, the
    face tree finds the coarse box's bottom face 1 mm away (nearer than the 7 mm to the fine
    box), and the particle ends thickness below it (z = 0.003)."""
    coarse_v, coarse_t = box(1.0, n=1)
    coarse_v = coarse_v * [0.01, 0.01, 0.01] + [0.0, 0.0, 0.016]
    x = np.array([[0.0005, 0.001, 0.007]])
    v = np.array([[0.0, 0.0, 1.0]])
    placed = resolve_against_two_parts(x, v, coarse_v, coarse_t, same_part=True, refine=refine)[PLACED]
    if refine == 0.0:
        np.testing.assert_array_equal(x[0], [0.0005, 0.001, 0.007])
        assert placed[0] == 1.0
    else:
        np.testing.assert_allclose(x[0], [0.0005, 0.001, 0.003], atol=1e-9)
        np.testing.assert_allclose(v[0], [0.0, 0.0, 0.0], atol=1e-12)
        assert placed[0] == 0.0


def test_face_trees_built_from_the_same_pose_share_their_shape_and_refit_their_own_boxes():
    """Every garment's simulation builds its face tree from the rest body: the shape (nodes,
    faces per leaf) is built once and shared, each tree refits boxes of its own; a tree first
    seen in another pose gets the shape that pose gives."""
    verts, tris = uv_sphere(0.1, 12, 24)
    regions = np.where(verts[:, 1] > 0.0, 1, 2).astype(np.uint8)
    a, b, c = (FaceTree(tris, np.arange(len(tris)), regions) for _ in range(3))
    a.update(verts)
    b.update(verts)
    stretched = verts * [1.0, 3.0, 0.5]  # the longest axis is another: other median splits
    c.update(stretched)
    assert all(x is y for x, y in zip(a.arrays()[1:], b.arrays()[1:]))
    assert a.box is not b.box
    b.update(verts + 0.05)
    np.testing.assert_array_equal(a.box[0], np.r_[verts.min(axis=0), verts.max(axis=0)])
    np.testing.assert_array_equal(b.box[0], np.r_[verts.min(axis=0), verts.max(axis=0)] + 0.05)
    assert not np.array_equal(c.arrays()[4], a.arrays()[4])  # (the faces' order in the leaves)
    fresh = FaceTree(tris, np.arange(len(tris)), regions)
    fresh._build_shape(verts)  # built again, not shared: the same shape
    for name in ("child", "first", "count", "order", "parent", "leaf"):
        np.testing.assert_array_equal(getattr(fresh, name), getattr(a, name))


def test_face_tree_boxes_hold_their_faces_and_its_query_finds_the_brute_force_nearest_face():
    """A sphere of two body parts (upper and lower half), the tree built on it and refitted
    after the upper half moved: every face lies in the box of every node above it, the two
    parts never share a box below the root, and for random points the query returns the
    nearest face that a brute-force search finds (front = inf: no face filtered)."""
    from cloth.geometry import closest_point_triangle
    verts, tris = uv_sphere(0.1, 12, 24)
    regions = np.where(verts[:, 1] > 0.0, 1, 2).astype(np.uint8)
    tree = FaceTree(tris, np.arange(len(tris)), regions)
    tree.update(verts)
    moved = verts + np.where(verts[:, 1:2] > 0.0, [0.03, 0.01, 0.0], 0.0)
    tree.update(moved)
    box, child, first, count, order, parent, leaf = tree.arrays()
    assert parent[0] == -1 and all(node in child[parent[node]] for node in range(1, len(child)))
    assert all(t in order[first[leaf[t]]:first[leaf[t]] + count[leaf[t]]] for t in range(len(tris)))
    face_region = regions[tris[:, 0]]
    below = [[] for _ in range(len(child))]  # faces under each node
    for node in range(len(child) - 1, -1, -1):
        below[node] = list(order[first[node]:first[node] + count[node]]) if child[node, 0] < 0 else \
            below[child[node, 0]] + below[child[node, 1]]
        corners = moved[tris[below[node]]].reshape(-1, 3)
        np.testing.assert_array_equal(box[node, :3], corners.min(axis=0))
        np.testing.assert_array_equal(box[node, 3:], corners.max(axis=0))
        if node > 0:
            assert len(set(face_region[below[node]])) == 1
    assert sorted(below[0]) == list(range(len(tris)))
    face_n = face_normals(moved, tris)
    rng = np.random.default_rng(3)
    q, stack = np.zeros(3), np.zeros(FACE_TREE_STACK, np.int32)

    def squared_distance(p, a, b, c):
        closest_point_triangle(p[0], p[1], p[2], moved, a, b, c, q)
        return float(((p - q) ** 2).sum())

    for p in rng.uniform(-0.15, 0.15, (200, 3)):
        d2 = [squared_distance(p, a, b, c) for a, b, c in tris]
        # from the root (no start face), from a random face's leaf, from the nearest face's leaf
        for start in (-1, int(rng.integers(len(tris))), int(np.argmin(d2))):
            t, b2, _, _ = tree_nearest_face(p[0], p[1], p[2], moved, tris, face_n, box, child, first, count, order,
                                            parent, leaf, start, -1, stack, np.inf, np.inf, q)
            assert b2 == pytest.approx(min(d2), abs=1e-15) and d2[t] == pytest.approx(min(d2), abs=1e-15)
            # nothing nearer than a bound that the nearest face does not beat
            assert tree_nearest_face(p[0], p[1], p[2], moved, tris, face_n, box, child, first, count, order, parent,
                                     leaf, start, -1, stack, min(d2) * 0.999, np.inf, q)[0] == -1
            # the faces of a skipped vertex (the ring's) are not tested: the nearest of the others
            skip = int(tris[t, 0])
            others = [d for k, d in enumerate(d2) if skip not in tris[k]]
            t2, b2, _, _ = tree_nearest_face(p[0], p[1], p[2], moved, tris, face_n, box, child, first, count, order,
                                             parent, leaf, start, skip, stack, np.inf, np.inf, q)
            assert skip not in tris[t2] and b2 == pytest.approx(min(others), abs=1e-15)


def test_resolve_contacts_takes_no_push_from_deep_behind_another_part():
    """The two parts intersect: the coarse box (4 cm wide, 6 cm tall, a vertex in the middle of
    each face) reaches 5 mm into the fine one. A particle 6 mm above the fine box is 11 mm
    behind the coarse box's bottom face: a push out of the coarse box (to z = -0.008) would
    land it inside the fine one, so past MAX_OTHER_PART_DEPTH (1 cm) it is left for the
    following frames."""
    coarse_v, coarse_t = box(1.0, n=2)
    coarse_v = coarse_v * [0.02, 0.02, 0.03] + [0.0, 0.0, 0.025]
    x = np.array([[0.0, 0.0, 0.006]])
    v = np.array([[0.0, 0.0, 1.0]])
    placed = resolve_against_two_parts(x, v, coarse_v, coarse_t)[PLACED]
    np.testing.assert_array_equal(x[0], [0.0, 0.0, 0.006])
    np.testing.assert_array_equal(v[0], [0.0, 0.0, 1.0])
    assert placed[0] == 1.0


def test_resolve_contacts_pushes_out_of_any_body_part():
    """The end-of-step pass finds the nearest body part over the whole body: a particle inside a
    second, unconnected box (another limb, which no walk over the mesh reaches from the first)
    is put on that box's nearest face plus thickness, and loses its inward velocity."""
    verts1, tris1 = box(0.3)
    verts = np.concatenate([verts1, verts1 + [2.0, 0.0, 0.0]])
    tris = np.concatenate([tris1, tris1 + len(verts1)]).astype(np.int32)
    mesh = BodyMesh.build(tris, len(verts))
    x = np.array([[2.1, 0.28, -0.05], [2.0, 0.45, 0.0]])
    v = np.array([[0.0, -1.0, 0.5], [0.0, -1.0, 0.0]])
    start = np.zeros(2, np.int32)  # both walks would start on the first box
    scratch = contact_scratch(2, np.array([2.0, 3.0]))
    resolve_contacts(x, v, verts, np.zeros_like(x), mesh.nbr_start, mesh.nbr_ids, mesh.triangles, mesh.tri_start,
                     mesh.tri_ids, mesh.tri_nbrs, mesh.regions, start, 0.003, np.zeros(2, np.uint8),
                     face_normals(verts, tris), np.zeros(3), *contact_grids(verts, mesh), *scratch)
    assert start[0] >= len(verts1)
    np.testing.assert_allclose(x[0], [2.1, 0.303, -0.05], atol=1e-9)
    np.testing.assert_allclose(v[0], [0.0, 0.0, 0.5], atol=1e-12)  # tangential velocity kept
    np.testing.assert_array_equal(x[1], [2.0, 0.45, 0.0])  # outside: untouched
    np.testing.assert_array_equal(v[1], [0.0, -1.0, 0.0])
    np.testing.assert_array_equal(scratch[PLACED], [0.0, 3.0])  # the placed one is held by later strain limiting


def test_strain_limit_caps_an_edge_by_inverse_mass_and_keeps_momentum():
    x = np.array([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0], [3.0, 0.0, 0.0], [3.5, 0.0, 0.0]])
    v = np.array([[-2.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [5.0, 0.0, 0.0]])
    inv_mass = np.array([1.0, 1.0 / 3.0, 0.0, 1.0])
    si, sj = np.array([0, 2], np.int32), np.array([1, 3], np.int32)
    rest = np.array([1.0, 0.25])
    limit_stretch(x, v, np.zeros_like(v), inv_mass, si, sj, rest, 2, 0.1)
    # 0.4 too long; the light particle moves 3 times as far as the heavy one
    np.testing.assert_allclose(x[0], [0.3, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(x[1], [1.4, 0.0, 0.0], atol=1e-12)
    # separating velocity removed, momentum kept: (1 * -2 + 3 * 1) / 4 = 0.25 each
    np.testing.assert_allclose(v[:2, 0], [0.25, 0.25], atol=1e-12)
    # a kinematic end (inverse mass 0) stays; the other end takes the whole correction
    np.testing.assert_array_equal(x[2], [3.0, 0.0, 0.0])
    np.testing.assert_allclose(x[3], [3.275, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(v[3], [0.0, 0.0, 0.0], atol=1e-12)
    before = x.copy()
    limit_stretch(x, v, np.zeros_like(v), inv_mass, si, sj, rest, 2, 0.1)  # within the limit now: untouched
    np.testing.assert_array_equal(x, before)


def rotation(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def test_body_following_moves_an_attached_particle_rigidly():
    verts, tris = box(0.3)
    mesh = BodyMesh.build(tris, len(verts))
    x = np.array([[0.05, 0.305, 0.1], [0.3 + 0.02, 0.1, -0.1], [0.1, -0.1, 0.3 + 0.2]])
    n = len(x)
    nearest = np.zeros(n, dtype=np.int32)
    from cloth.geometry import nearest_vertices

    nearest_vertices(x, verts, nearest, mesh.regions, np.full(n, 255, np.uint8))
    face, bary, height, anchor = np.zeros(n, np.int32), np.zeros((n, 3)), np.zeros(n), np.zeros((n, 3))
    free = np.zeros(n, np.uint8)
    attach_to_body(x, verts, mesh.triangles, mesh.tri_start, mesh.tri_ids, nearest, free, face, bary, height, anchor,
                   face_normals(verts, tris))
    np.testing.assert_allclose(height, [0.005, 0.02, 0.2], atol=1e-12)
    R = rotation([0.3, 1.0, -0.2], 0.7)
    t = np.array([0.4, -0.1, 0.25])
    moved = verts @ R.T + t
    body_vel, carrier, carried, followed = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3))
    v = np.zeros((n, 3))
    x0 = x.copy()
    dt = 1 / 60
    follow_w = np.full(n, -1.0)  # no weight last frame: the blend is taken as it is
    follow_body(x, v, moved, mesh.triangles, free, face, bary, height, anchor, body_vel, carrier, carried, 1 / dt,
                0.01, 0.04, followed, face_normals(moved, tris), follow_w, 0.5)
    rigid = x0 @ R.T + t
    np.testing.assert_allclose(followed, rigid, atol=1e-12)  # relative coordinates are preserved
    np.testing.assert_allclose(x[0], rigid[0], atol=1e-12)  # within `near`: follows fully
    w = (0.04 - 0.02) / (0.04 - 0.01)
    np.testing.assert_allclose(x[1], x0[1] + w * (rigid[1] - x0[1]), atol=1e-12)  # blended
    np.testing.assert_allclose(x[2], x0[2])  # beyond `far`: free cloth keeps its place
    np.testing.assert_allclose(carrier[0], 0.0)
    np.testing.assert_allclose(carrier[2], body_vel[2])
    np.testing.assert_allclose(carried, np.array([1.0, w, 0.0])[:, None] * body_vel, atol=1e-12)
    np.testing.assert_array_equal(v, 0.0)  # no weight last frame: nothing to keep
    np.testing.assert_allclose(follow_w, [1.0, w, 0.0])


def test_body_following_weight_eases_towards_the_distance_blend():
    """A particle 2 cm above a box (blend weight 2/3 between near 1 cm and far 4 cm) that was
    followed fully last frame is followed with 1 + s (2/3 - 1) this frame, s the easing; with
    the body translated by t each frame its weight approaches 2/3 geometrically, (1 - s)^k.
    Its world velocity, v + carried, stays the body's 60 t per second it had when carried fully
    (Decision): v takes what the weight no longer carries, (1 - w) 60 t."""
    verts, tris = box(0.3)
    mesh = BodyMesh.build(tris, len(verts))
    x = np.array([[0.05, 0.32, 0.1]])
    nearest = np.zeros(1, dtype=np.int32)
    from cloth.geometry import nearest_vertices

    nearest_vertices(x, verts, nearest, mesh.regions, np.full(1, 255, np.uint8))
    face, bary, height, anchor = np.zeros(1, np.int32), np.zeros((1, 3)), np.zeros(1), np.zeros((1, 3))
    free = np.zeros(1, np.uint8)
    attach_to_body(x, verts, mesh.triangles, mesh.tri_start, mesh.tri_ids, nearest, free, face, bary, height, anchor,
                   face_normals(verts, tris))
    follow_w = np.ones(1)
    blend, s = 2.0 / 3.0, 0.4
    t = np.array([0.01, 0.0, 0.0])
    v, body_vel, carrier, carried = np.zeros((1, 3)), np.zeros((1, 3)), np.zeros((1, 3)), np.zeros((1, 3))
    for k in range(1, 6):
        moved = verts + k * t
        x0 = x.copy()
        follow_body(x, v, moved, mesh.triangles, free, face, bary, height, anchor, body_vel, carrier, carried, 60.0,
                    0.01, 0.04, np.zeros((1, 3)), face_normals(moved, tris), follow_w, s)
        w = blend + (1 - blend) * (1 - s) ** k
        assert follow_w[0] == pytest.approx(w, abs=1e-12)
        np.testing.assert_allclose(v[0] + carried[0], 60.0 * t, atol=1e-12)
        np.testing.assert_allclose(v[0], (1 - w) * 60.0 * t, atol=1e-12)
        np.testing.assert_allclose(x[0], x0[0] + w * t, atol=1e-12)  # the box moved by t: w of it
        attach_to_body(x, moved, mesh.triangles, mesh.tri_start, mesh.tri_ids, nearest, free, face, bary, height,
                       anchor, face_normals(moved, tris))
        assert height[0] == pytest.approx(0.02, abs=1e-12)  # moved along the face: the same height


def test_fabric_presets_and_errors(tmp_path):
    presets = load_fabrics()
    assert {"cotton", "denim", "silk", "jersey"} <= set(presets)
    for f in presets.values():
        assert f.compression_stiffness < f.stretch_stiffness
    assert fabric("denim").density > fabric("silk").density
    table = {k: v for k, v in dataclasses.asdict(fabric("cotton")).items() if k != "name"}
    with pytest.raises(FabricError, match=r"\[wool\]\.density"):
        fabric_from_table("wool", {**table, "density": -1.0}, "user.toml")
    with pytest.raises(FabricError, match="unknown key"):
        fabric_from_table("wool", {**table, "stiffness": 3.0}, "user.toml")
    with pytest.raises(FabricError, match="missing key"):
        fabric_from_table("wool", {k: v for k, v in table.items() if k != "friction"}, "user.toml")
    with pytest.raises(FabricError, match=r"\[wool\]\.max_neighbour_ratio: must be >= 1"):
        fabric_from_table("wool", {**table, "max_neighbour_ratio": 0.5}, "user.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[wool\nfriction = 1\n")
    with pytest.raises(FabricError, match="bad.toml: not valid TOML"):
        load_fabrics(bad)
    with pytest.raises(FabricError, match="no fabric 'tweed'"):
        fabric("tweed")


def l_prism(depth=1.0):
    """A closed L-shaped prism (outward triangles): the L (0,0)-(2,0)-(2,1)-(1,1)-(1,2)-(0,2)
    in x, y, extruded from z = 0 to depth. Its inner corner is the edge x = y = 1."""
    ring = np.array([[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]], float)
    verts = np.concatenate([np.c_[ring, np.zeros(6)], np.c_[ring, np.full(6, depth)]])
    cap = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 5], [3, 4, 5]])  # the L, counter-clockwise seen from +z
    tris = [c[::-1] for c in cap] + [c + 6 for c in cap]  # bottom faces -z, top faces +z
    for k in range(6):
        a, b = k, (k + 1) % 6
        tris += [[a, b, b + 6], [a, b + 6, a + 6]]
    return verts, np.array(tris, dtype=np.int32)


def test_resolve_contacts_settles_a_particle_in_a_concave_corner_away_from_both_faces():
    """A particle just inside the inner corner of an L: the first push (along the corner edge's
    normal) leaves it nearer than thickness to both faces; the pass repeats from there and
    settles it thickness away from each, in the corner's outside quadrant."""
    verts, tris = l_prism()
    mesh = BodyMesh.build(tris, len(verts))
    face_n = face_normals(verts, tris)
    assert np.allclose(face_n[8:10, :3], [0, -1, 0])  # the first side, y = 0, faces out
    x = np.array([[0.999, 0.9985, 0.5]])
    v = np.zeros_like(x)
    resolve_contacts(x, v, verts, np.zeros_like(x), mesh.nbr_start, mesh.nbr_ids, mesh.triangles, mesh.tri_start,
                     mesh.tri_ids, mesh.tri_nbrs, mesh.regions, np.zeros(1, np.int32), 0.003, np.zeros(1, np.uint8),
                     face_n, np.zeros(3), *contact_grids(verts, mesh), *contact_scratch(len(x)))
    assert x[0, 0] >= 1.003 - 1e-9 and x[0, 1] >= 1.003 - 1e-9, x
    assert x[0, 0] < 1.0031 and x[0, 1] < 1.0031 and x[0, 2] == 0.5, x


NOTCH_HALF_ANGLE = np.radians(30.0)


def notch_prism(depth=1.0, half_angle=NOTCH_HALF_ANGLE):
    """A closed prism (outward triangles) whose section is a square with a V notch cut into its
    top: (0,0)-(2,0)-(2,2)-(1+w,2)-(1,0.5)-(1-w,2)-(0,2), w = 1.5 tan(half_angle), extruded
    from z = 0 to depth. The notch's walls are 2 half_angle apart (60°: their planes face each
    other no more than cos 120° = -0.5, a crease, not a slit)."""
    w = 1.5 * np.tan(half_angle)
    ring = np.array([[0, 0], [2, 0], [2, 2], [1 + w, 2], [1, 0.5], [1 - w, 2], [0, 2]], float)
    n = len(ring)
    verts = np.concatenate([np.c_[ring, np.zeros(n)], np.c_[ring, np.full(n, depth)]])
    cap = np.array([[0, 1, 4], [1, 2, 3], [1, 3, 4], [0, 4, 5], [0, 5, 6]])  # counter-clockwise seen from +z
    tris = [c[::-1] for c in cap] + [c + n for c in cap]
    for k in range(n):
        a, b = k, (k + 1) % n
        tris += [[a, b, b + n], [a, b + n, a + n]]
    return verts, np.array(tris, dtype=np.int32)


def test_resolve_contacts_solves_a_narrow_crease_for_both_walls_at_once():
    """A particle 1 cm inside the bottom of a 60° notch. The first push (along the bottom edge's
    pseudo-normal, +y) lands it nearer than thickness to both walls; pushing out of one wall
    then lands it behind the other, and alternating pushes close in on the answer by cos² 120°
    = 0.25 a round, never reaching it. The pass solves for a point in front of both planes at once:
    the notch's bisector x = 1 at thickness from each wall, y = 0.5 + 0.003 / sin 30°."""
    verts, tris = notch_prism()
    mesh = BodyMesh.build(tris, len(verts))
    face_n = face_normals(verts, tris)
    assert (face_n[:, 3] > 0).all()
    x = np.array([[1.0, 0.49, 0.5]])
    v = np.zeros_like(x)
    resolve_contacts(x, v, verts, np.zeros_like(x), mesh.nbr_start, mesh.nbr_ids, mesh.triangles, mesh.tri_start,
                     mesh.tri_ids, mesh.tri_nbrs, mesh.regions, np.zeros(1, np.int32), 0.003, np.zeros(1, np.uint8),
                     face_n, np.zeros(3), *contact_grids(verts, mesh), *contact_scratch(len(x)))
    np.testing.assert_allclose(x[0], [1.0, 0.5 + 0.003 / np.sin(NOTCH_HALF_ANGLE), 0.5], atol=1e-9)


def test_resolve_contacts_flags_a_particle_its_last_push_left_untested():
    """The same notch, with a free and a gripped particle at that point. The free one settles
    on the bisector after the crease solve and is tested there: settled. The gripped one gets
    no crease solve (it keeps to the surface), alternates between the walls for all
    CONTACT_ITERATIONS pushes and is flagged unsettled: the second contact pass of a frame
    tests it again even if nothing moves it in between."""
    verts, tris = notch_prism()
    mesh = BodyMesh.build(tris, len(verts))
    x = np.array([[1.0, 0.49, 0.5], [1.0, 0.49, 0.5]])
    scratch = contact_scratch(len(x))
    resolve_contacts(x, np.zeros_like(x), verts, np.zeros_like(x), mesh.nbr_start, mesh.nbr_ids, mesh.triangles,
                     mesh.tri_start, mesh.tri_ids, mesh.tri_nbrs, mesh.regions, np.zeros(2, np.int32), 0.003,
                     np.array([0, 1], np.uint8), face_normals(verts, tris), np.zeros(3), *contact_grids(verts, mesh),
                     *scratch)
    np.testing.assert_array_equal(scratch[UNSETTLED], [0, 1])
    np.testing.assert_allclose(x[0], [1.0, 0.5 + 0.003 / np.sin(NOTCH_HALF_ANGLE), 0.5], atol=1e-9)
    assert np.abs(x[1] - x[0]).max() > 1e-6  # closing in by alternate pushes, not solved


def test_resolve_contacts_places_a_gripped_particle_outside_and_leaves_its_velocity():
    """A waistband particle (gripped: kinematic, it follows the body) that the skin bulged over
    is placed outside like any other; its velocity, which only a free particle has, is kept."""
    verts, tris = box(0.3)
    mesh = BodyMesh.build(tris, len(verts))
    x = np.array([[0.1, 0.29, 0.0]])
    v = np.array([[0.0, -1.0, 0.0]])
    resolve_contacts(x, v, verts, np.zeros_like(x), mesh.nbr_start, mesh.nbr_ids, mesh.triangles, mesh.tri_start,
                     mesh.tri_ids, mesh.tri_nbrs, mesh.regions, np.zeros(1, np.int32), 0.003, np.ones(1, np.uint8),
                     face_normals(verts, tris), np.zeros(3), *contact_grids(verts, mesh), *contact_scratch(len(x)))
    np.testing.assert_allclose(x[0], [0.1, 0.303, 0.0], atol=1e-9)
    np.testing.assert_array_equal(v[0], [0.0, -1.0, 0.0])


def test_resolve_contacts_tests_only_the_active_particles():
    """The frame's last contact pass re-tests only the particles the held strain-limiting passes
    moved (`mark_moved`): an inactive particle is left where it is, even inside the body, and
    its placed inverse mass is not written."""
    verts, tris = box(0.3)
    mesh = BodyMesh.build(tris, len(verts))
    x = np.array([[0.1, 0.28, -0.05], [0.1, 0.28, 0.05]])  # both 2 cm below the top face
    before = x.copy()
    x[0, 0] += 0.0016  # moved 1.6 mm, the other 1.4 mm: only the first past 0.5 × 3 mm
    x[1, 0] += 0.0014
    active = np.zeros(2, np.uint8)
    mark_moved(x, before, 0.0015, active)
    np.testing.assert_array_equal(active, [1, 0])
    v = np.zeros_like(x)
    scratch = list(contact_scratch(2))
    scratch[ACTIVE] = active
    inside = x[1].copy()
    resolve_contacts(x, v, verts, np.zeros_like(x), mesh.nbr_start, mesh.nbr_ids, mesh.triangles, mesh.tri_start,
                     mesh.tri_ids, mesh.tri_nbrs, mesh.regions, np.zeros(2, np.int32), 0.003, np.zeros(2, np.uint8),
                     face_normals(verts, tris), np.zeros(3), *contact_grids(verts, mesh), *scratch)
    np.testing.assert_allclose(x[0], [0.1016, 0.303, -0.05], atol=1e-9)
    np.testing.assert_array_equal(x[1], inside)
    placed = scratch[PLACED]
    assert placed[0] == 0.0 and np.isnan(placed[1])


def quad_on_box(settings, ordered=False):
    """One 4 cm cotton quad (max strain 5 %, thickness 3 mm), stretched 30 % along x, 2 mm
    inside the top face (y = 0.3) of a box, at rest: (sim, positions). ordered: the box's
    mesh numbered along a Morton curve inside (BodyMesh.build's rest_vertices)."""
    from cloth.coarsen import CoarseMesh
    from cloth.garment import Garment
    from cloth.model import build_cloth_model
    from cloth.sim import ClothSim

    rest = np.array([[0.0, 0.3, 0.0], [0.0, 0.3, 0.04], [0.04, 0.3, 0.04], [0.04, 0.3, 0.0]])
    quad = np.array([[0, 1, 2, 3]], np.int32)
    garment = Garment("quad", rest, quad, np.arange(4))
    model = build_cloth_model(garment, fabric("cotton"), settings, rest,
                              CoarseMesh(rest, quad, np.zeros(0, np.int32), np.zeros((0, 3))))
    verts, tris = box(0.3)
    sim = ClothSim(model, BodyMesh.build(tris, len(verts), rest_vertices=verts if ordered else None), verts)
    assert (model.fabric.max_strain, model.fabric.thickness) == (0.05, 0.003)
    x = sim.state.x
    x[:] = [[-0.026, 0.298, 0.0], [-0.026, 0.298, 0.04], [0.026, 0.298, 0.04], [0.026, 0.298, 0.0]]
    sim.state.v[:] = 0.0
    return sim, x


@pytest.mark.parametrize("ordered", [False, True])
@pytest.mark.parametrize("slide_passes", [0, 1])
def test_slide_pass_lets_placed_particles_slide_back_to_the_strain_limit(slide_passes, ordered):
    """The quad of `quad_on_box`: the contact pass places all four on the face plus thickness
    (y = 0.303). Held there (slide_passes = 0), the stretched edges stay 5.2 cm long. The slide
    pass frees them for one strain-limiting pass: each x edge, its two ends of equal mass,
    shortens about its midpoint to exactly 1.05 × 4 cm along the face, the z edges (at rest)
    are untouched, and the second contact pass finds them all outside. The same with the box
    numbered in Morton order inside (the caller still passes its own vertices)."""
    sim, x = quad_on_box(SimSettings(slide_passes=slide_passes), ordered)
    sim.settle_contacts(sim.pose)
    np.testing.assert_allclose(x[:, 1], 0.303, atol=1e-12)
    half = 0.026 if slide_passes == 0 else 0.021
    np.testing.assert_allclose(x[:, [0, 2]], [[-half, 0.0], [-half, 0.04], [half, 0.04], [half, 0.0]], atol=1e-12)
    placed = sim.state.placed_inv_mass == 0.0
    assert placed.all() if slide_passes == 0 else not placed.any()


@pytest.mark.parametrize("blow_up", ["nan", "speed"])
def test_step_resets_exploded_particles_to_their_body_following_places_and_counts_them(blow_up):
    """The quad of `quad_on_box` settled on the still box for three frames, then a NaN in one
    particle's velocity (it reaches every particle of the quad through the springs in the first
    substep) or one particle thrown at 100 m/s (past max_speed; the strain limiting shares its
    speed with the other three): the step resets all four to their body-following places, which
    on a body that did not move are where the frame began, at rest, and counts them."""
    sim, x = quad_on_box(SimSettings())
    body = sim.pose.x.copy()
    for _ in range(3):
        sim.step(body, 1 / 60)
    assert sim.stats.reset_particles == 0
    before = x.copy()
    if blow_up == "nan":
        sim.state.v[1] = np.nan
    else:
        sim.state.v[0] = [100.0, 0.0, 0.0]
    sim.step(body, 1 / 60)
    assert (sim.stats.reset_particles, sim.stats.reset_frames) == (4, 1)
    np.testing.assert_allclose(x, before, atol=1e-12)
    np.testing.assert_array_equal(sim.state.v, 0.0)


def test_profiled_step_is_the_same_computation():
    """`ClothSim.step(profile=True)` runs the frame kernel by kernel to time integration and
    collision apart; positions and velocities stay bit for bit those of the fused kernels."""
    fused, x_fused = quad_on_box(SimSettings())
    timed, x_timed = quad_on_box(SimSettings())
    body = fused.pose.x.copy()
    for _ in range(6):
        fused.step(body, 1 / 60)
        timed.step(body, 1 / 60, profile=True)
        np.testing.assert_array_equal(x_fused, x_timed)
        np.testing.assert_array_equal(fused.state.v, timed.state.v)
    assert (timed.stage_seconds > 0).all()


def test_nearest_face_query_off_keeps_no_face_tree():
    """nearest_face_radius = 0 and no union pass: the simulation's body pose keeps no face tree
    (no refit per pose), and the contact passes still place the quad on the box (the same
    answer as with the query on). The union pass (on by default) reads the tree: with it the
    pose keeps one whatever the radius. A negative radius is refused."""
    results = []
    for radius in (0.0, REFINE_RADIUS):
        sim, x = quad_on_box(SimSettings(nearest_face_radius=radius, union_passes=0))
        assert (sim.pose.faces is None) == (radius == 0.0)
        sim.settle_contacts(sim.pose)
        results.append(x.copy())
    np.testing.assert_allclose(results[0][:, 1], 0.303, atol=1e-12)
    np.testing.assert_array_equal(results[0], results[1])
    assert SimSettings().nearest_face_radius == 0.0 and SimSettings().needs_face_tree
    sim, _ = quad_on_box(SimSettings())
    assert sim.pose.faces is not None
    with pytest.raises(ValueError, match="nearest_face_radius must be >= 0"):
        SimSettings(nearest_face_radius=-0.01)
    with pytest.raises(ValueError, match="union_passes must be 0, 1 or 2"):
        SimSettings(union_passes=3)


@pytest.mark.parametrize("kwargs, says", [
    ({"substeps": 0}, "SimSettings.substeps must be None or an integer >= 1, got 0"),
    ({"substeps": "8"}, "SimSettings.substeps must be None or an integer >= 1, got '8'"),
    ({"collide_every": 0}, "SimSettings.collide_every must be an integer >= 1, got 0"),
    ({"limit_passes": -1}, "SimSettings.limit_passes must be an integer >= 0, got -1"),
    ({"target_particles": 2.5}, "SimSettings.target_particles must be an integer >= 4, got 2.5"),
    ({"frame_rate": 0.0}, "SimSettings.frame_rate must be > 0 and finite, got 0.0"),
    ({"follow_easing": -0.01}, "SimSettings.follow_easing must be >= 0 and finite, got -0.01"),
    ({"follow_far": 0.005}, "SimSettings.follow_far must be > follow_near (0.01 m) and finite, got 0.005"),
    ({"max_stretch": 1.0}, "SimSettings.max_stretch must be > 1"),
    ({"gravity": float("nan")}, "SimSettings.gravity must be finite, got nan"),
])
def test_sim_settings_name_a_value_out_of_range(kwargs, says):
    with pytest.raises(ValueError, match=re.escape(says)):
        SimSettings(**kwargs)
    SimSettings(substeps=8, follow_easing=0.0)  # and values in range are taken


def canonical_triangles(v, t):
    """A mesh's triangles as sorted corner-position triples, each rotated to start at its
    smallest corner (winding kept): equal for the same surface under any numbering."""
    out = []
    for row in np.round(v[t] * 1e6).astype(np.int64):
        corners = [tuple(c) for c in row]
        k = corners.index(min(corners))
        out.append(tuple(corners[k:] + corners[:k]))
    return sorted(out)


def test_a_body_numbered_in_morton_order_inside_answers_in_the_callers_terms():
    """A box numbered at random (vertices and faces shuffled), two regions (x < 0, x >= 0), the
    top faces clothed. Built with its rest vertices, the mesh renumbers both along a Morton
    curve: the same triangles,
    windings, regions and clothed faces as positions; `internal` and a `BodyPose` update from
    the caller's vertices give them in the inner order, and the face normals match the
    caller's own faces'."""
    from cloth.collision import BODY_ORDER_CELL
    from cloth.geometry import morton_order

    verts, tris = box(0.3, 6)
    rng = np.random.default_rng(5)
    perm = rng.permutation(len(verts))  # caller's vertex perm[k] is box vertex k
    v = np.empty_like(verts)
    v[perm] = verts
    t = perm[tris][rng.permutation(len(tris))].astype(np.int32)
    regions = np.where(v[:, 0] < 0, 1, 2).astype(np.uint8)
    clothed = v[t][:, :, 1].min(axis=1) > 0.29
    mesh = BodyMesh.build(t, len(v), regions, clothed, rest_vertices=v)
    order = mesh.vertex_order
    np.testing.assert_array_equal(np.sort(order), np.arange(len(v)))
    inner = mesh.internal(v)
    np.testing.assert_array_equal(inner, v[order])
    np.testing.assert_array_equal(morton_order(inner, BODY_ORDER_CELL), np.arange(len(v)))
    assert canonical_triangles(inner, mesh.triangles) == canonical_triangles(v, t)
    assert canonical_triangles(inner, mesh.triangles[mesh.clothed_faces]) == canonical_triangles(v, t[clothed])
    np.testing.assert_array_equal(mesh.regions, regions[order])
    moved = v @ rotation([0.0, 1.0, 0.0], 0.3).T + [0.1, 0.2, 0.0]
    pose = BodyPose(mesh)
    pose.update(moved)
    np.testing.assert_array_equal(pose.x, moved[order])
    with pytest.raises(ValueError, match="body vertices must be"):
        pose.update(moved[:-1])  # one vertex short: the gather would read past the end
    mine = face_normals(moved, t)
    theirs = pose.face_n
    key = {tri: k for k, tri in enumerate(map(tuple, np.sort(order[mesh.triangles], axis=1)))}
    match = np.array([key[tuple(row)] for row in np.sort(t, axis=1)])
    np.testing.assert_allclose(theirs[match], mine, atol=1e-15)
    plain = BodyMesh.build(t, len(v), regions, clothed)
    assert plain.vertex_order is None
    np.testing.assert_array_equal(plain.internal(v), v)


def two_boxes(gap=0.05, half=0.1):
    """Two separate boxes side by side along x (parts 1 and 2), as one body: box A centred at
    the origin, box B at x = 2 half + gap; returns verts, tris, regions, B's lowest x."""
    va, ta = box(half, 4)
    vb = va + [2 * half + gap, 0.0, 0.0]
    verts = np.vstack([va, vb])
    tris = np.vstack([ta, ta + len(va)]).astype(np.int32)
    regions = np.r_[np.full(len(va), 1), np.full(len(vb), 2)].astype(np.uint8)
    return verts, tris, regions, half + gap


def collide_two_parts(x, mask, part_nearest, nearest, verts, tris, regions, thickness=0.003):
    mesh = BodyMesh.build(tris, len(verts), regions)
    x = np.array(x, dtype=float)
    v = np.zeros_like(x)
    contact = np.zeros(len(x), np.uint8)
    collide_particles(x, v, verts, np.zeros_like(x), mesh.nbr_start, mesh.nbr_ids, mesh.triangles, mesh.tri_start,
                      mesh.tri_ids, mesh.regions, np.array(mask, np.uint8), nearest, part_nearest, thickness, 0.0,
                      contact, np.zeros(len(x), np.uint8), face_normals(verts, tris), np.zeros_like(x),
                      np.full(len(x), -np.inf))
    return x, contact


def test_collision_walks_each_part_of_a_particle_near_two():
    """Box B's face at x = 0.15, a particle 1 cm inside it whose nearest vertex is on box A.
    One walk over both parts cannot leave A (the boxes share no edge) and finds A's ring, which
    the particle is outside of: not pushed. With a seed in each part (part_seeds) it walks each,
    is found inside B and put at B's face plus thickness; `nearest` is B's vertex, the nearer."""
    from cloth.collision import part_seeds
    verts, tris, regions, bx = two_boxes()
    p = [[bx + 0.01, 0.0, 0.0]]
    a_vertex = int(np.argmin(np.linalg.norm(verts[:len(verts) // 2] - [0.1, 0.0, 0.0], axis=1)))
    x, contact = collide_two_parts(p, [3], no_parts(1), np.array([a_vertex], np.int32), verts, tris, regions)
    assert contact[0] == 0 and x[0, 0] == bx + 0.01
    seeds = part_seeds(np.array(p), verts, regions, np.array([3], np.uint8))
    assert regions[seeds[0, 0]] == 1 and regions[seeds[0, 1]] == 2 and (seeds[0, 2:] == -1).all()
    seeds[0, 1] = int(np.argmax(verts[:, 0]))  # B's far side: the walk must find its way
    nearest = np.array([a_vertex], np.int32)
    x, contact = collide_two_parts(p, [3], seeds, nearest, verts, tris, regions)
    assert contact[0] == 1
    np.testing.assert_allclose(x[0], [bx - 0.003, 0.0, 0.0], atol=1e-12)
    assert regions[nearest[0]] == 2 and verts[nearest[0], 0] == pytest.approx(bx)
    # one part only: the seeds are not used (-1), the walk from nearest as before
    assert (part_seeds(np.array(p), verts, regions, np.array([1], np.uint8)) == -1).all()


@pytest.mark.parametrize("depth, pushed", [(0.005, True), (0.02, False)])
def test_a_part_outside_the_mask_pushes_only_from_near_its_surface(depth, pushed):
    """A particle that follows box A (mask 1) with box B tracked for collision (track_parts):
    5 mm inside B it is put out of B; 2 cm inside (deeper than MAX_OTHER_PART_DEPTH, where
    skinned parts intersect) it is left. `nearest` stays on A, the part it follows."""
    from cloth.collision import MAX_OTHER_PART_DEPTH
    assert 0.005 < MAX_OTHER_PART_DEPTH < 0.02
    verts, tris, regions, bx = two_boxes()
    p = [[bx + depth, 0.0, 0.0]]
    seeds = no_parts(1)
    seeds[0, 0] = int(np.argmin(np.linalg.norm(verts[:len(verts) // 2] - [0.1, 0.0, 0.0], axis=1)))
    seeds[0, 1] = int(np.argmin(np.linalg.norm(verts - [bx, 0.0, 0.0], axis=1)))
    nearest = np.array([seeds[0, 0]], np.int32)
    x, contact = collide_two_parts(p, [1], seeds, nearest, verts, tris, regions)
    assert contact[0] == pushed
    np.testing.assert_allclose(x[0, 0], bx - 0.003 if pushed else bx + depth, atol=1e-12)
    assert regions[nearest[0]] == 1


def test_track_parts_adds_the_part_the_contact_pass_found_and_drops_it_when_far():
    """mask 1 (box A): nearest_any on B adds B (and A's seed, from nearest); nearest_any on A
    adds nothing; once B's tracked vertex is farther than `drop`, B is dropped, A's seed kept."""
    from cloth.collision import track_parts
    verts, tris, regions, bx = two_boxes()
    a_v = int(np.argmin(np.linalg.norm(verts - [0.1, 0.0, 0.0], axis=1)))
    b_v = int(np.argmin(np.linalg.norm(verts - [bx, 0.0, 0.0], axis=1)))
    x = np.array([[0.125, 0.0, 0.0]])
    seeds = no_parts(1)
    args = (verts, regions, np.array([1], np.uint8), np.array([a_v], np.int32))
    track_parts(x, *args, np.array([a_v], np.int32), seeds, 0.06)
    assert (seeds == -1).all()
    track_parts(x, *args, np.array([b_v], np.int32), seeds, 0.06)
    assert seeds[0, 0] == a_v and seeds[0, 1] == b_v and (seeds[0, 2:] == -1).all()
    x[0] = [-0.05, 0.0, 0.0]  # 0.2 m from B's vertex
    track_parts(x, *args, np.array([a_v], np.int32), seeds, 0.06)
    assert seeds[0, 0] == a_v and seeds[0, 1] == -1


def test_the_nearest_vertex_grid_gives_the_brute_forces_answers():
    """The setup's nearest-vertex search through a grid: the same vertex as trying every one,
    ties (the lowest index), region masks (none matching: left as it was), points far outside
    the vertices, NaN points, a flat cloud; and with `within`, that vertex where it is within
    the distance and nothing (left as it was) where it is not."""
    from cloth.geometry import nearest_vertices, nearest_vertices_brute, nearest_vertices_in_grid

    rng = np.random.default_rng(5)
    for trial in range(60):
        n, m = rng.integers(64, 800), rng.integers(64, 800)
        v = rng.normal(size=(m, 3)) * [0.3, 1.0, 0.2] if trial % 4 else rng.uniform(-1, 1, (m, 3))
        p = rng.normal(size=(n, 3)) * rng.uniform(0.5, 4.0)
        if trial % 3 == 0:  # on a 0.1 lattice: many equally near vertices
            v, p = np.round(v, 1), np.round(p, 1)
        if trial % 5 == 0:
            v[rng.integers(0, m, 20)] = v[0]
        if trial % 6 == 0:
            v[:, 2] = 0.25
        p[:2] = [[np.nan, 0, 0], [np.inf, 0, 0]]
        regions = rng.integers(1, 16, m).astype(np.uint16)
        masks = rng.integers(0, 16, n).astype(np.uint16)
        masks[2] = 0
        brute, grid, chosen = np.full(n, -7, np.int32), np.full(n, -7, np.int32), np.full(n, -7, np.int32)
        nearest_vertices_brute(p, v, brute, regions, masks)
        nearest_vertices_in_grid(p, v, grid, regions, masks)
        np.testing.assert_array_equal(grid, brute, err_msg=f"trial {trial}")
        nearest_vertices(p, v, chosen, regions, masks)  # (brute force, so few pairs: BRUTE_PAIRS)
        np.testing.assert_array_equal(chosen, brute, err_msg=f"trial {trial}")
        assert brute[0] == brute[1] == brute[2] == -7
        within, near = 0.2, np.full(n, -7, np.int32)
        nearest_vertices(p, v, near, regions, masks, within)
        ok = brute >= 0
        d = np.full(n, np.inf)
        d[ok] = np.linalg.norm(p[ok] - v[brute[ok]], axis=1)
        np.testing.assert_array_equal(near[d <= within], brute[d <= within])
        assert np.all(near[d > within * 1.000001] == -7)
