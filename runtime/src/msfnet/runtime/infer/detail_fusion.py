"""Detail fusion: the network's shape, least squares' fine detail where the Lambertian fit holds.

The network regresses normals at half resolution: its low frequencies are robust (shadows,
highlights, inter-reflections) but its high frequencies are smoothed and noisy, so a 2 px wide
hairline disappears into the curvature noise. Per-pixel least squares keeps every pixel's detail
and is exact where the surface is Lambertian and lit by enough lights; it is biased where it is
not. So, per pixel:

    fused = unit( low(net) + s * (low(ls) - low(net)) + w * high(ls) + (1 - w) * high(net) )

with ``low`` a Gaussian of ``sigma`` px restricted to the mask (normalised convolution: nothing
leaks in from outside the mask) and ``high = n - low(n)``. ``w`` (detail weight) and ``s``
(shape weight) in [0, 1] are the *validity* of the least-squares fit
(:func:`lambertian_validity`): near 1 where its relative residual is at the noise level,
falling smoothly to 0 where highlights or shadows break the model; ``s`` falls off sooner
(a biased fit hurts the shape more than its detail). Smooth weights, not a binary switch, so no
seam is drawn where the fit goes bad.

Measured (docs/run.md, "Inspection"): DiLiGenT ball / bear / harvest 2.15 / 4.89 / 17.83 ->
1.96 / 4.89 / 17.40 deg (msf-eval); a rendered matte plate 3.40 -> 0.05 deg (the network's
rim at true silhouettes goes too), glossy plate 4.45 -> 1.99 deg (least squares 2.10);
psmImages detail ratio 0.61 / 0.58 / 0.65 -> 0.78 / 0.79 / 0.81.

Call it directly (``fuse_detail``; e.g. a half-resolution network upsampled to full size plus a
full-resolution least-squares solve) or through :class:`DetailFusionEstimator`, which runs both
estimators on one stack.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from msfnet.common.errors import InputError
from msfnet.runtime.infer.estimators import (
    Estimate,
    Estimator,
    LeastSquaresEstimator,
    TilingOptions,
)
from msfnet.runtime.infer.least_squares import rows_for_memory
from msfnet.runtime.infer.normalise import network_lights
from msfnet.runtime.results.profile import StageTimer
from msfnet.runtime.stack import Stack
from msfnet.runtime.stack.readers import unit_normals

DEFAULT_SIGMA = 2.0  # px: the detail check's scale (evaluate.detail_ratio.SIGMA_PX)
# Relative residuals of the Lambertian fit at which the detail / shape weights are exp(-1).
# Measured residuals (10th / 50th / 90th percentile): a rendered matte plate 0.001 throughout,
# a glossy one 0.002 / 0.007 / 0.038, DiLiGenT ball 0.016 / 0.022 / 0.21, bear 0.021 / 0.052 /
# 0.148, harvest 0.034 / 0.21 / 0.55, psmImages cat / owl / horse 0.03 / 0.06 / 0.1-0.2.
# Chosen on those (docs/run.md, Inspection): shape scale 0.03 (DiLiGenT, with detail scale
# 0.1: 0.02 -> 1.967 / 4.821 / 17.384 deg, 0.03 -> 1.914 / 4.830 / 17.377, 0.05 -> 1.865 /
# 4.971 / 17.401); detail scale 0.2 (psmImages detail ratio 0.69-0.74 at 0.1, 0.78-0.81 at
# 0.2, 0.84-0.85 at 0.5; DiLiGenT 1.947 / 4.869 / 17.333 deg at 0.2, all below the network
# alone's 2.151 / 4.894 / 17.826).
DEFAULT_RESIDUAL_SCALE = 0.2
DEFAULT_SHAPE_SCALE = 0.03
WEIGHT_SMOOTH_PX = 1.5  # the weight map's own smoothing: no pixel-to-pixel switching


@dataclass(frozen=True)
class FusionOptions:
    """sigma: low/high-pass split in px; residual_scale / shape_scale: the relative Lambertian
    residual at which least squares' detail / shape counts exp(-1)."""

    sigma: float = DEFAULT_SIGMA
    residual_scale: float = DEFAULT_RESIDUAL_SCALE
    shape_scale: float = DEFAULT_SHAPE_SCALE

    def __post_init__(self) -> None:
        for name in ("sigma", "residual_scale", "shape_scale"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"detail fusion {name} must be a positive number, got {v}")


