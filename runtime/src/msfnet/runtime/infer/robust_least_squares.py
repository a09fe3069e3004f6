"""Robust per-pixel least squares: the Lambertian fit with shadows and highlights dropped.

Plain least squares (infer/least_squares.py) weighs every light alike, so one highlight or a
cast shadow at a pixel tilts its normal, and the tilt changes from pixel to pixel along a shadow
edge: false detail exactly where an inspection user looks. Here each pixel's fit is re-solved a
few times with Tukey's biweight on its residuals (iteratively reweighted least squares, from a
solve on its brighter observations: shadows are dark), then solved once more, unweighted, on the
observations within ``KEEP_SPREADS`` robust spreads. So where every light fits, the result is
plain least squares with its noise and no more (a weighted solve would add the weights' own
noise); where a few lights break the model they drop out. Details that matter:

- the model is clamped, I = max(0, l . g): a light behind the surface (l . g <= 0) that reads
  dark is an attached shadow, consistent with the model but no equation for g, so it gets no
  weight in the solve and counts as explained;
- the spread is the pixel's median absolute residual x 1.4826, corrected for the three fitted
  unknowns, floored at the stack's typical relative noise (measured once on a sample of pixels),
  and at least MIN_RELATIVE_SPREAD, times the pixel's median brightness: a dozen residuals give a
  noisy spread, and the floor keeps plain noise and a calibration's few per cent from being
  mistaken for outliers;
- observations at an integer image's full scale are clipped, never used;
- the residual is the root-mean-square misfit per degree of freedom (kept observations minus 3)
  relative to the kept observations' RMS brightness, and 1 (no trust) where fewer than
  MIN_LIGHTS + 1 observations remain, so a pixel with no redundancy (3 lights, or 3 left after
  rejection) can never look like a perfect fit.

The detail fusion (infer/detail_fusion.py) takes its fine detail and its validity from this fit
(measured: docs/run.md, "Detail fusion").
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from msfnet.common.cpu import usable_cores
from msfnet.runtime.infer.least_squares import grey_values, rows_for_memory
from msfnet.runtime.infer.normalise import network_lights
from msfnet.runtime.stack import MIN_LIGHTS, Stack
from msfnet.runtime.stack.types import full_scale  # the albedo drops the same values

TUKEY_C = 4.685  # spreads at which an observation's weight reaches 0 (95 % Gaussian efficiency)
ITERATIONS = 3  # reweighting passes after the first solve (the fits barely move after the third)
START_LIGHTS = 4  # the first solve's fewest observations (the brightest left out)
KEEP_SPREADS = 3.0  # the final unweighted solve keeps observations within this many spreads
# the spread's floor never falls below this share of the brightness: a rig's LED intensities
# are known to a few per cent, and a light 2 % off must not become an outlier (at 1e-4 the fit
# dropped such lights and lost to plain least squares, 0.56 against 0.41 deg on a matte plate;
# shadows and highlights, tens of per cent off, still go)
MIN_RELATIVE_SPREAD = 0.01
NOISE_QUANTILE = 0.5
MAX_WORKERS = 4  # threads for the fit: its array loops scale to about this many cores
MIN_PIXELS_PER_WORKER = 4096  # below this a thread costs more than it saves
NOISE_SAMPLE = 4096  # pixels sampled (evenly) for the stack's typical relative noise
# working set of a band: per (mask pixel x light) the gather and usable mask, float64 grey
# values, their float32 copy, fit, residuals, weights and the median's sorted copy; per pixel
# the 3 x 3 systems and their solves, with a margin for the allocator's slack
# (tests/runtime/infer/test_detail_fusion_memory.py checks the peaks)
BYTES_PER_PIXEL_LIGHT = 72
BYTES_PER_PIXEL = 400
OUTPUT_BYTES_PER_PIXEL = 16  # the whole-image float32 normals (12) and residual (4)


@dataclass(frozen=True)
class RobustFit:
    """(H, W, 3) float32 unit ``normals`` and (H, W) float32 relative ``residual`` (module
    notes); zeros outside the mask; normals zero and residual 1 where no fit exists (a pixel
    black under every light, or fewer than MIN_LIGHTS + 1 usable observations)."""

    normals: np.ndarray
    residual: np.ndarray


def robust_least_squares(
    stack: Stack, max_memory_mb: float | None = None, rows: int | None = None
) -> RobustFit:
    """The robust fit of every mask pixel, in bands of rows within ``max_memory_mb`` (the whole
    process's budget, as :func:`~msfnet.runtime.infer.least_squares.least_squares_normals`);
    ``rows``: the band height, when the caller has already worked it out (:func:`band_rows`)."""
    h, w = stack.shape
    lights = network_lights(stack.lights).astype(np.float64)
    if rows is None:
        rows = band_rows(stack, max_memory_mb)
    full = full_scale(stack.images.dtype)
    noise = stack_noise(stack, lights, full, max_pixels=rows * w)  # a band's worth at most
    normals = np.zeros((h, w, 3), np.float32)
    residual = np.zeros((h, w), np.float32)
    for r0 in range(0, h, rows):
        band = slice(r0, min(h, r0 + rows))
        mask = stack.mask[band]
        if not mask.any():
            continue
        pixels = stack.images[:, band][:, mask, :]
        usable = None if full is None else _unclipped(pixels, full)
        g, res = _fit_parallel(grey_values(pixels, stack.intensities), lights, noise, usable)
        norm = np.linalg.norm(g, axis=0)
        normals[band][mask] = np.where(norm > 1e-12, g / np.maximum(norm, 1e-12), 0.0).T
        residual[band][mask] = np.where(norm > 1e-12, res, 1.0)
    return RobustFit(normals, residual)


def _fit_parallel(
    grey: np.ndarray, lights: np.ndarray, noise: float, usable: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`tukey_fit` on the band's pixels split among the CPUs this process may use (numpy
    releases the GIL in its array loops; the network has finished, so the cores are free). The
    pieces together hold what the band holds: the memory budget is unchanged."""
    workers = min(usable_cores(), MAX_WORKERS, max(1, grey.shape[1] // MIN_PIXELS_PER_WORKER))
    if workers == 1:
        return tukey_fit(grey, lights, noise, usable)
    cuts = np.linspace(0, grey.shape[1], workers + 1).astype(int)
    parts = [slice(a, b) for a, b in pairwise(cuts)]
    with ThreadPoolExecutor(workers) as pool:
        done = list(
            pool.map(
                lambda p: tukey_fit(
                    grey[:, p], lights, noise, None if usable is None else usable[:, p]
                ),
                parts,
            )
        )
    return np.concatenate([g for g, _ in done], axis=1), np.concatenate([r for _, r in done])


def band_rows(
    stack: Stack,
    max_memory_mb: float | None,
    reserve_mb: float = 0.0,
    what: str = "robust least squares",
) -> int:
    """Rows per band of :func:`robust_least_squares` within ``max_memory_mb`` (None: the whole
    image), its whole-image normals and residual counted, and ``reserve_mb`` held besides (a
    network's output when asked before the network runs); InputError when not even a few rows
    fit (callers ask before slow work)."""
    if max_memory_mb is None:
        return stack.shape[0]
    per_light = BYTES_PER_PIXEL_LIGHT + -(-BYTES_PER_PIXEL // stack.num_lights)
    return rows_for_memory(
        max_memory_mb,
        stack,
        bytes_per_pixel_light=per_light,
        output_bytes_per_pixel=OUTPUT_BYTES_PER_PIXEL,
        reserve_mb=reserve_mb,
        what=what,
    )


def _unclipped(pixels: np.ndarray, full: float) -> np.ndarray:
    """(N, P) bool: observations with no channel at the integer type's full scale."""
    return np.asarray(~(pixels >= full).any(axis=2))


def stack_noise(
    stack: Stack, lights: np.ndarray, full: float | None = None, max_pixels: int = NOISE_SAMPLE
) -> float:
    """The stack's typical relative noise: the median over evenly sampled mask pixels (at most
    NOISE_SAMPLE and ``max_pixels``: one band's working set) of each one's robust spread (no
    floor) over its median brightness."""
    ys, xs = np.nonzero(stack.mask)
    if not len(ys):  # Stack refuses an empty mask; a caller's own mask may still be one
        return 0.0
    count = max(1, min(NOISE_SAMPLE, max_pixels, len(ys)))
    pick = np.linspace(0, len(ys) - 1, count).astype(np.int64)
    pixels = stack.images[:, ys[pick], xs[pick], :]
    usable = None if full is None else _unclipped(pixels, full)
    grey = grey_values(pixels, stack.intensities)
    _, spread, bright = _iterate(grey.astype(np.float32), lights, 0.0, usable)
    ok = bright > 0
    return float(np.quantile(spread[ok] / bright[ok], NOISE_QUANTILE)) if ok.any() else 0.0


def _solve(
    weights: np.ndarray, grey: np.ndarray, lights: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(3, P) solutions of sum_i w_i (I_i - l_i . g)^2 per pixel and where the system was
    regular: the 3 x 3 normal equations from two float32 matrix products (outer products of the
    lights flattened to 9 columns), solved in float64 in closed form (the adjugate: rows of
    cross products; 5x faster than a batched LAPACK solve of 3 x 3 systems)."""
    outer = (lights[:, :, None] * lights[:, None, :]).reshape(len(lights), 9)
    a = (weights.T @ outer.astype(np.float32)).astype(np.float64).reshape(-1, 3, 3)
    b = ((weights * grey).T @ lights.astype(np.float32)).astype(np.float64)
    c0 = np.cross(a[:, 1], a[:, 2])
    c1 = np.cross(a[:, 2], a[:, 0])
    c2 = np.cross(a[:, 0], a[:, 1])
    det = np.einsum("pi,pi->p", a[:, 0], c0)
    scale = np.einsum("pij,pij->p", a, a) ** 1.5  # det relative to the system's size
    ok = np.abs(det) > 1e-9 * scale
    inv_det = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    # A symmetric: its inverse is [c0, c1, c2] / det (cofactor rows)
    g = np.stack([np.einsum("pi,pi->p", c, b) for c in (c0, c1, c2)], axis=0) * inv_det
    return g.astype(np.float32), ok


def _median_of(values: np.ndarray, include: np.ndarray) -> np.ndarray:
    """(P,) median over axis 0 of the ``include``d entries of (N, P) ``values`` (inf where
    none is included)."""
    ordered = np.sort(np.where(include, values, np.float32(np.inf)), axis=0)
    count = include.sum(axis=0)
    n = len(values)
    lo = np.take_along_axis(ordered, (np.maximum(count - 1, 0) // 2)[None, :], axis=0)[0]
    hi = np.take_along_axis(ordered, np.minimum(count // 2, n - 1)[None, :], axis=0)[0]
    return np.where(count > 0, (lo + hi) / 2, np.float32(np.inf)).astype(np.float32)


def _bright_start(grey: np.ndarray, use: np.ndarray) -> np.ndarray:
    """(N, P) float32 weights of the first solve: each pixel's brighter half of observations
    (at least START_LIGHTS) but its brightest. A cast shadow is dark and a highlight bright:
    from plain least squares, two shadowed lights of 12 tilted the start so far (26 deg) that
    the reweighting never recovered; from the brighter half it recovers with up to four."""
    n = len(grey)
    m = max(START_LIGHTS, n // 2)
    if n < m + 2:  # too few lights to leave any out
        return use
    kth = np.partition(grey, n - m, axis=0)[n - m]  # the m-th brightest
    return use * ((grey >= kth) & (grey < grey.max(axis=0)))


def _iterate(
    grey: np.ndarray, lights: np.ndarray, noise: float, usable: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The reweighting passes: (g (3, P), spread (P,), median brightness (P,)), all float32."""
    n = len(lights)
    use = np.ones(grey.shape, np.float32) if usable is None else usable.astype(np.float32)
    lights32 = lights.astype(np.float32)
    g, ok = _solve(_bright_start(grey, use), grey, lights)
    if not ok.all():
        g = np.where(ok, g, _solve(use, grey, lights)[0])
    bright = np.median(grey, axis=0)  # clipped observations read bright: still a brightness
    floor = np.float32(max(noise, MIN_RELATIVE_SPREAD)) * bright + np.float32(1e-12)
    correction = np.float32(np.sqrt(n / max(n - 3, 1)))
    spread = floor
    for _ in range(ITERATIONS):
        pred = lights32 @ g
        r = grey - np.maximum(pred, 0.0)  # the clamped model: attached shadows fit
        # the spread of the observations in the solve: attached shadows fit trivially (r = 0)
        # and would shrink it until every lit observation looked like an outlier
        mad = _median_of(np.abs(r), (pred > 0) & (use > 0))
        spread = np.maximum(np.float32(1.4826) * correction * mad, floor)
        u = r / (np.float32(TUKEY_C) * spread)
        w = np.maximum(1.0 - u * u, 0.0, dtype=np.float32) ** 2 * use * (pred > 0)
        enough = (w > 0.05).sum(axis=0) > MIN_LIGHTS
        new, ok = _solve(w, grey, lights)
        g = np.where(enough & ok, new, g)
    return g, spread, bright


def tukey_fit(
    grey: np.ndarray, lights: np.ndarray, noise: float = 0.0, usable: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """g = albedo x normal, (3, P) float64, and the relative residual, (P,) float32, of each
    pixel's robust fit (module notes).

    grey: (N, P) observations; lights: (N, 3); noise: the stack's typical relative noise
    (:func:`stack_noise`; 0: no floor but rounding); usable: (N, P) bool, False for clipped
    observations (None: all usable)."""
    grey = grey.astype(np.float32)
    use = np.ones(grey.shape, bool) if usable is None else usable
    g, spread, _ = _iterate(grey, lights, noise, usable)
    lights32 = lights.astype(np.float32)
    pred = lights32 @ g
    r = grey - np.maximum(pred, 0.0)
    explained = use & (np.abs(r) <= KEEP_SPREADS * spread)
    keep = explained & (pred > 0)  # attached shadows are explained but hold no equation
    final, ok = _solve(keep.astype(np.float32), grey, lights)
    enough = ok & (keep.sum(axis=0) > MIN_LIGHTS)
    g = np.where(enough, final, g)
    r = grey - np.maximum(lights32 @ g, 0.0)
    count = explained.sum(axis=0)
    misfit = np.sum(np.where(explained, r * r, 0.0), axis=0) / np.maximum(count - 3, 1)
    level = np.sum(np.where(explained, grey * grey, 0.0), axis=0) / np.maximum(count, 1)
    residual = np.where(
        enough & (level > 0), np.sqrt(misfit / np.maximum(level, 1e-30)), 1.0
    ).astype(np.float32)
    return g.astype(np.float64), residual


__all__ = ["RobustFit", "band_rows", "robust_least_squares", "stack_noise", "tukey_fit"]
