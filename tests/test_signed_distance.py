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
