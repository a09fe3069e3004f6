"""Small rendered surfaces with exact normals for the inspection-map tests.

Every surface is a height field z(row, col) in pixels with z toward the camera, returned with
its mask and its analytic unit normals in the camera frame (x right, y up, z to the camera).
The fixtures hand out the factory functions so each test can pick sizes and parameters.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

Surface = tuple[np.ndarray, np.ndarray, np.ndarray]  # height (NaN outside), mask, normals


def normals_from_slopes(dz_dcol: np.ndarray, dz_drow: np.ndarray) -> np.ndarray:
    """Unit normals of a height field from its slopes along columns and rows (y = -row)."""
    n = np.stack([-dz_dcol, dz_drow, np.ones_like(dz_dcol)], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def sphere_cap(h: int = 64, w: int = 72, radius: float = 40.0, cap: float = 28.0) -> Surface:
    """The part of a sphere (radius px) facing the camera, cut to a disc of radius ``cap``."""
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = cols - (w - 1) / 2, -(rows - (h - 1) / 2)
    mask = x**2 + y**2 < cap**2
    z = np.sqrt(np.clip(radius**2 - x**2 - y**2, 0, None))
    n = np.stack([x, y, z], axis=-1) / radius
    n[~mask] = 0
    return np.where(mask, z, np.nan), mask, n


def gaussian_bumps(h: int = 64, w: int = 72, masked: bool = False) -> Surface:
    """Two bumps and a dimple; full frame, or inside an ellipse when ``masked``."""
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    z = np.zeros((h, w))
    dc = np.zeros((h, w))
    dr = np.zeros((h, w))
    for r0, c0, amp, s in ((20, 22, 12.0, 7.0), (40, 50, -8.0, 9.0), (45, 20, 6.0, 5.0)):
        e = amp * np.exp(-((rows - r0) ** 2 + (cols - c0) ** 2) / (2 * s * s))
        z += e
        dc += -e * (cols - c0) / s**2
        dr += -e * (rows - r0) / s**2
    mask = np.ones((h, w), bool)
    if masked:
        mask = ((rows - h / 2) / (0.45 * h)) ** 2 + ((cols - w / 2) / (0.45 * w)) ** 2 < 1
    n = normals_from_slopes(dc, dr)
    n[~mask] = 0
    return np.where(mask, z, np.nan), mask, n


def dock(size: int = 64, step: float = 40.0, ramp_rows: int = 32, ramp_w: int = 40) -> Surface:
    """A loading dock: ground (z = 0, left) and a platform (z = step, right). In the top
    ``ramp_rows`` rows a linear ramp ``ramp_w`` px wide joins them; below, a vertical wall at
    the centre column, seen edge-on: its pixels hold grazing normals (-1, 0, 0), which bound
    the slope they tell (1/min_nz) far below the true jump. The step height is only known by
    going around through the ramp, so least squares smears it over the lower half while a
    discontinuity-aware solver should put it all at the wall."""
    rows, cols = np.mgrid[0:size, 0:size].astype(np.float64)
    c0 = size // 2
    lo, hi = c0 - ramp_w // 2, c0 + ramp_w // 2 - 1  # ramp pixels lo..hi: kinks fall between
    ramp = rows < ramp_rows
    s = np.clip((cols - lo + 0.5) / ramp_w, 0, 1)
    on_ramp = ramp & (cols >= lo) & (cols <= hi)
    z = np.where(ramp, step * s, np.where(cols > c0, step, np.where(cols == c0, step / 2, 0.0)))
    n = normals_from_slopes(np.where(on_ramp, step / ramp_w, 0.0), np.zeros_like(z))
    n[~ramp & (cols == c0)] = (-1.0, 0.0, 0.0)
    return z, np.ones((size, size), bool), n


def saddle(h: int = 48, w: int = 48, a: float = 0.01) -> Surface:
    """z = a (x^2 - y^2): principal curvatures +-2a at the centre, mean curvature 0."""
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = cols - (w - 1) / 2, -(rows - (h - 1) / 2)
    z = a * (x**2 - y**2)
    n = normals_from_slopes(2 * a * x, 2 * a * y)  # dz/drow = -dz/dy = 2 a y
    return z, np.ones((h, w), bool), n


def perspective_sphere(
    h: int = 60, w: int = 64, f: float = 80.0, radius: float = 1.0, distance: float = 4.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[float, float, float, float]]:
    """A sphere seen by a pinhole camera (fx = fy = f px, centre off the image centre):
    returns depth along the optical axis, mask, normals (camera frame, y up) and intrinsics."""
    cx, cy = w / 2 - 3.0, h / 2 + 2.0
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    ray = np.stack([(cols - cx) / f, (rows - cy) / f, np.ones_like(cols)], axis=-1)  # y down
    centre = np.array([0.15, -0.1, distance])
    # |t ray - centre|^2 = radius^2, nearest root
    a = np.sum(ray * ray, -1)
    b = -2 * ray @ centre
    c = centre @ centre - radius**2
    disc = b * b - 4 * a * c
    mask = disc > 0.02 * b * b  # stay off the grazing silhouette
    t = (-b - np.sqrt(np.clip(disc, 0, None))) / (2 * a)
    n_cv = (t[..., None] * ray - centre) / radius
    n = np.stack([n_cv[..., 0], -n_cv[..., 1], -n_cv[..., 2]], axis=-1)
    n[~mask] = 0
    return np.where(mask, t, np.nan), mask, n, (f, f, cx, cy)


@pytest.fixture
def surfaces() -> dict[str, Callable[..., object]]:
    return {
        "sphere_cap": sphere_cap,
        "bumps": gaussian_bumps,
        "dock": dock,
        "saddle": saddle,
        "perspective_sphere": perspective_sphere,
    }


def centred_rms(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    """RMS of a - b over the mask after removing the mean difference (the unknown offset)."""
    d = (a - b)[mask]
    d = d - d.mean()
    return float(np.sqrt(np.mean(d * d)))


@pytest.fixture
def rms() -> Callable[[np.ndarray, np.ndarray, np.ndarray], float]:
    return centred_rms
