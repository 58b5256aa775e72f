"""Garments worn over one another (cloth/layers.py, the layering Decision) on cases whose answers are known."""

from types import SimpleNamespace

import numpy as np
import pytest

from cloth.coarsen import CoarseMesh
from cloth.fabric import fabric
from cloth.garment import Garment
from cloth.geometry import closest_in_fan, closest_point_triangle, ray_triangle
from cloth.layers import (CROSS_REACH, LAYER_BAND, LAYER_DEPTH, LAYER_GAP, LAYER_SLOPE, LEAN, LayerState,
                          ease_lifts, keep_within_bounds, layer_outfit, layer_pair, rest_surface, sheet_track,
                          stack_layer)
from cloth.model import SimSettings, build_cloth_model
from cloth.surface import SurfaceSettings, build_surface_model
from cloth.topology import unique_edges
from tests.test_surface import grid_sheet

H = 0.01  # m: the grids' spacing


def grid(x0: float, x1: float, y: float, z1: float = 0.2):
    """A triangulated flat grid over [x0, x1] × [0, z1] at height y, spacing H: (vertices,
    triangles, edges), its normals +Y."""
    nx, nz = int(round((x1 - x0) / H)) + 1, int(round(z1 / H)) + 1
    xs, zs = np.meshgrid(x0 + np.arange(nx) * H, np.arange(nz) * H, indexing="ij")
    v = np.stack([xs.ravel(), np.full(xs.size, y), zs.ravel()], axis=1)
    vid = np.arange(nx * nz).reshape(nx, nz)
    tris = []
    for i in range(nx - 1):
        for k in range(nz - 1):
            a, b, c, d = vid[i, k], vid[i, k + 1], vid[i + 1, k + 1], vid[i + 1, k]
            tris += [(a, b, c), (a, c, d)]
    tris = np.array(tris, dtype=np.int32)
    return v, tris, unique_edges(tris)[0]


def up(n: int) -> np.ndarray:
    return np.tile([0.0, 1.0, 0.0], (n, 1))


def outer_and_inner(inner_y: float, outer_y: float = 0.0):
    """An outer sheet over x in [0, 0.4] at outer_y and an inner one over [0.1, 0.3] at inner_y."""
    po, to, eo = grid(0.0, 0.4, outer_y)
    pi, ti, ei = grid(0.1, 0.3, inner_y)
    return po, eo, pi, ti, ei, layer_pair(0, 1, po, to, eo, pi, ti, ei)


def test_ray_triangle_meets_a_triangle_where_the_line_crosses_it():
    """The triangle (0,0,0), (1,0,0), (0,0,1) in the plane y = 0: the line up through (0.25, ., 0.5)
    from 2 m below meets it at t = 2 with weights 0.25 (corner b) and 0.5 (corner c); from above,
    going up, at t = -3 (a line, not a half line); through (0.8, ., 0.8) (past the long edge) or along
    the plane, nowhere."""
    x = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(ray_triangle(0.25, -2.0, 0.5, 0.0, 1.0, 0.0, x, 0, 1, 2), (2.0, 0.25, 0.5), atol=1e-15)
    assert ray_triangle(0.25, 3.0, 0.5, 0.0, 1.0, 0.0, x, 0, 1, 2)[0] == pytest.approx(-3.0)
    assert ray_triangle(0.8, -2.0, 0.8, 0.0, 1.0, 0.0, x, 0, 1, 2)[0] == np.inf
    assert ray_triangle(-1.0, 0.0, 0.2, 1.0, 0.0, 0.0, x, 0, 1, 2)[0] == np.inf


def test_an_outer_sheet_behind_the_inner_one_is_brought_over_it_and_eases_off_beyond_its_edge():
    """The inner sheet 4 mm above the outer one (its wrinkles poking through): over the inner
    sheet the outer comes to exactly LAYER_GAP above it; beyond the inner's edge the lift falls
    off by LAYER_SLOPE along the outer sheet (one 1 cm step: 6 - 5 = 1 mm; two: none), and
    nothing of it comes down. The inner sheet stays, but for its two edges across x: there the
    outer slopes down within the gap of them, and they come down less than a millimetre."""
    po, eo, pi, ti, ei, m = outer_and_inner(0.004)
    p, q = po.copy(), pi.copy()
    s = LayerState(m)
    stack_layer(m, s, p, up(len(p)), q, up(len(q)))
    x = po[:, 0]
    over = (x > 0.1 - 1e-9) & (x < 0.3 + 1e-9)
    np.testing.assert_allclose(p[over, 1], 0.004 + LAYER_GAP, atol=1e-12)
    one_out = np.isclose(x, 0.09) | np.isclose(x, 0.31)
    np.testing.assert_allclose(p[one_out, 1], 0.004 + LAYER_GAP - LAYER_SLOPE * H, atol=1e-12)
    far = (x < 0.08 + 1e-9) | (x > 0.32 - 1e-9)
    assert np.all(p[far, 1] == 0.0)
    np.testing.assert_array_equal(p[:, [0, 2]], po[:, [0, 2]])  # along the normals only
    assert s.lift.moved == int(over.sum())
    rim = np.isclose(pi[:, 0], 0.1) | np.isclose(pi[:, 0], 0.3)
    assert np.all(q[~rim] == pi[~rim]) and np.all((q[rim, 1] < 0.004) & (q[rim, 1] > 0.003))
    assert s.press.moved == int(rim.sum())


