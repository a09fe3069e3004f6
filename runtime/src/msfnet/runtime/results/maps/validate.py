"""Input checks shared by every map: one place that turns bad arrays into ``InputError``.

The maps take the normals an estimator produced. Inside the mask a pixel may legitimately hold
a zero vector (least squares writes zeros where its fit is degenerate): such pixels are dropped
from the *valid* mask and get the documented "no value" of each map. NaN or infinite normals
inside the mask mean the estimator failed, and are refused with a message saying how many.
"""

from __future__ import annotations

import numpy as np

from msfnet.common.errors import InputError

MIN_NORM = 1e-6  # below this a normal counts as "no estimate" (zeros from a degenerate fit)


def check_mask(mask: np.ndarray, shape: tuple[int, int] | None = None) -> np.ndarray:
    """(H, W) array -> bool mask; ``shape`` (H, W) must match when given."""
    m = np.asarray(mask)
    if m.ndim != 2:
        raise InputError(f"mask must be H x W, got shape {m.shape}")
    if shape is not None and m.shape != tuple(shape):
        raise InputError(f"mask is {m.shape} but the normals are {tuple(shape)}")
    return m.astype(bool)


def check_normals(normals: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Validate (H, W, 3) normals against an (H, W) mask.

    Returns ``(unit, valid)``: float64 unit normals with zeros outside ``valid``, and the bool
    mask of pixels that are in ``mask`` and hold a non-zero normal.
    Raises InputError for a wrong shape or NaN/inf values inside the mask.
    """
    n = np.asarray(normals)
    if n.ndim != 3 or n.shape[2] != 3:
        raise InputError(f"normals must be H x W x 3, got shape {n.shape}")
    m = check_mask(mask, n.shape[:2])
    # one float64 copy, then worked on in place: an H x W x 3 float64 array is 24 B a pixel,
    # and the maps run within --max-memory beside the loaded stack
    n = np.array(n, dtype=np.float64)
    bad = m & ~np.isfinite(n).all(axis=2)
    if bad.any():
        raise InputError(
            f"normals contain NaN or infinite values at {int(bad.sum())} of "
            f"{int(m.sum())} mask pixels"
        )
    del bad
    n[~m] = 0.0  # whatever lies outside the mask is ignored
    norm = np.sqrt(np.einsum("hwc,hwc->hw", n, n))
    valid = m & (norm > MIN_NORM)
    n /= np.maximum(norm, MIN_NORM)[..., None]
    n[~valid] = 0.0
    return n, valid


__all__ = ["MIN_NORM", "check_mask", "check_normals"]
