"""Curvature of the surface straight from the normal field (no integration needed).

Mean curvature. For a surface z = f(x, y) with unit normal n = (-p, -q, 1) / sqrt(1 + p^2 + q^2)
(x right, y up, z toward the camera), the divergence of the normal's image-plane part is twice
the mean curvature:  H = (d nx/dx + d ny/dy) / 2.  With this sign a convex bump facing the
camera (a sphere of radius R seen from outside) has H = +1/R, a dimple H < 0, and a saddle
with equal and opposite bending H = 0. Units: 1/pixel. With image rows running down
(y = -row), d ny/dy = -d ny/drow.

Gaussian curvature and shape index. With p = -nx/nz, q = -ny/nz the Hessian of z is the
Jacobian of (p, q) (its off-diagonal averaged, as the measured field need not be integrable);
K = det(Hessian) / (1 + p^2 + q^2)^2. Principal curvatures k1 >= k2 follow from
H +- sqrt(H^2 - K), and Koenderink & van Doorn's shape index (Image and Vision Computing 10(8),
1992) S = (2/pi) atan2(k1 + k2, k1 - k2) runs from -1 (cup) over 0 (saddle) and 0.5 (ridge) to
+1 (cap), here with caps positive to match H. Where the curvedness sqrt((k1^2 + k2^2)/2) is
below ``flat`` the shape is undefined (planar) and S is NaN.

Derivatives are central differences inside the mask, one-sided where a neighbour is outside,
and 0 for a pixel with no neighbour along that axis. Pixels are treated as an orthographic grid
(for a perspective camera: the image-plane approximation, fine for distant objects). The
normals are first smoothed with a Gaussian of ``sigma`` pixels restricted to the mask
(normalised convolution), because differentiation amplifies estimation noise. Outside the
valid mask every map is NaN.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from msfnet.runtime.results.maps.validate import check_normals

DEFAULT_SIGMA = 1.0
DEFAULT_FLAT = 1e-4  # 1/px: below this curvedness a patch counts as planar
MIN_NZ = 0.05  # the slopes p, q of the shape index are bounded like the integrator's


@dataclass
class CurvatureMaps:
    """mean: (H, W) float32 mean curvature H in 1/px (cap > 0); gaussian: (H, W) float32 K in
    1/px^2; shape_index: (H, W) float32 in [-1, 1] (NaN where planar); curvedness: (H, W)
    float32 in 1/px. All NaN outside the valid mask."""

    mean: np.ndarray
    gaussian: np.ndarray
    shape_index: np.ndarray
    curvedness: np.ndarray


def masked_derivative(f: np.ndarray, valid: np.ndarray, axis: int) -> np.ndarray:
    """d f / d(index along axis) of an (H, W) field, using only pixels in ``valid``:
    central where both neighbours are valid, one-sided where one is, 0 where none is."""
    fz = np.where(valid, f, 0.0)
    lo, hi = [slice(None)] * 2, [slice(None)] * 2
    lo[axis], hi[axis] = slice(None, -1), slice(1, None)
    lo_t, hi_t = tuple(lo), tuple(hi)
    pair = valid[lo_t] & valid[hi_t]
    step = np.where(pair, fz[hi_t] - fz[lo_t], 0.0)
    # each pixel: its forward step plus its backward one, over how many it has
    total, count = np.zeros_like(fz), np.zeros(valid.shape)
    total[lo_t] += step
    total[hi_t] += step
    count[lo_t] += pair
    count[hi_t] += pair
    return np.where(valid, total / np.maximum(count, 1.0), 0.0)


def smooth_normals(normals: np.ndarray, valid: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing inside the mask only (normalised convolution), renormalised."""
    if sigma <= 0:
        return normals
    # SciPy's gaussian_filter kernel (cut at 4 sigma, normalised) through OpenCV, which a
    # fresh process has loaded already
    radius = int(4.0 * sigma + 0.5)

    def blur(a: np.ndarray) -> np.ndarray:
        if a.size == 0:  # OpenCV refuses an empty image
            return a.copy()
        size = (2 * radius + 1, 2 * radius + 1)
        return cv2.GaussianBlur(a, size, sigma, borderType=cv2.BORDER_CONSTANT)

    weight = blur(valid.astype(np.float64))
    out = np.empty_like(normals)
    for c in range(3):
        out[..., c] = blur(np.where(valid, normals[..., c], 0.0))
    out /= np.maximum(weight, 1e-12)[..., None]
    norm = np.linalg.norm(out, axis=2, keepdims=True)
    return np.where(valid[..., None], out / np.maximum(norm, 1e-12), 0.0)


def curvature_maps(
    normals: np.ndarray,
    mask: np.ndarray,
    *,
    sigma: float = DEFAULT_SIGMA,
    flat: float = DEFAULT_FLAT,
) -> CurvatureMaps:
    """Mean and Gaussian curvature, shape index and curvedness of (H, W, 3) unit normals.

    sigma: pre-smoothing in pixels (0 = none). flat: curvedness (1/px) below which the shape
    index is NaN. An empty mask gives all-NaN maps; a lone pixel gets H = K = 0.
    """
    unit, valid = check_normals(normals, mask)
    n = smooth_normals(unit, valid, sigma)
    nx, ny, nz = n[..., 0], n[..., 1], n[..., 2]

    def d_dx(f: np.ndarray) -> np.ndarray:
        return masked_derivative(f, valid, axis=1)

    def d_dy(f: np.ndarray) -> np.ndarray:  # y up, rows down
        return -masked_derivative(f, valid, axis=0)

    mean = 0.5 * (d_dx(nx) + d_dy(ny))
    c = np.maximum(nz, MIN_NZ)
    p, q = -nx / c, -ny / c
    zxx, zyy = d_dx(p), d_dy(q)
    zxy = 0.5 * (d_dy(p) + d_dx(q))
    gauss = (zxx * zyy - zxy**2) / (1.0 + p**2 + q**2) ** 2
    # The convex-positive sign is applied to H only; K is sign-invariant under z -> -z.
    root = np.sqrt(np.maximum(mean**2 - gauss, 0.0))
    k1, k2 = mean + root, mean - root
    curvedness = np.sqrt(0.5 * (k1**2 + k2**2))
    shape = (2.0 / np.pi) * np.arctan2(k1 + k2, k1 - k2)
    shape = np.where(curvedness >= flat, shape, np.nan)
    nan = np.float32(np.nan)

    def out(a: np.ndarray) -> np.ndarray:
        return np.where(valid, a, nan).astype(np.float32)

    return CurvatureMaps(out(mean), out(gauss), out(shape), out(curvedness))


def symmetric_range(values: np.ndarray, percentile: float = 99.0) -> float:
    """Robust symmetric colour range for a signed map: the ``percentile`` of |values| over the
    finite entries (a tiny positive number when there are none or all are 0)."""
    v = np.abs(values[np.isfinite(values)])
    top = float(np.percentile(v, percentile)) if v.size else 0.0
    return top if top > 0 else 1e-12


__all__ = [
    "CurvatureMaps",
    "curvature_maps",
    "masked_derivative",
    "smooth_normals",
    "symmetric_range",
]