@pytest.mark.parametrize("outer_y, lifted_to", [(0.005, 0.004 + LAYER_GAP), (0.0061, None), (0.01, None)])
def test_an_outer_sheet_over_the_inner_one_is_lifted_only_if_nearer_than_the_gap(outer_y, lifted_to):
    po, eo, pi, ti, ei, m = outer_and_inner(0.004, outer_y)
    p = po.copy()
    stack_layer(m, LayerState(m), p, up(len(p)), pi, up(len(pi)))
    if lifted_to is None:
        np.testing.assert_array_equal(p, po)
    else:
        over = (po[:, 0] > 0.1 - 1e-9) & (po[:, 0] < 0.3 + 1e-9)
        np.testing.assert_allclose(p[over, 1], lifted_to, atol=1e-12)


def test_an_outer_sheet_behind_the_inner_one_beyond_the_depth_is_lifted_only_along_its_normal_within_reach():
    """The inner sheet 12 mm over the outer one, beyond LAYER_DEPTH: by its closest points alone
    (cross_reach 0, the rule until the eighty-fourth session) the outer is another sheet, left.
    The ray along each outer vertex's normal crosses the inner sheet from behind 12 mm up, within
    CROSS_REACH: the outer comes to LAYER_GAP over it (cos 1: 14 mm). An inner sheet farther up
    than CROSS_REACH, or an outer sheet turned over (its normals away from the inner's), is left."""
    po, eo, pi, ti, ei, m = outer_and_inner(LAYER_DEPTH + 0.002)
    m.cross_reach = 0.0
    p = po.copy()
    stack_layer(m, LayerState(m), p, up(len(p)), pi, up(len(pi)))
    np.testing.assert_array_equal(p, po)
    po, eo, pi, ti, ei, m = outer_and_inner(LAYER_DEPTH + 0.002)
    assert m.cross_reach == CROSS_REACH
    p = po.copy()
    stack_layer(m, LayerState(m), p, up(len(p)), pi, up(len(pi)))
    over = (po[:, 0] > 0.1 - 1e-9) & (po[:, 0] < 0.3 + 1e-9)
    np.testing.assert_allclose(p[over, 1], LAYER_DEPTH + 0.002 + LAYER_GAP, atol=1e-12)
    np.testing.assert_array_equal(p[:, [0, 2]], po[:, [0, 2]])
    for inner_y, normals in ((CROSS_REACH + 0.002, up), (0.004, lambda k: -up(k))):
        po, eo, pi, ti, ei, m = outer_and_inner(inner_y)
        p = po.copy()
        stack_layer(m, LayerState(m), p, normals(len(p)), pi, up(len(pi)))
        np.testing.assert_array_equal(p, po)


@pytest.mark.parametrize("degrees", [40.0, 60.0])
def test_an_outer_sheet_leaning_against_the_inner_one_comes_over_its_tangent_plane(degrees):
    """The outer sheet's normals lean 40° off the inner's (a top's hem over a skirt bulging in a
    stride), its vertices 4 mm behind the inner sheet: each rises along its own normal until it
    is exactly LAYER_GAP over the inner's plane, s = (gap + 4 mm) / cos 40°. Before, the line
    along its normal passing farther than the gap from its closest inner point read as past the
    inner's edge, and the inner showed through. Leaning 60°, beyond 45°, each rises as far as
    it would leaning 45° (cos taken as LEAN): short of the gap, not twice the distance."""
    po, eo, pi, ti, ei, m = outer_and_inner(0.004)
    lean = np.radians(degrees)
    normals = np.tile([np.sin(lean), np.cos(lean), 0.0], (len(po), 1))
    p = po.copy()
    stack_layer(m, LayerState(m), p, normals, pi, up(len(pi)))
    x = po[:, 0]
    inside = (x > 0.12 - 1e-9) & (x < 0.24 + 1e-9)  # their lifts land over the inner sheet
    lift = (0.004 + LAYER_GAP) / max(np.cos(lean), LEAN)
    np.testing.assert_allclose(p[inside] - po[inside], lift * normals[inside], atol=1e-12)
    if np.cos(lean) >= LEAN:
        np.testing.assert_allclose(p[inside, 1], 0.004 + LAYER_GAP, atol=1e-12)
    else:  # 6 mm / 0.7 along a normal 60° off: 4.29 mm up, over the inner sheet but short of the gap
        assert np.all((p[inside, 1] > 0.004) & (p[inside, 1] < 0.004 + LAYER_GAP))


