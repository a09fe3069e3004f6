"""The ground-truth-free detail check: smoothing lowers it, added relief raises it."""

from __future__ import annotations

import cv2
import numpy as np

from msfnet.runtime.evaluate.detail_ratio import detail_ratio, highpass_energy


def _relief(h: int = 64) -> tuple[np.ndarray, np.ndarray]:
    yy, xx = np.mgrid[0:h, 0:h].astype(np.float64)
    z = 0.5 * np.sin(xx / 1.5) * np.sin(yy / 2.0)  # 1-3 px relief
    gy, gx = np.gradient(z)
    n = np.stack([-gx, gy, np.ones_like(z)], -1)
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    mask = np.zeros((h, h), bool)
    mask[6:-6, 6:-6] = True
    n[~mask] = 0
    return n.astype(np.float32), mask


def test_smoothing_removes_detail() -> None:
    n, mask = _relief()
    smooth = cv2.GaussianBlur(n, (0, 0), 1.5)
    smooth /= np.linalg.norm(smooth, axis=2, keepdims=True)
    ratio = detail_ratio(smooth, n, mask)
    assert ratio < 0.3, ratio
    assert detail_ratio(n, n, mask) == 1.0
    flat = np.zeros_like(n)
    flat[mask] = (0, 0, 1)
    assert highpass_energy(flat, mask) < 1e-10  # a plane has no detail, and the outline adds none


def test_tiny_mask_gives_nan_not_a_crash() -> None:
    n, _ = _relief()
    mask = np.zeros(n.shape[:2], bool)
    mask[30:33, 30:33] = True
    assert np.isnan(highpass_energy(n, mask))
