"""SPEC.md S104 and S106 formulas, kernel by kernel, on cases worked out by hand: the transfer
rates and the force interpolation along a bent chain, the three-direction average inside a
face, the normal force, ΔL_expected's sign rule with Δh_length and its clamp, the blended
shading normals, and the folds carried across the compression (Decision): to a lone triangle's
opposite corner, straight across a quad."""

import numpy as np
import pytest

from cloth.pn import build_tessellation
from cloth.topology import triangulate, unique_edges, vertex_cells
from cloth.wrinkles import (UNTESTED, deformation_heights, elastic_forces, fold_across, fold_lines, fold_quads,
                            normal_force, penetration_floor, quad_lattice, shading_normals)


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
    height 2, never under the floor 0).
    The body floor (cloth.layers' press), untested reach 4 mm: untested at 0, -4; body below at
    4 mm with height 2, 2 - 3 = -1 (below the reference surface); at 2.5 mm with height 5, 3.5;
    body above: its floor."""
    inf = UNTESTED
    dh = np.array([0.0, 2.0, 5.0, -3.0, 1.0, 2.0, 2.0, 2.0]) / 1000
    sd = np.array([inf, 4.0, 2.5, 1.5, 4.0, 4.0, 4.0, 4.0]) / 1000
    facing = np.array([0.0, 1.0, 0.9, -1.0, -0.8, 1.0, 1.0, 1.0])
    other = np.array([inf, inf, inf, inf, inf, 6.0, 1.5, 0.5]) / 1000
    dh_pen = np.array([0.0, 0.0, 0.0, -3.0, 0.0, 1.0, 0.0, 0.0]) / 1000
    floor, ceiling, body_floor = np.full(8, np.nan), np.full(8, np.nan), np.full(8, np.nan)
    penetration_floor(dh, sd, facing, other, dh_pen, 0.001, 0.004, 0.03, floor, ceiling, body_floor)
    np.testing.assert_allclose(floor * 1000, [0.0, 0.0, 3.5, -2.5, 0.0, 0.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(body_floor * 1000, [-4.0, -1.0, 3.5, -2.5, 0.0, -1.0, -1.0, -1.0], atol=1e-12)
    np.testing.assert_allclose(ceiling * 1000, [30.0, 30.0, 30.0, -2.5, 4.0, 6.0, 2.5, 2.0], atol=1e-12)


def lattice_index(t, b, c):
    return int(np.flatnonzero((t.lattice[:, 0] == b) & (t.lattice[:, 1] == c))[0])


def test_fold_lines_run_from_each_edge_to_the_opposite_corner():
    """Level 6: the point (a, b, c) = (2, 2, 2) is 2 steps from each edge, on the line from
    each opposite corner through the edge's middle (3 of 6), taper 1 - 2/6. (4, 1, 1) is 1 step
    from AB, on the line from C through b' = 6 * 1/5 = 1.2; from CA (depth b = 1) through
    c' = 6 * 1/5 = 1.2 too. Points on the coarse edges take no fold."""
    L = 6
    t = build_tessellation(np.array([[0, 1, 2]], dtype=np.int32), 3, L)
    src, weight = fold_lines(t.lattice, L)
    centre = lattice_index(t, 2, 2)
    for s, (first, second) in enumerate((((3, 0), (4, 0)), ((3, 3), (2, 4)), ((0, 3), (0, 4)))):
        assert tuple(src[s, centre]) == (lattice_index(t, *first), lattice_index(t, *second))
        np.testing.assert_allclose(weight[s, centre], (0.0, 2.0 / 3.0), atol=1e-12)
    k = lattice_index(t, 1, 1)
    assert tuple(src[0, k]) == (lattice_index(t, 1, 0), lattice_index(t, 2, 0))
    np.testing.assert_allclose(weight[0, k], (0.2, 5.0 / 6.0), atol=1e-12)
    assert tuple(src[2, k]) == (lattice_index(t, 0, 1), lattice_index(t, 0, 2))
    np.testing.assert_allclose(weight[2, k], (0.2, 5.0 / 6.0), atol=1e-12)
    b, c = t.lattice.T
    on_edges = (b == 0) | (c == 0) | (b + c == L)  # the coarse edges' particles: S106's alone
    assert np.all(weight[:, on_edges, 1] == 0.0) and np.all(weight[:, ~on_edges, 1] > 0.0)


def run_fold(t, dh, required, floor=None, ceiling=None, max_height=0.03, d_max=1.0, faces=None, p_smoothed=None):
    """fold_across on tessellation t (its coarse triangles lone, or halves of the quads in
    faces); the reference surface flat in XZ (or p_smoothed), the heights along +Y."""
    N = t.n_vertices
    if p_smoothed is None:
        p_smoothed = np.zeros((N, 3))
        p_smoothed[:, [0, 2]] = t.owner_weights[:, 1:]  # any surface: the heights are along +Y
    n_pn = np.tile([0.0, 1.0, 0.0], (N, 1))
    floor = np.zeros(N) if floor is None else floor
    ceiling = np.full(N, max_height) if ceiling is None else ceiling
    faces = np.full((0, 4), -1, dtype=np.int32) if faces is None else faces
    src, weight = fold_lines(t.lattice, t.level)
    groups, corner, quad_edges, flip = fold_quads(t.coarse_triangles, faces, t.coarse_edges)
    points, rs = quad_lattice(t.lattice, t.level)
    height = np.full(N, np.nan)
    p = p_smoothed + dh[:, None] * n_pn
    d_max = np.full(len(t.detail_edges), d_max)  # 1 m: no neighbour limit on this unit face
    start, ids = vertex_cells(N, t.detail_edges)
    fold_across(p_smoothed, n_pn, dh, floor, ceiling, t.face_ids, t.face_edges, t.edge_ids, np.asarray(required, float),
                t.interior_local, src, weight, groups, corner, quad_edges, flip, points, rs, t.detail_edges, d_max,
                start, ids, 0.0, np.zeros(t.edge_ids.shape), np.zeros(len(t.edge_ids)),
                np.zeros((2, 2 * len(t.lattice)), np.int32), height, p)
    np.testing.assert_allclose(p, p_smoothed + height[:, None] * n_pn, atol=1e-15)
    return height


def test_fold_across_carries_a_wrinkle_towards_the_opposite_corner():
    """A 6 mm wrinkle in the middle of the compressed edge AB (level 6, particles b = 2, 3, 4 at
    3, 6, 3 mm; corner B at 2 mm): the face's interior points on the line from C through the
    peak rise by 6 mm times the taper 1 - c/6, the others by the interpolated height times the
    taper; the particles on the coarse edges keep their heights. AB stretched and the other
    two compressed, with no wrinkles of their own: no fold."""
    L = 6
    t = build_tessellation(np.array([[0, 1, 2]], dtype=np.int32), 3, L)
    dh = np.zeros(t.n_vertices)
    ab = {b: t.face_ids[0, lattice_index(t, b, 0)] for b in range(L + 1)}
    dh[ab[2]], dh[ab[3]], dh[ab[4]] = 0.003, 0.006, 0.003
    dh[ab[L]] = 0.002  # corner B carries a height: edge BC, on the lines from A through B, takes none
    height = run_fold(t, dh, [1e-3, -1e-3, -1e-3])  # face_edges: AB, BC, CA
    for c in range(1, L):
        for b in range(1, L - c):  # the interior
            u = L * b / (L - c)  # where the line from C through (b, c) meets AB
            profile = np.interp(u, np.arange(L + 1), dh[[ab[m] for m in range(L + 1)]])
            expected = (1.0 - c / L) * profile
            assert height[t.face_ids[0, lattice_index(t, b, c)]] == pytest.approx(expected, abs=1e-15), (b, c)
    on_edges = t.edge_ids.ravel()
    np.testing.assert_array_equal(height[on_edges], dh[on_edges])
    assert height[t.face_ids[0, lattice_index(t, 2, 2)]] == pytest.approx(0.004, abs=1e-15)  # (1 - 2/6) 6 mm
    np.testing.assert_array_equal(run_fold(t, dh, [-1e-3, 1e-3, 1e-3]), dh)


def test_fold_across_keeps_higher_particles_and_the_ceiling_and_counts_from_the_floor():
    """A fold never lowers a particle (one already at 9 mm stays), stops at a particle's
    ceiling (a body part 1 mm above it), and carries the wrinkle above the edge's floors: an edge
    lifted 2 mm out of the body everywhere (floor 2 mm) with a 5 mm peak carries 3 mm, added
    to the interior particle's own floor."""
    L = 6
    t = build_tessellation(np.array([[0, 1, 2]], dtype=np.int32), 3, L)
    N = t.n_vertices
    ab = [t.face_ids[0, lattice_index(t, b, 0)] for b in range(L + 1)]
    floor = np.zeros(N)
    floor[ab] = 0.002
    dh = floor.copy()
    dh[ab[3]] = 0.005
    centre, below = t.face_ids[0, lattice_index(t, 3, 1)], t.face_ids[0, lattice_index(t, 2, 2)]
    high, capped = t.face_ids[0, lattice_index(t, 2, 1)], t.face_ids[0, lattice_index(t, 1, 4)]
    floor[centre] = 0.001
    dh[centre] = 0.001
    dh[high] = 0.009
    ceiling = np.full(N, 0.03)
    ceiling[capped] = 0.0005
    height = run_fold(t, dh, [1e-3, -1e-3, -1e-3], floor, ceiling)
    # (3, 1): 1 step from AB, on the line through b' = 6 * 3/5 = 3.6: 0.4 of the 3 mm peak, taper 5/6
    assert height[centre] == pytest.approx(0.001 + 5.0 / 6.0 * 0.4 * 0.003, abs=1e-15)
    assert height[below] == pytest.approx(2.0 / 3.0 * 0.003, abs=1e-15)  # through b' = 3, taper 4/6
    assert height[high] == 0.009  # the fold would give it (5/6) 0.4 3 mm = 1 mm
    assert height[capped] == 0.0005  # through b' = 3 too: (2/6) 3 mm = 1 mm without the ceiling


def test_fold_across_keeps_neighbours_as_close_in_height_as_the_edge_does():
    """Random wrinkle profiles on all three compressed edges of a face: no two neighbouring
    particles differ in drawn height by more than the largest step between neighbours along an
    edge (the taper shrinks a row's heights as much as the row's points spread along the edge)."""
    L = 6
    t = build_tessellation(np.array([[0, 1, 2]], dtype=np.int32), 3, L)
    rng = np.random.default_rng(7)
    for _ in range(20):
        dh = np.zeros(t.n_vertices)
        inner = t.edge_ids[:, 1:-1].ravel()
        dh[inner] = rng.uniform(0.0, 0.01, inner.size)
        height = run_fold(t, dh, [1e-3, 1e-3, 1e-3])
        edge_step = np.abs(np.diff(dh[t.edge_ids], axis=1)).max()
        steps = np.abs(height[t.detail_edges[:, 0]] - height[t.detail_edges[:, 1]])
        assert steps.max() <= edge_step * (1 + 1e-9)
        assert np.all(height >= dh)


def test_fold_across_takes_a_fold_off_where_it_parts_neighbours_beyond_the_limit():
    """On the unit face at level 6 (lattice spacing 1/6 m, its diagonals 0.24 m), wrinkles
    0.15 m high on the edges and two interior particles raised 0.3 m by S106 (scaled up so that
    heights matter against the spacing), neighbour limit 0.3 m: without the limit some folds
    part a raised particle from a neighbour farther than that; with it no edge with a raised
    end is too long, a particle is either at its fold or back at its Δh, and some folds stay."""
    L = 6
    t = build_tessellation(np.array([[0, 1, 2]], dtype=np.int32), 3, L)
    dh = np.zeros(t.n_vertices)
    dh[t.edge_ids[:, 2:-1:2].ravel()] = 0.15
    dh[np.random.default_rng(0).choice(t.face_ids[0, t.interior_local], 2, replace=False)] = 0.3
    e0, e1 = t.detail_edges.T

    def raised_too_long(h):
        ps = np.zeros((t.n_vertices, 3))
        ps[:, [0, 2]] = t.owner_weights[:, 1:]
        ps[:, 1] = h
        long = np.linalg.norm(ps[e0] - ps[e1], axis=1) > 0.3 + 1e-12
        return np.sum(long & ((h[e0] > dh[e0]) | (h[e1] > dh[e1])))

    free = run_fold(t, dh, [1, 1, 1], max_height=1.0)
    assert raised_too_long(free) > 0
    limited = run_fold(t, dh, [1, 1, 1], max_height=1.0, d_max=0.3)
    assert raised_too_long(limited) == 0
    assert np.all((limited == free) | (limited == dh)) and np.any(limited > dh)


UNIT_SQUARE = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 1.0], [0.0, 0.0, 1.0]])  # A, B, C, D in XZ