def test_the_lift_follows_the_inner_sheet_as_it_slides_and_keeps_out_of_a_body_above():
    """The inner sheet slides 3 cm along x over three frames: each outer vertex's nearest inner
    vertex is tracked by the walk, and the lifted band moves with it. Where S103 left an outer
    vertex a ceiling 1 mm above its height (a body part above it), it rises 1 mm only."""
    po, eo, pi, ti, ei, m = outer_and_inner(0.004)
    s = LayerState(m)
    for shift in (0.01, 0.02, 0.03):
        p = po.copy()
        moved = pi + [shift, 0.0, 0.0]
        stack_layer(m, s, p, up(len(p)), moved, up(len(pi)))
    x = po[:, 0]
    over = (x > 0.13 - 1e-9) & (x < 0.32 + 1e-9)  # (0.33 is beyond LAYER_REACH of the rest sheet)
    np.testing.assert_allclose(p[over, 1], 0.004 + LAYER_GAP, atol=1e-12)
    assert np.all(p[x < 0.11 + 1e-9, 1] == 0.0)
    # a body part 1 mm above some of the outer vertices (their S106 ceiling), none near the rest
    max_height = 0.03
    ceiling = np.full(len(po), max_height)
    held = over & (po[:, 2] < 0.05)
    ceiling[held] = 0.001
    state = SimpleNamespace(height=np.zeros(len(po)), ceiling=ceiling, facing=np.where(held, -1.0, 1.0),
                            n_pn=up(len(po)))
    p = po.copy()
    stack_layer(m, s, p, up(len(p)), pi + [0.03, 0.0, 0.0], up(len(pi)), state, max_height=max_height)
    np.testing.assert_allclose(p[held, 1], 0.001, atol=1e-12)
    np.testing.assert_allclose(p[over & ~held, 1], 0.004 + LAYER_GAP, atol=1e-12)


def held_outer(inner_y: float = 0.004):
    """The inner sheet inner_y over the outer one, which a body part holds down where z < 0.05
    (its S106 ceiling at its height: no room to rise)."""
    po, eo, pi, ti, ei, m = outer_and_inner(inner_y)
    ceiling = np.full(len(po), 0.03)
    held = po[:, 2] < 0.05 - 1e-9
    ceiling[held] = 0.0
    outer = SimpleNamespace(height=np.zeros(len(po)), ceiling=ceiling, facing=np.where(held, -1.0, 1.0),
                            n_pn=up(len(po)))
    return po, pi, m, outer, held


def test_where_the_outer_sheet_cannot_rise_the_inner_one_is_pressed_under_it_and_eases_off():
    """The inner sheet 4 mm over the outer one, the outer held down where z < 0.05: there the
    inner comes down to exactly LAYER_GAP under the outer (6 mm along its normal); elsewhere
    the outer rises to the gap over it and the inner stays (but for its edges across x, as in
    the first test), but next to the held part, where
    the outer slopes up, the inner comes down part of the way (at z = 0.04 at least the 6 mm
    press less LAYER_SLOPE × 1 cm). No inner vertex is left over the outer sheet."""
    po, pi, m, outer, held = held_outer()
    p, q = po.copy(), pi.copy()
    s = LayerState(m)
    stack_layer(m, s, p, up(len(p)), q, up(len(q)), outer, max_height=0.03)
    assert np.all(p[held, 1] == 0.0)
    z = pi[:, 2]
    np.testing.assert_allclose(q[z < 0.035, 1], -LAYER_GAP, atol=1e-12)
    assert np.all(q[np.isclose(z, 0.04), 1] <= 0.004 - (0.004 + LAYER_GAP - LAYER_SLOPE * H) + 1e-12)
    rim = np.isclose(pi[:, 0], 0.1) | np.isclose(pi[:, 0], 0.3)  # (as in the first test)
    assert np.all(q[(z > 0.055) & ~rim, 1] == 0.004)
    np.testing.assert_array_equal(q[:, [0, 2]], pi[:, [0, 2]])  # along the normals only
    over = {(round(a, 6), round(c, 6)): y for a, y, c in p}  # the outer sheet right over each (the same x, z)
    assert np.all(q[:, 1] < np.array([over[round(a, 6), round(c, 6)] for a, _, c in q]))
    assert s.press.moved > 0


