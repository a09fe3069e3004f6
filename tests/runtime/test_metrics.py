"""Metrics never reward a missing prediction: non-unit predictions score 180 deg."""

from __future__ import annotations

import json

import numpy as np
import pytest

from msfnet.runtime.files import json_text
from msfnet.runtime.metrics import angular_error_deg, error_map, normal_metrics


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
