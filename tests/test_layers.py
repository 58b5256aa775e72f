"""Garments worn over one another (cloth/layers.py, the layering Decision) on cases whose answers are known."""

import numpy as np

from cloth.coarsen import CoarseMesh
from cloth.collision import face_normals
from cloth.fabric import fabric
from cloth.garment import Garment
from cloth.layers import LAYER_BAND, LAYER_HEIGHT, LAYER_RAMP, layer_outfit, overlap_weight, rest_surface
from cloth.model import SimSettings, build_cloth_model
from cloth.surface import DetailedSurface, SurfaceSettings, build_surface_model
from tests.test_cloth_dynamics import box
from tests.test_surface import DT, body_mesh_of, compressed_strip, grid_sheet, run_frames


def sheet(x0: float, y: float, material: str, nx: int = 5, nz: int = 3, spacing: float = 0.04):
    verts, faces = grid_sheet(nx, nz, spacing, y)
    verts = verts + [x0, 0.0, 0.0]
    coarse = CoarseMesh(verts, faces, np.zeros(0, np.int32), np.zeros((0, 3)))
    cloth = build_cloth_model(Garment(material, verts, faces, np.arange(len(verts))), fabric(material), SimSettings(),
                              verts, coarse)
    return build_surface_model(cloth, SurfaceSettings())


def test_the_garment_farther_from_the_body_is_layered_over_the_other():
    """Two flat sheets over a floor of body vertices at y = 0: cotton at 12 mm over x in
    [0, 0.16], denim at 10 mm over [0.08, 0.24]. The cotton is outer: where the two overlap its
    vertices are kept the denim's thickness plus LAYER_HEIGHT further off the body, easing to
    nothing LAYER_BAND + LAYER_RAMP beyond the denim; the denim's heights stay under
    LAYER_HEIGHT under the cotton, and free beyond it."""
    outer, inner = sheet(0.0, 0.012, "cotton"), sheet(0.08, 0.010, "denim")
    xs, zs = np.meshgrid(np.linspace(-0.05, 0.3, 36), np.linspace(-0.05, 0.13, 19))
    floor = np.stack([xs.ravel(), np.zeros(xs.size), zs.ravel()], axis=1)
    assert layer_outfit([inner, outer], floor) == [(1, 0)]
    lift = inner.cloth.fabric.thickness + LAYER_HEIGHT
    x_out, x_in = rest_surface(outer)[:, 0], rest_surface(inner)[:, 0]
    over = x_out >= 0.08 - 1e-9
    np.testing.assert_allclose(outer.layer_clearance[over], lift, atol=1e-12)
    gap = np.hypot(np.maximum(0.08 - x_out, 0.0), 0.002)  # to the denim (its nearest vertex in the same z row)
    far = gap > LAYER_BAND + LAYER_RAMP
    assert far.any() and np.all(outer.layer_clearance[far] == 0.0)
    ramp = ~over & (gap > LAYER_BAND) & ~far
    assert ramp.any()
    assert np.all((outer.layer_clearance[ramp] > 0.0) & (outer.layer_clearance[ramp] < lift))
    under = x_in <= 0.16 + 1e-9
    np.testing.assert_allclose(inner.layer_cap[under], LAYER_HEIGHT, atol=1e-12)
    free = x_in > 0.16 + LAYER_BAND + LAYER_RAMP
    assert free.any() and np.all(inner.layer_cap[free] == inner.settings.max_height)
    # the weight itself: 1 within the band, linear over the ramp, 0 beyond
    np.testing.assert_allclose(overlap_weight(np.array([0.0, LAYER_BAND, LAYER_BAND + LAYER_RAMP / 2,
                                                        LAYER_BAND + LAYER_RAMP, 1.0])), [1.0, 1.0, 0.5, 0.0, 0.0])


def test_garments_that_do_not_overlap_are_not_layered():
    a, b = sheet(0.0, 0.01, "cotton"), sheet(0.3, 0.01, "cotton")
    assert layer_outfit([a, b], np.zeros((1, 3))) == []
    assert np.all(a.layer_clearance == 0.0) and np.all(b.layer_cap == a.settings.max_height)


def test_s103_keeps_a_layered_vertex_its_extra_clearance_off_the_body():
    """A flat sheet 3 mm above a box's top face, its half at x < 0.08 layered 5 mm: those
    particles rise to clearance + 5 mm = 6 mm above the top (S103, along their normals +Y) and
    S106 keeps them there; the other half, 3 mm off already, stays on its reference surface."""
    bv, bt = box(half=0.2, n=8)
    bv = bv + [0.08, -0.203, 0.04]  # top face at y = -3 mm, under the whole sheet
    body = body_mesh_of(bv, bt)
    m = sheet(0.0, 0.0, "cotton")
    surf = DetailedSurface(m)
    x = m.cloth.rest_positions.copy()
    layered = rest_surface(m)[:, 0] < 0.08 - 1e-9
    m.layer_clearance[layered] = 0.005
    nearest = np.array([int(np.argmin(np.linalg.norm(bv - q, axis=1))) for q in x], dtype=np.int32)
    for _ in range(3):
        p, _ = surf.step(x, nearest, np.ascontiguousarray(bv), body, face_normals(bv, bt), DT)
    clearance = m.settings.clearance
    assert np.all(p[layered, 1] >= -0.003 + clearance + 0.005 - 1e-6)
    np.testing.assert_allclose(p[layered, 1], -0.003 + clearance + 0.005, atol=2e-3)  # and no higher
    inner = ~layered & (rest_surface(m)[:, 0] > 0.08 + 0.03)  # away from the step between the halves
    np.testing.assert_allclose(p[inner, 1], 0.0, atol=1e-9)


def test_s106_keeps_a_capped_vertex_under_its_cap():
    """A strip compressed by 20 % grows wrinkles (tests/test_surface.py); with its cap at 2 mm no
    height exceeds 2 mm."""
    m, x = compressed_strip(0.8)
    surf = DetailedSurface(m)
    run_frames(surf, x, 10)
    assert surf.state.dh.max() > 0.004  # it does wrinkle, uncapped
    m2, x2 = compressed_strip(0.8)
    m2.layer_cap[:] = LAYER_HEIGHT
    surf2 = DetailedSurface(m2)
    run_frames(surf2, x2, 10)
    assert surf2.state.dh.max() <= LAYER_HEIGHT + 1e-12
    assert surf2.state.dh.max() > 0.5 * LAYER_HEIGHT