def test_the_press_stops_at_the_body_floor_and_not_beyond_the_depth():
    """The same, the inner's body floor 3 mm under its height (S103: the body 4 mm below, 1 mm
    clearance): the held part comes down 3 mm, to 1 mm over the outer sheet, not to the gap
    under it. An inner sheet more than LAYER_DEPTH over the outer one is another sheet, left."""
    po, pi, m, outer, held = held_outer()
    inner = SimpleNamespace(height=np.zeros(len(pi)), body_floor=np.full(len(pi), -0.003), n_pn=up(len(pi)))
    p, q = po.copy(), pi.copy()
    stack_layer(m, LayerState(m), p, up(len(p)), q, up(len(q)), outer, inner, max_height=0.03)
    z = pi[:, 2]
    np.testing.assert_allclose(q[z < 0.035, 1], 0.001, atol=1e-12)
    assert np.all(q[:, 1] >= 0.001 - 1e-12)
    po, pi, m, outer, held = held_outer(LAYER_DEPTH + 0.002)
    outer.ceiling[:], outer.facing[:] = 0.0, -1.0  # held everywhere: nothing rises, the press alone
    p, q = po.copy(), pi.copy()
    stack_layer(m, LayerState(m), p, up(len(p)), q, up(len(q)), outer, max_height=0.03)
    np.testing.assert_array_equal(p, po)
    np.testing.assert_array_equal(q, pi)


def test_the_lift_goes_along_the_reference_normals_not_the_wrinkles_shading_normals():
    """The first test's sheets, the outer's shading normals tilted 30° one way and the other in
    alternate rows across x (a wrinkled surface), its reference normals (n_pn) +Y: each outer vertex
    over the inner sheet rises straight up to LAYER_GAP over it, and its neighbours stay as far apart
    across x as they were (along the shading normals they would part by 2 × 6 mm × tan 30°)."""
    po, eo, pi, ti, ei, m = outer_and_inner(0.004)
    tilt = np.radians(30.0) * np.where(np.round(po[:, 0] / H).astype(int) % 2 == 0, 1.0, -1.0)
    shading = np.stack([np.sin(tilt), np.cos(tilt), np.zeros(len(po))], axis=1)
    outer = SimpleNamespace(height=np.zeros(len(po)), ceiling=np.full(len(po), 0.03), facing=np.ones(len(po)),
                            n_pn=up(len(po)))
    p = po.copy()
    stack_layer(m, LayerState(m), p, shading, pi.copy(), up(len(pi)), outer, max_height=0.03)
    x = po[:, 0]
    over = (x > 0.12 - 1e-9) & (x < 0.28 + 1e-9)
    np.testing.assert_allclose(p[over, 1], 0.004 + LAYER_GAP, atol=1e-12)
    np.testing.assert_array_equal(p[:, [0, 2]], po[:, [0, 2]])


def test_a_body_part_merely_near_does_not_stop_a_lift():
    """The held_outer sheets, but where the outer's ceiling is low S103 found another body part
    near it, not above it (facing >= 0: the other thigh beside a skirt pinched in the stride):
    the outer rises to LAYER_GAP over the inner everywhere, and the inner stays (but for its edges
    across x, as in the first test)."""
    po, pi, m, outer, held = held_outer()
    outer.facing = np.ones(len(po))
    p, q = po.copy(), pi.copy()
    s = LayerState(m)
    stack_layer(m, s, p, up(len(p)), q, up(len(q)), outer, max_height=0.03)
    x = po[:, 0]
    over = (x > 0.12 - 1e-9) & (x < 0.28 + 1e-9)
    np.testing.assert_allclose(p[over, 1], 0.004 + LAYER_GAP, atol=1e-12)
    rim = np.isclose(pi[:, 0], 0.1) | np.isclose(pi[:, 0], 0.3)
    assert np.all(q[~rim, 1] == 0.004)


@pytest.mark.parametrize("inner_height, lifted", [(0.02, True), (0.005, False)])
def test_an_outer_sheet_between_the_inner_one_and_the_body_is_lifted_however_deep(inner_height, lifted):
    """The inner sheet 15 mm over the outer one, beyond LAYER_DEPTH, by the closest points alone
    (no rays: cross_reach 0). Where the inner stands 20 mm over its body floor (leggings bridging
    the crotch), the outer lies between it and the body: it comes to LAYER_GAP over the inner.
    Where the inner stands 5 mm over it, 15 mm under the inner is in the body or past it: the
    outer is another sheet, left alone."""
    po, eo, pi, ti, ei, m = outer_and_inner(0.015)
    m.cross_reach = 0.0
    inner = SimpleNamespace(height=np.full(len(pi), inner_height), body_floor=np.zeros(len(pi)), n_pn=up(len(pi)))
    p, q = po.copy(), pi.copy()
    stack_layer(m, LayerState(m), p, up(len(p)), q, up(len(q)), None, inner)
    x = po[:, 0]
    over = (x > 0.12 - 1e-9) & (x < 0.28 + 1e-9)
    if lifted:
        np.testing.assert_allclose(p[over, 1], 0.015 + LAYER_GAP, atol=1e-12)
    else:
        np.testing.assert_array_equal(p, po)
    np.testing.assert_array_equal(q, pi)


