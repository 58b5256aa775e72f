"""The S103 signed distance to the body: triangle adjacency and the walk over faces, against
the independent signed distance of the acceptance tests (tests/signed_distance.py, which
shares no code with cloth/)."""

import numpy as np
import pytest
from numba import njit

from cloth.collision import (BodyMesh, deepest_plane, face_normals, face_walk_distance, ring_signed_distance,
                             walk_nearest)
from cloth.topology import triangle_neighbours
from cloth.wrinkles import _detail_signed_distance
from tests.signed_distance import SignedDistance
from tests.test_cloth_dynamics import box, uv_sphere


@njit  # not cached: numba's cache would not see a change in the cloth/ functions it calls
def _walk_all(points, body_x, tris, tri_nbrs, tri_start, tri_ids, nbr_start, nbr_ids, regions, start, face_n, out):
    q = np.zeros(3)
    for i in range(points.shape[0]):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        v = walk_nearest(px, py, pz, body_x, nbr_start, nbr_ids, start[i], regions, 255)
        f = deepest_plane(px, py, pz, body_x, tris, tri_start, tri_ids, v, face_n)[1]
        out[i] = face_walk_distance(px, py, pz, body_x, tris, tri_nbrs, tri_start, tri_ids, nbr_start, nbr_ids, regions,
                                    f, face_n, q)[0]


def test_triangle_neighbours_of_a_closed_mesh_are_mutual():
    _, tris = box(half=0.1, n=3)
    nb = triangle_neighbours(tris)
    assert nb.shape == tris.shape and (nb >= 0).all()  # closed: every edge has a triangle beyond
    for t, row in enumerate(nb):
        for e, o in enumerate(row):
            a, b = tris[t, e], tris[t, (e + 1) % 3]
            assert t in nb[o]  # mutual
            assert {a, b} <= set(tris[o])  # across the shared edge


def test_triangle_neighbours_of_an_open_edge_are_missing():
    nb = triangle_neighbours(np.array([[0, 1, 2], [2, 1, 3]], dtype=np.int32))
    np.testing.assert_array_equal(nb, [[-1, 1, -1], [0, -1, -1]])


@pytest.mark.parametrize("shape", ["sphere", "box"])
def test_face_walk_distance_matches_brute_force(shape):
    """Points within 1 cm of the surface, inside and outside, walks started at a corner of the
    face each point was made from:
    the same signed distance as the exact closest point over every triangle."""
    if shape == "sphere":
        verts, tris = uv_sphere(radius=0.1, n_lat=24, n_lon=48)
    else:
        verts, tris = box(half=0.1, n=6)
    rng = np.random.default_rng(3)
    t = rng.integers(0, len(tris), 400)
    w = rng.dirichlet(np.ones(3), 400)
    a, b, c = verts[tris[t, 0]], verts[tris[t, 1]], verts[tris[t, 2]]
    normal = np.cross(b - a, c - a)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    points = w[:, :1] * a + w[:, 1:2] * b + w[:, 2:] * c + normal * rng.uniform(-0.01, 0.01, (400, 1))
    expected = SignedDistance(tris, len(verts))(verts, points)
    body = BodyMesh.build(tris, len(verts))
    start = tris[t, rng.integers(0, 3, 400)].astype(np.int32)  # seeded nearby, as S103 seeds its walks
    out = np.zeros(len(points))
    _walk_all(points, np.ascontiguousarray(verts, dtype=np.float64), body.triangles, body.tri_nbrs, body.tri_start,
              body.tri_ids, body.nbr_start, body.nbr_ids, body.regions, start, face_normals(verts, tris), out)
    np.testing.assert_allclose(out, expected, atol=1e-9)


@njit  # (not cached, as above)
def _detail_all(points, seeds, body_x, tris, tri_nbrs, tri_start, tri_ids, nbr_start, nbr_ids, regions, body_face,
                face_n, out, near_vertex=np.zeros(0, dtype=np.int32)):  # (empty: the seed alone checks the walk)
    q = np.zeros(3)
    no_parts = np.zeros((0, 2), dtype=np.int32)  # no walks in other body parts: the walk itself
    no_groups = np.zeros((0, 3), dtype=np.int32)
    part_face = np.full(points.shape[0], -1, dtype=np.int32)
    for i in range(points.shape[0]):
        out[i] = _detail_signed_distance(points, i, seeds[i], points, np.zeros(3, dtype=np.int32), no_parts, no_groups,
                                         np.zeros((0, 3)), 0, -1, body_x, nbr_start, nbr_ids, regions, tris, tri_start,
                                         tri_ids, tri_nbrs, body_face, part_face, near_vertex, face_n, q)[0]


