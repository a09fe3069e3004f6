"""Where the calibration sphere(s) are in the image: circles from a mask or from the images.

Pixel convention: (x, y) = (column, row) of pixel centres, row 0 at the top.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from msfnet.common.errors import InputError
from msfnet.common.vocabulary import opt


@dataclass(frozen=True)
class Circle:
    cx: float
    cy: float
    r: float

    def contains(self, h: int, w: int, shrink: float = 1.0) -> np.ndarray:
        y, x = np.mgrid[:h, :w]
        return (x - self.cx) ** 2 + (y - self.cy) ** 2 <= (self.r * shrink) ** 2


def finite_lstsq(a: np.ndarray, b: np.ndarray, what: str) -> np.ndarray:
    """``lstsq`` that refuses NaN/inf first: LAPACK's SVD can loop forever on them, ignoring
    Ctrl-C (``--intrinsics 0 0 0 0`` hung msf-calib at 100 % CPU)."""
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise InputError(f"non-finite values in {what} (check the intrinsics, mask and images)")
    return np.linalg.lstsq(a, b, rcond=None)[0]


def fit_circle(x: np.ndarray, y: np.ndarray, iterations: int = 10) -> Circle:
    """Algebraic (Kasa) fit refined by Gauss-Newton on the geometric distance."""
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    if len(x) < 3:
        raise InputError(f"a circle needs at least 3 edge points, got {len(x)}")
    a = np.c_[x, y, np.ones_like(x)]
    sol = finite_lstsq(a, x * x + y * y, "the circle fit")
    cx, cy = sol[0] / 2, sol[1] / 2
    r = np.sqrt(max(sol[2] + cx * cx + cy * cy, 1e-12))
    for _ in range(iterations):
        dx, dy = x - cx, y - cy
        d = np.hypot(dx, dy) + 1e-12
        jac = np.c_[-dx / d, -dy / d, -np.ones_like(d)]
        step = finite_lstsq(jac, -(d - r), "the circle fit")
        cx, cy, r = cx + step[0], cy + step[1], r + step[2]
        if np.abs(step).max() < 1e-6:
            break
    return Circle(float(cx), float(cy), float(r))


def crack_points(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mid-points between inside and outside 4-neighbours: an unbiased sub-pixel boundary.

    Boundaries along the image border are left out, so a sphere cut by the frame still fits.
    """
    m = mask.astype(bool)
    ys, xs = np.nonzero(m[:, 1:] != m[:, :-1])
    yv, xv = np.nonzero(m[1:, :] != m[:-1, :])
    return np.r_[xs + 0.5, xv.astype(np.float64)], np.r_[ys.astype(np.float64), yv + 0.5]


def fit_circles_from_mask(
    mask: np.ndarray, min_area: int = 200, source: str | Path | None = None
) -> list[Circle]:
    """One circle per connected blob of the mask (several spheres allowed), left to right.
    ``source``: the mask file, named by the error when there is no sphere."""
    m = np.asarray(mask).astype(np.uint8)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    circles = []
    for k in range(1, count):
        if stats[k, cv2.CC_STAT_AREA] < min_area:
            continue
        x, y = crack_points(labels == k)
        if len(x) < 20:
            continue
        circles.append(fit_circle(x, y))
    if not circles:
        raise InputError(
            f"no sphere found in the mask (no blob of at least {min_area} pixels)", source
        )
    return sorted(circles, key=lambda c: c.cx)


def _stretch(img: np.ndarray) -> np.ndarray:
    """Grey, log-stretched to 8 bit so a dark chrome sphere's rim becomes an edge."""
    g = img.astype(np.float64)
    lo, hi = np.percentile(g, [1, 99.5])
    g = np.log1p(np.clip(g - lo, 0, None) / max((hi - lo) / 200.0, 1e-9))
    return np.clip(g / max(g.max(), 1e-9) * 255, 0, 255).astype(np.uint8)


