"""Classical per-pixel least-squares photometric stereo (``--method l2``), no model needed.

Lambertian model on grey values: I_i = rho * <l_i, n>, with I = mean over RGB of image / light
intensity. Solves for g = rho * n by least squares over the lights and normalises. Optional
trimming drops each pixel's darkest (shadow) and brightest (highlight) fractions of lights.
"""

from __future__ import annotations

import numpy as np

from msfnet.common.errors import InputError
from msfnet.common.vocabulary import opt
from msfnet.runtime.infer.normalise import network_lights
from msfnet.runtime.infer.tiling import BASE_MEMORY_MB
from msfnet.runtime.instrument import memory_in_use_mb
from msfnet.runtime.stack import MIN_LIGHTS, Stack

# working set per (mask pixel x light): the RGB gather (as held: 12 B float32, 6 B uint16; an
# integer one's float32 copy lives only while grey is computed), float64 grey and, when
# trimming, ranks and weights (measured: under 64 B).
BYTES_PER_PIXEL_LIGHT = 64
MIN_ROWS = 8


def least_squares_normals(
    stack: Stack,
    trim_shadows: float = 0.0,
    trim_highlights: float = 0.0,
    max_memory_mb: float | None = None,
    in_use_mb: float | None = None,
) -> np.ndarray:
    """(H, W, 3) float32 unit normals, zeros outside the mask (and where the fit is degenerate).

    ``max_memory_mb``: the whole process's budget; work in bands of image rows so that what the
    process already holds (the loaded stack, the runtime) plus the output and a band's working
    set stay within it (a 96-light full-frame stack otherwise needs several GB at once).
    ``in_use_mb``: what is held besides the stack, default measured (resident memory minus the
    stack; the runtime's BASE_MEMORY_MB where it cannot be measured).
    """
    if not (0 <= trim_shadows < 1 and 0 <= trim_highlights < 1):
        raise InputError("trim fractions must lie in [0, 1)")
    h, w = stack.shape
    rows = h
    if max_memory_mb is not None:
        rows = rows_for_memory(max_memory_mb, stack, in_use_mb)
    out = np.zeros((h, w, 3), np.float32)
    for r0 in range(0, h, rows):
        band = slice(r0, min(h, r0 + rows))
        mask = stack.mask[band]
        if mask.any():
            unit = _solve(stack.images[:, band][:, mask, :], stack, trim_shadows, trim_highlights)
            out[band][mask] = unit.T
    return out


def rows_for_memory(
    max_memory_mb: float,
    stack: Stack,
    in_use_mb: float | None = None,
    bytes_per_pixel_light: int = BYTES_PER_PIXEL_LIGHT,
    output_bytes_per_pixel: int = 12,
    reserve_mb: float = 0.0,
    what: str = "least squares",
) -> int:
    """Image rows per band so that the stack, what else the process holds (``in_use_mb``, see
    :func:`least_squares_normals`), the output and the band's working set (``bytes_per_pixel_light``
    per pixel and light) fit in ``max_memory_mb``; InputError (quoting the budget as given) when
    not even MIN_ROWS fit. ``output_bytes_per_pixel``: the whole-image results the caller
    returns (normals: 12); ``reserve_mb``: what the caller will hold besides while the bands
    run (e.g. a network's output, computed after this check); ``what``: the step the message
    names."""
    if not (np.isfinite(max_memory_mb) and max_memory_mb > 0):
        raise InputError(
            f"{opt('max_memory_mb')} must be a positive number of MB, got {max_memory_mb}",
            option="max_memory_mb",
        )
    h, w = stack.shape
    per_row = w * stack.num_lights * bytes_per_pixel_light
    stack_mb = stack.images.nbytes / 2**20
    if in_use_mb is None:
        rss = memory_in_use_mb()
        in_use_mb = BASE_MEMORY_MB if rss is None else max(rss - stack_mb, 0.0)
    out_mb = h * w * output_bytes_per_pixel / 2**20  # the whole-image results returned
    held_mb = stack_mb + in_use_mb + out_mb + reserve_mb
    budget = (max_memory_mb - held_mb) * 2**20
    rows = int(budget // per_row) if budget > 0 else 0
    if rows < min(MIN_ROWS, h):
        need = held_mb + min(MIN_ROWS, h) * per_row / 2**20
        raise InputError(
            f"{opt('max_memory_mb', float(max_memory_mb))} MB is too small for {what} on "
            f"this stack: it takes {stack_mb:.1f} MB loaded, the process "
            f"{in_use_mb:.0f} MB besides, and at least {need:.1f} MB in all",
            option="max_memory_mb",
        )
    return min(rows, h)


def grey_values(pixels: np.ndarray, intensities: np.ndarray) -> np.ndarray:
    """(N, P) float64 grey values of gathered (N, P, 3) pixels divided by the light intensity.
    Integer pixels are cast first (exact in float32: the numbers a float32 stack gives, and no
    integer arithmetic); the copy lives only here."""
    if pixels.dtype.kind != "f":
        pixels = pixels.astype(np.float32)
    ratio = pixels / intensities[:, None, :]
    # the channels' mean, summed as numpy's mean sums three (the same bits), without its
    # reduction over a 3-long last axis: 3x faster on a station's 256 x 256 part
    grey = ratio[..., 0] + ratio[..., 1]
    grey += ratio[..., 2]
    grey /= grey.dtype.type(3)
    return grey.astype(np.float64)


def _solve(
    pixels: np.ndarray, stack: Stack, trim_shadows: float, trim_highlights: float
) -> np.ndarray:
    """(3, P) unit normals of the gathered mask pixels (N, P, 3)."""
    lights = network_lights(stack.lights).astype(np.float64)  # (N, 3)
    n = lights.shape[0]
    grey = grey_values(pixels, stack.intensities)  # (N, P)
    lo = int(np.floor(trim_shadows * n))
    hi = n - int(np.floor(trim_highlights * n))
    if hi - lo < MIN_LIGHTS:
        raise InputError(
            f"trimming leaves {hi - lo} of {n} lights per pixel; at least {MIN_LIGHTS} needed"
        )
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
    return np.where(norm > 1e-12, g / np.maximum(norm, 1e-12), 0.0)


__all__ = ["grey_values", "least_squares_normals", "memory_in_use_mb", "rows_for_memory"]