def test_the_candidates_reach_over_the_body_the_inner_garment_covers():
    """A floor of body vertices over x in [-0.1, 0.5]; the inner sheet 5 mm over it on x in
    [0.1, 0.3], the outer one 8 cm over it on [0, 0.4] (a skirt hanging clear of the leggings at
    rest). By distance alone (LAYER_REACH) none of the outer is a candidate; with the body, the
    outer's vertices over the body within LAYER_REACH of the inner sheet are (the thigh striding
    into the skirt brings the leggings with it), and every inner vertex under the outer is."""
    body = grid(-0.1, 0.5, 0.0)[0]
    po, to, eo = grid(0.0, 0.4, 0.08)
    pi, ti, ei = grid(0.1, 0.3, 0.005)
    assert len(layer_pair(0, 1, po, to, eo, pi, ti, ei).over.candidates) == 0
    m = layer_pair(0, 1, po, to, eo, pi, ti, ei, body_rest=body)
    x = po[m.over.candidates, 0]
    assert x.min() == pytest.approx(0.08) and x.max() == pytest.approx(0.32)  # 5 mm up, 2 cm across: within 3 cm
    assert len(m.over.candidates) == 25 * 21
    np.testing.assert_array_equal(m.under.candidates, np.arange(len(pi)))
    # an inner sheet reaching beyond the outer: its vertices more than LAYER_REACH past the outer's edge are not
    pi, ti, ei = grid(0.1, 0.5, 0.005)
    m = layer_pair(0, 1, po, to, eo, pi, ti, ei, body_rest=body)
    assert pi[m.under.candidates, 0].max() == pytest.approx(0.42)  # (0.43: exactly LAYER_REACH, not within)


def sheet(x0: float, y: float, material: str, nx: int = 5, nz: int = 3, spacing: float = 0.04):
    verts, faces = grid_sheet(nx, nz, spacing, y)
    verts = verts + [x0, 0.0, 0.0]
    coarse = CoarseMesh(verts, faces, np.zeros(0, np.int32), np.zeros((0, 3)))
    cloth = build_cloth_model(Garment(material, verts, faces, np.arange(len(verts))), fabric(material), SimSettings(),
                              verts, coarse)
    return build_surface_model(cloth, SurfaceSettings())


def floor(x0=-0.05, x1=0.3):
    xs, zs = np.meshgrid(np.linspace(x0, x1, 36), np.linspace(-0.05, 0.13, 19))
    return np.stack([xs.ravel(), np.zeros(xs.size), zs.ravel()], axis=1)


def test_the_garment_farther_from_the_body_where_two_overlap_is_the_outer_one():
    """Cotton 12 mm over a floor of body vertices over x in [0, 0.16], denim 10 mm over [0.08,
    0.24]: the cotton is outer; its vertices within LAYER_REACH of the denim are tested. Apart,
    they are not layered."""
    inner, outer = sheet(0.08, 0.010, "denim"), sheet(0.0, 0.012, "cotton")
    pairs = layer_outfit([inner, outer], floor())
    assert [(m.outer, m.inner) for m in pairs] == [(1, 0)]
    swapped = layer_outfit([sheet(0.08, 0.014, "denim"), outer], floor())
    assert [(m.outer, m.inner) for m in swapped] == [(0, 1)]
    assert LAYER_BAND < 0.03
    apart = layer_outfit([sheet(0.0, 0.01, "cotton"), sheet(0.3, 0.01, "cotton")], floor(-0.05, 0.5))
    assert apart == []


def test_three_garments_are_stacked_from_the_inside_out():
    """Trousers at 10 mm, a shirt at 12 mm and a jacket at 14 mm over the same floor, all
    overlapping: the shirt is lifted over the trousers before the jacket over the shirt, in
    whatever order the garments come, and a frame in which the trousers' wrinkles rise 7 mm
    (to 17 mm) ends with the shirt 2 mm over them and the jacket 2 mm over the shirt."""
    made = {"trousers": (0.010, "denim"), "shirt": (0.012, "cotton"), "jacket": (0.014, "denim")}
    for names in (("jacket", "shirt", "trousers"), ("trousers", "jacket", "shirt")):
        models = [sheet(0.0, made[n][0], made[n][1]) for n in names]
        pairs = layer_outfit(models, floor())
        k = {n: names.index(n) for n in names}
        order = [(m.outer, m.inner) for m in pairs]
        assert order.index((k["shirt"], k["trousers"])) < order.index((k["jacket"], k["shirt"]))
        assert (k["jacket"], k["trousers"]) in order
        rest = [rest_surface(m) for m in models]
        p = {n: rest[k[n]].copy() for n in names}
        p["trousers"][:, 1] += 0.007
        for m in pairs:
            outer, inner = names[m.outer], names[m.inner]
            stack_layer(m, LayerState(m), p[outer], up(len(p[outer])), p[inner], up(len(p[inner])))
        mid = (rest[0][:, 0] > 0.02) & (rest[0][:, 0] < 0.14)  # away from the sheets' edges
        np.testing.assert_allclose(p["shirt"][mid, 1], 0.017 + LAYER_GAP, atol=1e-9)
        np.testing.assert_allclose(p["jacket"][mid, 1], 0.017 + 2 * LAYER_GAP, atol=1e-9)


