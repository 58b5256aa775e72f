"""S102-S106 on cases whose answers are known: PN triangles, flat and compressed sheets,
stretched faces, penetration avoidance against a box and a sphere."""

import re
from types import SimpleNamespace

import numpy as np
import pytest

from cloth.coarsen import CoarseMesh
from cloth.collision import BodyMesh, BodyPose, VertexGrid, face_normals
from cloth.fabric import fabric
from cloth.garment import Garment
from cloth.model import SimSettings, build_cloth_model
from cloth.geometry import vertex_normals
from cloth.pn import build_tessellation, pn_control_points, pn_evaluate, pn_surface
from cloth.surface import DetailedSurface, SurfaceSettings, build_surface_model
from cloth.winding import WindingGrid
from tests.test_cloth_dynamics import box, uv_sphere

DT = 1.0 / 60.0


def grid_sheet(nx=5, nz=3, spacing=0.04, y=0.0):
    """A flat quad sheet in the XZ plane, normals +Y."""
    xs, zs = np.meshgrid(np.arange(nx) * spacing, np.arange(nz) * spacing, indexing="ij")
    verts = np.stack([xs.ravel(), np.full(xs.size, y), zs.ravel()], axis=1)
    vid = np.arange(nx * nz).reshape(nx, nz)
    faces = [(vid[i, k], vid[i, k + 1], vid[i + 1, k + 1], vid[i + 1, k]) for i in range(nx - 1) for k in range(nz - 1)]
    return verts, np.array(faces, dtype=np.int32)


def sheet_model(nx=5, nz=3, spacing=0.04, level=6, material="cotton"):
    verts, faces = grid_sheet(nx, nz, spacing)
    coarse = CoarseMesh(verts, faces, np.zeros(0, np.int32), np.zeros((0, 3)))
    g = Garment("sheet", verts, faces, np.arange(len(verts)))
    cloth = build_cloth_model(g, fabric(material), SimSettings(), verts, coarse)
    return build_surface_model(cloth, SurfaceSettings(level=level))


def evaluate(tess, x, normals):
    T = len(tess.coarse_triangles)
    ctrl, nctrl = np.zeros((T, 10, 3)), np.zeros((T, 6, 3))
    pn_control_points(x, normals, tess.coarse_triangles, ctrl, nctrl)
    p, n = np.zeros((tess.n_vertices, 3)), np.zeros((tess.n_vertices, 3))
    pn_evaluate(ctrl, nctrl, tess.owner_face, tess.owner_weights, p, n)
    return p, n, ctrl, nctrl


@pytest.mark.parametrize("key, value, says", [
    ("level", 0, "SurfaceSettings.level must be an integer >= 1, got 0"),
    ("level", 6.0, "SurfaceSettings.level must be an integer >= 1, got 6.0"),
    ("constraint_passes", 0, "SurfaceSettings.constraint_passes must be an integer >= 1"),
    ("clearance", -0.001, "SurfaceSettings.clearance must be >= 0 and finite, got -0.001"),
    ("tip_share", float("nan"), "SurfaceSettings.tip_share must be >= 0 and finite, got nan"),
    ("max_height", 0.0, "SurfaceSettings.max_height must be > 0 and finite, got 0.0"),
    ("max_lift", float("inf"), "SurfaceSettings.max_lift must be > 0 and finite, got inf"),
    ("max_step_scale", 0.5, "SurfaceSettings.max_step_scale must be >= 1"),
])
def test_surface_settings_name_a_value_out_of_range(key, value, says):
    with pytest.raises(ValueError, match=re.escape(says)):
        SurfaceSettings(**{key: value})
    SurfaceSettings()  # the defaults are valid


def test_tessellation_counts_and_shared_vertices():
    verts, faces = grid_sheet(4, 3)
    tris = np.concatenate([faces[:, [0, 1, 2]], faces[:, [0, 2, 3]]])
    for level in (1, 4, 6, 12):
        t = build_tessellation(tris, len(verts), level)
        E = len(t.coarse_edges)
        interior = (level - 1) * (level - 2) // 2
        assert t.n_vertices == len(verts) + E * (level - 1) + len(tris) * interior
        assert len(t.triangles) == len(tris) * level**2
        assert len(np.unique(t.triangles)) == t.n_vertices  # every vertex is used, none twice
        # Euler characteristic of a disc: V - E + F = 1 (no cracks, no duplicated vertices)
        d_edges = np.unique(np.sort(np.concatenate([t.triangles[:, [0, 1]], t.triangles[:, [1, 2]],
                                                    t.triangles[:, [2, 0]]]), axis=1), axis=0)
        assert t.n_vertices - len(d_edges) + len(t.triangles) == 1


def curved_patch():
    """Two triangles on a sphere of radius 1 with the sphere's normals."""
    x = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.6, 0.8], [0.6, 0.6, np.sqrt(1 - 0.72)]])
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    return x, np.array([[0, 1, 2], [1, 3, 2]], dtype=np.int32), x.copy()


def test_pn_triangles_reproduce_corners_and_corner_normals():
    x, tris, normals = curved_patch()
    tess = build_tessellation(tris, len(x), 6)
    p, n, _, _ = evaluate(tess, x, normals)
    np.testing.assert_allclose(p[: len(x)], x, atol=1e-14)  # coarse vertex i is detailed vertex i
    np.testing.assert_allclose(n[: len(x)], normals, atol=1e-14)
    # between the corners the surface bulges towards the sphere: nearer radius 1 than the flat triangle
    r = np.linalg.norm(p, axis=1)
    flat = np.linalg.norm((x[tris[0, 0]] + x[tris[0, 1]] + x[tris[0, 2]]) / 3.0)
    centre = tess.face_ids[0, np.flatnonzero((tess.lattice == (2, 2)).all(axis=1))[0]]
    assert abs(r[centre] - 1.0) < 0.2 * abs(flat - 1.0)


def test_pn_triangles_keep_a_planar_patch_planar():
    verts, faces = grid_sheet(3, 3)
    verts = verts @ np.array([[0.8, 0.6, 0.0], [-0.6, 0.8, 0.0], [0.0, 0.0, 1.0]]).T  # a tilted plane
    tris = np.concatenate([faces[:, [0, 1, 2]], faces[:, [0, 2, 3]]]).astype(np.int32)
    normals = np.zeros_like(verts)
    vertex_normals(verts, tris, normals)
    tess = build_tessellation(tris, len(verts), 6)
    p, n, _, _ = evaluate(tess, verts, normals)
    plane_n = normals[0]
    np.testing.assert_allclose((p - verts[0]) @ plane_n, 0.0, atol=1e-15)
    np.testing.assert_allclose(n, np.broadcast_to(plane_n, n.shape), atol=1e-14)


def test_pn_triangles_are_watertight_across_shared_edges():
    """The neighbouring face's own patch, evaluated on the shared edge, hits the shared vertices."""
    x, tris, normals = curved_patch()
    tess = build_tessellation(tris, len(x), 6)
    p, n, ctrl, nctrl = evaluate(tess, x, normals)
    L = tess.level
    for f in range(len(tris)):
        for k, (b, c) in enumerate(tess.lattice):
            vid = tess.face_ids[f, k]
            if tess.owner_face[vid] == f:
                continue
            # evaluate face f's patch at this lattice point and compare with the shared vertex
            one = np.zeros((1, 3)), np.zeros((1, 3))
            pn_evaluate(ctrl, nctrl, np.array([f], np.int32), np.array([[(L - b - c) / L, b / L, c / L]]), *one)
            np.testing.assert_allclose(one[0][0], p[vid], atol=1e-15)
            np.testing.assert_allclose(one[1][0], n[vid], atol=1e-14)


def test_pn_surface_face_by_face_gives_the_per_vertex_bits():
    """pn_surface evaluates face by face from one weight table; pn_evaluate vertex by vertex."""
    x, tris, normals = curved_patch()
    for level in (1, 4, 6, 9):
        tess = build_tessellation(tris, len(x), level)
        T = len(tris)
        q, m = np.zeros((tess.n_vertices, 3)), np.zeros((tess.n_vertices, 3))
        pn_surface(tess, x, np.zeros_like(x), np.zeros((T, 10, 3)), np.zeros((T, 6, 3)), q, m)
        # pn_surface takes the coarse normals from the mesh: the reference gets the same ones
        cn = np.zeros_like(x)
        vertex_normals(x, tess.coarse_triangles, cn)
        p, n, _, _ = evaluate(tess, x, cn)
        assert np.array_equal(p, q) and np.array_equal(n, m)
        assert tess.owned.sum() == tess.n_vertices  # every vertex written once


def run_frames(surf, x, frames):
    for _ in range(frames):
        p, n = surf.step(x, None, None, None, None, DT)
    return p, n


def arc_lengths(surf, p):
    ids = surf.model.tess.edge_ids
    return np.linalg.norm(np.diff(p[ids], axis=1), axis=2).sum(axis=1)


def test_flat_unstressed_sheet_stays_flat():
    m = sheet_model()
    surf = DetailedSurface(m)
    p, n = run_frames(surf, m.cloth.rest_positions.copy(), 30)
    assert np.abs(surf.state.dh).max() == 0.0
    np.testing.assert_allclose(p[:, 1], 0.0, atol=1e-15)
    np.testing.assert_allclose(n, np.broadcast_to([0.0, 1.0, 0.0], n.shape), atol=1e-12)


def compressed_strip(ratio=0.8):
    m = sheet_model(nx=5, nz=3)
    x = m.cloth.rest_positions.copy()
    x[:, [0, 2]] *= ratio  # every coarse edge 20 % shorter than at rest
    return m, x


