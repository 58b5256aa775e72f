"""SPEC.md S104 and S106 formulas, kernel by kernel, on cases worked out by hand: the transfer
rates and the force interpolation along a bent chain, the three-direction average inside a
face, the normal force, ΔL_expected's sign rule with Δh_length and its clamp, and the
blended shading normals."""

import numpy as np
import pytest

from cloth.pn import build_tessellation
from cloth.wrinkles import (UNTESTED, deformation_heights, elastic_forces, normal_force, penetration_floor,
                            shading_normals)


def single_face(level, corners):
    """One coarse triangle (vertices 0, 1, 2) at this level, its detailed vertices on the flat
    triangle through `corners` (3, 3)."""
    t = build_tessellation(np.array([[0, 1, 2]], dtype=np.int32), 3, level)
    p = t.owner_weights @ np.asarray(corners, dtype=float)
    return t, p


# the transfer rates and the normal force's directions are float32: to about 1e-7
RATES_RTOL = 1e-6


def run_elastic(t, p, coarse_force, edge_force, exponent=1.0):
    Q = len(t.chain_ids)
    ef = np.full((t.n_vertices, 3), np.nan)
    elastic_forces(p, np.asarray(coarse_force, float), np.asarray(edge_force, float), t.edge_ids, t.line_start,
                   t.chain_ids, exponent, np.zeros((3, Q), np.float32), np.zeros(Q, np.float32), np.zeros(3),
                   np.zeros(3), ef)
    return ef


def bent_shares(exponent):
    """The shares of the chain below for any exponent: rates 1, 0.5^exponent, 1."""
    r = 0.5 ** exponent
    return [0.5 / (2 + r), (1 + r / 2) / (2 + r), (1.5 + r) / (2 + r)]


@pytest.mark.parametrize("exponent, shares", [(1.0, [0.2, 0.5, 0.8]), (2.0, [2 / 9, 0.5, 7 / 9]),
                                              (0.5, bent_shares(0.5)), (1.5, bent_shares(1.5))])
def test_force_along_a_bent_edge_follows_the_transfer_rates(exponent, shares):
    """S104 steps 2-3 on the coarse edge 0 → 1 at level 4: its chain runs straight for two
    segments, turns by 60° at the middle particle and runs straight again, so the rates of its
    three inner particles are c = 1, cos 60° = 0.5, 1 (mapped by max(c, 0)^exponent). With
    f_1 = 0 and f_n = (10, 0, 0): ef_i = (Σ_{j<i} c_j + c_i / 2) / Σ c_j · 10 = 2, 5, 8
    (exponent 1; c² gives 20/9, 5, 70/9; 0.5 and 1.5 go through the other two mappings)."""
    s3 = np.sqrt(3.0)
    t, p = single_face(4, [[0, 0, 0], [3, 0, s3], [0, 3, 0]])
    assert tuple(t.coarse_edges[0]) == (0, 1)
    chain = t.edge_ids[0]
    p[chain] = [[0, 0, 0], [1, 0, 0], [2, 0, 0], [2.5, 0, s3 / 2], [3, 0, s3]]
    edge_force = np.zeros((len(t.coarse_edges), 2, 3))
    edge_force[0, 1] = (10.0, 0.0, 0.0)
    coarse_force = np.zeros((3, 3))
    ef = run_elastic(t, p, coarse_force, edge_force, exponent)
    np.testing.assert_allclose(ef[chain[1:4]], np.outer(shares, [10.0, 0.0, 0.0]), rtol=RATES_RTOL, atol=1e-12)
    np.testing.assert_array_equal(ef[:3], coarse_force)  # step 1: the coarse particles' own forces