def test_detailed_particle_walk_starts_from_its_last_face_and_re_anchors_at_the_seed():
    """Two spheres 0.3 m apart; points near the first. A first walk (no face remembered), then
    walks from the remembered faces after the points moved by up to 2 mm (the usual case),
    then walks remembered on the second sphere (the cloth jumped: a recovery, a reset): all give
    the exact signed distance; the last are re-anchored at the coarse seed, a vertex of the
    first sphere nearer than anything on the second."""
    v1, t1 = uv_sphere(radius=0.1, n_lat=16, n_lon=32)
    verts = np.concatenate([v1, v1 + [0.3, 0.0, 0.0]])
    tris = np.concatenate([t1, t1 + len(v1)]).astype(np.int32)
    rng = np.random.default_rng(5)
    d = rng.normal(size=(200, 3))
    points = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.09, 0.11, (200, 1))
    body = BodyMesh.build(tris, len(verts))
    body_x = np.ascontiguousarray(verts, dtype=np.float64)
    face_n = face_normals(verts, tris)
    body_face = np.full(len(points), -1, dtype=np.int32)
    for case in ("first walk", "moved", "remembered on the other sphere"):
        if case == "moved":
            points = points + rng.uniform(-0.002, 0.002, points.shape)
        elif case.startswith("remembered"):
            body_face += len(t1)
        seeds = np.argmin(np.linalg.norm(v1[None] - points[:, None], axis=2), axis=1).astype(np.int32)
        expected = SignedDistance(tris, len(verts))(verts, points)
        out = np.zeros(len(points))
        _detail_all(points, seeds, body_x, body.triangles, body.tri_nbrs, body.tri_start, body.tri_ids,
                    body.nbr_start, body.nbr_ids, body.regions, body_face, face_n, out)
        np.testing.assert_allclose(out, expected, atol=1e-9, err_msg=case)
        assert (body_face >= 0).all() and (body_face < len(t1)).all()  # faces of the first sphere remembered


@pytest.mark.parametrize("own_vertex", [True, False])
def test_a_walk_stopped_farther_than_the_particles_own_vertex_walks_again_from_it(own_vertex):
    """Decision (S103, the particle's own vertex): two spheres 0.3 m apart, points 1-10 mm from
    the first (inside and out), their walks remembered on the second sphere (a walk that stopped
    on a local minimum of the distance) and their seeds there too, farther than that answer, so
    the seed does not call it wrong. Each point's own nearest vertex, walked from the one it
    found the frame before (on the first sphere), is nearer than the answer: the walk starts
    again from it and gives the exact signed distance. Without it the answer stays on the second
    sphere, 0.15 m or more from the point."""
    v1, t1 = uv_sphere(radius=0.1, n_lat=16, n_lon=32)
    verts = np.concatenate([v1, v1 + [0.3, 0.0, 0.0]])
    tris = np.concatenate([t1, t1 + len(v1)]).astype(np.int32)
    rng = np.random.default_rng(7)
    d = rng.normal(size=(100, 3))
    d[:, 0] = -np.abs(d[:, 0])  # the first sphere's far side from the second
    points = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.09, 0.11, (100, 1))
    body = BodyMesh.build(tris, len(verts))
    body_x = np.ascontiguousarray(verts, dtype=np.float64)
    face_n = face_normals(verts, tris)
    far = len(v1) + np.argmax(v1[:, 0])  # the second sphere's vertex farthest from the first
    seeds = np.full(len(points), far, dtype=np.int32)
    body_face = np.full(len(points), len(t1) + int(np.argmax(v1[t1].mean(axis=1)[:, 0])), dtype=np.int32)
    last = np.argmin(np.linalg.norm(v1[None] - points[:, None], axis=2), axis=1)
    near_vertex = (np.roll(last, 1) if own_vertex else np.zeros(0)).astype(np.int32)  # (a vertex of the first)
    out = np.zeros(len(points))
    _detail_all(points, seeds, body_x, body.triangles, body.tri_nbrs, body.tri_start, body.tri_ids, body.nbr_start,
                body.nbr_ids, body.regions, body_face, face_n, out, near_vertex)
    expected = SignedDistance(tris, len(verts))(verts, points)
    if own_vertex:
        np.testing.assert_allclose(out, expected, atol=1e-9)
        assert (body_face < len(t1)).all()
        np.testing.assert_array_equal(near_vertex, last)  # each point's nearest vertex, kept for the next frame
    else:
        assert np.all(np.abs(out) > 0.15) and (body_face >= len(t1)).all()