def test_compressed_strip_grows_wrinkles_that_restore_its_length():
    """Every coarse edge 20 % shorter than at rest: wrinkles grow until the detailed arc length
    along the coarse edges is back to rest, within 5 % in the median (S105 averages the
    requirement per coarse vertex over its edges, so single edges end between 0.8 and 1.3)."""
    m, x = compressed_strip(0.8)
    surf = DetailedSurface(m)
    run_frames(surf, x, 1)
    start = arc_lengths(surf, surf.state.p_smoothed) / m.edge_rest  # the reference surface, no wrinkles
    assert np.all(start < 0.81)
    p, _ = run_frames(surf, x, 240)
    assert surf.state.dh.max() > 0.003  # wrinkles, millimetres high
    ratio = arc_lengths(surf, p) / m.edge_rest
    assert abs(np.median(ratio) - 1.0) < 0.05, ratio
    assert np.all((ratio > 0.8) & (ratio < 1.3)), ratio
    # no neighbour farther than the fabric allows, the folds drawn across the compression included
    d = np.linalg.norm(p[m.d_edges[:, 0]] - p[m.d_edges[:, 1]], axis=1)
    assert np.all(d <= m.d_max * (1 + 1e-9))
    s = surf.state
    assert np.all(s.height >= s.dh)  # folds across the compression only raise (Decision)
    # the strip is all quads: its folds run straight across each (the diagonals' particles may rise)
    assert np.all(m.fold_corner >= 0) and np.all(m.fold_groups[:, 1] >= 0)
    diagonals = np.zeros(len(m.tess.coarse_edges), dtype=bool)
    diagonals[m.tess.face_edges[np.arange(len(m.fold_corner)), (m.fold_corner + 1) % 3]] = True
    outer = m.tess.edge_ids[~diagonals].ravel()  # the quads' edges' particles: as S106 left them
    np.testing.assert_array_equal(s.height[outer], s.dh[outer])
    np.testing.assert_allclose(p, s.p_smoothed + s.height[:, None] * s.n_pn, atol=1e-15)


def test_fully_stretched_faces_stay_flat():
    m = sheet_model()
    x = m.cloth.rest_positions * np.array([1.1, 1.0, 1.1])  # every edge longer than at rest
    surf = DetailedSurface(m)
    p, _ = run_frames(surf, x, 60)
    assert np.all(surf.state.edge_required < 0)
    np.testing.assert_allclose(p[:, 1], 0.0, atol=1e-15)


def test_stretched_region_comes_down_flat_edges_included():
    """Heights left from earlier wrinkles (3 mm on every detailed particle) on a sheet now
    stretched everywhere: one frame later the whole sheet is flat, the particles on the coarse
    edges between the stretched faces included (Decision in S106's flat rule: before it, an
    edge's particles kept their height, a bump on every edge)."""
    m = sheet_model()
    surf = DetailedSurface(m)
    x = m.cloth.rest_positions * np.array([1.1, 1.0, 1.1])
    n_coarse = m.tess.n_coarse
    surf.state.dh[n_coarse:] = 0.003
    p, _ = surf.step(x, None, None, None, None, DT)
    assert np.all(surf.state.edge_required < 0) and np.all(surf.state.edge_deficit < 0)
    np.testing.assert_array_equal(surf.state.dh, 0.0)
    np.testing.assert_allclose(p[:, 1], 0.0, atol=1e-15)


def test_wrinkles_on_a_compressed_edge_stay_when_they_make_its_faces_look_stretched():
    """Along x the coarse cloth is 10 % short, along z 10 % long (the diagonals a little long
    too). Heights of 6 mm on the x edges' particles make those edges longer than at rest, so
    every face looks fully stretched: the faces' interiors come down (S106), but the x edges
    keep their wrinkles, because the reference surface is short along them; the z edges'
    particles come down."""
    m = sheet_model()
    surf = DetailedSurface(m)
    t = m.tess
    x = m.cloth.rest_positions * np.array([0.9, 1.0, 1.1])
    rest = m.cloth.rest_positions
    along_x = np.abs(rest[t.coarse_edges[:, 0], 2] - rest[t.coarse_edges[:, 1], 2]) < 1e-12
    along_z = np.abs(rest[t.coarse_edges[:, 0], 0] - rest[t.coarse_edges[:, 1], 0]) < 1e-12
    x_particles = t.edge_ids[along_x][:, 1:-1].ravel()
    z_particles = t.edge_ids[along_z][:, 1:-1].ravel()
    surf.state.dh[x_particles] = 0.006
    surf.step(x, None, None, None, None, DT)
    s = surf.state
    assert np.all(s.edge_required < 0)  # every face looks fully stretched
    assert np.all(s.edge_deficit[along_x] > 0) and np.all(s.edge_deficit[~along_x] < 0)
    np.testing.assert_array_equal(s.dh[t.face_ids[:, t.interior_local]], 0.0)
    np.testing.assert_array_equal(s.dh[z_particles], 0.0)
    assert np.all(s.dh[x_particles] > 0.003)  # the neighbour-distance limit takes some off


def test_length_requirement_per_vertex_counts_only_compressed_edges():
    """S105 with the per-vertex Decision: along x the cloth is 5 % short, along z 20 % long. A
    coarse vertex's requirement is the mean of its compressed edges' ΔLE_required (the long
    ones do not count, where a signed mean would be negative: no wrinkle at all); the
    particles on a long edge take none; those on a compressed edge between two vertices get
    the vertices' interpolated value."""
    m = sheet_model()
    surf = DetailedSurface(m)
    t = m.tess
    x = m.cloth.rest_positions * np.array([0.95, 1.0, 1.2])
    surf.step(x, None, None, None, None, DT)  # flat sheet: the reference surface is the surface
    s = surf.state
    req = s.edge_required
    arc = np.linalg.norm(np.diff(s.p_smoothed[t.edge_ids], axis=1), axis=2).sum(axis=1)  # no heights yet
    np.testing.assert_allclose(req, m.edge_rest - arc, atol=1e-15)
    np.testing.assert_allclose(s.edge_deficit, req, atol=1e-15)
    positive = np.zeros(t.n_coarse)
    compressed = np.zeros(t.n_coarse)
    signed = np.zeros(t.n_coarse)
    for (a, b), r in zip(t.coarse_edges, req):
        if r > 0:
            positive[[a, b]] += r
            compressed[[a, b]] += 1
        signed[[a, b]] += r
    np.testing.assert_allclose(s.vertex_required, positive / compressed, atol=1e-15)
    assert np.all(s.vertex_required > 0) and np.all(signed < 0)
    for e, r in enumerate(req):
        inner = t.edge_ids[e, 1:-1]
        if r <= 0:
            np.testing.assert_array_equal(s.required[inner], 0.0)
        else:
            a, b = t.coarse_edges[e]
            w = np.arange(1, t.level) / t.level
            np.testing.assert_allclose(s.required[inner], (1 - w) * s.vertex_required[a] + w * s.vertex_required[b],
                                       atol=1e-15)


def test_step_scale_gives_a_compressed_edge_back_its_rest_length():
    """S106 step 2's amount (Decision): a straight coarse edge 20 % short, its six detailed
    segments flat, the patent's step raising every other particle by 0.1 mm. Scaled so the
    arc length is the rest length, the raised particles stand 0.6/0.8 of a segment high (a
    3-4-5 triangle per segment: 2.4 mm for a 24 mm edge). A face whose only compressed edge
    is that one scales its interior by the same factor; an edge long enough is left alone;
    the force clamp still bounds every step."""
    from cloth.wrinkles import match_required_length

    rest = 0.024
    ps = np.zeros((9, 3))
    ps[:7, 0] = np.linspace(0.0, 0.8 * rest, 7)  # edge 0: particles 0..6
    ps[7] = [0.01, 0.0, 0.01]  # a face interior particle
    ps[8] = [0.0, 0.0, 0.02]
    n = np.tile([0.0, 1.0, 0.0], (9, 1))
    edge_ids = np.array([[0, 1, 2, 3, 4, 5, 6], [6, 7, 7, 7, 7, 7, 8], [8, 7, 7, 7, 7, 7, 0]], dtype=np.int32)
    edge_rest = np.full(3, rest)
    edge_required = np.array([0.2 * rest, -0.001, -0.001])  # edges 1 and 2 long enough
    face_ids = np.array([[7]], dtype=np.int32)
    face_edges = np.array([[0, 1, 2]], dtype=np.int32)
    interior = np.array([0], dtype=np.int32)
    step = np.array([0.0, 1e-4, 0.0, 1e-4, 0.0, 1e-4, 0.0, 1e-4, 0.0])
    scale = np.zeros(3)

    def run(vf, max_scale=100.0):
        dh_def = step.copy()
        match_required_length(ps, n, np.zeros(9), dh_def, np.zeros(9), np.full(9, vf), 3.0, DT, np.full(9, 0.03),
                              edge_ids, edge_required, edge_rest, np.full((3, 6), 1.25 * rest / 6), 0.36, face_ids,
                              face_edges, interior, max_scale, 1e-12, 30, scale, np.zeros(7))
        return dh_def

    dh_def = run(vf=1e3)  # the force clamp (3 m/(N s) x vf x dt = 50 m) does not bind
    np.testing.assert_allclose(dh_def[[1, 3, 5]], 0.1 * rest, rtol=1e-9)
    p = ps + dh_def[:, None] * n
    assert abs(np.linalg.norm(np.diff(p[:7], axis=0), axis=1).sum() - rest) < 1e-12
    np.testing.assert_allclose(scale, [0.1 * rest / 1e-4, -1.0, -1.0], rtol=1e-9)
    np.testing.assert_allclose(dh_def[7], 0.1 * rest, rtol=1e-9)  # the face's mean factor
    np.testing.assert_array_equal(dh_def[[0, 2, 4, 6, 8]], 0.0)  # no step, none scaled in
    dh_def = run(vf=1e-3 / (3.0 * DT))  # a clamp of 1 mm: the edge stays short
    np.testing.assert_allclose(dh_def[[1, 3, 5, 7]], 1e-3, rtol=1e-12)
    dh_def = run(vf=1e3, max_scale=8.0)  # at most eight times the patent's step
    np.testing.assert_allclose(dh_def[[1, 3, 5, 7]], 8e-4, rtol=1e-12)


