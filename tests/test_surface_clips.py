"""The detailed surface through a real clip with every outfit: finite, heights within their
bounds, unit shading normals, the coarse vertices on the surface, the folds across the
compression drawn only outwards over the quad-dominant coarse faces, and the layering (the top
lifted over the bottom along the top's normals, outward and bounded; the bottom pressed under
the top along its reference normals, no lower than the body allows), and the moves out of the
body (along the normal, and out of creases) bounded and each from inside the body as a whole."""

import numpy as np
import pytest

from cloth.creases import CREASE_MOVE, EXIT_DIRECTIONS, EXIT_FACE_REACH, EXIT_REACH
from cloth.surface import SurfaceSettings
from cloth.winding import winding_numbers
from services.cloth_job import OUTFITS, run_cloth_clip


@pytest.mark.parametrize("outfit", OUTFITS)
def test_surface_through_the_run_clip(body, data, outfit):
    checked, lifted, pressed, creased, from_outside, exited = [], [], [], [], [], []

    def on_frame(index, session, body_frame, positions):
        layered = [p.copy() for p, _ in session.detailed]
        lifted.append(sum(ls.lift.moved for _, ls in session.layers))
        pressed.append(sum(ls.press.moved for _, ls in session.layers))
        for lm, ls in session.layers:  # take the layering's lifts and presses off again (cloth.layers.apply_lifts)
            lift = np.minimum(ls.lift.move, ls.lift.room)
            assert lift.min() >= 0.0 and lift.max() <= lm.max_lift
            c = lm.over.candidates  # the outer's along its reference normals
            layered[lm.outer][c] -= lift[:, None] * session.surfaces[lm.outer].state.n_pn[c]
            # the inner's along its reference normals, down to no lower than its body floor
            inner = session.surfaces[lm.inner].state
            press = np.minimum(ls.press.move, ls.press.room)
            c = lm.under.candidates
            assert press.min() >= 0.0 and press.max() <= lm.max_lift
            assert np.all((press == 0.0) | (inner.height[c] - press >= inner.body_floor[c] - 1e-12))
            layered[lm.inner][c] += press[:, None] * inner.n_pn[c]
        for surf, (_, n), p, x in zip(session.surfaces, session.detailed, layered, positions):
            s, st, m = surf.state, surf.model.settings, surf.model
            # and the moves out of creases (cloth.creases: off the normal, never a coarse vertex, bounded)
            # first the moves out along ±n_i (cloth.creases.out_along_normals: along the normal, a coarse
            # vertex so or the way around within EXIT_REACH, bounded, each from inside the body as a whole)
            k = surf.exited
            ids, moves = s.exit_ids[:k], s.exit_moves[:k]
            assert len(np.unique(ids)) == k
            # (or, with no way out along ±n_i within EXIT_REACH, through the nearest face, within EXIT_FACE_REACH)
            along, length = np.sum(moves * s.n_pn[ids], axis=1), np.linalg.norm(moves, axis=1)
            normal = np.isclose(np.abs(along), length, rtol=1e-9, atol=0.0)
            coarse = ids < len(x)
            assert np.all(length[coarse] <= EXIT_REACH + st.lift_clearance + 1e-12)
            # (off the normal: along one of the ways around)
            turned = moves[coarse & ~normal] / length[coarse & ~normal, None]
            assert np.all(np.max(turned @ EXIT_DIRECTIONS.T, axis=1) > 1.0 - 1e-9)
            assert np.all(length[normal] <= EXIT_REACH + st.lift_clearance + 1e-12)
            assert np.all(length <= EXIT_FACE_REACH + 1e-12)
            p[ids] -= moves
            wind = np.zeros(k, dtype=np.int64)
            winding_numbers(p[ids], session.pose.x, session.body_mesh.winding_faces, *session.pose.winding.arrays(),
                            wind)
            assert np.all(wind > 0)
            exited.append(k)
            k = surf.creased
            assert np.all(s.creased_ids[:k] >= len(x)) and len(np.unique(s.creased_ids[:k])) == k
            assert np.all(np.linalg.norm(s.crease_moves[:k], axis=1) <= 2 * CREASE_MOVE)
            creased.append(k)
            p[s.creased_ids[:k]] -= s.crease_moves[:k]
            # each from inside the body as a whole (its winding number), never from outside it
            wind = np.zeros(k, dtype=np.int64)
            winding_numbers(p[s.creased_ids[:k]], session.pose.x, session.body_mesh.winding_faces,
                            *session.pose.winding.arrays(), wind)
            from_outside.append(int(np.sum(wind == 0)))
            if not checked:  # every coarse triangle drawn once, most of them as halves of quads
                faces = m.fold_groups[m.fold_groups >= 0]
                np.testing.assert_array_equal(np.sort(faces), np.arange(len(m.tess.coarse_triangles)))
                assert np.mean(m.fold_corner >= 0) > 0.5
            # as drawn: Δh, or higher in a fold across the compression
            assert np.all(s.height >= s.dh)
            np.testing.assert_allclose(p, s.p_smoothed + s.height[:, None] * s.n_pn, atol=1e-12)
            assert np.isfinite(p).all() and np.isfinite(n).all()
            assert s.dh.min() >= -st.max_height and s.dh.max() <= 2 * st.max_height
            # below the reference surface only where S103 found a body part above (Decision)
            low = s.dh < 0.0
            assert np.all(s.facing[low] < 0.0) and np.all(np.isfinite(s.sd[low]))
            np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-9)
            # the coarse particles are detailed vertices 0..n-1, moved only along their normal (by S103's lifts;
            # the moves out along ±n_i were taken off above)
            off = p[: len(x)] - x
            np.testing.assert_allclose(off, s.dh[: len(x), None] * s.n_pn[: len(x)], atol=1e-12)
        checked.append(index)

    report = run_cloth_clip(body, data / "garments" / outfit, data / "mocap" / "cmu_npybvh_example_75f.bvh",
                            on_frame=on_frame, surface=SurfaceSettings())
    assert report.nan_frames == 0 and len(checked) == report.frames > 30
    layers = outfit != "female_sportsuit01"  # the sport suit's top and bottom do not meet
    assert (len(report.layer_ms) == report.frames) == layers and (sum(lifted) > 0) == layers
    assert (sum(pressed) > 0) == layers
    assert sum(creased) > 0 and sum(from_outside) == 0 and sum(exited) > 0
    assert all(len(v) == report.frames for v in report.surface_ms.values())