@njit  # (not cached, as above)
def _ring_all(points, vertices, body_x, tris, tri_nbrs, tri_start, tri_ids, face_n, out, faces):
    q = np.zeros(3)
    for i in range(points.shape[0]):
        r = ring_signed_distance(points[i, 0], points[i, 1], points[i, 2], body_x, tris, tri_nbrs, tri_start, tri_ids,
                                 vertices[i], face_n, q)
        out[i] = r[0]
        faces[i] = r[7]


def test_ring_distance_takes_its_side_from_the_closest_feature_at_a_sharp_edge():
    """A thin wedge (a prism whose ridge is 2.3° sharp, like a fold of skinned skin); a point
    1 cm outside its ridge edge, near the ridge's end vertex, whose faces hold the closest
    point. Outside, at 1 cm (the independent test agrees): the side comes from the edge's two
    faces. The end vertex's area-weighted normal leans to the other face, which it touches
    with twice the area, and would put the point inside."""
    a, b, c, length = (-0.02, 0.0), (0.02, 0.0), (0.0, 1.0), 1.0
    verts = np.array([[*a, 0], [*b, 0], [*c, 0], [*a, length], [*b, length], [*c, length]], float)
    a0, b0, c0, a1, b1, c1 = range(6)
    tris = np.array([[a0, c0, b0], [a1, b1, c1], [a0, b0, b1], [a0, b1, a1],  # caps, base
                     [b0, c0, c1], [b0, c1, b1],  # side b-c: c0 in one triangle
                     [c0, a0, a1], [c0, a1, c1]], dtype=np.int32)  # side c-a: c0 in both
    mesh = BodyMesh.build(tris, 6)
    face_n = face_normals(verts, tris)
    d = 0.9 * face_n[4, :3] + 0.1 * face_n[6, :3]  # within the ridge's normal cone, nearer side b-c
    d /= np.linalg.norm(d)
    point = np.array([[0.0, 1.0, 0.02]]) + 0.01 * d
    out = np.zeros(1)
    faces = np.zeros(1, dtype=np.int64)
    _ring_all(point, np.array([c0], np.int32), verts, mesh.triangles, mesh.tri_nbrs, mesh.tri_start, mesh.tri_ids,
              face_n, out, faces)
    np.testing.assert_allclose(SignedDistance(tris, 6)(verts, point), [0.01], atol=1e-12)
    np.testing.assert_allclose(out, [0.01], atol=1e-12)


@njit  # (not cached, as above)
def _walk_from(point, body_x, tris, tri_nbrs, tri_start, tri_ids, nbr_start, nbr_ids, regions, start, face_n):
    q = np.zeros(3)
    return face_walk_distance(point[0], point[1], point[2], body_x, tris, tri_nbrs, tri_start, tri_ids, nbr_start,
                              nbr_ids, regions, start, face_n, q)


def test_a_face_walk_settled_on_an_edge_looks_across_the_faces_other_edges():
    """Decision (S103's walk, across the other edges): face A flat under p = (0, 1, 0), its nearest
    point on its edge to face B (1.118 away), B folded down from that edge so that its own nearest
    point is the same one, and face C across A's next edge rising to 0.54 from p. A walk from A
    once stopped on the shared edge (the face beyond no nearer); now it looks at A's other
    neighbours too, goes over to C, and reads the exact distance over all three faces. Started on
    C it reads the same, and on B it comes back to C as well."""
    from trimesh.triangles import closest_point
    verts = np.array([[-1.0, 0.0, 0.5], [1.0, 0.0, 0.5], [0.0, 0.0, 3.0], [0.0, -2.0, 0.4], [0.5, 0.8, 0.0]])
    tris = np.array([[0, 1, 2], [1, 0, 3], [2, 1, 4]], dtype=np.int32)  # A, B, C
    body = BodyMesh.build(tris, len(verts))
    p = np.array([0.0, 1.0, 0.0])
    exact = np.linalg.norm(closest_point(verts[tris], np.repeat(p[None], 3, axis=0)) - p, axis=1)
    assert np.isclose(exact[0], np.sqrt(1.25)) and np.isclose(exact[1], exact[0]) and exact[2] < 0.55
    for start in range(3):
        d = _walk_from(p, np.ascontiguousarray(verts), body.triangles, body.tri_nbrs, body.tri_start, body.tri_ids,
                       body.nbr_start, body.nbr_ids, body.regions, start, face_normals(verts, tris))
        assert np.isclose(abs(d[0]), exact.min(), atol=1e-12), start
        assert d[-1] == 2, start