def test_step_scale_counts_what_the_neighbour_distance_takes_back():
    """S106 step 2 (Decision): a straight coarse edge 40 % short (six segments of 2.4 mm, rest
    4 mm, d_max 5 mm), the patent's step a plateau of 0.1 mm. Scaled alone, the plateau would
    stand 6.8 mm high with 7.2 mm first and last segments, which step 5 takes back. Brought
    down to d_max from their neighbours as step 5 does, the heights ramp up by
    sqrt(5² - 2.4²) = 4.39 mm from each coarse vertex to a plateau of 8.31 mm, where the arc
    length is the rest length again and no segment is longer than d_max."""
    from cloth.wrinkles import match_required_length

    rest = 0.024
    ps = np.zeros((7, 3))
    ps[:, 0] = np.linspace(0.0, 0.6 * rest, 7)
    n = np.tile([0.0, 1.0, 0.0], (7, 1))
    edge_ids = np.arange(7, dtype=np.int32)[None, :]
    dh_def = np.array([0.0, 1e-4, 1e-4, 1e-4, 1e-4, 1e-4, 0.0])
    scale = np.zeros(1)
    match_required_length(ps, n, np.zeros(7), dh_def, np.zeros(7), np.full(7, 1e3), 3.0, DT, np.full(7, 0.03),
                          edge_ids, np.array([0.4 * rest]), np.array([rest]), np.full((1, 6), 0.005), 0.36,
                          np.zeros((0, 1), dtype=np.int32), np.zeros((0, 3), dtype=np.int32),
                          np.zeros(0, dtype=np.int32), 100.0, 1e-12, 30, scale, np.zeros(7))
    rise = np.sqrt(0.005**2 - 0.0024**2)
    top = rise + np.sqrt(0.0046**2 - 0.0024**2)  # 10 + 2 x 2.4 + 2 x 4.6 = 24 mm
    np.testing.assert_allclose(dh_def, [0.0, rise, top, top, top, rise, 0.0], atol=1e-9)
    p = ps + dh_def[:, None] * n
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    assert abs(seg.sum() - rest) < 1e-9 and seg.max() <= 0.005 + 1e-12
    assert 0.9 * top / 1e-4 < scale[0] < 100.0  # the plateau's factor, short of the bound

@pytest.mark.parametrize("widen", [True, False])
def test_a_wrinkle_on_a_compressed_edge_widens_into_a_fold(widen):
    """S106 step 5 (Decision): every coarse edge along x 20 % short, one particle on such an
    edge 6 mm high, all else flat. Along the edge its neighbours are close enough (5.3 mm apart
    in the plane, d_max 8.3 mm), but its neighbours off the edge (6.7 mm in the plane) are
    not. Widened, it keeps its 6 mm and those neighbours rise until they are exactly d_max
    from it (6 - 5 = 1 mm); without the Decision it comes down to them (5 mm). A particle 7 mm
    high beside a coarse vertex comes down to d_max from it or lower: folds lift no coarse
    vertex."""
    from cloth.wrinkles import apply_constraints

    m = sheet_model()  # cotton: d_max 1.25 times the rest spacing
    t = m.tess
    surf = DetailedSurface(m)
    x = m.cloth.rest_positions * np.array([0.8, 1.0, 1.0])
    surf.step(x, None, None, None, None, DT)  # the reference surface and S105's requirements
    s = surf.state
    rest = m.cloth.rest_positions
    along_x = np.abs(rest[t.coarse_edges[:, 0], 2] - rest[t.coarse_edges[:, 1], 2]) < 1e-12
    assert np.all(s.edge_required[along_x] > 0)
    inner = np.where(along_x & (rest[t.coarse_edges[:, 0], 2] == 0.04))[0][0]  # an edge inside the sheet
    k = t.edge_ids[inner, 3]
    dh = np.zeros(t.n_vertices)
    dh[k] = 0.006
    corner, beside = t.edge_ids[inner, 0], t.edge_ids[inner, 1]
    dh[beside] = 0.007  # too high for its coarse vertex (5.3 mm away in the plane, d_max 8.3 mm)
    p = np.zeros_like(s.p)
    apply_constraints(s.p_smoothed, s.n_pn, dh, np.zeros(t.n_vertices), np.full(t.n_vertices, 0.03), t.face_ids,
                      t.face_edges, s.edge_required,
                      s.edge_deficit, t.edge_ids, t.interior_local, m.d_edges, m.d_max, m.height_allowance,
                      m.d_edge_start, m.d_edge_ids, 6, 0.03, s.flat_edge, s.moved, s.stamp, s.start_h, widen, s.fold,
                      p)
    d = np.linalg.norm(p[m.d_edges[:, 0]] - p[m.d_edges[:, 1]], axis=1)
    assert np.all(d <= m.d_max * (1 + 1e-9))
    spacing = 0.04 / t.level
    off_edge = [j for j in range(t.n_vertices)
                if abs(abs(s.p_smoothed[j, 2] - s.p_smoothed[k, 2]) - spacing) < 1e-9
                and abs(s.p_smoothed[j, 0] - s.p_smoothed[k, 0]) < 1e-9]
    assert len(off_edge) == 2  # straight across the edge, one on each side
    d_max = 1.25 * spacing  # cotton
    # a coarse vertex is never lifted by a fold (S103 skips faces by their corners' distance):
    # the wrinkle beside it comes down (at least) to d_max from it instead
    assert dh[corner] == 0.0
    a = 0.8 * spacing
    assert dh[beside] <= np.sqrt((1.25 * spacing) ** 2 - a ** 2) * (1 + 1e-9)
    if widen:
        np.testing.assert_allclose(dh[k], 0.006, rtol=1e-12)  # to rounding
        np.testing.assert_allclose(dh[off_edge], 0.006 - np.sqrt(d_max ** 2 - spacing ** 2), rtol=1e-9)
    else:
        np.testing.assert_allclose(dh[k], np.sqrt(d_max ** 2 - spacing ** 2), rtol=1e-9)
        np.testing.assert_array_equal(dh[off_edge], 0.0)


def test_an_edge_stretched_beyond_the_limit_keeps_the_slope_allowed_at_rest():
    """S106 step 5 (Decision): the sheet stretched 1.5 times along x, so its detailed edges
    along x are longer than d_max (1.25 times rest) before any height. One particle is held
    6 mm up (an S103 lift: its floor). Its neighbours along x may be parted from it as far as
    on an edge at rest: |p_i - p_j|² <= ref² + d_max² - rest², a height difference of
    0.75 rest = 5 mm on a flat sheet; so they rise to 1 mm, as do its neighbours along z (at
    rest, d_max itself). Every edge ends within its limit. (Without the Decision no height
    brings an x edge within d_max: both ends would rise to 6 mm and the edge stay too long.)"""
    from cloth.wrinkles import apply_constraints

    m = sheet_model()  # cotton: d_max 1.25 times the rest spacing
    t = m.tess
    surf = DetailedSurface(m)
    x = m.cloth.rest_positions * np.array([1.5, 1.0, 1.0])
    surf.step(x, None, None, None, None, DT)
    s = surf.state
    spacing = 0.04 / t.level
    k = int(np.argmin(np.linalg.norm(s.p_smoothed - [0.09, 0.0, 0.04], axis=1)))  # inside a face
    assert np.linalg.norm(s.p_smoothed[k] - [0.09, 0.0, 0.04]) < 1e-9 and k >= t.n_coarse
    dh = np.zeros(t.n_vertices)
    floor = np.zeros(t.n_vertices)
    dh[k] = floor[k] = 0.006
    p = np.zeros_like(s.p)
    apply_constraints(s.p_smoothed, s.n_pn, dh, floor, np.full(t.n_vertices, 0.03), t.face_ids, t.face_edges,
                      s.edge_required, s.edge_deficit,
                      t.edge_ids, t.interior_local, m.d_edges, m.d_max, m.height_allowance, m.d_edge_start,
                      m.d_edge_ids, 4, 0.03, s.flat_edge, s.moved, s.stamp, s.start_h, True, s.fold, p)
    ref = np.linalg.norm(s.p_smoothed[m.d_edges[:, 0]] - s.p_smoothed[m.d_edges[:, 1]], axis=1)
    stretched = ref > m.d_max
    assert stretched.sum() > 100  # the edges along x
    rest2 = (m.d_max / 1.25) ** 2
    limit = np.where(stretched, np.sqrt(ref**2 + m.d_max**2 - rest2), m.d_max)
    d = np.linalg.norm(p[m.d_edges[:, 0]] - p[m.d_edges[:, 1]], axis=1)
    assert np.all(d <= limit * (1 + 1e-9))
    assert dh[k] == 0.006
    q = s.p_smoothed
    along_x = [j for j in range(t.n_vertices) if abs(abs(q[j, 0] - q[k, 0]) - 1.5 * spacing) < 1e-9
               and abs(q[j, 2] - q[k, 2]) < 1e-9]
    along_z = [j for j in range(t.n_vertices) if abs(abs(q[j, 2] - q[k, 2]) - spacing) < 1e-9
               and abs(q[j, 0] - q[k, 0]) < 1e-9]
    assert len(along_x) == 2 and len(along_z) == 2
    np.testing.assert_allclose(dh[along_x + along_z], 0.006 - 0.75 * spacing, rtol=1e-9)
    others = np.setdiff1d(np.arange(t.n_vertices), [k] + along_x + along_z)
    assert np.abs(dh[others]).max() < 0.006 - 0.75 * spacing  # the lift spreads no farther than it must


def test_a_fold_over_a_curved_limb_comes_down_where_its_top_stands_too_wide():
    """S106 step 5 (Decision): two neighbours on a cylinder of radius 5 cm, 0.2 rad apart (9.98 mm
    on the reference surface), both 20 mm up along their radial normals: 13.98 mm apart, beyond
    d_max (12 mm). Neither can meet the limit alone: along one's normal the other stays at least
    r sin 0.2 = 13.9 mm away. Both come down together until the edge is d_max long, and no
    further; before the Decision the edge stayed too long."""
    from cloth.wrinkles import apply_constraints

    radius, angle, d_max = 0.05, 0.2, 0.012
    phi = np.array([-angle / 2, angle / 2])
    n = np.stack([np.sin(phi), np.cos(phi), np.zeros(2)], axis=1)
    ps = radius * n
    dh = np.full(2, 0.02)
    assert (radius + dh[0]) * np.sin(angle) > d_max  # out of reach of either end alone
    p = np.zeros((2, 3))
    no_faces = np.zeros((0, 28), np.int32)
    apply_constraints(ps, n, dh, np.zeros(2), np.full(2, 0.03), no_faces, np.zeros((0, 3), np.int32), np.zeros(0),
                      np.zeros(0), np.zeros((0, 7), np.int32), np.zeros(0, np.int32), np.array([[0, 1]], np.int32),
                      np.array([d_max]), 1 - 1 / 1.25**2, np.array([0, 1, 2], np.int64), np.zeros(2, np.int32), 4,
                      0.03, np.zeros(0, np.uint8), np.zeros((2, 2), np.int32), np.zeros(2, np.int32), np.zeros(2),
                      True, np.zeros(2, np.uint8), p)
    np.testing.assert_allclose(np.linalg.norm(p[0] - p[1]), d_max, rtol=1e-9)
    assert np.all(dh > 0.009)  # about half their height left
    np.testing.assert_allclose(p, ps + dh[:, None] * n, atol=1e-15)


