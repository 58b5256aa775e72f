"""Acceptance over every shipped clip: retarget + skin every frame."""

import numpy as np
import pytest

from services.body_job import run_clip
from tests.conftest import CLIPS


@pytest.fixture(scope="module", params=CLIPS)
def report(request, body, mocap):
    return run_clip(body, mocap / f"{request.param}.bvh")


def test_no_nan_anywhere(report):
    assert report.frames > 0
    assert report.nan_frames == 0
    assert np.isfinite(report.ankle_position_error).all()


def test_ankle_error(report):
    err = report.ankle_position_error.max(axis=1)
    assert np.median(err) <= 0.005
    assert np.percentile(err, 99) <= 0.02


def test_feet_stay_above_the_floor(report):
    assert report.lowest_sole.min() >= -0.01


def test_floor_lift_is_small(report):
    """Lifting ankle targets off the floor corrects foot proportions now and then; it does not
    re-pose the character (large lifts happen on the converters' T-pose frames, placed below the floor)."""
    assert np.median(report.floor_lift) < 0.005
    assert np.percentile(report.floor_lift[1:], 95) < 0.03
