"""Every shipped clip × outfit at 60 Hz: no NaN ever reaches the output, no coarse particle is deeper
than 1 mm inside the body after a step, the waistband stays within 3 cm of the body surface, and no
garment is thrown off the body (on no frame are a fifth of its particles more than 10 cm from the
skin: a skirt's hem swinging out with the legs reaches a tenth; the run's sprint blew the open silk
blouse off the torso, 23 %, before the thirty-ninth session), on every frame (independent signed
distance, tests/signed_distance.py: exact closest points, the sign from the skin's winding number).

Edge stretch is measured by the same module (python -m tests.cloth_acceptance) and reported in
docs/cloth.md; it does not meet the issue's bound yet on every garment (see there)."""

import pytest

from services.cloth_job import OUTFITS
from tests.cloth_acceptance import measure
from tests.conftest import CLIPS


@pytest.mark.parametrize("clip", CLIPS)
@pytest.mark.parametrize("outfit", OUTFITS)
def test_garments_stay_finite_outside_the_body_and_at_the_waist(body, data, outfit, clip):
    records, report = measure(body, data, outfit, clip)
    assert report.frames > 30
    for r in records:
        assert r.nan_frames == 0, r.name
        assert len(r.depth) == report.frames
        inside = [i for i, d in enumerate(r.depth) if d < -0.001]
        assert not inside, (f"{r.name}: a particle deeper than 1 mm on {len(inside)} frames (first {inside[:5]}), "
                            f"deepest {r.deepest * 1000:.1f} mm")
        assert max(r.off_body) < 0.2, f"{r.name}: {max(r.off_body) * 100:.0f} % of its particles off the body"
        if r.name.endswith(".bottom"):
            assert len(r.waist_gap) == report.frames
            assert max(r.waist_gap) < 0.03, f"{r.name}: waistband {max(r.waist_gap) * 100:.1f} cm from the body"