def body_mesh_of(verts, tris):
    return BodyMesh.build(tris, len(verts))


@pytest.mark.parametrize("shape", ["box", "sphere"])
def test_detailed_particle_inside_a_body_ends_outside(shape):
    """A sheet over a box / sphere whose top pokes through the sheet's middle: every detailed
    particle ends outside (exact signed distance to the analytic shape)."""
    if shape == "box":
        bv, bt = box(half=0.05, n=8)
        bv = bv + [0.08, -0.045, 0.04]  # top face at y = +5 mm, under the sheet's middle
    else:
        bv, bt = uv_sphere(radius=0.05, n_lat=32, n_lon=64)
        bv = bv + [0.08, -0.044, 0.04]
    body = body_mesh_of(bv, bt)
    m = sheet_model()
    surf = DetailedSurface(m)
    x = m.cloth.rest_positions.copy()
    nearest = np.array([int(np.argmin(np.linalg.norm(bv - q, axis=1))) for q in x], dtype=np.int32)
    p, _ = surf.step(x, nearest, np.ascontiguousarray(bv), body, face_normals(bv, bt), DT)
    if shape == "box":
        c = np.array([0.08, -0.045, 0.04])
        q = np.abs(p - c)
        inside = np.all(q < 0.05 - 1e-9, axis=1)
        assert surf.tested > 0 and surf.state.dh_pen.max() > 0.004
        assert not inside.any()
    else:
        r = np.linalg.norm(p - [0.08, -0.044, 0.04], axis=1)
        # the tessellated sphere lies inside the analytic one by its chord sag; check against the mesh radius
        sag = 0.05 * (1 - np.cos(np.pi / 32))
        assert surf.state.dh_pen.max() > 0.004
        assert r.min() >= 0.05 - sag - 1e-6


def test_the_clearance_grows_below_level_6_with_the_triangles_sag():
    """Decision (the triangles' sag, `SurfaceSettings.lift_clearance`): 1 mm at level 6 and above, 1 mm x 6 / L
    below it, unless set."""
    assert SurfaceSettings().lift_clearance == 0.001
    assert SurfaceSettings(level=8).lift_clearance == 0.001
    assert SurfaceSettings(level=3).lift_clearance == pytest.approx(0.002)
    assert SurfaceSettings(level=4).lift_clearance == pytest.approx(0.0015)
    assert SurfaceSettings(level=3, clearance=0.0005).lift_clearance == 0.0005


@pytest.mark.parametrize("level, clearance, centroids_out", [(6, None, True), (3, None, True), (3, 0.001, False)])
def test_a_sheet_over_a_small_sphere_keeps_its_triangles_out_at_a_low_level(level, clearance, centroids_out):
    """A sheet over a sphere of radius 3 cm whose top pokes 4 mm through it: S103 lifts every detailed particle
    the level's clearance out of the sphere. At level 3 a detailed triangle is about 13 mm across, and over the
    sphere its middle sags about 1.2 mm towards it: with 1 mm of clearance (as at level 6) some triangles' centroids
    end inside the sphere, with the level's 2 mm none does; at level 6 (triangles half as wide, a quarter of the
    sag) 1 mm keeps them out."""
    bv, bt = uv_sphere(radius=0.03, n_lat=32, n_lon=64)
    centre = np.array([0.08, -0.026, 0.04])
    bv = bv + centre
    body = body_mesh_of(bv, bt)
    cloth = sheet_model().cloth
    surf = DetailedSurface(build_surface_model(cloth, SurfaceSettings(level=level, clearance=clearance)))
    x = cloth.rest_positions.copy()
    nearest = np.array([int(np.argmin(np.linalg.norm(bv - q, axis=1))) for q in x], dtype=np.int32)
    p, _ = surf.step(x, nearest, np.ascontiguousarray(bv), body, face_normals(bv, bt), DT)
    radius = 0.03 * np.cos(np.pi / 32)  # (the mesh's faces lie inside the analytic sphere by their chord sag)
    vertex = np.linalg.norm(p - centre, axis=1) - radius
    centroid = np.linalg.norm(p[surf.model.tess.triangles].mean(axis=1) - centre, axis=1) - radius
    clearance = surf.model.settings.lift_clearance
    assert surf.state.dh_pen.max() > 0.004
    assert vertex.min() >= clearance - 1e-4  # every particle the clearance out
    assert (centroid.min() > 0.0) == centroids_out


def test_a_body_part_pressing_from_the_outer_side_lowers_the_sheet_and_lets_it_go():
    """Decision (S103): a box above the sheet (on its outer side, along n_i) whose bottom
    reaches 5 mm below it, like a hand pressed on a skirt. Lifting would carry the particles
    through the whole box; they go down instead, to the box's bottom less the clearance
    (y = -6 mm where the bottom face is nearest), and S106 keeps them there. When the box has
    gone, the sheet is flat at its reference surface again."""
    bv, bt = box(half=0.05, n=8)
    centre = np.array([0.08, 0.045, 0.04])  # bottom face at y = -5 mm
    body = body_mesh_of(bv + centre, bt)
    m = sheet_model()
    surf = DetailedSurface(m)
    x = m.cloth.rest_positions.copy()

    def step(offset):
        b = np.ascontiguousarray(bv + centre + offset)
        nearest = np.array([int(np.argmin(np.linalg.norm(b - q, axis=1))) for q in x], dtype=np.int32)
        return surf.step(x, nearest, b, body, face_normals(b, bt), DT)[0].copy()

    p = step(0.0)
    s = surf.state
    q = np.abs(p - centre)
    assert not np.all(q < 0.05 + 0.001 - 1e-9, axis=1).any()  # every particle clearance outside the box
    under = np.all(np.abs(s.p_smoothed - centre)[:, [0, 2]] < 0.05 - 0.005, axis=1)  # away from the side walls
    assert under.sum() > 100
    np.testing.assert_allclose(p[under, 1], -0.006, atol=1e-9)
    assert np.all(s.dh_pen[under] < 0.0) and s.dh_pen.max() <= 0.0  # lowered, nothing lifted
    outside = np.any(np.abs(s.p_smoothed - centre)[:, [0, 2]] > 0.05 + 0.01, axis=1)
    np.testing.assert_allclose(p[outside, 1], 0.0, atol=1e-12)
    p = step(np.array([0.0, 0.2, 0.0]))  # the box lifted away
    np.testing.assert_allclose(p[:, 1], 0.0, atol=1e-12)


@pytest.mark.parametrize("face_margin,lift_search", [(0.01, True), (0.01, False), (0.005, True)])
def test_a_coarse_face_whose_corners_stand_off_the_body_is_tested_between_them(face_margin, lift_search):
    """Decision (S103): a cube of half-width 13 mm whose top is 3 mm above the flat sheet, under
    the middle of the coarse edge from (0, 0, 40) to (40, 0, 40) mm. That edge's end particles
    are 7 mm from the cube, farther than the 5 mm contact_margin of that time; every other coarse particle is
    farther still. With face_margin 10 mm the faces around the edge are tested from their
    corners' first subdivision (the mid-edge particle, inside) down, and the particles over
    the cube are found inside and end outside it: lifted by S103's search (lift_search; their
    walks end on the cube's side walls, along which n_i runs), or without it moved out by
    `leave_creases`; with face_margin = contact_margin (the rule before) they are never tested
    and stay inside it."""
    bv, bt = box(half=0.013, n=6)
    centre = np.array([0.02, -0.01, 0.04])
    bv = np.ascontiguousarray(bv + centre)
    body = body_mesh_of(bv, bt)
    # (the rule before: faces tested only as far as the 5 mm contact margin of that time)
    m = build_surface_model(sheet_model().cloth, SurfaceSettings(face_margin=face_margin, lift_search=lift_search,
                                                                 contact_margin=min(0.0075, face_margin)))
    surf = DetailedSurface(m)
    x = m.cloth.rest_positions.copy()
    nearest = np.array([int(np.argmin(np.linalg.norm(bv - q, axis=1))) for q in x], dtype=np.int32)
    p, _ = surf.step(x, nearest, bv, body, face_normals(bv, bt), DT)
    inside = np.all(np.abs(p - centre) < 0.013 - 1e-9, axis=1)
    over = np.all(np.abs(surf.state.p_smoothed - centre)[:, [0, 2]] < 0.013 - 1e-9, axis=1)
    assert over.sum() == 9  # a 3 x 3 block of the lattice (spacing 6.7 mm)
    if face_margin > 0.005:
        assert not inside.any()
        assert np.isfinite(surf.state.sd[over]).all()  # tested
        if lift_search:
            assert surf.state.dh_pen[over].min() > 0.003  # lifted
        else:
            assert surf.state.sd[over].max() < 0.0 and surf.creased >= over.sum()  # left inside, then moved out
    else:
        assert inside[over].all() and np.isinf(surf.state.sd[over]).all()  # never tested


