"""A garment worn over another of the same depth (cloth/coarse_layers.py): known answers, then two tops."""

import numpy as np
import pytest

from cloth.coarse_layers import (COARSE_DEPTH, CoarseLayerState, carry_with_body, coarse_pair, hold_over,
                                 mesh_distances, same_depth_pairs)
from cloth.layers import layer_outfit
from tests.test_layers import floor, grid, sheet

GAP = 0.003


class _Cloth:
    """The arrays of a ClothState that keep_over reads and writes."""

    def __init__(self, x, normals):
        self.x = np.array(x, dtype=np.float64)
        self.v = np.zeros_like(self.x)
        self.normals = np.array(normals, dtype=np.float64)


def inner_sheet():
    """The inner cloth: a flat grid over x, z in [0.1, 0.3] x [0, 0.2] at y = 0, normals +Y."""
    pi, ti, _ = grid(0.1, 0.3, 0.0)
    return pi, ti


def held(points, normals=None, inv_mass=None, velocity=None):
    """Outer particles at points, kept over the inner sheet: (their positions after, velocities after, moved)."""
    pi, ti = inner_sheet()
    points = np.asarray(points, dtype=np.float64)
    outer = _Cloth(points, np.tile([0.0, 1.0, 0.0], (len(points), 1)) if normals is None else normals)
    if velocity is not None:
        outer.v[:] = velocity
    m = coarse_pair(1, 0, points, pi, ti, GAP, reach=1.0)
    s = CoarseLayerState(m, len(pi))
    s.inner_x[:] = pi
    s.inner_n[:] = [0.0, 1.0, 0.0]
    s.ready[0] = 1
    moved = hold_over(m, s, outer, np.ones(len(points)) if inv_mass is None else inv_mass)
    return outer.x, outer.v, moved


@pytest.mark.parametrize("y", [-0.02, -0.001, 0.0, 0.002])
def test_a_particle_behind_the_inner_cloth_or_nearer_than_the_gap_is_put_the_gap_over_it(y):
    """Over the middle of the sheet, behind it by up to COARSE_DEPTH or in front of it by less
    than the gap: put at exactly y = GAP, straight along the sheet's normal, its velocity into
    the sheet taken out and the rest kept."""
    x, v, moved = held([[0.2, y, 0.1]], velocity=[0.3, -1.0, 0.5])
    assert moved == 1
    np.testing.assert_allclose(x, [[0.2, GAP, 0.1]], atol=1e-15)
    np.testing.assert_allclose(v, [[0.3, 0.0, 0.5]], atol=1e-15)
    x, v, _ = held([[0.2, y, 0.1]], velocity=[0.0, 2.0, 0.0])  # already leaving it: kept
    np.testing.assert_allclose(v, [[0.0, 2.0, 0.0]])


@pytest.mark.parametrize("where, why", [([0.2, GAP + 1e-4, 0.1], "over it by the gap already"),
                                        ([0.2, -COARSE_DEPTH - 1e-3, 0.1], "another sheet, far behind"),
                                        ([0.36, -0.01, 0.1], "beside it, past its edge")])
def test_a_particle_is_left_where_it_is(where, why):
    x, v, moved = held([where], velocity=[0.0, -1.0, 0.0])
    assert moved == 0, why
    np.testing.assert_array_equal(x, [where])
    np.testing.assert_array_equal(v, [[0.0, -1.0, 0.0]])


def test_a_gripped_particle_or_one_turned_away_from_the_inner_cloth_is_not_moved():
    p = [[0.2, -0.01, 0.1], [0.15, -0.01, 0.05]]
    x, _, moved = held(p, inv_mass=np.array([0.0, 1.0]))
    assert moved == 1 and np.array_equal(x[0], p[0]) and x[1, 1] == pytest.approx(GAP)
    x, _, moved = held(p, normals=np.array([[0.0, -1.0, 0.0], [0.0, 1.0, 0.0]]))  # the first: a fold's far side
    assert moved == 1 and np.array_equal(x[0], p[0])


def test_a_tilted_inner_cloth_pushes_along_its_own_normal():
    """The inner sheet turned 30° about z: a particle 1 cm behind it comes out the gap over it along its normal."""
    pi, ti = inner_sheet()
    a = np.radians(30.0)
    rot = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    pi = pi @ rot.T
    n = rot @ [0.0, 1.0, 0.0]
    foot = rot @ [0.2, 0.0, 0.1]
    outer = _Cloth([foot - 0.01 * n], [n])
    m = coarse_pair(1, 0, outer.x, pi, ti, GAP, reach=1.0)
    s = CoarseLayerState(m, len(pi))
    s.inner_x[:] = pi
    s.inner_n[:] = n
    s.ready[0] = 1
    assert hold_over(m, s, outer, np.ones(1)) == 1
    np.testing.assert_allclose(outer.x[0], foot + GAP * n, atol=1e-12)


