"""Detail fusion: the network's shape, least squares' fine detail where the Lambertian fit holds.

The network regresses normals at half resolution: its low frequencies are robust (shadows,
highlights, inter-reflections) but its high frequencies are smoothed and noisy, so a 2 px wide
hairline disappears into the curvature noise. Per-pixel least squares keeps every pixel's detail
and is exact where the surface is Lambertian and lit by enough lights; it is biased where it is
not. So, per pixel:

    fused = unit( low(net) + s * (low(ls) - low(net)) + w * high(ls) + (1 - w) * high(net) )

with ``low`` a Gaussian of ``sigma`` px restricted to the mask (normalised convolution: nothing
leaks in from outside the mask) and ``high = n - low(n)``. ``ls`` is the *robust* fit
(infer/robust_least_squares.py: shadows and highlights down-weighted per pixel), ``w`` (detail
weight) and ``s`` (shape weight) in [0, 1] its *validity* (:func:`validity`): near 1 where its
relative residual is at the noise level, falling smoothly to 0 where even the robust fit breaks;
``s`` falls off sooner (a biased fit hurts the shape more than its detail). The detail weight
is exp(-(r / scale)^4): flat while the residual is a few per cent (noise, a mild gloss: the
fit's detail is still the surface's), steep once the fit breaks (shadow edges, inter-reflection),
which a Gaussian exp(-(r / scale)^2) cannot do at once. Smooth weights, not a binary switch,
so no seam is drawn where the fit goes bad. ``sigma`` sits above the detail check's scale
(evaluate/detail_ratio.py, 2 px): a Gaussian split at the check's own scale hands over only part
of that band; at 3 px the band passes whole. Measured: docs/run.md, "Detail fusion".

Call it directly (``fuse_detail``; e.g. a half-resolution network upsampled to full size plus a
full-resolution robust solve) or through :class:`DetailFusionEstimator`, which runs both on one
stack.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from msfnet.common.errors import InputError
from msfnet.common.vocabulary import declare, opt
from msfnet.runtime.engines.method import RunMethod
from msfnet.runtime.infer.estimators import Estimate, Estimator, TilingOptions
from msfnet.runtime.infer.robust_least_squares import RobustFit, band_rows, robust_least_squares
from msfnet.runtime.infer.tiling import BASE_MEMORY_MB
from msfnet.runtime.instrument import StageTimer, memory_in_use_mb
from msfnet.runtime.stack import Stack
from msfnet.runtime.stack.readers import unit_normals

# ModelOptions.detail_fusion, named by the fusion's own refusal
declare("detail_fusion", "--no-detail-fusion", "store_false")

DEFAULT_SIGMA = 3.0  # px: 1.5x the detail check's scale (evaluate.detail_ratio.SIGMA_PX)
# Relative residuals of the robust fit (per degree of freedom) at which the detail / shape
# weights are exp(-1), and the powers of their fall-off. Chosen on DiLiGenT (MAE) and psmImages
# (detail ratio) together, split 3 px; the sweep is in docs/run.md, "Detail fusion".
DEFAULT_RESIDUAL_SCALE = 0.19
DEFAULT_SHAPE_SCALE = 0.03
DETAIL_POWER = 4
SHAPE_POWER = 2
WEIGHT_SMOOTH_PX = 1.5  # the weight map's own smoothing: no pixel-to-pixel switching
# A rig's calibration error (LED intensities or light directions slightly off) raises the fit's
# residual on every pixel of a part, where a highlight, a shadow or a broken fit raise it on
# some: the weights read the residual above the part's floor (its FLOOR_PERCENTILE-th
# percentile), up to FLOOR_CAP, the floor a calibration within a few per cent leaves. Above the
# cap the floor is the material's own and stays (docs/benchmark.md, 2026-12-08).
FLOOR_PERCENTILE = 25.0
FLOOR_CAP = 0.02
# Fusion in row bands: the working set per pixel of a band (the weights, both low-passes, the
# sum and its normalisation; measured ~160 B with tracemalloc, kept with a margin), the band's
# context on either side in sigmas (OpenCV's float Gaussian reaches 4 sigma), the least rows.
FUSION_BYTES_PER_PIXEL = 200
FUSION_HALO_SIGMAS = 4.5
MIN_FUSION_ROWS = 32


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
    :func:`validity`; mask: (H, W) bool; sigma: the low/high-pass split in px;
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
    # a pixel the network gave no normal (NaN, zeros: a broken model) stays without one, so it
    # is scored 180 deg as docs/run.md says, not dressed up by least squares as ~11 deg
    length = np.linalg.norm(normals_net.astype(np.float32), axis=-1)
    answered = np.isfinite(length) & (length > 0.5)
    return unit_normals(fused * (m & answered)[..., None]).astype(np.float32)


@dataclass(frozen=True)
class Validity:
    """(H, W) float32 maps, 0 outside the mask: ``detail`` and ``shape`` weights for
    :func:`fuse_detail`, from the robust fit's residual."""

    detail: np.ndarray
    shape: np.ndarray