def test_a_finer_particle_is_tested_while_its_parents_distances_leave_it_room_inside():
    """Decision (S103, the Lipschitz reach): a sphere of radius 1.5 mm around a particle of the
    finest lattice whose parents are none of them a coarse corner, each more than 6 mm away: the
    particle is 1 mm inside the sphere, every parent more than the contact margin (7.5 mm) outside it.
    By the margin alone the particle was never tested and stayed inside; as the distance to
    the body changes no faster than the position, a parent's distance that is less than the
    clearance plus how far it lies from the particle leaves room for it inside, and where every
    parent's does, the particle is tested: it is found inside and lifted out."""
    m = build_surface_model(sheet_model().cloth, SurfaceSettings(face_margin=0.03))
    t = m.tess
    x = m.cloth.rest_positions.copy()
    rest = DetailedSurface(m)
    rest.step(x, np.zeros(len(x), np.int32), *far_body(), DT)
    flat = rest.state.p_smoothed.copy()
    f = 2  # a coarse triangle in the sheet's middle
    best, best_gap = -1, 0.0
    for loc in range(t.parents.shape[0]):
        par = t.parents[loc][t.parents[loc] >= 0]
        if len(par) == 0 or np.any(t.parents[par, 0] < 0):
            continue  # a corner, or a corner's child
        gap = np.linalg.norm(flat[t.face_ids[f, par]] - flat[t.face_ids[f, loc]], axis=1).min()
        if gap > best_gap:
            best, best_gap = loc, gap
    assert best_gap > 0.006
    vid = t.face_ids[f, best]
    r, c = 0.0015, flat[vid] - [0.0, 0.0005, 0.0]  # a sphere whose top stands 1 mm over the particle
    bv, bt = uv_sphere(radius=r, n_lat=16, n_lon=32)
    bv = np.ascontiguousarray(bv + c)
    par_ids = t.face_ids[f, t.parents[best][t.parents[best] >= 0]]
    gap_out = np.linalg.norm(flat[par_ids] - c, axis=1) - r
    reach = 0.001 + np.linalg.norm(flat[par_ids] - c, axis=1)  # the clearance plus each one's distance
    # beyond the margin, room inside
    assert np.all(gap_out > SurfaceSettings().contact_margin) and np.all(gap_out < reach)
    nearest = np.array([int(np.argmin(np.linalg.norm(bv - q, axis=1))) for q in x], dtype=np.int32)
    surf = DetailedSurface(m)
    p, _ = surf.step(x, nearest, bv, body_mesh_of(bv, bt), face_normals(bv, bt), DT)
    sag = r * (1 - np.cos(np.pi / 16))  # (the mesh lies inside the analytic sphere by its chord sag)
    assert np.linalg.norm(p[vid] - c) > r - sag
    assert np.isfinite(surf.state.sd[vid]) and surf.state.dh_pen[vid] > 0.0014
    assert np.all(np.isfinite(surf.state.sd[par_ids]))


def stuck_over_the_lower_box(recheck=False, part_b=False):
    """The body of the tests of walks stopped on a local minimum, after the sheet's first frame: a
    box whose top lies 3 mm under the whole sheet, a small box whose bottom lies 5 cm over its
    middle and, with part_b, a smaller box 7.5-8.5 cm over it as a second body part (with a vertex
    grid of 10 cm cells); the particle's own vertex off, the Lipschitz check as given, every coarse
    particle's nearest vertex on the lower box. Returns a namespace: surf, s (its state), t (its
    tessellation), x, nearest, bv, body, face_n, grid (None without part_b), f (a coarse triangle in
    the sheet's middle), vid (its first particle after the corners, read 3 mm), lower_faces (the
    lower box's face count: faces below it are its), upper_bottom (a face on the upper box's bottom),
    upper_top (a vertex on its top), ov and b0 (part B's vertices and the first one's index)."""
    lv, lt = box(half=0.1, n=8)
    lv = lv + [0.08, -0.103, 0.04]
    uv, ut = box(half=0.01, n=2)
    uv = uv + [0.08, 0.06, 0.04]
    ov, ot = box(half=0.005, n=1)
    ov = ov + [0.08, 0.08, 0.04]
    meshes = [(lv, lt), (uv, ut)] + ([(ov, ot)] if part_b else [])
    starts = np.cumsum([0] + [len(v) for v, _ in meshes])
    bv = np.ascontiguousarray(np.concatenate([v for v, _ in meshes]))
    bt = np.concatenate([tr + k for (_, tr), k in zip(meshes, starts)]).astype(np.int32)
    regions = np.r_[np.full(len(lv) + len(uv), 1), np.full(len(bv) - len(lv) - len(uv), 2)].astype(np.uint16)
    body, face_n = BodyMesh.build(bt, len(bv), regions), face_normals(bv, bt)
    grid = None
    if part_b:
        grid = VertexGrid(len(bv), cell=0.1)
        grid.update(bv, regions)
    surf = DetailedSurface(build_surface_model(sheet_model().cloth, SurfaceSettings(own_vertex=False,
                                                                                    recheck=recheck)))
    x = surf.model.cloth.rest_positions.copy()
    nearest = np.array([int(np.argmin(np.linalg.norm(lv - q, axis=1))) for q in x], dtype=np.int32)
    surf.step(x, nearest, bv, body, face_n, DT, grid)
    t, f = surf.model.tess, 2
    vid = t.face_ids[f, int(t.order[3])]
    assert np.isclose(surf.state.sd[vid], 0.003)
    upper_bottom = len(lt) + int(np.argmin(bv[bt[len(lt):len(lt) + len(ut)]].mean(axis=1)[:, 1]))
    return SimpleNamespace(surf=surf, s=surf.state, t=t, x=x, nearest=nearest, bv=bv, body=body, face_n=face_n,
                           grid=grid, f=f, vid=vid, lower_faces=len(lt), upper_bottom=upper_bottom,
                           upper_top=len(lv) + int(np.argmax(uv[:, 1])), ov=ov, b0=len(lv) + len(uv))


@pytest.mark.parametrize("recheck", [True, False])
def test_a_reading_farther_than_its_parents_allow_is_walked_again_from_theirs(recheck):
    """Decision (S103, the Lipschitz check): a sheet 3 mm over a box, a small box 5 cm over the
    sheet. After a first frame every particle's walk ends on the lower box; then one finer
    particle's walk is remembered on the upper box (a walk stopped on a local minimum), and the
    coarse seeds are put there too, so the seed check does not catch it (nor the particle's own
    vertex: off). Its tested parents read 3 mm, 2 cm from it, so its reading of 5 cm cannot
    be right: with the check it walks again from a parent's face and reads the lower box, 3 mm
    (the exact distance); without it reads the upper box."""
    b = stuck_over_the_lower_box(recheck)
    s, t, f, vid = b.s, b.t, b.f, b.vid
    loc = int(t.order[3])  # the first particle after the corners, tested from them
    par_ids = t.face_ids[f, t.parents[loc][t.parents[loc] >= 0]]
    assert np.allclose(s.sd[par_ids], 0.003)
    assert (s.body_face[np.isfinite(s.sd)] < b.lower_faces).all()
    s.body_face[vid] = b.upper_bottom
    b.nearest[:] = b.upper_top
    b.surf.step(b.x, b.nearest, b.bv, b.body, b.face_n, DT)
    assert np.allclose(s.sd[par_ids], 0.003)  # (their walks start on the lower box, as before)
    gap = np.linalg.norm(s.p[par_ids] - s.p[vid], axis=1).min()
    assert 0.001 < gap < 0.021  # (an edge's midpoint, 2 cm from its corners)
    if recheck:
        assert np.isclose(s.sd[vid], 0.003) and s.body_face[vid] < b.lower_faces
    else:
        assert s.sd[vid] > 0.045 and s.body_face[vid] >= b.lower_faces


def test_a_walk_reading_farther_than_a_corners_nearest_vertex_walks_again_from_it():
    """Decision (S103, the nearest corner's seed): the two boxes of the Lipschitz check's test, its
    check and the particle's own vertex off. After a first frame one finer particle's walk is
    remembered on the upper box (5 cm over the sheet: a walk stopped on a local minimum), and the
    first corner of its coarse face gets a nearest vertex on the upper box's top. The nearest of
    its corners' nearest vertices, on the lower box, is nearer to it than 5 cm, so the reading is
    a local minimum's: it walks again from that vertex and reads the lower box, 3 mm. With the
    first corner's vertex as its seed (the rule before), the upper box's reading stood."""
    b = stuck_over_the_lower_box()
    s, t, f, vid, nearest = b.s, b.t, b.f, b.vid, b.nearest
    s.body_face[vid] = b.upper_bottom
    nearest[t.face_ids[f, 0]] = b.upper_top
    seeds = b.bv[nearest[t.face_ids[f, t.order[:3]]]]
    assert np.linalg.norm(seeds - s.p[vid], axis=1).min() < 0.045 < np.linalg.norm(seeds[0] - s.p[vid])
    b.surf.step(b.x, nearest, b.bv, b.body, b.face_n, DT)
    assert np.isclose(s.sd[vid], 0.003) and s.body_face[vid] < b.lower_faces


def test_a_nearer_reading_from_the_last_frames_walk_in_another_part_decides_in_the_same_part():
    """Decision (S103, a nearer reading in the same part): the two boxes of the Lipschitz check's
    test, one body part, its check and the particle's own vertex off, every seed on the upper box.
    One finer particle's walk is remembered on the upper box (5 cm away: a walk stopped on a local
    minimum) and its walk in another part on the lower box's top (as where such a walk ended the
    frame before). That walk ends in the first walk's part: it reads 3 mm, the nearer reading
    decides, and the next frame's walk starts from where it ended. (Before, a walk that came back
    to the first walk's part was dropped, and the 5 cm reading stood.)"""
    b = stuck_over_the_lower_box()
    s, vid = b.s, b.vid
    s.part_face[vid] = s.body_face[vid]  # (on the lower box's top)
    s.body_face[vid] = b.upper_bottom
    b.nearest[:] = b.upper_top
    b.surf.step(b.x, b.nearest, b.bv, b.body, b.face_n, DT)
    assert np.isclose(s.sd[vid], 0.003) and s.body_face[vid] < b.lower_faces and s.part_face[vid] == -1


def test_a_seed_of_the_walked_part_nearer_than_the_reading_walks_again_from_it():
    """Decision (S103, a seed nearer than the reading): the two boxes of the Lipschitz check's test
    as one body part (A), and a small box 7.5-8.5 cm over the sheet as another (B); its check and the
    particle's own vertex off, a vertex grid of 10 cm cells. After a first frame one finer particle's
    walk is remembered on the upper box of A (5 cm away: a walk stopped on a local minimum), and
    every coarse particle's nearest vertex is put on B, farther than that, so the nearest corner's
    seed does not fire. The seeds of A near the corners (the grid's, on the lower box's top) are
    nearer to it than 5 cm: it walks again from the nearest and reads the lower box, 3 mm. Before,
    the part the first walk ended in was never walked again, and the 5 cm reading stood."""
    b = stuck_over_the_lower_box(part_b=True)
    s, t, f, vid = b.s, b.t, b.f, b.vid
    assert s.part_face[vid] == -1
    s.body_face[vid] = b.upper_bottom
    nearest = np.array([b.b0 + int(np.argmin(np.linalg.norm(b.ov - q, axis=1))) for q in b.x], dtype=np.int32)
    assert np.linalg.norm(b.bv[nearest[t.face_ids[f, t.order[:3]]]] - s.p[vid], axis=1).min() > 0.05  # (no seed)
    b.surf.step(b.x, nearest, b.bv, b.body, b.face_n, DT, b.grid)
    assert np.isclose(s.sd[vid], 0.003) and s.body_face[vid] < b.lower_faces