def test_the_closest_point_on_a_vertex_s_triangles_skips_those_that_point_away_and_finds_the_same():
    """On a sheet rippled like a garment's wrinkles (y = 4 mm sin(2π x / 3 cm)), for points
    within 6 mm of it, over crests and in hollows: the closest point on the triangles around
    their nearest vertex is the nearest of every one of those triangles' closest points, to
    rounding (a third of them, whose two edges from the vertex both point away from p, have the
    vertex as theirs and are not computed), and its weights give that point back."""
    p, tris, edges = grid(0.0, 0.2, 0.0, 0.12)
    p[:, 1] = 0.004 * np.sin(2.0 * np.pi * p[:, 0] / 0.03)
    track = sheet_track(p[:1] + [0.0, 0.01, 0.0], np.zeros((0, 2), np.int32), p, tris, edges)
    rng = np.random.default_rng(3)
    q = np.zeros(3)
    points = np.stack([rng.uniform(0.05, 0.15, 300), rng.uniform(-0.01, 0.01, 300), rng.uniform(0.03, 0.09, 300)], 1)
    points[:, 1] += 0.004 * np.sin(2.0 * np.pi * points[:, 0] / 0.03)
    skipped = 0
    for point in points:
        v = int(np.argmin(np.linalg.norm(p - point, axis=1)))
        fan = track.tri_ids[track.tri_start[v]:track.tri_start[v + 1]]
        d2_fan = np.inf
        for a, b, c in tris[fan]:
            closest_point_triangle(*point, p, a, b, c, q)
            d2_fan = min(d2_fan, float(np.sum((point - q) ** 2)))
            others = [u for u in (a, b, c) if u != v]
            skipped += all((point - p[v]) @ (p[u] - p[v]) <= 0.0 for u in others)
        d2, t, a, b, c, wb, wc, qx, qy, qz = closest_in_fan(*point, p, v, track.tri_start, track.tri_ids, tris, q)
        assert d2 == pytest.approx(d2_fan, rel=1e-12, abs=1e-20)
        assert t in fan and {a, b, c} == set(tris[t].tolist()) and a == v
        np.testing.assert_allclose((1 - wb - wc) * p[a] + wb * p[b] + wc * p[c], [qx, qy, qz], atol=1e-15)
    assert skipped > 300  # of about 1,800: the skip is taken


def test_the_moves_ease_off_as_an_exact_cone_whatever_the_edges_order():
    """A chain of eight candidates, its edges listed out of order, each edge's drop 2 mm: a move
    of 10 mm at the third and 3 mm at the seventh fall off 2 mm an edge on both sides and meet
    (the cone of the larger wins where both reach), never below what was asked, never negative."""
    rest = np.stack([np.arange(8) * 0.004, np.zeros(8), np.zeros(8)], axis=1)  # 4 mm edges: drop 2 mm
    edges = np.array([[5, 6], [0, 1], [6, 7], [2, 3], [4, 5], [1, 2], [3, 4]], np.int32)
    other, other_tris, other_edges = grid(0.0, 0.04, 0.005, 0.02)
    track = sheet_track(rest, edges, other, other_tris, other_edges, reach=1.0)
    assert list(track.candidates) == list(range(8))
    move = np.array([0.0, 0.0, 0.010, 0.0, 0.0, 0.0, 0.003, 0.0])
    ease_lifts(track.spread_start, track.spread_nbrs, track.spread_nbr_drop, move, np.zeros(8, np.int32),
               np.zeros(8, np.uint8))
    np.testing.assert_allclose(move, [0.006, 0.008, 0.010, 0.008, 0.006, 0.004, 0.003, 0.001], atol=1e-15)