def test_the_inner_cloth_is_carried_rigidly_with_the_body_as_the_body_following_carries_it():
    """Two particles on one body triangle's relative coordinates (3 cm and 1 cm over it): the
    body turned 90° about y and moved; followed fully (weight 1, or none yet) each is where the
    same coordinates on the moved triangle put it; at weight 0 it stays; at 0.5, half way."""
    body = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]])
    tris = np.array([[0, 1, 2]], dtype=np.int32)
    bary = np.array([[0.5, 0.25, 0.25]] * 4)
    height = np.array([0.03, 0.01, 0.03, 0.03])
    x = bary @ body + height[:, None] * [0.0, 0.0, 1.0]
    rot = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    moved = body @ rot.T + [0.2, 0.1, -0.3]
    n = np.cross(moved[1] - moved[0], moved[2] - moved[0])
    face_n = (n / np.linalg.norm(n))[None, :]
    out = np.zeros((4, 3))
    carry_with_body(x, np.array([1.0, -1.0, 0.0, 0.5]), np.zeros(4, dtype=np.int32), bary, height, moved, tris, face_n,
                    out)
    expected = x @ rot.T + [0.2, 0.1, -0.3]
    np.testing.assert_allclose(out[:2], expected[:2], atol=1e-15)
    np.testing.assert_array_equal(out[2], x[2])
    np.testing.assert_allclose(out[3], 0.5 * (x[3] + expected[3]), atol=1e-15)


def test_distances_to_a_mesh():
    pi, ti = inner_sheet()
    d = mesh_distances(np.array([[0.2, 0.05, 0.1], [0.0, 0.0, 0.1], [0.4, -0.03, 0.24]]), pi, ti)
    np.testing.assert_allclose(d, [0.05, 0.1, np.sqrt(0.1**2 + 0.03**2 + 0.04**2)], atol=1e-12)


def test_garments_at_the_same_depth_are_worn_the_later_over_the_earlier_and_the_layering_agrees():
    """Two sheets 4 mm apart over the same place: worn over one another, the later over the
    earlier, whichever is nearer the body (the detailed layering's pair agrees); a sheet that
    overlaps another over a band (a hem over a waistband) is not."""
    a, b = sheet(0.0, 0.012, "cotton"), sheet(0.0, 0.008, "silk")
    rest = [m.cloth.rest_positions for m in (a, b)]
    tris = [m.cloth.triangles for m in (a, b)]
    pairs = same_depth_pairs(rest, tris, [0.003, 0.002])
    assert [(p.outer, p.inner, p.gap) for p in pairs] == [(1, 0, 0.002)]
    assert min(pairs[0].overlap) > 0.9 and len(pairs[0].candidates) == len(rest[1])
    assert [(m.outer, m.inner) for m in layer_outfit([a, b], floor())] == [(0, 1)]  # farther from the body
    assert [(m.outer, m.inner) for m in layer_outfit([a, b], floor(), {(1, 0)})] == [(1, 0)]
    band = sheet(0.12, 0.010, "denim")  # 2 of either sheet's 5 columns over the other
    assert same_depth_pairs([rest[0], band.cloth.rest_positions], [tris[0], band.cloth.triangles], [0.003] * 2) == []
    # a small garment lying on a larger one (a crop top under a shirt): all of it within the band, a third of the other
    small = sheet(0.04, 0.008, "cotton", nx=3, nz=2)
    pairs = same_depth_pairs([small.cloth.rest_positions, rest[0]], [small.cloth.triangles, tris[0]], [0.003] * 2)
    assert [(p.outer, p.inner) for p in pairs] == [(1, 0)]
    assert pairs[0].overlap[1] == 1.0 and pairs[0].overlap[0] < 0.5


def _behind(outer_x, inner_x, m, depth=0.005):
    """The share of the outer's tested particles more than depth behind the inner's coarse cloth,
    by the closest point over all its triangles (not the walk under test) and that triangle's normal."""
    dist, tri, at = mesh_distances(outer_x[m.candidates], inner_x, m.triangles, closest=True)
    corners = inner_x[m.triangles[tri]]
    n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    h = np.einsum("ij,ij->i", outer_x[m.candidates] - at, n / np.linalg.norm(n, axis=1)[:, None])
    return float(np.mean((h < -depth) & (dist < 0.03)))


