"""Angular-error metrics for normal maps: the one implementation every command and test uses."""

from __future__ import annotations

import numpy as np


def angular_error_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between vectors along the last axis, in degrees, as atan2(|a x b|, a . b) in float64.

    arccos of a float32 dot product cannot resolve angles below ~0.03 deg; this form can.
    """
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    dot = np.sum(a * b, axis=-1)
    return np.degrees(np.arctan2(cross, dot))


def normal_metrics(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    """MAE, median, err15/err30 (share of mask pixels under 15/30 deg) over the mask."""
    err = angular_error_deg(pred[mask], gt[mask])
    if err.size == 0:
        raise ValueError("empty mask: no pixel to score")
    return {
        "mae_deg": float(err.mean()),
        "median_deg": float(np.median(err)),
        "err15": float(np.mean(err < 15.0)),
        "err30": float(np.mean(err < 30.0)),
        "pixels": int(err.size),
    }


def error_map(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W) angular error in degrees, 0 outside the mask."""
    out = np.zeros(mask.shape, np.float64)
    out[mask] = angular_error_deg(pred[mask], gt[mask])
    return out
