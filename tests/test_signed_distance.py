"""The acceptance tests' independent signed distance, on shapes whose distances are known."""

import numpy as np
import trimesh

from tests.signed_distance import SignedDistance


def test_signed_distance_to_a_box_is_exact_inside_and_outside():
    box = trimesh.creation.box(extents=(0.4, 0.6, 0.2))
    sd = SignedDistance(box.faces, len(box.vertices), cell=0.05)
    pts = np.array([[0.0, 0.0, 0.0], [0.19, 0.0, 0.0], [0.0, 0.35, 0.0], [0.3, 0.4, 0.0], [0.0, 0.0, -0.5]])
    want = [-0.1, -0.01, 0.05, np.hypot(0.1, 0.1), 0.4]  # centre; near a face; above; off an edge; far
    np.testing.assert_allclose(sd(box.vertices, pts), want, atol=1e-12)


def test_signed_distance_follows_moving_vertices_and_signs_a_sphere():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    sd = SignedDistance(sphere.faces, len(sphere.vertices), cell=0.05)
    rng = np.random.default_rng(3)
    dirs = rng.standard_normal((400, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    r = rng.uniform(0.0, 1.2, 400)
    keep = np.abs(r - 0.5) > 0.02  # off the facets' 1 cm sagitta
    shift = np.array([1.0, -2.0, 0.5])
    d = sd(sphere.vertices + shift, dirs[keep] * r[keep, None] + shift)
    np.testing.assert_array_equal(np.sign(d), np.sign(r[keep] - 0.5))
    np.testing.assert_allclose(d, r[keep] - 0.5, atol=0.012)


def solid_angle_winding(vertices, faces, points):
    """The generalized winding number (Jacobson et al. 2013): the faces' solid angles at each
    point over 4 pi, brute force."""
    out = []
    for p in points:
        a, b, c = (vertices[faces[:, k]] - p for k in range(3))
        la, lb, lc = (np.linalg.norm(q, axis=1) for q in (a, b, c))
        num = np.einsum("ij,ij->i", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", b, c) * la
               + np.einsum("ij,ij->i", c, a) * lb)
        out.append(2.0 * np.arctan2(num, den).sum() / (4.0 * np.pi))
    return np.array(out)


def test_winding_numbers_count_a_self_intersecting_surface_and_sign_the_distance():
    """Two boxes that overlap, as one surface (it intersects itself, like a skinned thigh raised
    into the belly): winding 0 outside, 1 in one box, 2 in both, equal to the solid-angle
    winding number at random points, and at points exactly below and above the edges between
    two faces (the top-left rule counts each crossing once). The point 5 cm
    inside box A whose nearest face is box B's, buried in A and facing it, is inside by 5 cm:
    the pseudo-normal's sign called it outside."""
    a = trimesh.creation.box(extents=(0.4, 0.4, 0.4))
    b = trimesh.creation.box(extents=(0.4, 0.4, 0.4))
    b.apply_translation((0.3, 0.1, 0.0))
    v = np.vstack([a.vertices, b.vertices])
    f = np.vstack([a.faces, b.faces + len(a.vertices)])
    sd = SignedDistance(f, len(v), cell=0.05)
    pts = np.array([[-0.15, 0.0, 0.0], [0.15, 0.05, 0.0], [0.45, 0.1, 0.0], [0.0, 0.5, 0.0], [-0.3, 0.0, 0.0]])
    np.testing.assert_array_equal(sd.winding_numbers(v, pts), [1, 2, 1, 0, 0])
    rng = np.random.default_rng(7)
    rand = rng.uniform([-0.3, -0.3, -0.3], [0.6, 0.4, 0.3], (300, 3))
    np.testing.assert_array_equal(sd.winding_numbers(v, rand), np.round(solid_angle_winding(v, f, rand)))
    # on both diagonals of the boxes' square faces seen from below, one the edge of two triangles
    diag = np.array([[cx + t, y, s * t] for cx in (0.0, 0.3) for t in (-0.15, -0.05, 0.0, 0.05, 0.15)
                     for s in (-1.0, 1.0) for y in (-0.25, 0.0, 0.15)])
    np.testing.assert_array_equal(sd.winding_numbers(v, diag), np.round(solid_angle_winding(v, f, diag)))
    p = np.array([[0.05, 0.0, 0.0]])  # in A, 5 cm in front of B's face x = 0.1
    np.testing.assert_allclose(sd(v, p), [-0.05], atol=1e-12)
    np.testing.assert_allclose(SignedDistance(f, len(v), cell=0.05, pseudo_normal_sign=True)(v, p), [0.05], atol=1e-12)