def far_body():
    """A box 1 m under the sheet (nothing near it): the flat reference surface."""
    bv, bt = box(half=0.05, n=2)
    bv = np.ascontiguousarray(bv + [0.08, -1.0, 0.04])
    return bv, body_mesh_of(bv, bt), face_normals(bv, bt)


def test_a_coarse_face_bulging_towards_the_body_is_tested_from_its_corners_bulge_farther():
    """Decision (S103, the bulge): a coarse dome (a paraboloid of curvature radius 25 mm at its
    apex, in the middle of the centre quad) under a wide box, like a sleeve's cloth under an arm:
    the box lies on the cloth's outer side (the corners face it: facing < 0), and its bottom is
    5.5 mm above the centre quad's corners, farther than face_margin = contact_margin (5 mm). The
    PN patch bulges 7 mm above those corners, so 9 of its reference particles are inside the box.
    The corners count as near from face_margin plus that bulge (`bulge_towards_body`): the quad is
    tested and no particle stays inside. (By face_margin alone it was skipped: all 9 stayed.)"""
    verts, faces = grid_sheet(4, 4, 0.04)
    verts[:, 1] = -((verts[:, 0] - 0.06) ** 2 + (verts[:, 2] - 0.06) ** 2) / (2 * 0.025)
    coarse = CoarseMesh(verts, faces, np.zeros(0, np.int32), np.zeros((0, 3)))
    cloth = build_cloth_model(Garment("dome", verts, faces, np.arange(len(verts))), fabric("cotton"), SimSettings(),
                              verts, coarse)
    m = build_surface_model(cloth, SurfaceSettings(face_margin=0.005))
    half = 0.03
    centre = np.array([0.06, -0.0105 + half, 0.06])  # bottom face at y = -10.5 mm, over the centre quad
    bv, bt = box(half=half, n=6)
    bv = np.ascontiguousarray(bv + centre)
    surf = DetailedSurface(m)
    x = m.cloth.rest_positions.copy()
    nearest = np.array([int(np.argmin(np.linalg.norm(bv - q, axis=1))) for q in x], dtype=np.int32)
    p, _ = surf.step(x, nearest, bv, body_mesh_of(bv, bt), face_normals(bv, bt), DT)
    s = surf.state
    corners = np.flatnonzero(np.isclose(x[:, 1], -0.016))  # the centre quad's
    assert len(corners) == 4 and np.all(s.sd[corners] > 0.0054) and np.all(s.facing[corners] < -0.5)
    assert np.sum(np.all(np.abs(s.p_smoothed - centre) < half, axis=1)) == 9
    assert s.p_smoothed[:, 1].max() > -0.016 + 0.006  # the bulge
    assert not np.all(np.abs(p - centre) < half - 1e-9, axis=1).any()


@pytest.mark.parametrize("find_parts,arm_bit", [(True, 2), (False, 2), (True, 256)])
def test_a_particle_inside_another_body_part_is_found_by_a_walk_in_that_part(find_parts, arm_bit):
    """Two body parts: a torso box 4 mm under the sheet, whose faces every walk from the coarse
    particles' nearest vertices (on the torso) ends on, and an arm box in the sheet's middle
    whose bottom is 1 mm under it. The nearest surface to the particles over the arm's bottom
    is the arm's: they are 1 mm inside it, though the walk on the torso says 4 mm outside. The
    walk that starts in the arm (through the vertex grid) finds it; they go down, out of the
    arm, to y = -2 mm (1 mm under its bottom, 2 mm over the torso), and no particle is left
    inside the arm. Without the grid they stay where they are, inside the arm. The same with the
    arm's region bit past the first eight (as a MakeHuman forearm's is)."""
    tv, tt = box(half=0.05, n=8)
    tv = tv + [0.08, -0.054, 0.04]  # torso: top face at y = -4 mm
    av, at = box(half=0.02, n=8)
    av = av + [0.08, 0.019, 0.04]  # arm: bottom face at y = -1 mm, x 0.06-0.10, z 0.02-0.06
    bv = np.ascontiguousarray(np.vstack([tv, av]))
    bt = np.vstack([tt, at + len(tv)]).astype(np.int32)
    regions = np.r_[np.full(len(tv), 1), np.full(len(av), arm_bit)].astype(np.uint16)
    body = BodyMesh.build(bt, len(bv), regions)
    grid = VertexGrid(len(bv))
    grid.update(bv, regions)
    m = sheet_model()
    surf = DetailedSurface(m)
    x = m.cloth.rest_positions.copy()
    nearest = np.array([int(np.argmin(np.linalg.norm(tv - q, axis=1))) for q in x], dtype=np.int32)
    p = surf.step(x, nearest, bv, body, face_normals(bv, bt), DT, grid if find_parts else None)[0]
    s = surf.state
    over = np.all(np.abs(s.p_smoothed - [0.08, 0.0, 0.04])[:, [0, 2]] < 0.02 - 0.004, axis=1)  # off the arm's walls
    assert over.sum() > 20
    if find_parts:
        np.testing.assert_allclose(p[over, 1], -0.002, atol=1e-9)
        inside_arm = np.all(np.abs(p - [0.08, 0.019, 0.04]) < 0.02 - 1e-9, axis=1)  # (some lie on its walls)
        assert not inside_arm.any()
    else:
        np.testing.assert_allclose(p[over, 1], 0.0, atol=1e-12)


def test_a_coarse_vertex_no_lift_gets_out_goes_back_to_its_coarse_particle():
    """Decision (S103, back to where S101 put it): a box beside a coarse vertex's normal (x 5-8.2 cm,
    y 5-45 mm over the sheet), and the vertex's height carried at 20 mm, 2 mm inside the box's side
    wall. Its nearest surface is that wall, whose normal is across n_i (n_i . n_body = 0), so no move
    along n_i gets it out. It goes back to the coarse particle (Δh = 0), 5 mm under the box: outside,
    read there. (Before, it kept its height inside the box.)"""
    m = sheet_model()
    x = m.cloth.rest_positions.copy()
    c0 = int(np.argmin(np.linalg.norm(x - [0.08, 0.0, 0.04], axis=1)))
    bv, bt = box(half=0.5, n=4)
    bv = np.ascontiguousarray(bv * [0.032, 0.04, 0.04] + [0.066, 0.025, 0.04])
    surf = DetailedSurface(m)
    nearest = np.array([int(np.argmin(np.linalg.norm(bv - q, axis=1))) for q in x], dtype=np.int32)
    surf.state.dh[c0] = 0.02
    p = surf.step(x, nearest, bv, body_mesh_of(bv, bt), face_normals(bv, bt), DT)[0]
    s = surf.state
    np.testing.assert_allclose(p[c0], x[c0], atol=1e-12)
    assert s.dh[c0] == 0.0 and np.isclose(s.sd[c0], 0.005)
    assert not np.all((p > bv.min(axis=0)) & (p < bv.max(axis=0)), axis=1).any()


def torso_under_arm(torso_top, arm_bottom, arm_top, arm_quads=8):
    """A torso box (10 cm, its top face at y = torso_top) under the sheet's middle and an arm box
    (x 5-11 cm, z 1-7 cm, y arm_bottom..arm_top) across it, two body parts: (torso vertices, body
    vertices, triangles, BodyMesh, VertexGrid, WindingGrid), the grids updated."""
    tv, tt = box(half=0.05, n=8)
    tv = tv + [0.08, torso_top - 0.05, 0.04]
    av, at = box(half=0.03, n=arm_quads)
    half = 0.5 * (arm_top - arm_bottom)
    av = av * [1.0, half / 0.03, 1.0] + [0.08, arm_bottom + half, 0.04]
    return (tv, *torso_and_arm(tv, tt, av, at))


def torso_and_arm(tv, tt, av, at):
    """Two boxes (vertices, triangles) as two body parts, torso then arm: (body vertices,
    triangles, BodyMesh, VertexGrid, WindingGrid), the grids updated."""
    bv = np.ascontiguousarray(np.vstack([tv, av]))
    bt = np.vstack([tt, at + len(tv)]).astype(np.int32)
    regions = np.r_[np.full(len(tv), 1), np.full(len(av), 2)].astype(np.uint16)
    body = BodyMesh.build(bt, len(bv), regions)
    grid = VertexGrid(len(bv))
    grid.update(bv, regions)
    winding = WindingGrid(body.winding_faces, len(bv), cell=0.01)
    winding.update(bv)
    return bv, bt, body, grid, winding