def unit_quad(level, first=0):
    """The quad ABCD on the unit square (u along X, v along Z), written from corner `first` so
    that the split (along the shorter diagonal, here the first one written) is AC for first 0
    and BD for first 1; its tessellation, the detailed vertices' (u, v) and the faces."""
    faces = np.roll(np.arange(4, dtype=np.int32), -first)[None, :]
    tris, _ = triangulate(faces, UNIT_SQUARE)
    t = build_tessellation(tris, 4, level)
    corners = UNIT_SQUARE[t.coarse_triangles[t.owner_face]]  # (N, 3, 3)
    p = np.einsum("nk,nkd->nd", t.owner_weights, corners)
    return t, p, faces


def coarse_edge(t, i, j):
    return int(np.flatnonzero((t.coarse_edges[:, 0] == min(i, j)) & (t.coarse_edges[:, 1] == max(i, j)))[0])


def edge_profile(t, i, j, heights):
    """dh with `heights` (L + 1) along the coarse edge from vertex i to vertex j."""
    e = coarse_edge(t, i, j)
    ids = t.edge_ids[e] if i < j else t.edge_ids[e][::-1]
    return ids, np.asarray(heights, float)


def test_fold_quads_finds_each_quads_halves_and_their_frames():
    """A quad ABCD (0-3) split along AC and a lone triangle B E C: the quad's halves are drawn
    together, each with its corner off the diagonal (B in ABC, D in ACD) and its four edges in
    the frame O, N, P, O': for ABC, O = B, N = C, P = A, O' = D, so e0 = BA, e1 = CD, e2 = BC,
    e3 = AD and the diagonal e4 = CA, with the parameter running from B, C, B, A and C."""
    faces = np.array([[0, 1, 2, 3], [1, 4, 2, -1]], dtype=np.int32)
    tris = np.array([[0, 1, 2], [0, 2, 3], [1, 4, 2]], dtype=np.int32)
    edges, _ = unique_edges(tris)
    groups, corner, quad_edges, flip = fold_quads(tris, faces, edges)
    np.testing.assert_array_equal(groups, [[0, 1], [2, -1]])
    np.testing.assert_array_equal(corner, [1, 2, -1])
    def index(i, j):
        return int(np.flatnonzero((edges[:, 0] == min(i, j)) & (edges[:, 1] == max(i, j)))[0])
    np.testing.assert_array_equal(quad_edges[0], [index(1, 0), index(2, 3), index(1, 2), index(0, 3), index(2, 0)])
    np.testing.assert_array_equal(flip[0], [1, 0, 0, 0, 1])
    # ACD: O = D, N = A, P = C, O' = B: e0 = DC, e1 = AB, e2 = DA, e3 = CB, e4 = AC
    np.testing.assert_array_equal(quad_edges[1], [index(3, 2), index(0, 1), index(3, 0), index(2, 1), index(0, 2)])
    np.testing.assert_array_equal(flip[1], [1, 0, 1, 1, 0])
    assert np.all(quad_edges[2] == -1)


