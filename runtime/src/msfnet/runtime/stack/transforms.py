"""Real-camera inputs: region of interest, integer downscaling, linearisation, automatic mask.

The loader applies them in this order: ROI -> downscale -> linearise -> auto-mask. The first
three run per image inside the decoding threads, so only the reduced images are ever held in
memory (a 20 MP stack cropped to the object costs the object's pixels, not the sensor's).

Why this order: cropping first makes every later step cheaper; linearising after the area
average is an approximation (the mean of encoded values is not the encoding of the mean), but
inside a smooth object the difference is second order and it saves K^2 power evaluations per
output pixel; the mask is computed last, from the same linear values the estimators see.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

import cv2
import numpy as np

from msfnet.common.errors import InputError
from msfnet.common.vocabulary import declare, opt, verbatim
from msfnet.runtime.stack.types import as_held

# LoadOptions' switches, named by these transforms' messages (declared here too: load.py
# imports this module, not the other way)
declare("srgb", "--srgb", "store_true")
declare("auto_mask", "--auto-mask", "store_true")

Roi = tuple[int, int, int, int]  # x, y, width, height in pixels of the stored images


def parse_roi(text: str) -> Roi:
    """``"x,y,w,h"`` (pixels, origin top-left) -> a tuple; an argparse type."""
    parts = [p.strip() for p in text.replace(" ", ",").split(",") if p.strip()]
    try:
        x, y, w, h = (int(p) for p in parts)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(
            f"{text!r}: expected four integers x,y,w,h (e.g. 100,80,400,300)"
        ) from exc
    if x < 0 or y < 0 or w < 1 or h < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: x and y must be >= 0, w and h >= 1")
    return x, y, w, h


def check_roi(roi: Roi, shape: tuple[int, int], src: object = None) -> None:
    x, y, w, h = roi
    ih, iw = shape
    if x + w > iw or y + h > ih:
        box = verbatim(f"{x},{y},{w},{h}")
        raise InputError(f"{opt('roi', box)} reaches past the {iw}x{ih} image", src, option="roi")  # type: ignore[arg-type]


def halo_roi(
    roi: Roi, shape: tuple[int, int], halo: int, multiple: int = 1, align: int = 1
) -> tuple[Roi, tuple[int, int, int, int]]:
    """``roi`` grown by ``halo`` held pixels (``halo * multiple`` stored pixels, ``multiple``
    being the downscale factor, so blocks stay aligned) on every side, clipped to the image of
    stored ``shape``; and the original ROI's box (y0, y1, x0, x1) inside the grown crop, in held
    pixels. Load the grown ROI, run the network on it (it then sees the real image around the
    ROI, as inside an image: see infer.tiled's edge context), and crop the outputs to the box:
    no rim drawn at the crop's edges.

    ``align``: where it can, the grown crop starts on a multiple of ``align`` held pixels of
    the image (grown by up to ``align - 1`` more): the network downsamples, so a crop off the
    grid of a full-image run's tiles (contract.INPUT_MULTIPLE) gives other, equally valid,
    numbers.
    """
    x, y, w, h = roi
    ih, iw = shape
    check_roi(roi, shape, None)
    k = multiple
    g = halo * k

    def before(v: int) -> int:
        """Stored pixels to add before ``v``: a multiple of k (blocks on the ROI's grid), on
        the aligned grid where ``v`` itself is on the block grid."""
        plain = min(g, v) // k * k
        if v % k == 0 and align > 1:
            step = align * k
            return v - (v - plain) // step * step
        return plain

    left, top = before(x), before(y)
    right, bottom = min(g, iw - (x + w)), min(g, ih - (y + h))
    grown = (x - left, y - top, w + left + right, h + top + bottom)
    box = (top // k, top // k + h // k, left // k, left // k + w // k)
    return grown, box


def crop(arr: np.ndarray, roi: Roi | None) -> np.ndarray:
    """Rows and columns of the ROI from an (H, W, ...) array (a view)."""
    if roi is None:
        return arr
    x, y, w, h = roi
    return arr[y : y + h, x : x + w]


def area_downscale(arr: np.ndarray, k: int) -> np.ndarray:
    """Mean of each k x k block of an (H, W, ...) array, as float32; a remainder of fewer than
    k rows or columns at the bottom/right is dropped (so every output pixel is a full block)."""
    if k == 1:
        return arr.astype(np.float32, copy=False)
    h, w = arr.shape[0] // k, arr.shape[1] // k
    if h == 0 or w == 0:
        raise InputError(
            f"{opt('downscale', k)}: the image ({arr.shape[1]}x{arr.shape[0]}) is "
            f"smaller than one {k}x{k} block",
            option="downscale",
        )
    block = arr[: h * k, : w * k].reshape(h, k, w, k, *arr.shape[2:])
    # float64 accumulation: a 16-bit block sum can exceed float32's exact integer range
    return block.mean(axis=(1, 3), dtype=np.float64).astype(np.float32)


def downscale_mask(mask: np.ndarray, k: int) -> np.ndarray:
    """A block is object when at least half of its pixels are (the loader's > 127 rule)."""
    if k == 1:
        return mask
    return area_downscale(mask.astype(np.float32), k) >= 0.5


def downscale_normals(normals: np.ndarray, k: int) -> np.ndarray:
    """Block mean of unit normals, renormalised; blocks without any normal stay zero."""
    if k == 1:
        return normals
    mean = area_downscale(normals, k).astype(np.float64)
    norm = np.linalg.norm(mean, axis=-1, keepdims=True)
    return np.where(norm > 1e-6, mean / np.maximum(norm, 1e-6), 0.0).astype(np.float32)


def white_level(dtype: np.dtype) -> float:
    """The value that stands for full scale in stored images of this type."""
    if dtype == np.uint8:
        return 255.0
    if dtype == np.uint16:
        return 65535.0
    return 1.0  # float images (EXR, npz) are taken as already normalised


def srgb_to_linear(v: np.ndarray) -> np.ndarray:
    """The sRGB EOTF (IEC 61966-2-1) on values normalised to 0..1."""
    v = np.asarray(v, np.float32)
    return np.where(
        v <= 0.04045, v / 12.92, np.power((np.maximum(v, 0.04045) + 0.055) / 1.055, 2.4)
    ).astype(np.float32)


def linearise(
    img: np.ndarray, white: float, srgb: bool = False, gamma: float | None = None
) -> np.ndarray:
    """Encoded camera values -> linear values in the same units (0..white), float32."""
    if not srgb and gamma is None:
        return img.astype(np.float32, copy=False)
    v = np.clip(img.astype(np.float32) / np.float32(white), 0.0, None)
    lin = srgb_to_linear(v) if srgb else np.power(v, np.float32(gamma))
    return (lin * np.float32(white)).astype(np.float32)


def _otsu_bin(hist: np.ndarray, centres: np.ndarray) -> int:
    """Last bin of the lower class of Otsu's split (Otsu 1979). When the two populations are
    separated by empty bins every split in the gap scores the same: take the middle of that
    plateau, not its first bin on the lower population's tail."""
    w0 = np.cumsum(hist)  # pixels at or below each bin
    w1 = w0[-1] - w0
    s0 = np.cumsum(hist * centres)
    m0 = s0 / np.maximum(w0, 1)
    m1 = (s0[-1] - s0) / np.maximum(w1, 1)
    between = w0 * w1 * (m0 - m1) ** 2
    best = int(np.argmax(between))
    end = best
    while end + 1 < len(hist) and between[end + 1] >= between[best] * (1 - 1e-9):
        end += 1
    return (best + end) // 2


def valley_threshold(values: np.ndarray, bins: int = 256) -> float:
    """Otsu's split moved to the emptiest point of the (lightly smoothed) histogram between
    the two classes' modes.

    Otsu favours the class with the larger spread: on an object's peak brightness, whose dark
    tail (dark paint, self-shadowed pits) reaches down towards a dark backdrop, it cuts into
    that tail. The valley between the modes is where the two populations meet.
    """
    v = np.asarray(values, np.float64).ravel()
    if v.max() <= v.min():
        return float(v.max())
    hist, edges = np.histogram(v, bins=bins, range=(float(v.min()), float(v.max())))
    hist = hist.astype(np.float64)
    centres = (edges[:-1] + edges[1:]) / 2
    t = _otsu_bin(hist, centres)
    x = np.arange(-6, 7)
    smooth = np.convolve(hist, np.exp(-0.5 * (x / 2.0) ** 2), mode="same")
    lo = int(np.argmax(smooth[: t + 1]))
    # the upper mode, ignoring the pile-up of clipped (saturated) values in the top bins
    top = bins - 3
    hi = t + 1 + int(np.argmax(smooth[t + 1 : top])) if t + 1 < top else t
    if hi - lo < 2:
        return float(edges[t + 1])
    gap = smooth[lo : hi + 1]
    floor = gap.min() * (1 + 1e-9) + 1e-12
    start = end = int(np.argmax(gap <= floor))
    while end + 1 < len(gap) and gap[end + 1] <= floor:  # a flat (empty) valley: its middle
        end += 1
    return float(centres[lo + (start + end) // 2])


def _step(values: np.ndarray) -> float:
    """The smallest difference between two distinct values: the quantisation step of
    integer-coded pixels (also after --srgb or --downscale); ~0 for values with real noise."""
    distinct = np.unique(values)
    return float(np.diff(distinct).min()) if distinct.size > 1 else 0.0


def auto_mask(images: np.ndarray, *, min_share: float = 0.1) -> np.ndarray:
    """Object mask of a stack shot against a dark background.

    Every surface point facing the camera is lit by some light, so the per-pixel maximum over
    the stack (and the colour channels) separates object from background far better than any
    single image. The split is made on ``log(peak + typical)``, ``typical`` being the median
    peak: logarithmic above it (on linear values the split would fall between highlights and
    the rest of the object: a shiny object's peak spans decades), linear below it (a plain
    logarithm stretches the backdrop's few dark codes into a mode of their own and splits the
    backdrop instead: docs/benchmark.md). Otsu's threshold, moved to the histogram's valley
    between the two classes (:func:`valley_threshold`), then a morphological open (specks of
    lit background) and close (dark pits inside the object) with a kernel of ~1 % of the
    image, then only the connected components of at least ``min_share`` of the largest one's
    area.
    """
    peak = images.max(axis=(0, 3)) if images.ndim == 4 else images.max(axis=0)
    step = 1.0 if peak.dtype.kind in "ui" else _step(peak)
    if peak.dtype.kind != "f":  # integer stacks: the float32 values a float32 stack would give
        peak = peak.astype(np.float32)
    # the median is the backdrop's level when the object covers less than half the frame and
    # an object level otherwise: either way darker values are noise to compress, not to
    # stretch. At least 8 quantisation steps: on a nearly black 8-bit backdrop (median 1
    # code) the logarithm parts codes 0, 1, 2 into spikes with empty bins between them, and
    # the emptiest valley is found there. The last floor, 80 dB below the brightest pixel,
    # is for a black frame.
    median = float(np.median(peak))
    typical = max(median, 8 * step, float(peak.max()) * 1e-4, 1e-30)
    level = np.log(peak + np.float32(typical))
    mask = (level > valley_threshold(level)).astype(np.uint8)
    size = max(3, (round(min(mask.shape) / 100) // 2) * 2 + 1)  # odd
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, kernel)
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, kernel)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if count <= 1:
        raise InputError(
            f"{opt('auto_mask')} found no object: the per-pixel maximum over the stack "
            f"has no bright region against a dark background (give {opt('mask')})",
            option="auto_mask",
        )
    areas = stats[1:, cv2.CC_STAT_AREA]
    keep = np.flatnonzero(areas >= min_share * areas.max()) + 1
    return np.isin(labels, keep)


@dataclass(frozen=True)
class Transforms:
    """The per-image part (ROI, downscale, linearise) with what it needs to know."""

    roi: Roi | None = None
    downscale: int = 1
    srgb: bool = False
    gamma: float | None = None
    white: float | None = None  # full-scale value; None = from each image's dtype

    def __post_init__(self) -> None:
        if self.srgb and self.gamma is not None:
            raise InputError(
                f"{opt('srgb')} and {opt('gamma')} both linearise: give one of them", option="srgb"
            )
        if self.gamma is not None and not (np.isfinite(self.gamma) and self.gamma > 0):
            gamma = opt("gamma", verbatim(f"{self.gamma}"))
            raise InputError(f"{gamma}: must be a positive number (e.g. 2.2)")
        if self.downscale < 1:
            raise InputError(
                f"{opt('downscale', self.downscale)}: must be a positive integer",
                option="downscale",
            )

    @property
    def active(self) -> bool:
        return self.roi is not None or self.changes_values

    @property
    def changes_values(self) -> bool:
        """Whether pixel values change (block means, linearisation), not only which are kept."""
        return self.downscale > 1 or self.srgb or self.gamma is not None

    def image(self, img: np.ndarray, src: object = None) -> np.ndarray:
        """One decoded (H, W[, 3]) image after ROI, downscale, linearisation: uint8/uint16 kept
        as stored when no value changes (a crop), else float32 (block means and linear values
        are fractions; see :func:`~.types.held_dtype` for the other types)."""
        if self.roi is not None:
            check_roi(self.roi, img.shape[:2], src)
        if not self.changes_values:
            return as_held(crop(img, self.roi))
        white = self.white or white_level(img.dtype)
        out = area_downscale(crop(img, self.roi), self.downscale)
        return linearise(out, white, self.srgb, self.gamma)

    def mask(self, mask: np.ndarray) -> np.ndarray:
        return downscale_mask(crop(mask, self.roi), self.downscale)

    def normals(self, normals: np.ndarray) -> np.ndarray:
        return downscale_normals(crop(normals, self.roi), self.downscale)

    def describe(self) -> dict[str, object]:
        lin = "srgb" if self.srgb else (f"gamma {self.gamma:g}" if self.gamma else None)
        roi = list(self.roi) if self.roi else None
        return {"roi": roi, "downscale": self.downscale, "linearise": lin}


__all__ = [
    "Roi",
    "Transforms",
    "area_downscale",
    "auto_mask",
    "check_roi",
    "crop",
    "downscale_mask",
    "downscale_normals",
    "halo_roi",
    "linearise",
    "parse_roi",
    "srgb_to_linear",
    "valley_threshold",
    "white_level",
]