def walk_frames(body, data, n: int):
    """The walk at 60 Hz from its frame 1 (the first is the converter's T-pose): (the animator, the
    first frame's configuration, n - 1 frames of skinned body vertices)."""
    from skinning.animate import BodyAnimator
    from skinning.source import BVHSource

    frames = []
    with BVHSource(data / "mocap" / "cmu_131_01_walk_3dsmax.bvh", every=2, max_frames=n) as source:
        animator = BodyAnimator(body, source.skeleton)
        for f in source:
            out = animator(f.local_rot, f.root_position)
            if f.index == 1:
                q0 = out.retarget.q.copy()
            if f.index >= 1:
                frames.append(out.vertices.copy())
    return animator, q0, frames


def test_two_tops_stay_one_over_the_other_through_the_walk_whichever_thread_steps_them(body, data):
    """The silk blouse over the T-shirt, coarse cloths, the walk's first 100 frames at 60 Hz: the
    blouse's particles more than 5 mm behind the T-shirt's cloth are under 2 % on average
    (measured: 0.8 %), where each simulated against the body alone leaves more than three times
    as many (6.8 %). Stepped on two threads, the result is the same bit for bit."""
    from services.cloth_job import OutfitSession, collision_body, find_outfit, load_outfit_models

    animator, q0, frames = walk_frames(body, data, 101)
    mesh = collision_body(body)
    outfit = load_outfit_models(body, animator, mesh, find_outfit(data, "female_casualsuit01.top+"
                                                                        "female_elegantsuit01.top"))
    m = outfit.over[0]
    assert (m.outer, m.inner) == (1, 0)

    def run(threads, worn_over=True):
        session = OutfitSession(body, animator, mesh, outfit, threads=threads)
        if not worn_over:
            session.sims[m.outer].worn_over = []
        session.preroll(q0, 1 / 60, blend_seconds=0.5, settle_seconds=0.25)
        shares, moved = [], 0
        for v in frames:
            session.step_cloth(v, 1 / 60)
            shares.append(_behind(session.sims[1].state.x, session.sims[0].state.x, m))
            moved += session.sims[1].over_moved
        ends = [s.state.x.copy() for s in session.sims]
        session.close()
        return float(np.mean(shares)), ends, moved

    worn, ends, moved = run(1)
    apart, _, none = run(1, worn_over=False)
    assert worn < 0.02 and apart > 3 * worn, (worn, apart)
    assert moved > len(frames) and none == 0  # the pushes are counted (ClothSim.over_moved)
    _, threaded, _ = run(2)
    for a, b in zip(threaded, ends):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("outfit", ["female_casualsuit01.top+female_elegantsuit01.top", "female_elegantsuit01"])
def test_two_tops_layered_on_two_threads_are_the_same_bit_for_bit(body, data, outfit):
    """The two tops, and the elegant outfit's blouse over its skirt, at level 6 (each garment with
    more than SPLIT_CANDIDATES vertices to layer: on two threads the helper measures half of each):
    a few walk frames stepped on one thread and on two give the same coarse cloths and the same
    layered detailed surfaces, bit for bit."""
    from cloth.layers import SPLIT_CANDIDATES
    from cloth.surface import SurfaceSettings
    from services.cloth_job import OutfitSession, build_outfit, collision_body, find_outfit

    animator, q0, frames = walk_frames(body, data, 6)
    mesh = collision_body(body)
    outfit, surfaces, layers = build_outfit(body, animator, mesh,
                                            find_outfit(data, outfit), surface=SurfaceSettings())
    assert min(len(layers[0].over.candidates), len(layers[0].under.candidates)) >= SPLIT_CANDIDATES

    def run(threads):
        session = OutfitSession(body, animator, mesh, outfit, surface_models=surfaces, layers=layers, threads=threads)
        assert session._split_layers
        session.preroll(q0, 1 / 60, blend_seconds=0.1, settle_seconds=0.1)
        for v in frames:
            session.step_cloth(v, 1 / 60)
        got = [s.state.x.copy() for s in session.sims] + [a.copy() for p, n in session.detailed for a in (p, n)]
        session.close()
        return got

    for a, b in zip(run(1), run(2)):
        np.testing.assert_array_equal(a, b)