@pytest.mark.parametrize("first", [0, 1])
def test_a_fold_runs_straight_across_a_quad_blending_its_two_edges(first):
    """Level 6, wrinkles on the quad's compressed edges AB (v = 0) and DC (v = 1), none on the
    others or the diagonal: every particle off the quad's outer edges, the diagonal's included,
    is drawn at (1 - v) W_AB(u) + v W_DC(u), whichever diagonal splits the quad; AB alone
    compressed, the fold tapers to nothing at DC; the outer edges keep their heights."""
    L = 6
    t, uv, faces = unit_quad(L, first)
    u, v = uv[:, 0], uv[:, 2]
    rng = np.random.default_rng(first)
    w_ab, w_dc = np.zeros(L + 1), np.zeros(L + 1)
    w_ab[1:L] = rng.uniform(0.0, 0.008, L - 1)
    w_dc[1:L] = rng.uniform(0.0, 0.008, L - 1)
    dh = np.zeros(t.n_vertices)
    ab, _ = edge_profile(t, 0, 1, w_ab)
    dc, _ = edge_profile(t, 3, 2, w_dc)
    dh[ab], dh[dc] = w_ab, w_dc
    required = np.full(len(t.coarse_edges), -1e-3)
    inside = (u > 1e-9) & (u < 1 - 1e-9) & (v > 1e-9) & (v < 1 - 1e-9)
    m = np.rint(u * L).astype(int)
    for both in (True, False):
        required[coarse_edge(t, 0, 1)] = 1e-3
        required[coarse_edge(t, 3, 2)] = 1e-3 if both else -1e-3
        height = run_fold(t, dh, required, faces=faces, p_smoothed=uv)
        expected = (1 - v) * w_ab[m] + (v * w_dc[m] if both else 0.0)
        np.testing.assert_allclose(height[inside], expected[inside], atol=1e-15)
        np.testing.assert_array_equal(height[~inside], dh[~inside])
    # a ridge from AB's peak to DC's at the same place runs straight across at the peaks' heights
    assert np.sum(inside & (m == 3)) == L - 1