@pytest.mark.parametrize("side", [1.0, -1.0])
def test_a_lower_lift_rises_until_neighbours_are_within_their_edge_bound(side):
    """Two outer neighbours 10 mm apart, normals +Y, the first lifted 20 mm and the second not
    at all (20 mm apart once lifted). With a maximum neighbour distance of 11 mm the second
    rises to the smallest lift that brings them exactly 11 mm apart, 20 - sqrt(11² - 10²) mm
    (the lower root); the first keeps its lift. An edge 15 mm long before the lifts may stay
    15 mm long; where no lift of the lower one brings them nearer (normals leaning 45° away
    from each other) it is left; the room caps a rise, and then the higher lift may give way
    (`keep_within_bounds`'s give_way), down to the upper root. The same for an inner garment pressed down
    (side -1) along normals that point the other way."""
    p = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0]])
    n = up(2)
    candidates, edges = np.array([0, 1], np.int32), np.array([[0, 1]], np.int32)

    def lifted(limit, lifts, room=(1.0, 1.0), points=p, normals=n, give_way=False):
        bound = np.array([limit])
        lift, rooms = np.array(lifts, float), np.array(room, float)
        keep_within_bounds(points, side * normals, side, candidates, edges, bound, lift, rooms, 2, False)
        if give_way:
            keep_within_bounds(points, side * normals, side, candidates, edges, bound, lift, rooms, 1, True)
        lift = np.minimum(lift, rooms)
        q = points + lift[:, None] * normals
        return lift, np.linalg.norm(q[0] - q[1])

    lift, d = lifted(0.011, [0.02, 0.0])
    assert lift[0] == 0.02 and lift[1] == pytest.approx(0.02 - np.sqrt(0.011**2 - 0.01**2), abs=1e-15)
    assert d == pytest.approx(0.011, abs=1e-15)
    lift, d = lifted(0.011, [0.0, 0.02])  # the other way round
    assert lift[1] == 0.02 and d == pytest.approx(0.011, abs=1e-15)
    long = p.copy()
    long[1, 0] = 0.015
    _, d = lifted(0.011, [0.02, 0.0], points=long)
    assert d == pytest.approx(0.015, abs=1e-15)  # as long as before the lifts, no longer
    apart = np.array([[-1.0, 1.0, 0.0], [1.0, 1.0, 0.0]]) / np.sqrt(2.0)
    lift, d = lifted(0.011, [0.02, 0.0], normals=apart)  # 28 mm apart, and farther if the second rises
    assert lift[1] == 0.0 and d > 0.027
    lift, d = lifted(0.011, [0.02, 0.0], room=(1.0, 0.001))
    assert lift[1] == 0.001 and d > 0.011
    # giving way: the higher comes down to the upper root, 1 + sqrt(11² - 10²) mm
    lift, d = lifted(0.011, [0.02, 0.0], room=(1.0, 0.001), give_way=True)
    assert lift[1] == 0.001 and lift[0] == pytest.approx(0.001 + np.sqrt(0.011**2 - 0.01**2), abs=1e-15)
    assert d == pytest.approx(0.011, abs=1e-15)
    lift, d = lifted(0.011, [0.02, 0.0], room=(1.0, 0.0), normals=apart, give_way=True)  # leaning apart: down
    assert 0.0 < lift[0] < 0.002 and d == pytest.approx(0.011, abs=1e-15)  # to 1.4 mm, where they part 11 mm
    lift, d = lifted(0.011, [0.0, 0.0])
    assert np.all(lift == 0.0) and d == pytest.approx(0.01, abs=1e-15)


def box_over_the_sheets() -> tuple:
    """A body part over the middle of outer_and_inner's sheets: a 10 cm box, its bottom at y = 5 mm,
    as stack_layer's body (its vertices, triangles and winding grid)."""
    from cloth.winding import WindingGrid
    from tests.test_cloth_dynamics import box
    bx, bt = box(half=0.05, n=4)
    bx = np.ascontiguousarray(bx + [0.2, 0.055, 0.1])
    g = WindingGrid(bt.astype(np.int32), len(bx), cell=0.01)
    g.update(bx)
    return (bx, bt.astype(np.int32), *g.arrays())


