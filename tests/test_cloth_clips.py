"""Outfits through a real clip (the short run): no NaN, garments stay on, waistband at the waist."""

import numpy as np
import pytest

from services.cloth_job import OUTFITS, run_cloth_clip


@pytest.mark.parametrize("outfit", OUTFITS)
def test_outfit_stays_on_through_the_run_clip(body, data, outfit):
    waist_gap = []

    def on_frame(index, session, body_frame, positions):
        bottom = session.sims[1]
        grip = np.flatnonzero(bottom.model.grip)
        pts = positions[1][grip]
        skin = body_frame.vertices[: body.n_visible]
        d = np.sqrt(((pts[:, None, :] - skin[None, :, :]) ** 2).sum(-1)).min(axis=1)  # independent of the sim
        waist_gap.append(d.max())

    r = run_cloth_clip(body, data / "garments" / outfit, data / "mocap" / "cmu_npybvh_example_75f.bvh", every=2,
                       on_frame=on_frame)
    assert r.frames == 37 and r.nan_frames == 0
    for m in r.models:
        assert 300 <= m.n_particles <= 400
    assert max(waist_gap) < 0.03
