"""The acceptance's independent ray casts (tests/rays.py) on cases whose answers are known."""

import numpy as np
import trimesh

from tests.rays import RayCaster


def test_rays_meet_a_flat_sheet_where_it_is_and_nowhere_else():
    """A 10 cm square at z = 0 (two triangles): rays up from 1 cm under it meet it at 1 cm, a
    ray slanted 45° at √2 cm; past its edge, away from it, or with a reach shorter than the
    distance, none."""
    x = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.1, 0.1, 0.0], [0.0, 0.1, 0.0]])
    rays = RayCaster(np.array([[0, 1, 2], [0, 2, 3]]))
    s = np.sqrt(0.5)
    origins = np.array([[0.03, 0.07, -0.01], [0.05, 0.05, -0.01], [0.15, 0.05, -0.01], [0.05, 0.05, -0.01],
                        [0.05, 0.05, -0.02]])
    dirs = np.array([[0.0, 0.0, 1.0], [s, 0.0, s], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
    t, face = rays.first_hits(x, origins, dirs, 0.015)
    np.testing.assert_allclose(t[:2], [0.01, 0.01 * np.sqrt(2)], atol=1e-15)
    assert np.all(np.isinf(t[2:]))
    np.testing.assert_array_equal(face, [1, 0, -1, -1, -1])  # (0.03, 0.07) lies in the second triangle


def test_rays_from_the_centre_of_a_sphere_meet_its_facets_at_the_first_of_two_shells():
    """From the centre of an icosphere (radius 10 cm), 500 rays in random directions meet it between
    its facets' distance and its radius, each once; with a second sphere of radius 12 cm around it
    the first hit is still the inner one; with a reach of 5 cm, none."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    outer = trimesh.creation.icosphere(subdivisions=3, radius=0.12)
    x = np.concatenate([sphere.vertices, outer.vertices])
    tris = np.concatenate([sphere.faces, outer.faces + len(sphere.vertices)])
    rng = np.random.default_rng(3)
    d = rng.normal(size=(500, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    centre = np.zeros((500, 3))
    facet = np.min(np.abs(np.einsum("ij,ij->i", sphere.triangles_center, sphere.face_normals)))
    for mesh_x, mesh_t in ((sphere.vertices, sphere.faces), (x, tris)):
        t, face = RayCaster(mesh_t).first_hits(mesh_x, centre, d, 0.2)
        assert np.all((t >= facet - 1e-12) & (t <= 0.1 + 1e-12))
        assert np.all((face >= 0) & (face < len(sphere.faces)))  # the inner sphere's
    assert np.all(np.isinf(RayCaster(tris).first_hits(x, centre, d, 0.05)[0]))


def test_the_acceptance_counts_an_inner_sheet_in_front_of_the_outer_one_as_showing_through():
    """An outer sheet over x in [0, 0.4] at y = 0 and an inner one over [0.1, 0.3] (normals +Y): 4 mm
    in front of it every inner vertex shows through, 8 mm in front more than CROSS_DEEP; 4 mm behind
    it, none does and all are covered; with the outer's faces all taken as its rim, none is counted."""
    from tests.surface_acceptance import CROSS_DEEP, crossings
    from tests.test_layers import grid, up
    po, to, _ = grid(0.0, 0.4, 0.0)
    rays = RayCaster(to)
    no_rim = np.zeros(len(to), dtype=bool)
    for y, crossed, deep in ((0.004, True, False), (2 * CROSS_DEEP - 0.002, True, True), (-0.004, False, False)):
        pi = grid(0.1, 0.3, y)[0]
        n = len(pi)
        assert crossings(rays, po, pi, up(n), no_rim) == (n, n if crossed else 0, n if deep else 0)
    assert crossings(rays, po, grid(0.1, 0.3, 0.004)[0], up(n), np.ones(len(to), dtype=bool)) == (0, 0, 0)


def test_the_acceptance_turns_normals_pointing_into_the_body_before_casting():
    """A box body with its top at y = 0; the inner sheet 4 mm over it, the outer 8 mm, every inner
    normal -Y (a fold turned inside out). Along those normals the outer reads as under every inner
    vertex (all showing through); turned away from the body first (`away_from_body`, all of them),
    it is over every one, and none shows. Normals already pointing out are left."""
    from tests.signed_distance import SignedDistance
    from tests.surface_acceptance import away_from_body, crossings
    from tests.test_layers import grid, up
    box = trimesh.creation.box(extents=(0.6, 0.2, 0.4))
    body_x = box.vertices + [0.2, -0.1, 0.1]
    sd = SignedDistance(box.faces, len(body_x), cell=0.05)
    po, to, _ = grid(0.0, 0.4, 0.008)
    pi = grid(0.1, 0.3, 0.004)[0]
    n = len(pi)
    rays, no_rim = RayCaster(to), np.zeros(len(to), dtype=bool)
    assert crossings(rays, po, pi, -up(n), no_rim) == (n, n, 0)
    normals, turned = away_from_body(sd, body_x, pi, -up(n))
    assert turned.all()
    np.testing.assert_array_equal(normals, up(n))
    assert crossings(rays, po, pi, normals, no_rim) == (n, 0, 0)
    normals, turned = away_from_body(sd, body_x, pi, up(n))
    assert not turned.any()
    np.testing.assert_array_equal(normals, up(n))


def test_the_acceptance_lists_each_vertex_deeper_than_a_millimetre_with_what_s103_knew():
    """`deep_rows` (`python -m tests.surface_acceptance --deep FILE`): of three detailed vertices
    1.5 mm, 0.5 mm and 3 mm inside by the independent distances, the first (a coarse particle's,
    index under n_coarse = 1) and the third are listed, in mm, with S103's state and the skin vertex
    nearest to each (and its region); none when nothing is deeper than 1 mm."""
    from types import SimpleNamespace

    from tests.surface_acceptance import DEEP_COLUMNS, deep_rows
    p = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    skin = np.array([[2.1, 0.0, 0.0], [0.1, 0.0, 0.0]])
    state = SimpleNamespace(sd=np.array([0.004, 0.001, np.inf]), other=np.array([0.006, np.inf, np.inf]),
                            behind=np.array([1, 0, 0], np.uint8), facing=np.array([0.5, 1.0, -0.25]),
                            dh=np.array([0.002, 0.0, -0.01]), floor=np.array([0.001, 0.0, -0.01]),
                            ceiling=np.array([0.03, 0.03, -0.01]))
    rows = deep_rows(7, "g", p, np.array([-0.0015, -0.0005, -0.003]), state, 1, skin, ["hand", "torso"])
    assert [len(r) for r in rows] == [len(DEEP_COLUMNS)] * 2
    assert rows[0] == (7, "g", 0, 1, -1.5, 4.0, 6.0, 1, 0.5, 2.0, 1.0, 30.0, 1, "torso")
    assert rows[1] == (7, "g", 2, 0, -3.0, np.inf, np.inf, 0, -0.25, -10.0, -10.0, -10.0, 0, "hand")
    assert deep_rows(7, "g", p, np.full(3, -0.001), state, 1, skin, ["hand", "torso"]) == []