def test_crossing_folds_in_a_quad_draw_the_higher():
    """AB (v = 0) and BC (u = 1) compressed: (u, v) drawn at the larger of (1 - v) W_AB(u) and
    u W_BC(v). A compressed diagonal adds its own fold across it, and its particles keep their
    heights (its arc length is S105's measure)."""
    L = 6
    t, uv, faces = unit_quad(L)
    u, v = uv[:, 0], uv[:, 2]
    w = 0.001 * np.array([0, 2, 5, 6, 5, 2, 0], float)
    dh = np.zeros(t.n_vertices)
    ab, _ = edge_profile(t, 0, 1, w)
    bc, _ = edge_profile(t, 1, 2, w[::-1] * 0.5)
    dh[ab], dh[bc] = w, w[::-1] * 0.5
    required = np.full(len(t.coarse_edges), -1e-3)
    required[[coarse_edge(t, 0, 1), coarse_edge(t, 1, 2)]] = 1e-3
    height = run_fold(t, dh, required, faces=faces, p_smoothed=uv)
    inside = (u > 1e-9) & (u < 1 - 1e-9) & (v > 1e-9) & (v < 1 - 1e-9)
    mu, mv = np.rint(u * L).astype(int), np.rint(v * L).astype(int)
    expected = np.maximum((1 - v) * w[mu], u * 0.5 * w[::-1][mv])
    np.testing.assert_allclose(height[inside], expected[inside], atol=1e-15)
    diagonal = coarse_edge(t, 0, 2)
    dh[t.edge_ids[diagonal, 3]] = 0.02  # a tall wrinkle in the middle of AC, compressed
    required[diagonal] = 1e-3
    height = run_fold(t, dh, required, faces=faces, p_smoothed=uv)
    centre_b = t.face_ids[0, np.flatnonzero((t.lattice[:, 0] == 2) & (t.lattice[:, 1] == 2))[0]]
    assert height[centre_b] == pytest.approx(max(2 / 3 * 0.02, expected[centre_b]), abs=1e-15)
    np.testing.assert_array_equal(height[t.edge_ids[diagonal]], dh[t.edge_ids[diagonal]])
    assert np.any(expected[t.edge_ids[diagonal]] > dh[t.edge_ids[diagonal]])  # a stretched one would rise


