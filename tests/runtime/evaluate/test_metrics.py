"""Metrics never reward a missing prediction: non-unit predictions score 180 deg."""

from __future__ import annotations

import json

import numpy as np
import pytest

from msfnet.common.files import json_text
from msfnet.runtime.evaluate.metrics import (
    angular_error_deg,
    deviation_deg,
    error_map,
    normal_metrics,
)


def _sphere(h: int = 20) -> tuple[np.ndarray, np.ndarray]:
    yy, xx = np.mgrid[0:h, 0:h] / (h - 1) * 2 - 1
    mask = xx**2 + yy**2 < 0.8
    n = np.stack([xx, -yy, np.sqrt(np.clip(1 - xx**2 - yy**2, 0, None))], -1)
    n[~mask] = 0
    return n.astype(np.float32), mask


def test_small_angles_are_resolved() -> None:
    a = np.array([0.0, 0.0, 1.0])
    b = np.array([np.sin(np.radians(1e-3)), 0.0, np.cos(np.radians(1e-3))])
    assert angular_error_deg(a, b) == pytest.approx(1e-3, rel=1e-6)


@pytest.mark.parametrize("bad", ["zero", "nan", "inf", "short"])
def test_invalid_predictions_score_180(bad: str) -> None:
    gt, mask = _sphere()
    pred = gt.copy()
    quarter = np.zeros_like(mask)
    quarter[:10, :10] = True
    quarter &= mask
    pred[quarter] = {"zero": 0.0, "nan": np.nan, "inf": np.inf, "short": 0.5}[bad]
    m = normal_metrics(pred, gt, mask)
    assert m.invalid == quarter.sum() > 0
    perfect = normal_metrics(gt, gt, mask)
    assert perfect.mae_deg < 1e-6 and perfect.invalid == 0
    # blanking part of the object makes the score worse, never better
    assert m.mae_deg == pytest.approx(180 * quarter.sum() / mask.sum(), rel=1e-6)
    assert m.err15 == pytest.approx(1 - quarter.sum() / mask.sum())
    err = error_map(pred, gt, mask)
    assert np.all(err[quarter] == 180) and np.isnan(err[~mask]).all()
    json.loads(json_text(m.as_dict()))  # always valid JSON


def test_all_black_prediction_is_the_worst_score() -> None:
    gt, mask = _sphere()
    m = normal_metrics(np.zeros_like(gt), gt, mask)
    assert m.mae_deg == 180 and m.err15 == 0 and m.invalid == mask.sum()


def test_pixels_without_ground_truth_are_not_scored() -> None:
    gt, mask = _sphere()
    gt2 = gt.copy()
    gt2[5, 10] = 0  # a hole in the ground truth inside the mask
    assert mask[5, 10]
    m = normal_metrics(gt, gt2, mask)
    assert m.gt_missing == 1 and m.pixels == mask.sum() - 1 and m.mae_deg < 1e-6
    json_text({"x": float("nan")})  # NaN becomes null, never bare NaN
    assert json.loads(json_text({"x": float("nan")})) == {"x": None}


def _rotated_about_y(n: np.ndarray, deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    rot = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    return (n @ rot.T).astype(np.float32)


def test_deviation_of_two_maps_in_either_layout() -> None:
    """mean/max angle over the mask, for (H, W, 3) maps and for (1, 3, H, W) network output."""
    _, mask = _sphere()
    ref = np.zeros((*mask.shape, 3), np.float32)
    ref[..., 2] = 1.0  # facing the camera: a rotation about y turns each normal by its angle
    out = ref.copy()
    out[mask] = _rotated_about_y(ref[mask], 2.0)
    out[10, 10] = _rotated_about_y(ref[10, 10], 5.0)  # one pixel further off
    assert mask[10, 10]
    outside = ~mask
    out[outside] = [1.0, 0.0, 0.0]  # far off outside the mask: never scored
    mean, mx = deviation_deg(out, ref, mask)
    n = mask.sum()
    assert mx == pytest.approx(5.0, abs=1e-4)
    assert mean == pytest.approx((2.0 * (n - 1) + 5.0) / n, abs=1e-4)
    chw = deviation_deg(out.transpose(2, 0, 1)[None], ref.transpose(2, 0, 1)[None], mask)
    assert chw == pytest.approx((mean, mx))
    assert deviation_deg(ref, out, mask) == pytest.approx((mean, mx))  # symmetric
    assert deviation_deg(ref, ref, mask) == (0.0, 0.0)


@pytest.mark.parametrize("bad", ["zero", "nan", "short"])
@pytest.mark.parametrize("which", ["out", "ref"])
def test_deviation_scores_a_broken_pixel_180(bad: str, which: str) -> None:
    """A zero or NaN output (a broken engine) can never look like a perfect match."""
    ref, mask = _sphere()
    out = ref.copy()
    (out if which == "out" else ref)[mask] = {"zero": 0.0, "nan": np.nan, "short": 0.5}[bad]
    assert deviation_deg(out, ref, mask) == (180.0, 180.0)


def test_deviation_refuses_mismatched_shapes_and_empty_masks() -> None:
    ref, mask = _sphere()
    with pytest.raises(ValueError, match="different shapes"):
        deviation_deg(ref, ref[:-1], mask)
    with pytest.raises(ValueError, match="expected"):
        deviation_deg(ref[..., :2], ref[..., :2], mask)
    with pytest.raises(ValueError, match="mask"):
        deviation_deg(ref, ref, mask[:-1])
    with pytest.raises(ValueError, match="empty"):
        deviation_deg(ref, ref, np.zeros_like(mask))
