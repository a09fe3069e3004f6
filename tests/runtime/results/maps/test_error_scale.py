"""The error picture's colour scale follows the data: the 99th percentile rounded up by at
most a quarter, never past 180 deg."""

from __future__ import annotations

import numpy as np
import pytest

from msfnet.runtime.results.maps.pictures import error_range, scale_ceiling


@pytest.mark.parametrize(
    ("value", "top"),
    [(109.1, 120.0), (134.6, 150.0), (16.8, 20.0), (7.3, 8.0), (0.021, 0.025), (2.0, 2.0)],
)
def test_scale_ceiling(value: float, top: float) -> None:
    assert scale_ceiling(value) == pytest.approx(top)
    assert value <= scale_ceiling(value) <= 1.25 * value


def test_harvest_like_errors_get_a_scale_near_their_99th_percentile() -> None:
    """Least squares on harvest: 99th percentile 109 deg, largest 135: the scale was 0-200
    (1-2-5 rounding), most of the object near-black."""
    rng = np.random.default_rng(0)
    err = np.clip(rng.gamma(2.0, 17.0, (200, 300)), 0, 134.6)
    mask = np.ones(err.shape, bool)
    p99 = float(np.percentile(err, 99))
    top = error_range(err, mask)
    assert p99 <= top <= 1.25 * p99, (p99, top)
    assert top < 200
    assert error_range(np.full((4, 4), 179.0), np.ones((4, 4), bool)) == 180.0  # the most
