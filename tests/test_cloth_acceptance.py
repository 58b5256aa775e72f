"""Every shipped clip × outfit at 60 Hz: no NaN ever reaches the output, and the waistband stays
within 3 cm of the body surface on every frame (independent signed distance, tests/signed_distance.py).

Penetration depth and edge stretch are measured by the same module (python -m tests.cloth_acceptance)
and reported in the README; they do not meet the issue's bounds yet (see the README)."""

import pytest

from services.cloth_job import OUTFITS
from tests.cloth_acceptance import measure
from tests.conftest import CLIPS


@pytest.mark.parametrize("clip", CLIPS)
@pytest.mark.parametrize("outfit", OUTFITS)
def test_garments_stay_finite_and_waistbands_stay_at_the_waist(body, data, outfit, clip):
    records, report = measure(body, data, outfit, clip, full=False)
    assert report.frames > 30
    for r in records:
        assert r.nan_frames == 0, r.name
        if r.name.endswith(".bottom"):
            assert len(r.waist_gap) == report.frames
            assert max(r.waist_gap) < 0.03, f"{r.name}: waistband {max(r.waist_gap) * 100:.1f} cm from the body"