def test_folds_across_a_quad_keep_neighbour_steps_within_one_and_a_half_edge_steps():
    """Random wrinkles (zero at the corners) on all four compressed outer edges of a quad: a step
    along a row blends the two edges' steps; one across the rows moves the blend by a wrinkle's
    height over L, and a wrinkle is at most L/2 edge steps high (it starts from zero at the
    corners), so half a step; along the lattice's diagonal the two add up. No two neighbours
    differ by more than 1.5 times the largest step along an edge (the larger of two folds
    keeps that bound)."""
    L = 6
    t, uv, faces = unit_quad(L)
    rng = np.random.default_rng(3)
    outer = [coarse_edge(t, i, (i + 1) % 4) for i in range(4)]
    required = np.full(len(t.coarse_edges), -1e-3)
    required[outer] = 1e-3
    worst = 0.0
    for _ in range(50):
        dh = np.zeros(t.n_vertices)
        inner = t.edge_ids[outer, 1:-1].ravel()
        dh[inner] = rng.uniform(0.0, 0.01, inner.size)
        height = run_fold(t, dh, required, faces=faces, p_smoothed=uv)
        edge_step = np.abs(np.diff(dh[t.edge_ids[outer]], axis=1)).max()
        steps = np.abs(height[t.detail_edges[:, 0]] - height[t.detail_edges[:, 1]])
        worst = max(worst, steps.max() / edge_step)
        assert np.all(height >= dh)
    assert worst <= 1.5 + 1e-9