@pytest.mark.parametrize("arm_quads", [8, 2])
def test_a_particle_behind_another_body_parts_surface_goes_out_along_its_normal(arm_quads):
    """Decision (`creases.out_along_normals`, sixtieth session): a torso box whose top face, 4 mm
    under the sheet, is buried in an arm box the sheet runs through (its bottom 12 mm under the
    sheet, its top 8 mm over it). The nearest surface to the particles over the arm's middle is
    the torso's buried top, 4 mm below them, facing them: S103 reads them outside. Its walk in
    the arm finds them behind the arm's surface (`behind`), so the winding number is asked, and
    they go up along n_i, out of the arm's top, the clearance beyond it; no detailed particle is
    left inside the arm, the coarse vertex in its middle included (along its normal too, since the
    seventy-second session; it was left inside before). With the arm's sides in 2
    x 2 quads (vertices 3 cm apart) most of those walks end at a vertex farther than the part
    could be nearest from (`other_part_distance`), and p behind every face around it marks them
    the same. (The moves out of creases are off here: they take the particles the arm's walk
    ended within 1 cm of out through the nearest wall, and not those it ended farther from.)"""
    # torso: top face at y = -4 mm; arm: y -12..8 mm, x 0.05-0.11, z 0.01-0.07
    tv, bv, bt, body, grid, winding = torso_under_arm(-0.004, -0.012, 0.008, arm_quads)
    m = build_surface_model(sheet_model().cloth, SurfaceSettings(creases=False))
    surf = DetailedSurface(m)
    x = m.cloth.rest_positions.copy()
    nearest = np.array([int(np.argmin(np.linalg.norm(tv - q, axis=1))) for q in x], dtype=np.int32)
    p = surf.step(x, nearest, bv, body, face_normals(bv, bt), DT, grid, winding=winding.arrays())[0]
    s = surf.state
    fine = np.arange(len(p)) >= m.tess.n_coarse
    middle = fine & np.all(np.abs(s.p_smoothed - [0.08, 0.0, 0.04])[:, [0, 2]] < 0.022, axis=1)  # 8 mm+ off the walls
    assert middle.sum() > 20
    assert np.all(s.behind[middle] == 1)
    np.testing.assert_allclose(s.sd[middle], 0.004, atol=1e-9)  # S103: outside, over the torso's buried top
    np.testing.assert_allclose(p[middle, 1], 0.008 + SurfaceSettings().lift_clearance, atol=1e-5)
    assert surf.exited >= middle.sum() and surf.creased == 0
    inside_arm = np.all(np.abs(p - [0.08, -0.002, 0.04]) < [0.03 - 1e-6, 0.01 - 1e-6, 0.03 - 1e-6], axis=1)
    assert not inside_arm.any()
    centre = np.flatnonzero(np.all(np.abs(x - [0.08, 0.0, 0.04])[:, [0, 2]] < 0.022, axis=1))  # coarse vertices
    assert len(centre) == 1
    np.testing.assert_allclose(p[centre, 1], 0.008 + SurfaceSettings().lift_clearance, atol=1e-5)
    np.testing.assert_allclose(p[centre][:, [0, 2]], x[centre][:, [0, 2]], atol=1e-12)  # straight up its normal


@pytest.mark.parametrize("height_reach", [False, True])
def test_particles_raised_into_a_body_part_over_the_cloth_are_tested(height_reach):
    """Decision (S103's heights' reach, `wrinkles.avoid_penetration`): a sheet 2 cm over a torso box,
    under an arm box whose bottom is 5 mm over it (x 5-11 cm, z 1-7 cm), with S103's margins at 2 mm:
    its coarse faces' corners are all farther than that from the body, so S103 skips the faces. The
    detailed particles over the arm's middle carry Δh = 2 cm from the frame before, which takes them
    into the arm. With the heights' reach their faces count as near (the corners within the margin
    plus the largest |Δh|), S103 tests every one of them and none is left inside the arm; without,
    none is tested and S106's neighbour distances bring them down only to 0-10 mm, 8 inside it."""
    tv, bv, bt, body, grid, winding = torso_under_arm(-0.02, 0.005, 0.017)  # torso top y = -20 mm, arm y 5..17 mm
    m = build_surface_model(sheet_model().cloth, SurfaceSettings(height_reach=height_reach, face_margin=0.002,
                                                                 contact_margin=0.002))
    surf = DetailedSurface(m)
    x = m.cloth.rest_positions.copy()
    nearest = np.array([int(np.argmin(np.linalg.norm(tv - q, axis=1))) for q in x], dtype=np.int32)
    surf.step(x, nearest, bv, body, face_normals(bv, bt), DT, grid, winding=winding.arrays())
    s = surf.state
    assert s.dh.max() == 0.0 and np.all(np.isfinite(s.sd) == (np.arange(len(s.p)) < len(x)))  # corners only
    fine = np.arange(len(s.p)) >= m.tess.n_coarse
    raised = fine & np.all(np.abs(s.p_smoothed - [0.08, 0.0, 0.04])[:, [0, 2]] < 0.022, axis=1)
    s.dh[raised] = 0.02  # (Δh_last_frame)
    p = surf.step(x, nearest, bv, body, face_normals(bv, bt), DT, grid, winding=winding.arrays())[0]
    inside_arm = np.all(np.abs(p - [0.08, 0.011, 0.04]) < [0.03 - 1e-6, 0.006 - 1e-6, 0.03 - 1e-6], axis=1)
    assert raised.sum() == 48
    if height_reach:
        assert np.isfinite(s.sd[raised]).all() and not inside_arm.any()
    else:
        assert not np.isfinite(s.sd[raised]).any() and inside_arm.sum() == 8
        assert p[raised, 1].max() < 0.0101


def test_particles_lowered_under_a_body_part_are_tested_where_they_would_come_back_to():
    """Decision (S103's heights' reach inside a face, eighty-fifth session): a small arm box (x 9-11
    cm, z 1-3 cm, y -4..6 mm) through the sheet's reference surface between coarse vertices, a torso
    box 26 mm under the sheet. The particles over the arm carry Δh = -13 mm from the frame before
    (S103 lowered them under the arm then), 9 mm under it. Their parents, lowered too, read 9-10 mm
    from the arm: by the Lipschitz reach alone (each parent within the clearance plus its distance)
    the finest one under the arm's middle was not tested, and S106's floor for an untested particle,
    the reference surface, took it back up into the arm (the walk's silk blouse at frame 68: 3 mm
    into the arm, lowered by 22 mm the frame before). The reach counts a particle's |Δh| too now:
    every particle under the arm is tested, stays 1 mm under it, and none ends inside."""
    m = build_surface_model(sheet_model().cloth, SurfaceSettings())
    tv, tt = box(half=0.05, n=8)
    tv = tv + [0.08, -0.026 - 0.05, 0.04]  # torso: top face at y = -26 mm
    av, at = box(half=0.01, n=4)
    av = av * [1.0, 0.5, 1.0] + [0.10, 0.001, 0.02]  # arm: x 9-11 cm, y -4..6 mm, z 1-3 cm
    bv, bt, body, grid, winding = torso_and_arm(tv, tt, av, at)
    surf = DetailedSurface(m)
    x = m.cloth.rest_positions.copy()
    assert not np.any(np.all(np.abs(x - [0.10, 0.001, 0.02]) < [0.01, 0.005, 0.01], axis=1))  # no coarse vertex in it
    nearest = np.array([int(np.argmin(np.linalg.norm(tv - q, axis=1))) for q in x], dtype=np.int32)
    surf.step(x, nearest, bv, body, face_normals(bv, bt), DT, grid, winding=winding.arrays())
    s = surf.state
    fine = np.arange(len(s.p)) >= m.tess.n_coarse
    over_arm = fine & np.all(np.abs(s.p_smoothed - [0.10, 0.0, 0.02])[:, [0, 2]] < 0.014, axis=1)
    s.dh[:] = 0.0
    s.dh[over_arm] = -0.013  # (Δh_last_frame: lowered under the arm, now 9 mm under it, 13 mm over the torso)
    p = surf.step(x, nearest, bv, body, face_normals(bv, bt), DT, grid, winding=winding.arrays())[0]
    inside_arm = np.all(np.abs(p - [0.10, 0.001, 0.02]) < [0.01 - 1e-6, 0.005 - 1e-6, 0.01 - 1e-6], axis=1)
    under_arm = np.all(np.abs(s.p_smoothed - [0.10, 0.0, 0.02])[:, [0, 2]] < 0.01, axis=1)
    assert over_arm.sum() > under_arm.sum() >= 9
    assert np.isfinite(s.sd[under_arm]).all()
    assert not inside_arm.any()


def test_a_small_body_part_anywhere_under_the_sheet_is_left_by_every_detailed_particle():
    """A small arm box (12 mm, its bottom 1 mm under the sheet) at 60 places over a torso box 4 mm
    under the sheet: no detailed particle that is not a coarse vertex stays inside it. S103 used
    to rule the arm out for a particle by its hierarchy parents' distances to the other body
    parts, but a parent on a coarse edge or corner was measured in the neighbouring coarse face,
    whose corners had no seed in the arm: 31 of the 60 places left 1-4 particles inside."""
    m = sheet_model()
    tv, tt = box(half=0.12, n=16)
    tv = tv + [0.08, -0.124, 0.04]  # torso: top face at y = -4 mm
    av, at = box(half=0.006, n=4)
    regions = np.r_[np.full(len(tv), 1), np.full(len(av), 2)].astype(np.uint16)
    bt = np.vstack([tt, at + len(tv)]).astype(np.int32)
    x = m.cloth.rest_positions.copy()
    nearest = np.array([int(np.argmin(np.linalg.norm(tv - q, axis=1))) for q in x], dtype=np.int32)
    left = []
    for cx in np.arange(0.01, 0.155, 0.01):
        for cz in (0.015, 0.035, 0.055, 0.075):
            centre = np.array([cx, 0.005, cz])  # arm: bottom face at y = -1 mm
            bv = np.ascontiguousarray(np.vstack([tv, av + centre]))
            body = BodyMesh.build(bt, len(bv), regions)
            grid = VertexGrid(len(bv))
            grid.update(bv, regions)
            p = DetailedSurface(m).step(x, nearest, bv, body, face_normals(bv, bt), DT, grid)[0]
            inside = np.all(np.abs(p[m.tess.n_coarse:] - centre) < 0.006 - 1e-6, axis=1)
            if inside.any():
                left.append((round(cx, 3), cz, int(inside.sum())))
    assert left == []


def _height_over(p, tri, a):
    """The detailed surface's height over point a: (height, triangle) of the triangle under it in x-z."""
    u, v, w = p[tri[:, 0]], p[tri[:, 1]], p[tri[:, 2]]

    def cross2(o, s, t):
        return (s[:, 0] - o[:, 0]) * (t[:, 2] - o[:, 2]) - (s[:, 2] - o[:, 2]) * (t[:, 0] - o[:, 0])

    q = np.broadcast_to(a, u.shape)
    area = cross2(u, v, w)
    l0, l1, l2 = cross2(v, w, q) / area, cross2(w, u, q) / area, cross2(u, v, q) / area
    under = np.flatnonzero((l0 >= -1e-12) & (l1 >= -1e-12) & (l2 >= -1e-12))
    assert len(under) >= 1
    k = under[0]
    return l0[k] * u[k, 1] + l1[k] * v[k, 1] + l2[k] * w[k, 1], k


