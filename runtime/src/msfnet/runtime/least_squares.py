"""Classical per-pixel least-squares photometric stereo (``--method l2``), no model needed.

Lambertian model on grey values: I_i = rho * <l_i, n>, with I = mean over RGB of image / light
intensity. Solves for g = rho * n by least squares over the lights and normalises. Optional
trimming drops each pixel's darkest (shadow) and brightest (highlight) fractions of lights.
"""

from __future__ import annotations

import numpy as np

from .errors import InputError
from .preprocess import network_lights
from .stack import Stack


def least_squares_normals(stack: Stack, trim_shadows: float = 0.0,
                          trim_highlights: float = 0.0) -> np.ndarray:
    """(H, W, 3) float32 unit normals, zeros outside the mask (and where the fit is degenerate)."""
    if not (0 <= trim_shadows < 1 and 0 <= trim_highlights < 1):
        raise InputError("trim fractions must lie in [0, 1)")
    lights = network_lights(stack.lights).astype(np.float64)  # (N, 3)
    n = lights.shape[0]
    # only mask pixels: (N, P) grey values divided by the light intensity
    grey = (stack.images[:, stack.mask, :] / stack.intensities[:, None, :]).mean(axis=2)
    grey = grey.astype(np.float64)
    lo = int(np.floor(trim_shadows * n))
    hi = n - int(np.floor(trim_highlights * n))
    if hi - lo < 3:
        raise InputError(f"trimming leaves {hi - lo} of {n} lights per pixel; at least 3 needed")
    if lo == 0 and hi == n:
        g = np.linalg.pinv(lights) @ grey  # (3, P): one solve shared by every pixel
    else:
        ranks = np.argsort(np.argsort(grey, axis=0), axis=0)
        keep = ((ranks >= lo) & (ranks < hi)).astype(np.float64)  # (N, P)
        a = np.einsum("np,ni,nj->pij", keep, lights, lights)
        b = np.einsum("np,ni->pi", keep * grey, lights)
        ok = np.abs(np.linalg.det(a)) > 1e-9
        g = np.zeros((grey.shape[1], 3))
        g[ok] = np.linalg.solve(a[ok], b[ok][..., None])[..., 0]
        g = g.T
    norm = np.linalg.norm(g, axis=0)
    unit = np.where(norm > 1e-12, g / np.maximum(norm, 1e-12), 0.0)
    out = np.zeros((*stack.shape, 3), np.float32)
    out[stack.mask] = unit.T
    return out


__all__ = ["least_squares_normals"]