def test_force_inside_a_face_averages_the_three_lattice_directions():
    """S104 step 4 at level 3 on a flat triangle: every line is straight, so an edge particle a
    third of the way from corner U takes f_U + (f_V - f_U)/4 (step 3: (0 + 1/2) / 2), and the
    one interior point, the middle of a line of three in each of the three directions, takes
    the mean of each line's two ends, averaged over the directions. A field equal everywhere
    is kept everywhere."""
    t, p = single_face(3, [[0, 0, 0], [1, 0, 0], [0, 0, 1]])
    f = np.array([[3.0, 0, 0], [0, 6.0, 0], [0, 0, 9.0]])  # at corners A, B, C
    edge_force = np.stack([f[t.coarse_edges[:, 0]], f[t.coarse_edges[:, 1]]], axis=1)
    ef = run_elastic(t, p, f, edge_force)
    vid = {(int(b), int(c)): int(t.face_ids[0, k]) for k, (b, c) in enumerate(t.lattice)}

    def near(u, v):  # the edge particle a third of the way from corner u to corner v
        return f[u] + 0.25 * (f[v] - f[u])

    A, B, C = 0, 1, 2
    np.testing.assert_allclose(ef[vid[1, 0]], near(A, B), rtol=RATES_RTOL)
    np.testing.assert_allclose(ef[vid[2, 1]], near(B, C), rtol=RATES_RTOL)
    lines = [(near(B, A), near(C, A)),  # a = 1: (2, 0) on AB and (0, 2) on CA
             (near(A, B), near(C, B)),  # b = 1: (1, 0) on AB and (1, 2) on BC
             (near(A, C), near(B, C))]  # c = 1: (0, 1) on CA and (2, 1) on BC
    expected = np.mean([(e1 + e2) / 2 for e1, e2 in lines], axis=0)
    np.testing.assert_allclose(ef[vid[1, 1]], expected, rtol=RATES_RTOL)
    same = run_elastic(t, p, np.tile([1.0, -2.0, 0.5], (3, 1)), np.tile([1.0, -2.0, 0.5], (len(t.coarse_edges), 2, 1)))
    np.testing.assert_allclose(same, np.tile([1.0, -2.0, 0.5], (t.n_vertices, 1)), rtol=1e-12)


def test_normal_force_sums_the_neighbours_forces_along_the_edges():
    """S104 step 5: vf_i = Σ_j (p_i - p_j)/|p_i - p_j| . ef_j. Particle 0 at the origin with
    neighbours at x = 2, z = 1 and x = -1 pushing towards it with 2 and 3 N (the third
    pushes nothing): vf_0 = 2 + 3 = 5. Particle 0's own force (1, 0, 1) pushes its neighbours
    by 1, 1 and -1."""
    p = np.array([[0.0, 0, 0], [2, 0, 0], [0, 0, 1], [-1, 0, 0]])
    ef = np.array([[1.0, 0, 1], [-2, 0, 0], [0, 0, -3], [0, 0, 0]])
    vf = np.full(4, np.nan)
    normal_force(p, ef, np.array([[0, 1], [0, 2], [0, 3]], dtype=np.int32), vf)
    np.testing.assert_allclose(vf, [5.0, 1.0, 1.0, -1.0], rtol=RATES_RTOL)  # float32 directions


def test_deformation_heights_expected_length_and_the_force_clamp():
    """S106 steps 1-4 on the chain 0 - 1 - 2 (k_out 2, Δt 0.1, particle 0 a coarse vertex).
    vf = (0, 3, 1), particle 1 raised 1 cm: both of its edges have the higher particle pushed
    more, so ΔL_expected,1 = 2·3 + 2·2 = 10 (particle 2: +4). Δh_length,1 = k_out vf_1 ·
    ΔL_required / ΔL_expected = 6 · 0.5 / 10 = 0.3 (the units Decision), under the clamp
    k_out vf Δt = 0.6; required 5 gives 3, clamped to 0.6. Particle 2's requirement has the
    other sign than its ΔL_expected: no length step, and the smaller of 0 and the force term
    is 0. With particle 0 raised 2 cm the edge 0 - 1 has the higher particle pushed less:
    its term counts -6, and ΔL_expected,1 = -6 + 4 = -2; a requirement of -0.1 (the same sign)
    gives Δh_length,1 = 6 · -0.1 / -2 = 0.3."""
    edges = np.array([[0, 1], [1, 2]], dtype=np.int32)
    vf = np.array([0.0, 3.0, 1.0])

    def run(dh, required):
        expected, out = np.zeros(3), np.full(3, np.nan)
        deformation_heights(vf, np.asarray(dh, float), np.asarray(required, float), edges, 1, 2.0, 0.1, expected, out)
        return expected, out

    expected, out = run([0, 0.01, 0], [0, 0.5, -0.2])
    np.testing.assert_allclose(expected, [6.0, 10.0, 4.0], rtol=1e-12)
    np.testing.assert_allclose(out, [0.0, 0.3, 0.0], rtol=1e-12)
    _, out = run([0, 0.01, 0], [0, 5.0, 0])
    np.testing.assert_allclose(out[1], 0.6, rtol=1e-12)
    expected, out = run([0.02, 0.01, 0], [0, -0.1, 0])
    np.testing.assert_allclose(expected, [-6.0, -2.0, 4.0], rtol=1e-12)
    np.testing.assert_allclose(out[1], 6.0 * -0.1 / -2.0, rtol=1e-12)  # both negative: a step of 0.3


