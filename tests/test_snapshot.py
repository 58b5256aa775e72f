"""A session's state saved and restored in place (cloth.snapshot, OutfitSession.snapshot)."""

import numpy as np

from cloth.collision import BodyMesh
from cloth.layers import SheetMoves
from cloth.snapshot import StateSnapshot, state_arrays
from cloth.surface import SurfaceSettings
from services.cloth_job import OUTFITS, OutfitSession, load_outfit_models
from skinning.animate import BodyAnimator
from skinning.body import body_clothed_faces, body_regions
from skinning.source import BVHSource


class _State:
    def __init__(self):
        self.x = np.arange(6.0).reshape(2, 3)
        self.count = 3  # not an array: not saved
        self.moves = SheetMoves.__new__(SheetMoves)  # a state object of the cloth package, held
        self.moves.move = np.array([1.0, 2.0])
        self.scratch = np.zeros(2)


def test_a_snapshot_restores_every_array_in_place_nested_ones_too():
    s = _State()
    assert sorted(name for _, name, _ in state_arrays(s)) == ["move", "scratch", "x"]
    x, move = s.x, s.moves.move
    snap = StateSnapshot(s)
    assert snap.nbytes == 6 * 8 + 2 * 8 + 2 * 8
    s.x += 10.0
    s.moves.move[:] = -1.0
    s.count = 7
    s.scratch = np.ones(5)  # replaced by a step with another shape
    snap.restore()
    assert s.x is x and s.moves.move is move  # the same arrays: kernels' argument tuples still see them
    np.testing.assert_array_equal(s.x, np.arange(6.0).reshape(2, 3))
    np.testing.assert_array_equal(s.moves.move, [1.0, 2.0])
    np.testing.assert_array_equal(s.scratch, np.zeros(2))
    assert s.count == 7
    s.x[0, 0] = 99.0
    snap.restore()  # restorable again: the snapshot kept its own copy
    assert s.x[0, 0] == 0.0


def test_a_restored_session_steps_on_as_a_freshly_settled_one_bit_for_bit(body, data):
    """The casual outfit (coarse, detailed, layered) settled into the run clip's first pose and
    saved; eight frames stepped; restored; the next frames then give what a session settled
    afresh into that pose gives, bit for bit. Without the restore they do not."""
    frames = []
    with BVHSource(data / "mocap" / "cmu_npybvh_example_75f.bvh", every=2, max_frames=20) as source:
        animator = BodyAnimator(body, source.skeleton)
        for f in source:
            if f.index == 0:
                continue  # the converter's T-pose
            out = animator(f.local_rot, f.root_position)
            if f.index == 1:
                q0 = out.retarget.q.copy()
            frames.append(out.vertices.copy())
    mesh = BodyMesh.build(body.triangles, body.n_visible, body_regions(body), body_clothed_faces(body))
    outfit = load_outfit_models(body, animator, mesh, data / "garments" / OUTFITS[0])
    settings = SurfaceSettings(level=3)

    def settled():
        session = OutfitSession(body, animator, mesh, outfit, settings, threads=1)
        session.preroll(q0, 1 / 60, blend_seconds=0.2, settle_seconds=0.1)
        return session

    def run(session, vertices):
        out = []
        for v in vertices:
            session.step_cloth(v, 1 / 60)
            out.append([s.state.x.copy() for s in session.sims] + [p.copy() for p, _ in session.detailed])
        return out

    fresh = settled()
    expected = run(fresh, frames[:4])
    restored = settled()
    start = restored.snapshot()
    assert start.nbytes > 1_000_000  # the detailed surfaces' arrays are in it
    run(restored, frames[4:12])
    moved_on = run(restored, frames[:1])  # stepped on without the restore: not the fresh start
    assert not all(np.array_equal(a, b) for a, b in zip(moved_on[0], expected[0]))
    start.restore()
    got = run(restored, frames[:4])
    for frame_got, frame_expected in zip(got, expected):
        for a, b in zip(frame_got, frame_expected):
            np.testing.assert_array_equal(a, b)


def test_a_snapshot_goes_onto_another_object_of_the_same_kind_and_nothing_else():
    a, b = _State(), _State()
    a.x += 5.0
    a.moves.move[:] = 7.0
    x = b.x
    moved = StateSnapshot(a).onto(b)
    a.x[:] = 0.0  # (the original is not read again)
    moved.restore()
    assert b.x is x
    np.testing.assert_array_equal(b.x, np.arange(6.0).reshape(2, 3) + 5.0)
    np.testing.assert_array_equal(b.moves.move, [7.0, 7.0])

    class _Other(_State):  # the same arrays under the same names, another kind of state
        pass

    for other in ((b, b), (_Other(),)):
        try:
            StateSnapshot(a).onto(*other)
        except ValueError:
            continue
        raise AssertionError(f"a snapshot of one _State onto {other} was taken")