def _weight(residual: np.ndarray, mask: np.ndarray, scale: float, power: int) -> np.ndarray:
    raw = np.exp(-((residual / scale) ** power)).astype(np.float32)
    m = mask.astype(np.float32)
    smooth = cv2.GaussianBlur(raw * m, (0, 0), WEIGHT_SMOOTH_PX)
    norm = cv2.GaussianBlur(m, (0, 0), WEIGHT_SMOOTH_PX)
    # never above the pixel's own weight: smoothing must not lend trust to a pixel whose fit
    # failed (a dark speck, no redundancy left), only ease the rise from it
    weight = np.minimum(smooth / np.maximum(norm, 1e-6), raw)
    return np.where(mask, weight, 0.0).astype(np.float32)


def residual_floor(residual: np.ndarray, mask: np.ndarray) -> float:
    """The part's residual floor: its FLOOR_PERCENTILE-th percentile over the fitted pixels,
    at most FLOOR_CAP (0 without a fitted pixel)."""
    fitted = residual[mask & (residual < 1)]
    return min(float(np.percentile(fitted, FLOOR_PERCENTILE)), FLOOR_CAP) if fitted.size else 0.0


def above_floor(residual: np.ndarray, floor: float) -> np.ndarray:
    """The residual above ``floor``, taken off in quadrature (a calibration error's misfit adds
    to the surface's; taking it off linearly cost DiLiGenT ball 0.14 deg, this 0.07); failed
    fits (1) kept."""
    lifted = np.sqrt(np.maximum(np.square(residual, dtype=np.float32) - floor**2, 0))
    return np.where(residual >= 1, residual, lifted).astype(np.float32)


def validity(fit: RobustFit, mask: np.ndarray, options: FusionOptions | None = None) -> Validity:
    """The weights exp(-(residual / scale)^power) of a robust fit (DETAIL_POWER for the detail,
    SHAPE_POWER for the shape), smoothed over WEIGHT_SMOOTH_PX inside the mask and capped at
    each pixel's own (a failed fit has residual 1: weight ~0)."""
    o = options or FusionOptions()
    return Validity(
        _weight(fit.residual, mask, o.residual_scale, DETAIL_POWER),
        _weight(fit.residual, mask, o.shape_scale, SHAPE_POWER),
    )