@pytest.mark.parametrize("arm_gap, seen", [(None, True), (0.002, True), (0.001, False)])
def test_the_triangle_over_a_body_tip_keeps_it_the_clearance_under_the_surface(arm_gap, seen):
    """Decision (the body's tips against the detailed triangles): the body vertex 8 mm out of
    its ring in the middle of a square of particles, without the tip allowance, came 0.26 mm
    through the triangle over it (the test above). With the pose's vertex tips the corners of
    the triangle over it rise along their normals until its plane lies the clearance over the
    vertex (by about 1.26 mm; the surface there leans a little, so 1.00-1.04 mm straight up),
    and through ten more frames, S106 included, it stays there without rising again. With
    another body part 2 mm over the surface there (an arm box), a raised corner would come
    nearer it than the clearance: nothing rises, the vertex shows through as before, and no
    particle enters the arm. With the arm 1 mm over it and unseen by S103 (no vertex grid: no
    walks in other parts), a raised corner would end inside it: the body's winding number
    refuses that (without the winding grid the corners rise into the arm)."""
    lattice = 0.04 / 6
    bv, bt, apex = raised_box_top(0.008, shift=lattice / 2)
    n_box = len(bv)
    regions = np.ones(len(bv), dtype=np.uint8)
    a = bv[apex].copy()
    if arm_gap is not None:  # an arm lying over the surface: its bottom face arm_gap over the tip's triangle
        av, at = box(half=0.01, n=4)
        arm_lo = np.array([a[0] - 0.01, a[1] - 0.00026 + arm_gap, a[2] - 0.01])
        av = av + arm_lo + 0.01
        bv = np.ascontiguousarray(np.vstack([bv, av]))
        bt = np.vstack([bt, at + len(bv) - len(av)]).astype(np.int32)
        regions = np.r_[regions, np.full(len(av), 2, dtype=np.uint8)]
    body = BodyMesh.build(bt, len(bv), regions)
    pose = BodyPose(body, face_tree=False, tips=True)
    pose.update(bv)
    grid = VertexGrid(len(bv))
    grid.update(pose.x, body.regions, body.parts)
    winding = WindingGrid(body.winding_faces, len(bv), cell=0.01)
    winding.update(pose.x)
    if not seen:
        grid = None
    verts, faces = grid_sheet()
    coarse = CoarseMesh(verts, faces, np.zeros(0, np.int32), np.zeros((0, 3)))
    cloth = build_cloth_model(Garment("sheet", verts, faces, np.arange(len(verts))), fabric("cotton"), SimSettings(),
                              verts, coarse)
    surf = DetailedSurface(build_surface_model(cloth, SurfaceSettings(tip_share=0.0)))
    x = cloth.rest_positions.copy()
    # (the coarse particles' nearest vertices on the box: S103's walks start there, and reach the arm only
    # through the vertex grid's seeds)
    nearest = np.array([int(np.argmin(np.linalg.norm(bv[:n_box] - q, axis=1))) for q in x], dtype=np.int32)
    tri = surf.model.tess.triangles
    clearance = surf.model.settings.lift_clearance
    for frame in range(11):
        p, _ = surf.step(x, nearest, pose.x, body, pose.face_n, DT, grid, face_tip=pose.face_tips(),
                         winding=winding.arrays(), vertex_tip=pose.vertex_tip)
        height, k = _height_over(p, tri, a)
        if arm_gap is None:
            assert clearance - 1e-9 <= height - a[1] <= clearance + 1e-4
            assert surf.covered == (1 if frame == 0 else 0)  # (raised once, kept after)
        else:
            assert surf.covered == 0
            assert a[1] - height > 0.0002  # through the surface, as without the vertex tips
            inside = np.all((p > arm_lo + 1e-9) & (p < arm_lo + 0.02 - 1e-9), axis=1)
            assert not inside.any()


def test_wrinkles_under_another_body_part_stay_out_of_it():
    """Decision (S103-S106): a compressed strip grows wrinkles over a torso box 2 mm below it,
    under an arm box whose bottom is 4 mm above its middle. The particles under the arm are
    nearest to the torso (facing it), and S103 measures the arm 4 mm away through the vertex
    grid; S106 lets them rise no farther than that less the clearance, so in no frame does a
    particle enter the arm, and those under it stop at y = 3 mm while the wrinkles elsewhere
    grow higher than the arm's bottom."""
    m, x = compressed_strip(0.8)
    c = x.mean(axis=0)
    tv, tt = box(half=0.1, n=10)
    tv = tv + [c[0], -0.102, c[2]]  # torso: top face at y = -2 mm
    av, at = box(half=0.02, n=8)
    arm = np.array([c[0], 0.024, c[2]])  # arm: bottom face at y = 4 mm over the strip's middle
    bv = np.ascontiguousarray(np.vstack([tv, av + arm]))
    bt = np.vstack([tt, at + len(tv)]).astype(np.int32)
    regions = np.r_[np.full(len(tv), 1), np.full(len(av), 2)].astype(np.uint8)
    body = BodyMesh.build(bt, len(bv), regions)
    grid = VertexGrid(len(bv))
    grid.update(bv, regions)
    nearest = np.array([int(np.argmin(np.linalg.norm(tv - q, axis=1))) for q in x], dtype=np.int32)
    fn = face_normals(bv, bt)
    surf = DetailedSurface(m)
    for _ in range(240):
        p = surf.step(x, nearest, bv, body, fn, DT, grid)[0]
        assert not np.all(np.abs(p - arm) < 0.02 - 1e-9, axis=1).any()  # nothing inside the arm
    under = np.all(np.abs(surf.state.p_smoothed - c)[:, [0, 2]] < 0.02 - 0.004, axis=1)  # off the arm's walls
    assert under.sum() > 20
    assert p[under, 1].max() == pytest.approx(0.003, abs=1e-9)
    assert p[~under, 1].max() > 0.004


def raised_box_top(height, shift=0.0):
    """A box whose top face lies 0.5 mm under the sheet of `sheet_model()` and whose top vertex
    nearest the sheet's middle is raised by `height` (a vertex standing out of its ring, as on
    a coarse body mesh), the box shifted by `shift` along x and z. Returns (vertices, triangles,
    the raised vertex)."""
    bv, bt = box(half=0.1, n=10)
    bv = bv + [0.08 + shift, -0.1005, 0.04 + shift]
    top = np.flatnonzero(np.isclose(bv[:, 1], -0.0005))
    apex = top[np.argmin(np.linalg.norm(bv[top][:, [0, 2]] - [0.08 + shift, 0.04 + shift], axis=1))]
    bv[apex, 1] += height
    return np.ascontiguousarray(bv), bt, apex


def test_face_tip_heights_measure_a_vertex_standing_out_of_its_ring():
    """A vertex of a flat box top raised by 8 mm stands 8 mm out of its flat ring (along a
    vertex normal within a few degrees of +y); the faces around it carry that, the flat top
    away from it and from the box's edges nothing (its neighbours lie under their ring: 0)."""
    bv, bt, apex = raised_box_top(0.008)
    pose = BodyPose(body_mesh_of(bv, bt), face_tree=False, tips=True)
    pose.update(bv)
    pose.face_tips()
    assert pose.vertex_tip[apex] == pytest.approx(0.008, rel=0.02)
    around = np.any(bt == apex, axis=1)
    np.testing.assert_allclose(pose.face_tip[around], pose.vertex_tip[apex], rtol=1e-12)
    centre = bv[apex] - [0.0, 0.008, 0.0]
    flat = np.all(np.isclose(bv[bt][:, :, 1], -0.0005), axis=1) & ~around
    inner = flat & np.all(np.abs(bv[bt][:, :, [0, 2]] - centre[[0, 2]]) < 0.07, axis=(1, 2))
    inner &= ~np.any(np.isin(bt, np.flatnonzero(np.linalg.norm(bv - bv[apex], axis=1) < 0.021)), axis=1)
    assert inner.sum() > 50
    np.testing.assert_array_equal(pose.face_tip[inner], 0.0)


@pytest.mark.parametrize("tip_share", [0.0, SurfaceSettings().tip_share])
def test_a_body_vertex_standing_out_between_particles_stays_under_the_surface(tip_share):
    """Decision (S103 tests particles, not triangles): a body vertex 8 mm out of its ring (2 cm
    around) lies in the middle of a square of detailed particles (4.7 mm from each). Lifted
    the clearance off the faces around it, those particles stand 7.7 mm over the flat top,
    and the vertex comes 0.3 mm through the detailed triangle over it. With a share of its
    tip height counted off their distance (tip_share 0.25: 2 mm) they stand 9.9 mm over it,
    and the vertex stays 1.9 mm under the surface."""
    lattice = 0.04 / 6
    bv, bt, apex = raised_box_top(0.008, shift=lattice / 2)
    body = body_mesh_of(bv, bt)
    pose = BodyPose(body, face_tree=False, tips=True)
    pose.update(bv)
    verts, faces = grid_sheet()
    coarse = CoarseMesh(verts, faces, np.zeros(0, np.int32), np.zeros((0, 3)))
    cloth = build_cloth_model(Garment("sheet", verts, faces, np.arange(len(verts))), fabric("cotton"), SimSettings(),
                              verts, coarse)
    surf = DetailedSurface(build_surface_model(cloth, SurfaceSettings(tip_share=tip_share)))
    x = cloth.rest_positions.copy()
    nearest = np.array([int(np.argmin(np.linalg.norm(bv - q, axis=1))) for q in x], dtype=np.int32)
    p, _ = surf.step(x, nearest, pose.x, body, pose.face_n, DT, face_tip=pose.face_tips())
    # the surface's height over the raised vertex: the detailed triangle under it in x-z
    a = bv[apex]
    tri = surf.model.tess.triangles
    height, k = _height_over(p, tri, a)
    corner_distance = np.linalg.norm((p[tri[k]] - a)[:, [0, 2]], axis=1)
    np.testing.assert_allclose(corner_distance, lattice / np.sqrt(2), rtol=1e-6)  # the square's middle
    if tip_share == 0.0:
        assert a[1] - height > 0.0002  # through the surface (by 0.26 mm)
    else:
        assert height - a[1] > 0.0015  # under it (by 1.9 mm)