def test_shading_normals_blend_by_height():
    """S106 step 7: n = normalize(α n_deform + (1 - α) n_pnt), α = min(1, Δh / h_normal). One
    triangle in the XZ plane (n_deform +Y) whose PN normals point along +X: heights 0,
    h_normal / 2 and 2 h_normal give +X, the diagonal and +Y."""
    p = np.array([[0.0, 0, 0], [0, 0, 1], [1, 0, 0]])  # wound so that its normal is +Y
    tris = np.array([[0, 1, 2]], dtype=np.int32)
    n_pn = np.tile([1.0, 0, 0], (3, 1))
    h = 0.004
    out = np.full((3, 3), np.nan)
    shading_normals(p, tris, n_pn, np.array([0.0, h / 2, 2 * h]), h, np.zeros((3, 3)), out)
    np.testing.assert_allclose(out, [[1, 0, 0], [np.sqrt(0.5), np.sqrt(0.5), 0], [0, 1, 0]], atol=1e-12)


def test_penetration_floor_and_ceiling():
    """The heights S106 may give a particle after S103 (clearance 1 mm, max_height 30 mm, mm):
    untested: 0 to 30. Body below (facing >= 0) at 4 mm, height 2: down by 4 - 1 = 3 mm, not
    below 0: floor 0, ceiling 30; at 2.5 mm with height 5: floor 3.5. Body above (facing < 0),
    lowered to -3 and 1.5 mm under it: up by 0.5 at most, ceiling -2.5, floor -2.5; one under a
    body part 4 mm above at height 1: ceiling 4, floor 0. Decision: another body part 6 mm away
    (before S103 moved the particle by 1 mm), body below: up by 6 - 1 - 1 = 4 mm at most,
    ceiling 2 + 4 = 6; 1.5 mm away: up by 0.5, ceiling 2.5; 0.5 mm away: no rise (ceiling =
    height 2, never under the floor 0)."""
    inf = UNTESTED
    dh = np.array([0.0, 2.0, 5.0, -3.0, 1.0, 2.0, 2.0, 2.0]) / 1000
    sd = np.array([inf, 4.0, 2.5, 1.5, 4.0, 4.0, 4.0, 4.0]) / 1000
    facing = np.array([0.0, 1.0, 0.9, -1.0, -0.8, 1.0, 1.0, 1.0])
    other = np.array([inf, inf, inf, inf, inf, 6.0, 1.5, 0.5]) / 1000
    dh_pen = np.array([0.0, 0.0, 0.0, -3.0, 0.0, 1.0, 0.0, 0.0]) / 1000
    floor, ceiling = np.full(8, np.nan), np.full(8, np.nan)
    penetration_floor(dh, sd, facing, other, dh_pen, 0.001, 0.03, floor, ceiling)
    np.testing.assert_allclose(floor * 1000, [0.0, 0.0, 3.5, -2.5, 0.0, 0.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(ceiling * 1000, [30.0, 30.0, 30.0, -2.5, 4.0, 6.0, 2.5, 2.0], atol=1e-12)