def test_a_fold_across_a_quad_is_taken_off_where_it_parts_neighbours_beyond_the_limit():
    """The unit quad at level 6 (spacing 1/6 m), its outer edges compressed: a smooth 0.3 m
    wrinkle on AB and 0.4 m spikes at every other particle of BC; neighbour limit 0.3 m. Without
    the limit the spikes' folds rise beside lower particles (the diagonal's among the raised),
    farther than that; with it no raised particle is, each is at its fold or back at its Δh, and
    the smooth fold stays, on the diagonal too."""
    L = 6
    t, uv, faces = unit_quad(L)
    dh = np.zeros(t.n_vertices)
    dh[t.edge_ids[coarse_edge(t, 0, 1)]] = 0.1 * np.array([0, 1, 2, 3, 2, 1, 0])
    dh[t.edge_ids[coarse_edge(t, 1, 2), 1::2]] = 0.4
    diagonal = t.edge_ids[coarse_edge(t, 0, 2)]
    e0, e1 = t.detail_edges.T

    def raised_too_long(h):
        ps = uv.copy()
        ps[:, 1] = h
        long = np.linalg.norm(ps[e0] - ps[e1], axis=1) > 0.3 + 1e-12
        return np.sum(long & ((h[e0] > dh[e0]) | (h[e1] > dh[e1])))

    required = np.ones(len(t.coarse_edges))
    required[coarse_edge(t, 0, 2)] = -1.0  # the diagonal stretched: its particles are drawn too
    free = run_fold(t, dh, required, max_height=1.0, faces=faces, p_smoothed=uv)
    assert raised_too_long(free) > 0
    limited = run_fold(t, dh, required, max_height=1.0, d_max=0.3, faces=faces, p_smoothed=uv)
    assert raised_too_long(limited) == 0
    assert np.all((limited == free) | (limited == dh))
    assert 0 < np.sum(limited > dh) < np.sum(free > dh) and np.any(limited[diagonal] > dh[diagonal])


def test_a_compressed_diagonal_folds_parallel_to_the_other_diagonal():
    """A 20 mm wrinkle on the quad's compressed diagonal AC, 2 steps from C (level 6), nothing
    else: in ABC (O = B, N = C, P = A) the line through (r, s) = (1, 3) parallel to BD meets AC
    at t = (1 - 3 + 6) / 2 = 2 steps from C, 1 step (of 2) from it towards AB or BC: half the
    wrinkle, 10 mm (the corner rule would have drawn it from t = 1.5, towards B). (1, 2) meets
    AC halfway between the particles 2 and 3 from C (10 mm), 1.5 of 2.5 steps from it: 4 mm.
    The same in ACD by symmetry; the diagonal's and the outer edges' particles keep theirs."""
    L = 6
    t, uv, faces = unit_quad(L)
    diagonal = coarse_edge(t, 0, 2)
    dh = np.zeros(t.n_vertices)
    dh[t.edge_ids[diagonal, L - 2]] = 0.02  # edge_ids run from A (0) to C (2)
    required = np.full(len(t.coarse_edges), -1e-3)
    required[diagonal] = 1e-3
    height = run_fold(t, dh, required, faces=faces, p_smoothed=uv)

    def at(face, weights):  # the detailed vertex of a face at lattice weights of its corners 0, 1, 2
        k = np.flatnonzero((t.lattice[:, 0] == weights[1]) & (t.lattice[:, 1] == weights[2]))[0]
        return t.face_ids[face, k]

    assert tuple(t.coarse_triangles[0]) == (0, 1, 2) and tuple(t.coarse_triangles[1]) == (0, 2, 3)
    # ABC: weights (A, B, C) = (r, L - r - s, s); ACD: O = D, N = A, P = C, weights (A, C, D) = (s, r, L - r - s)
    assert height[at(0, (1, 2, 3))] == pytest.approx(0.01, abs=1e-15)
    assert height[at(0, (1, 3, 2))] == pytest.approx(0.004, abs=1e-15)
    # in ACD, C is P: t counts from A, so the wrinkle is at t = 4; (r, s) = (3, 1) meets it: r - s + 6 = 8
    assert height[at(1, (1, 3, 2))] == pytest.approx(0.01, abs=1e-15)
    np.testing.assert_array_equal(height[t.edge_ids.ravel()], dh[t.edge_ids.ravel()])
    assert np.all(height >= dh) and np.count_nonzero(height > dh) > 4