def test_no_lift_or_press_takes_a_vertex_into_the_body():
    """The Decision never into the body: the first test's sheets with a body part (a box, its
    bottom at y = 5 mm) right over the middle of the outer sheet: the outer's lift to LAYER_GAP over
    the inner (6 mm) would end inside it, so there it is halved (3 mm, outside); elsewhere the lift
    is whole. The inner is then pressed under the outer that is left, away from the body, as before."""
    body = box_over_the_sheets()
    po, eo, pi, ti, ei, m = outer_and_inner(0.004)
    p, q = po.copy(), pi.copy()
    s = LayerState(m)
    stack_layer(m, s, p, up(len(p)), q, up(len(q)), body=body)
    x, z = po[:, 0], po[:, 2]
    over = (x > 0.1 - 1e-9) & (x < 0.3 + 1e-9)
    under_box = (np.abs(x - 0.2) < 0.05 - 1e-9) & (np.abs(z - 0.1) < 0.05 - 1e-9)
    beside = over & ((np.abs(x - 0.2) > 0.05 + 1e-9) | (np.abs(z - 0.1) > 0.05 + 1e-9))
    np.testing.assert_allclose(p[under_box, 1], 0.5 * (0.004 + LAYER_GAP), atol=1e-12)
    np.testing.assert_allclose(p[beside, 1], 0.004 + LAYER_GAP, atol=1e-12)
    on_walls = (np.abs(x - 0.2) < 0.05 + 1e-9) & (np.abs(z - 0.1) < 0.05 + 1e-9)  # (on them: either)
    assert s.lift.held == int(np.sum(np.isclose(p[:, 1], 0.5 * (0.004 + LAYER_GAP))))
    assert under_box.sum() <= s.lift.held <= on_walls.sum()
    np.testing.assert_array_equal(p[:, [0, 2]], po[:, [0, 2]])
    xi, zi = pi[:, 0], pi[:, 2]
    inner_under = (np.abs(xi - 0.2) < 0.05 - 1e-9) & (np.abs(zi - 0.1) < 0.05 - 1e-9)
    # (where the outer steps back up at the box's walls the press eases off a little)
    assert np.all((q[inner_under, 1] > 0.5 * (0.004 + LAYER_GAP) - LAYER_GAP - 1e-12) & (q[inner_under, 1] < 0.0015))
    over_at = {(round(a, 6), round(c, 6)): y for a, y, c in p}
    assert np.all(q[:, 1] < np.array([over_at[round(a, 6), round(c, 6)] for a, _, c in q]))
    assert s.press.held == 0
    # without the body the lift is whole everywhere
    p = po.copy()
    stack_layer(m, LayerState(m), p, up(len(p)), pi.copy(), up(len(pi)))
    np.testing.assert_allclose(p[under_box, 1], 0.004 + LAYER_GAP, atol=1e-12)


def test_no_move_ends_inside_the_body_from_a_fold_s_pocket_nor_from_inside():
    """keep_out_of_body on three vertices lifted 3 cm up (+Y), a body of two 5 cm boxes: A over y in
    [0, 0.05], and under it B over [-0.06, -0.01] with its faces turned inside out (winding number -1
    inside: the skin folded over itself at a crease, outside the flesh). From inside B into A the lift
    is halved until it ends between them (before, a start read "not outside" was left alone and
    ended 1 mm in the hip); from inside A it is undone (along the normal it went deeper into
    another part as often as out); from outside, ending in the open, it stays."""
    from cloth.layers import keep_out_of_body
    from cloth.winding import WindingGrid
    from tests.test_cloth_dynamics import box
    a, ta = box(half=0.025, n=4)
    b, tb = box(half=0.025, n=4)
    x = np.ascontiguousarray(np.concatenate([a + [0.0, 0.025, 0.0], b + [0.0, -0.035, 0.0]]))
    tris = np.ascontiguousarray(np.concatenate([ta, tb[:, ::-1] + len(a)]).astype(np.int32))
    g = WindingGrid(tris, len(x), cell=0.01)
    g.update(x)
    start = np.array([[0.001, -0.02, 0.002], [0.001, 0.012, 0.002], [0.1, 0.0, 0.0]])
    lift = 0.03
    p = start + [0.0, lift, 0.0]
    move, room = np.full(3, lift), np.full(3, 0.05)
    held = keep_out_of_body(p, up(3), 1.0, np.arange(3, dtype=np.int32), move, room, x, tris, *g.arrays())
    assert held == 2
    np.testing.assert_allclose(p[0], start[0] + [0.0, 0.5 * lift, 0.0], atol=1e-15)  # y = -5 mm: between the boxes
    np.testing.assert_allclose(p[1], start[1], atol=1e-15)
    np.testing.assert_allclose(p[2], start[2] + [0.0, lift, 0.0], atol=1e-15)
    np.testing.assert_allclose(room, [0.5 * lift, 0.0, 0.05])


def test_a_helper_thread_measuring_half_of_each_garment_changes_nothing(monkeypatch):
    """The previous test's sheets and box, every garment measured in two halves (the second on a
    helper thread, as two tops are: SPLIT_CANDIDATES lowered for sheets this small): the lifts,
    presses, holds and counts are those of one thread, bit for bit."""
    import cloth.layers as layers
    from services.spin import SpinWorker
    body = box_over_the_sheets()
    po, eo, pi, ti, ei, m = outer_and_inner(0.004)
    runs = []
    worker = SpinWorker(0.0)
    try:
        for helper, split in ((None, layers.SPLIT_CANDIDATES), (worker, 10)):
            monkeypatch.setattr(layers, "SPLIT_CANDIDATES", split)
            p, q, s = po.copy(), pi.copy(), LayerState(m)
            stack_layer(m, s, p, up(len(p)), q, up(len(q)), body=body, helper=helper)
            runs.append((p, q, s.lift.moved, s.lift.held, s.press.moved, s.lift.nearest.copy()))
    finally:
        worker.close()
    assert runs[0][3] > 0  # some lifts were held back out of the box: keep_out_of_body was split too
    for a, b in zip(*runs):
        np.testing.assert_array_equal(a, b)
