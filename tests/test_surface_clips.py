"""The detailed surface through a real clip with every outfit: finite, heights within their
bounds, unit shading normals, and the coarse vertices on the surface."""

import numpy as np
import pytest

from cloth.surface import SurfaceSettings
from services.cloth_job import OUTFITS, run_cloth_clip


@pytest.mark.parametrize("outfit", OUTFITS)
def test_surface_through_the_run_clip(body, data, outfit):
    checked = []

    def on_frame(index, session, body_frame, positions):
        for surf, (p, n), x in zip(session.surfaces, session.detailed, positions):
            s, st = surf.state, surf.model.settings
            assert np.isfinite(p).all() and np.isfinite(n).all()
            assert s.dh.min() >= -st.max_height and s.dh.max() <= 2 * st.max_height
            # below the reference surface only where S103 found a body part above (Decision)
            low = s.dh < 0.0
            assert np.all(s.facing[low] < 0.0) and np.all(np.isfinite(s.sd[low]))
            np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-9)
            # the coarse particles are detailed vertices 0..n-1, moved only along their normal
            off = p[: len(x)] - x
            np.testing.assert_allclose(off, s.dh[: len(x), None] * s.n_pn[: len(x)], atol=1e-12)
        checked.append(index)

    report = run_cloth_clip(body, data / "garments" / outfit, data / "mocap" / "cmu_npybvh_example_75f.bvh",
                            on_frame=on_frame, surface=SurfaceSettings())
    assert report.nan_frames == 0 and len(checked) == report.frames > 30
    assert all(len(v) == report.frames for v in report.surface_ms.values())
