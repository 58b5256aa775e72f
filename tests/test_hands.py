"""Hand clearance (skinning/hands.py): a hand sunk into the body turns out with its arm."""

import numpy as np
import pytest
import trimesh

from skinning.hands import HandSettings, axis_angle_matrix, hand_turn, turned

MARGIN = 0.006


def test_turned_point_and_axis_angle_matrix_are_the_same_rotation():
    rng = np.random.default_rng(3)
    out, m = np.empty(3), np.empty((3, 3))
    turned(np.array([1.0, 0.0, 0.0]), np.zeros(3), np.array([0.0, 0.0, 1.0]), np.pi / 2, out)
    np.testing.assert_allclose(out, [0.0, 1.0, 0.0], atol=1e-15)  # right-handed: x -> y about z
    for _ in range(20):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle, p, s = rng.uniform(-3, 3), rng.normal(size=3), rng.normal(size=3)
        turned(p, s, axis, angle, out)
        axis_angle_matrix(axis, angle, m)
        np.testing.assert_allclose(out, s + m @ (p - s), atol=1e-12)
        np.testing.assert_allclose(m @ m.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(m) == pytest.approx(1.0)


class SphereBody:
    """A round 'hip' (radius 0.15 m at the origin) as the body, a small cluster of points as the hand,
    and a shoulder 0.25 m above; the arm turns about z through the shoulder (towards +x)."""

    def __init__(self):
        mesh = trimesh.creation.icosphere(subdivisions=6, radius=0.15)  # 40,962 vertices, ~4 mm apart
        self.radius = 0.15
        self.body = np.asarray(mesh.vertices, dtype=np.float64)
        self.normals = self.body / np.linalg.norm(self.body, axis=1, keepdims=True)
        self.shoulder = np.array([0.05, 0.25, 0.0])
        self.axis = np.array([0.0, 0.0, 1.0])

    def turn(self, hand: np.ndarray, settings: HandSettings = HandSettings()) -> float:
        x = np.ascontiguousarray(np.vstack([self.body, hand]))
        n = len(self.body)
        ids = np.arange(n, dtype=np.int64)
        return hand_turn(x, np.arange(n, n + len(hand), dtype=np.int64), self.shoulder, self.axis,
                         np.deg2rad(settings.max_turn_deg), settings.bisections, ids, self.normals,
                         np.zeros(n, dtype=np.int64), np.eye(3)[None], np.zeros((n, 3)), np.empty(n, dtype=np.int64),
                         settings.margin, settings.near, np.empty((3, 3)))

    def clear_angle(self, hand: np.ndarray) -> float:
        """Exact: the smallest turn (sampled every 0.001 degree) putting every point margin outside."""
        a = np.deg2rad(np.arange(0.0, 45.0, 0.001))[:, None]
        r = hand - self.shoulder
        x = self.shoulder[0] + np.cos(a) * r[:, 0] - np.sin(a) * r[:, 1]  # about z through the shoulder
        y = self.shoulder[1] + np.sin(a) * r[:, 0] + np.cos(a) * r[:, 1]
        clear = (np.sqrt(x * x + y * y + r[:, 2] ** 2) >= self.radius + MARGIN).all(axis=1)
        return float(a[np.argmax(clear), 0]) if clear.any() else np.inf

    def hand(self, depth: float, lateral: float = 1.0) -> np.ndarray:
        """A 3 x 3 x 3 cluster 2 cm wide, centred `depth` inside the sphere's side (+x), at height 0."""
        g = np.linspace(-0.01, 0.01, 3)
        cube = np.stack(np.meshgrid(g, g, g), axis=-1).reshape(-1, 3)
        centre = np.array([lateral * (self.radius - depth), 0.0, 0.0])
        return cube + centre


def test_a_hand_inside_the_body_turns_out_by_the_smallest_angle_that_clears_it():
    sphere = SphereBody()
    for depth in (0.0, 0.02, 0.04):
        hand = sphere.hand(depth)
        turn = sphere.turn(hand)
        exact = sphere.clear_angle(hand)
        assert 0.0 < exact < np.deg2rad(25.0)
        # the nearest vertex of a sphere sampled 4 mm apart reads the distance to within 0.1 mm
        assert turn == pytest.approx(exact, abs=np.deg2rad(0.1))
        out = np.empty(3)
        for p in hand:
            turned(p, sphere.shoulder, sphere.axis, turn, out)
            assert np.linalg.norm(out) > sphere.radius + MARGIN - 2e-4  # outside, a garment's thickness away


def test_a_hand_clear_of_the_body_or_held_against_it_on_purpose_is_left_alone():
    sphere = SphereBody()
    assert sphere.turn(sphere.hand(-0.03)) == 0.0  # 3 cm outside: nothing to do
    assert sphere.turn(sphere.hand(-0.03, lateral=-1.0)) == 0.0  # on the other side, outside
    # deep on the far side: turning outwards drives it further in, no turn up to 45 degrees clears it
    assert sphere.turn(sphere.hand(0.03, lateral=-1.0)) == 0.0


def test_the_turn_grows_continuously_with_the_depth_and_fades_out_before_the_limit():
    sphere = SphereBody()
    settings = HandSettings(max_turn_deg=20.0)
    depths = np.linspace(-0.02, 0.07, 181)
    turns = np.array([sphere.turn(sphere.hand(d), settings) for d in depths])
    exact = np.array([sphere.clear_angle(sphere.hand(d)) for d in depths[::10]])
    assert turns[0] == 0.0 and turns[-1] == 0.0  # clear; then too deep for 20 degrees
    assert np.abs(np.diff(np.degrees(turns))).max() < 0.6  # no jump between depths 0.5 mm apart
    full = exact < np.deg2rad(20.0 * 2 / 3)
    np.testing.assert_allclose(turns[::10][full], exact[full], atol=np.deg2rad(0.1))  # below the fade: exact
    assert (turns[::10][~full] <= exact[~full] + 1e-9).all()  # in the fade: less than it needs


def test_the_walkers_hand_on_her_hip_ends_outside_the_body(body, mocap):
    """The CMU walk's left hand rests on the hip: copied to the broader character it lies wholly
    inside the hip (independent check: the winding number of the clothed skin)."""
    from cloth.winding import WindingGrid, closed_faces, winding_numbers
    from skinning.animate import BodyAnimator
    from skinning.body import body_clothed_faces
    from skinning.retarget import IKSettings
    from skinning.source import BVHSource

    sk = body.skeleton
    vis = np.arange(body.n_visible)
    dominant = body.weight_bones[vis, np.argmax(body.weight_values[vis], axis=1)]
    hand = np.flatnonzero(np.isin(dominant, [sk.index(b) for b in ("LeftHand", "LeftFingerBase", "LeftHandFinger1",
                                                                    "LThumb")]))
    grid = WindingGrid(closed_faces(body.triangles, body_clothed_faces(body)), body.n_visible)

    def inside(frame):
        x = np.ascontiguousarray(frame.vertices[: body.n_visible])
        grid.update(x)
        w = np.empty(len(hand), dtype=np.int32)
        winding_numbers(np.ascontiguousarray(x[hand] - 0.002 * frame.normals[hand]), x, grid.tris, *grid.arrays(), w)
        return int((w >= 1).sum())

    counts, turns = {}, {}
    for hands in (None, HandSettings()):
        with BVHSource(mocap / "cmu_131_01_walk_3dsmax.bvh", every=2) as src:
            animator = BodyAnimator(body, src.skeleton, ik=IKSettings(hand_clearance=hands))
            for frame in src:
                f = animator(frame.local_rot, frame.root_position)
                if frame.index == 120:
                    counts[hands is None] = inside(f)
                    turns[hands is None] = np.degrees(f.retarget.arm_turn[0])
                    break
    assert counts[True] > 1000  # without: nearly all of the hand's 1,595 vertices are in the hip
    assert counts[False] < 20  # with: only the few at the wrist's cap
    assert turns[False] > turns[True] + 10.0  # the arm turned out, and the turn is reported