def _masked_low(normals: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    m = mask.astype(np.float32)
    n = np.nan_to_num(normals.astype(np.float32)) * m[..., None]
    weight = cv2.GaussianBlur(m, (0, 0), sigma)
    return cv2.GaussianBlur(n, (0, 0), sigma) / np.maximum(weight, 1e-6)[..., None] * m[..., None]


def fuse_detail(
    normals_net: np.ndarray,
    normals_ls: np.ndarray,
    weights: np.ndarray,
    mask: np.ndarray,
    sigma: float = DEFAULT_SIGMA,
    shape_weights: np.ndarray | None = None,
) -> np.ndarray:
    """Fused (H, W, 3) float32 unit normals, zeros outside ``mask``.

    normals_net, normals_ls: (H, W, 3) unit normals of the same pixels (the network's may come
    from a lower resolution, upsampled); weights: (H, W) in [0, 1], how far least squares'
    detail is trusted (1: its high-pass replaces the network's; 0: the network alone), e.g.
    :func:`lambertian_validity`; mask: (H, W) bool; sigma: the low/high-pass split in px;
    shape_weights: (H, W) in [0, 1], how far least squares' low-pass replaces the network's
    (None: never, the network keeps the shape everywhere).
    """
    if normals_net.shape != normals_ls.shape or normals_net.shape[:2] != mask.shape:
        raise InputError(
            f"detail fusion: shapes differ (network {normals_net.shape}, least squares "
            f"{normals_ls.shape}, mask {mask.shape})"
        )
    for what, arr in (("weights", weights), ("shape weights", shape_weights)):
        if arr is not None and arr.shape != mask.shape:
            raise InputError(f"detail fusion: {what} {arr.shape} but mask {mask.shape}")
    m = mask.astype(bool)
    w = np.clip(np.nan_to_num(weights.astype(np.float32)), 0.0, 1.0)[..., None]
    net = np.nan_to_num(normals_net.astype(np.float32))
    ls = np.nan_to_num(normals_ls.astype(np.float32))
    low_net = _masked_low(net, m, sigma)
    low_ls = _masked_low(ls, m, sigma)
    fused = low_net + w * (ls - low_ls) + (1.0 - w) * (net - low_net)
    if shape_weights is not None:
        s = np.clip(np.nan_to_num(shape_weights.astype(np.float32)), 0.0, 1.0)[..., None]
        fused += s * (low_ls - low_net)
    return unit_normals(fused * m[..., None]).astype(np.float32)


@dataclass(frozen=True)
class Validity:
    """(H, W) float32 maps, 0 outside the mask: ``residual`` of the Lambertian fit (relative),
    ``detail`` and ``shape`` weights for :func:`fuse_detail`."""

    residual: np.ndarray
    detail: np.ndarray
    shape: np.ndarray


def lambertian_residual(stack: Stack, max_memory_mb: float | None = None) -> np.ndarray:
    """Per pixel, how badly one albedo-scaled normal explains the N grey values under the
    stack's lights: |I - max(0, L g)| / |I| with g the unconstrained least-squares solution,
    so attached shadows it cannot fit and highlights both raise it. (H, W) float32, 0 outside
    the mask (1 where a pixel is black under every light)."""
    h, w = stack.shape
    lights = network_lights(stack.lights).astype(np.float64)
    pinv = np.linalg.pinv(lights)
    residual = np.zeros((h, w), np.float32)
    rows = h if max_memory_mb is None else rows_for_memory(max_memory_mb, stack)
    for r0 in range(0, h, rows):
        band = slice(r0, min(h, r0 + rows))
        mask = stack.mask[band]
        if not mask.any():
            continue
        px = stack.images[:, band][:, mask, :].astype(np.float32)
        grey = (px / stack.intensities[:, None, :]).mean(axis=2).astype(np.float64)  # (N, P)
        fit = np.maximum(lights @ (pinv @ grey), 0.0)
        num = np.sqrt(np.sum((grey - fit) ** 2, axis=0))
        den = np.sqrt(np.sum(grey**2, axis=0))
        residual[band][mask] = np.where(den > 0, num / np.maximum(den, 1e-30), 1.0)
    return residual


def _weight(residual: np.ndarray, mask: np.ndarray, scale: float) -> np.ndarray:
    raw = np.exp(-((residual / scale) ** 2)).astype(np.float32)
    m = mask.astype(np.float32)
    smooth = cv2.GaussianBlur(raw * m, (0, 0), WEIGHT_SMOOTH_PX)
    norm = cv2.GaussianBlur(m, (0, 0), WEIGHT_SMOOTH_PX)
    return np.where(mask, smooth / np.maximum(norm, 1e-6), 0.0).astype(np.float32)


def lambertian_validity(
    stack: Stack, options: FusionOptions | None = None, max_memory_mb: float | None = None
) -> Validity:
    """The residual (:func:`lambertian_residual`) and the weights exp(-(residual / scale)^2),
    smoothed over WEIGHT_SMOOTH_PX inside the mask."""
    o = options or FusionOptions()
    residual = lambertian_residual(stack, max_memory_mb)
    return Validity(
        residual,
        _weight(residual, stack.mask, o.residual_scale),
        _weight(residual, stack.mask, o.shape_scale),
    )


class DetailFusionEstimator:
    """The network (any network estimator: plain, fine detail) and least squares on the same
    stack, fused by :func:`fuse_detail` with :func:`lambertian_validity` weights. Costs one
    least-squares solve and one residual pass on top of the network (DiLiGenT, 96 lights:
    ~1-2 s against 30-170 s of network)."""

    method = "msf"

    def __init__(self, network: Estimator, options: FusionOptions | None = None) -> None:
        self.network = network
        self.options = options or FusionOptions()
        self.least_squares = LeastSquaresEstimator()

    def describe(self) -> dict[str, object]:
        o = self.options
        return {
            **self.network.describe(),
            "detail_fusion": (
                f"least squares where the Lambertian residual is small (detail scale "
                f"{o.residual_scale:g}, shape scale {o.shape_scale:g}, sigma {o.sigma:g} px)"
            ),
        }

    def estimate(
        self, stack: Stack, tiling: TilingOptions, timer: StageTimer, progress: bool = False
    ) -> Estimate:
        base = self.network.estimate(stack, tiling, timer, progress)
        ls = self.least_squares.estimate(stack, tiling, timer, progress)
        with timer("postprocess"):
            v = lambertian_validity(stack, self.options, tiling.max_memory_mb)
            normals = fuse_detail(
                base.normals, ls.normals, v.detail, stack.mask, self.options.sigma, v.shape
            )
        return Estimate(normals, base.plan, base.flops)


__all__ = [
    "DEFAULT_RESIDUAL_SCALE",
    "DEFAULT_SHAPE_SCALE",
    "DEFAULT_SIGMA",
    "DetailFusionEstimator",
    "FusionOptions",
    "Validity",
    "fuse_detail",
    "lambertian_residual",
    "lambertian_validity",
]
