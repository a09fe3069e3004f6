"""Angular-error metrics for normal maps: the one implementation every command and test uses.

A predicted pixel that is not a unit vector (zero, NaN, or a norm off by more than
``UNIT_TOLERANCE``) is a failure: it scores 180 deg and is counted in ``invalid``. It never
scores 0, so a black or blanked-out prediction cannot improve a score. Mask pixels without a
valid ground-truth normal are left out of the score and counted in ``gt_missing``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

UNIT_TOLERANCE = 0.05  # |n| outside [0.95, 1.05] is not a normal


def angular_error_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between vectors along the last axis, in degrees, as atan2(|a x b|, a . b) in float64.

    arccos of a float32 dot product cannot resolve angles below ~0.03 deg; this form can.
    """
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    dot = np.sum(a * b, axis=-1)
    return np.degrees(np.arctan2(cross, dot))


def deviation_deg(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """(mean, max) angle in degrees between two normal maps over the mask pixels.

    The maps are both (1, 3, H, W), as a network or engine returns them, or both (H, W, 3), as
    msf-run saves them; ``mask`` is (H, W) bool. Compares two predictions (an engine against a
    reference), so it is symmetric: a pixel where either map is not a unit vector (zero, NaN,
    wrong length) scores 180 deg, as in :func:`normal_metrics`, so a broken output can never
    look like a perfect match. ValueError for other shapes or an empty mask.
    """
    a, b, mask = np.asarray(a), np.asarray(b), np.asarray(mask, bool)
    if a.shape != b.shape:
        raise ValueError(f"deviation_deg: maps of different shapes {a.shape} and {b.shape}")
    if a.ndim == 4 and a.shape[:2] == (1, 3):
        a, b = a[0].transpose(1, 2, 0), b[0].transpose(1, 2, 0)
    elif not (a.ndim == 3 and a.shape[-1] == 3):
        raise ValueError(f"deviation_deg: expected (1, 3, H, W) or (H, W, 3) maps, got {a.shape}")
    if mask.shape != a.shape[:2]:
        raise ValueError(f"deviation_deg: mask {mask.shape} does not match the maps {a.shape}")
    if not mask.any():
        raise ValueError("deviation_deg: the mask is empty")
    pa, pb = a[mask], b[mask]
    with np.errstate(invalid="ignore"):
        err = angular_error_deg(np.nan_to_num(pa), np.nan_to_num(pb))
    err[~(is_unit(pa) & is_unit(pb))] = 180.0
    return float(err.mean()), float(err.max())


def is_unit(v: np.ndarray, tolerance: float = UNIT_TOLERANCE) -> np.ndarray:
    """Boolean per vector (last axis): finite and of length 1 within ``tolerance``."""
    with np.errstate(invalid="ignore"):
        norm = np.linalg.norm(np.asarray(v, np.float64), axis=-1)
        return np.isfinite(norm) & (np.abs(norm - 1.0) <= tolerance)


@dataclass(frozen=True)
class NormalMetrics:
    mae_deg: float  # mean angular error over the scored pixels
    median_deg: float
    err15: float  # share of scored pixels under 15 deg
    err30: float
    pixels: int  # scored pixels (mask pixels with a valid ground truth)
    invalid: int = 0  # predictions that were not unit vectors (scored as 180 deg)
    gt_missing: int = 0  # mask pixels without a valid ground-truth normal (not scored)

    def as_dict(self) -> dict[str, float | int]:
        return asdict(self)


def error_map(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W) angular error in degrees: 180 where the prediction is not a unit vector, NaN
    where the pixel is not scored (outside the mask or no valid ground truth)."""
    out = np.full(mask.shape, np.nan, np.float64)
    scored = mask & is_unit(gt)
    err = angular_error_deg(np.nan_to_num(pred[scored]), gt[scored])
    err[~is_unit(pred[scored])] = 180.0
    out[scored] = err
    return out


def normal_metrics(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> NormalMetrics:
    """MAE, median, err15/err30 over the mask (see the module docstring for failures)."""
    scored = mask & is_unit(gt)
    if not scored.any():
        raise ValueError("no pixel to score: the mask is empty or has no valid ground truth")
    valid = is_unit(pred[scored])
    err = angular_error_deg(np.nan_to_num(pred[scored]), gt[scored])
    err[~valid] = 180.0
    return NormalMetrics(
        mae_deg=float(err.mean()),
        median_deg=float(np.median(err)),
        err15=float(np.mean(err < 15.0)),
        err30=float(np.mean(err < 30.0)),
        pixels=int(err.size),
        invalid=int((~valid).sum()),
        gt_missing=int(mask.sum() - scored.sum()),
    )


__all__ = [
    "UNIT_TOLERANCE",
    "NormalMetrics",
    "angular_error_deg",
    "deviation_deg",
    "error_map",
    "is_unit",
    "normal_metrics",
]