def _refine_edge(grey: np.ndarray, c: Circle, rays: int = 180, band: float = 0.06) -> Circle:
    """Strongest radial step along rays near the guess (sub-pixel), then a robust circle fit."""
    g = cv2.GaussianBlur(grey.astype(np.float32), (0, 0), 1.0)
    radii = np.linspace(c.r * (1 - band), c.r * (1 + band), max(int(2 * band * c.r * 4), 16))
    th = np.linspace(0, 2 * np.pi, rays, endpoint=False)
    xs = c.cx + np.cos(th)[:, None] * radii[None]
    ys = c.cy + np.sin(th)[:, None] * radii[None]
    prof = cv2.remap(
        g,
        xs.astype(np.float32),
        ys.astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=np.nan,
    )
    grad = np.abs(np.gradient(prof, axis=1))
    px, py, strength = [], [], []
    for i in range(rays):
        row = grad[i]
        if not np.all(np.isfinite(prof[i])):
            continue  # ray leaves the image
        k = int(np.argmax(row))
        if 0 < k < len(row) - 1:
            a, b, cc = row[k - 1], row[k], row[k + 1]
            den = a - 2 * b + cc
            off = 0.5 * (a - cc) / den if den < 0 else 0.0
            rr = np.interp(k + off, np.arange(len(radii)), radii)
            px.append(c.cx + np.cos(th[i]) * rr)
            py.append(c.cy + np.sin(th[i]) * rr)
            strength.append(b)
    if len(px) < 12:
        return c
    ax, ay, s = np.asarray(px), np.asarray(py), np.asarray(strength)
    keep = s >= np.percentile(s, 30)  # rays across weak or occluded edges are unreliable
    fit = fit_circle(ax[keep], ay[keep])
    for _ in range(3):  # drop outliers (sphere stand, reflections of the rim)
        d = np.abs(np.hypot(ax - fit.cx, ay - fit.cy) - fit.r)
        keep = d < max(1.0, 3 * 1.4826 * np.median(d[keep]))
        if keep.sum() < 12:
            break
        fit = fit_circle(ax[keep], ay[keep])
    return fit


def fit_circles_from_images(
    images: np.ndarray, count: int = 1, source: str | Path | None = None
) -> list[Circle]:
    """Find ``count`` sphere silhouettes in a stack (N, H, W[, 3]) without a mask (``source``:
    where the images came from, named by the error when no sphere is found).

    Hough circles on the log-stretched mean image give a first guess; each is refined on the
    strongest radial edge. Less reliable than a mask: check the diagnostic image.
    """
    imgs = np.asarray(images)
    total = np.zeros(imgs.shape[1:3])
    for img in imgs:  # float64 one light at a time, not a float64 copy of the stack
        a = np.asarray(img, np.float64)
        total += a.mean(axis=-1) if a.ndim == 3 else a
    mean = _stretch(total / len(imgs))
    h, w = mean.shape
    blurred = cv2.GaussianBlur(mean, (0, 0), 2.0)
    found: list[Circle] = []
    for acc in (40, 30, 20, 12):
        hough = cv2.HoughCircles(
            blurred,
            cv2.HOUGH_GRADIENT,
            dp=1.5,
            minDist=min(h, w) / 4,
            param1=60,
            param2=acc,
            minRadius=int(min(h, w) * 0.08),
            maxRadius=int(min(h, w) * 0.55),
        )
        found = _spheres(mean, [] if hough is None else hough[0], count)
        if len(found) >= count:
            break
    if not found:
        raise InputError(
            f"could not find the sphere in the images: pass a mask ({opt('mask')})", source
        )
    if len(found) < count:
        raise InputError(
            f"found only {len(found)} sphere{'s' if len(found) > 1 else ''} in the images, "
            f"not {count} ({opt('spheres', count)}): pass a mask ({opt('mask')}) or a lower "
            f"{opt('spheres')}",
            source,
        )
    return sorted(found, key=lambda c: c.cx)


def _spheres(mean: np.ndarray, hough: np.ndarray, count: int) -> list[Circle]:
    """Up to ``count`` refined Hough circles, strongest first, that can be spheres: at least
    half inside the image and not overlapping one already taken. At its lowest threshold
    Hough otherwise offers a circle around the real sphere, far outside the picture, whose
    estimates were averaged in (``--spheres 2`` on one sphere: 9 deg off)."""
    h, w = mean.shape
    taken: list[Circle] = []
    for f in hough:
        if len(taken) == count:
            break
        # A narrow band keeps inner edges (bright rim reflections) from capturing the fit.
        c = _refine_edge(mean, _refine_edge(mean, Circle(*map(float, f[:3]))), band=0.04)
        inside = float(c.contains(h, w).sum()) / (np.pi * c.r * c.r)
        # spheres side by side touch: a few per cent of edge-fit noise is not an overlap
        apart = all(np.hypot(c.cx - o.cx, c.cy - o.cy) > 0.95 * (c.r + o.r) for o in taken)
        if inside >= 0.5 and apart:
            taken.append(c)
    return taken


__all__ = [
    "Circle",
    "crack_points",
    "fit_circle",
    "fit_circles_from_images",
    "fit_circles_from_mask",
]