class DetailFusionEstimator:
    """The network (any network estimator: plain, fine detail) and the robust least-squares fit
    on the same stack, fused by :func:`fuse_in_bands` (:func:`validity` weights). Costs one
    robust solve on top of the network (docs/run.md, Detail fusion)."""

    method = "msf"

    def __init__(self, network: Estimator, options: FusionOptions | None = None) -> None:
        self.network = network
        self.options = options or FusionOptions()

    def describe(self) -> RunMethod:
        o = self.options
        said = (
            f"robust least squares where its Lambertian residual r is small (detail weight "
            f"exp(-(r/{o.residual_scale:g})^{DETAIL_POWER}), shape weight "
            f"exp(-(r/{o.shape_scale:g})^{SHAPE_POWER}), sigma {o.sigma:g} px)"
        )
        return replace(self.network.describe(), detail_fusion=said)

    def estimate(
        self, stack: Stack, tiling: TilingOptions, timer: StageTimer, progress: bool = False
    ) -> Estimate:
        # a budget too small fails before the network: the network's output and the fused
        # normals (12 B a pixel each) are held beside the fit's own whole-image results
        h, w = stack.shape
        rows = band_rows(
            stack,
            tiling.max_memory_mb,
            reserve_mb=2 * h * w * 12 / 2**20,
            what=f"the detail fusion ({opt('detail_fusion')} runs without it)",
        )
        base = self.network.estimate(stack, tiling, timer, progress)
        with timer("postprocess"):
            fit = robust_least_squares(stack, rows=rows)
            normals = fuse_in_bands(
                base.normals, fit, stack.mask, self.options, _fusion_rows(stack, tiling)
            )
        return Estimate(normals, base.plan, base.flops)


def _fusion_rows(stack: Stack, tiling: TilingOptions) -> int:
    """Rows per fusion band: what the process may still take under the budget over
    FUSION_BYTES_PER_PIXEL per pixel, at least MIN_FUSION_ROWS (None budget: the whole image)."""
    h, w = stack.shape
    if tiling.max_memory_mb is None:
        return h
    held = memory_in_use_mb()
    out_mb = h * w * 12 / 2**20  # the fused normals, filled band by band
    room_mb = tiling.max_memory_mb - (held if held is not None else BASE_MEMORY_MB) - out_mb
    rows = int(room_mb * 2**20 // (w * FUSION_BYTES_PER_PIXEL)) if room_mb > 0 else 0
    return int(np.clip(rows, MIN_FUSION_ROWS, h))


def fuse_in_bands(
    normals_net: np.ndarray,
    fit: RobustFit,
    mask: np.ndarray,
    options: FusionOptions | None = None,
    rows: int | None = None,
) -> np.ndarray:
    """:func:`validity` of the residual :func:`above_floor` + :func:`fuse_detail` in bands of
    ``rows`` image rows, each computed with FUSION_HALO_SIGMAS x sigma rows of context on either
    side (the Gaussians' reach), so the result is the whole image's and the working set one
    band's. A band spans only the columns of its mask pixels and the same context: outside the
    mask every term is zero, so the rest of the width changes nothing beyond float rounding
    (OpenCV's filters may round differently at another width: within 2e-7; an object on 5 % of
    the image fuses ~4x faster)."""
    o = options or FusionOptions()
    floor = residual_floor(fit.residual, mask)  # the whole part's, applied band by band
    h = mask.shape[0]
    rows = h if rows is None else max(1, rows)
    halo = int(np.ceil(FUSION_HALO_SIGMAS * max(o.sigma, WEIGHT_SMOOTH_PX)))
    out = np.zeros(normals_net.shape, np.float32)
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        a, b = max(0, r0 - halo), min(h, r1 + halo)
        if not mask[r0:r1].any():
            continue
        cols = np.flatnonzero(mask[a:b].any(axis=0))
        c0, c1 = max(0, int(cols[0]) - halo), min(mask.shape[1], int(cols[-1]) + 1 + halo)
        m = mask[a:b, c0:c1]
        part = RobustFit(fit.normals[a:b, c0:c1], above_floor(fit.residual[a:b, c0:c1], floor))
        v = validity(part, m, o)
        fused = fuse_detail(normals_net[a:b, c0:c1], part.normals, v.detail, m, o.sigma, v.shape)
        out[r0:r1, c0:c1] = fused[r0 - a : r1 - a]
    return out


__all__ = [
    "DEFAULT_RESIDUAL_SCALE",
    "DEFAULT_SHAPE_SCALE",
    "DEFAULT_SIGMA",
    "DetailFusionEstimator",
    "FusionOptions",
    "Validity",
    "above_floor",
    "fuse_detail",
    "fuse_in_bands",
    "residual_floor",
    "validity",
]
