"""Pixel-registered maps for other vision tools: float32 TIFF data and same-size PNG views.

Every file here has exactly the input's width and height, pixel (r, c) of a map is pixel (r, c)
of the input images (a figure with axes and a colour bar lives only in report.html). Data files
are single-page float32 TIFF (uncompressed, so HALCON ``read_image``, OpenCV
``cv2.imread(..., cv2.IMREAD_UNCHANGED)``, Matrox and Cognex read them as they are); NaN marks
pixels outside the mask. Views are 16-bit grey (height, local shape) or 8-bit RGB (signed maps
on a diverging palette), for a person.

Conventions (documented in maps.json too):
- gradient p = dz/d(column), q = dz/d(row): image axes, rows down (so a surface rising towards
  the top of the image has q < 0). z is toward the camera.
- units: with ``pixel_size_mm`` heights are in mm and curvatures in 1/mm (mean) and 1/mm^2
  (Gaussian), else in px, 1/px and 1/px^2; gradients are dimensionless either way (orthographic:
  one unit of z is one pixel pitch).
- local shape: height minus its smooth trend, the trend being a quadric fitted around each
  pixel with Gaussian weights of ``local_size`` px inside the mask (:func:`local_trend`).
  Relief narrower than about that size stays, the part's tilt and bow go (Matrox' "local
  shape", Keyence's "characteristic size").
- albedo.tif holds three samples per pixel in R, G, B order; OpenCV's imread returns them
  reversed (its BGR order), tifffile and HALCON as stored. Outside the mask every TIFF holds
  NaN; albedo.tif is NaN inside too where no observation was kept (maps.albedo). The normals
  are not repeated as a TIFF (normals.npy holds them; gradient_p / gradient_q are their
  registered form).
- placement: with --roi / --downscale the maps are a part of the stored image (:class:`Frame`,
  maps.json's "frame"); the TIFFs carry it in their XPosition / YPosition tags and the scale in
  XResolution / YResolution (:func:`tiff_placement`).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from msfnet.common.errors import InputError
from msfnet.common.imageio import image_header
from msfnet.common.vocabulary import declare, opt
from msfnet.runtime.results.maps.extent import mask_box

# MapOptions.local_size_px, named by the size check here
declare("local_size_px", "--local-size")

DEFAULT_LOCAL_SIZE_PX = 12.0
TREND_DEGREE = 2  # the local shape's trend: a quadric around each pixel (see local_trend)
TREND_TRUNCATE = 4.0  # the trend's Gaussian weights end at 4 sigma (as OpenCV's float kernels)
TREND_FFT_RADIUS = 24  # kernels wider than this many px each side are applied by FFT
TREND_CHUNK = 1 << 16  # pixels whose 6 x 6 systems are solved together
TREND_CACHE_PIXELS = 1 << 20  # trend weights (48 B a pixel) kept for the next part's mask
VIEW_PERCENTILE = 99.5  # a view's range: this percentile of |value| (one hot pixel does not set it)


@dataclass(frozen=True)
class Units:
    """What one unit of each registered map means."""

    height: str
    curvature: str
    gaussian_curvature: str

    @classmethod
    def of(cls, pixel_size_mm: float | None) -> Units:
        if pixel_size_mm is None:
            return cls("px", "1/px", "1/px^2")
        return cls("mm", "1/mm", "1/mm^2")


@dataclass(frozen=True)
class Frame:
    """Where the maps sit in the stored images: ``origin_xy`` is the --roi's top-left corner in
    stored-image pixels ((0, 0) without one), ``downscale`` the --downscale factor K (1 without).
    Map pixel (col, row) is the mean of stored pixels x0 + K col .. x0 + K col + K - 1 (rows
    likewise), so its centre lies at image (x0 + K col + (K - 1) / 2, y0 + K row + (K - 1) / 2)
    (:meth:`image_xy`)."""

    origin_xy: tuple[int, int] = (0, 0)
    downscale: int = 1

    def __post_init__(self) -> None:
        x0, y0 = (int(v) for v in self.origin_xy)
        if (x0, y0) != tuple(self.origin_xy) or x0 < 0 or y0 < 0:
            raise InputError(f"frame origin {self.origin_xy}: must be two integers >= 0")
        if int(self.downscale) != self.downscale or self.downscale < 1:
            raise InputError(f"frame downscale {self.downscale}: must be an integer >= 1")
        object.__setattr__(self, "origin_xy", (x0, y0))
        object.__setattr__(self, "downscale", int(self.downscale))

    @classmethod
    def of_cut(cls, roi: Sequence[int] | None, downscale: int | None) -> Frame:
        """The frame of maps loaded with ``roi`` (x, y, w, h; None: the whole image) and
        ``downscale`` (None or 1: none), as --roi / --downscale / LoadOptions give them."""
        origin = (int(roi[0]), int(roi[1])) if roi else (0, 0)
        return cls(origin, int(downscale or 1))

    def as_dict(self) -> dict[str, object]:
        """maps.json's "frame": {"origin_xy": [x0, y0], "downscale": K}."""
        return {"origin_xy": list(self.origin_xy), "downscale": self.downscale}

    @property
    def is_identity(self) -> bool:
        """The maps are the whole stored image at its own resolution."""
        return self.origin_xy == (0, 0) and self.downscale == 1

    def image_xy(self, col: float, row: float) -> tuple[float, float]:
        """The stored-image position (x, y) of map pixel (col, row)'s centre."""
        k = self.downscale
        half = (k - 1) / 2.0
        return self.origin_xy[0] + k * col + half, self.origin_xy[1] + k * row + half


def check_local_size(size_px: float, shape: tuple[int, int]) -> None:
    """InputError when the local shape's characteristic size exceeds the maps' longer side: its
    trend would span more than the whole image (nothing left to measure), and the Gaussian
    sums behind it grow with the size. The default size is always accepted: on a part smaller
    than it (a thumbnail, a tiny ROI) its trend is one quadric over the whole part."""
    longer = max(shape)
    if size_px > max(longer, DEFAULT_LOCAL_SIZE_PX):
        raise InputError(
            f"{opt('local_size_px', float(size_px))} px is larger than the maps' longer side "
            f"({longer} px for {shape[1]} x {shape[0]}, after {opt('roi')} / {opt('downscale')}): "
            "the trend would span the whole part; "
            f"give at most {max(longer, int(DEFAULT_LOCAL_SIZE_PX))}",
            option="local_size_px",
        )


def tiff_placement(frame: Frame, image_pixel_size_mm: float | None) -> dict[str, Any]:
    """tifffile.imwrite arguments that place a map in its stored image (TIFF 6.0 tags).

    With a pixel size (``image_pixel_size_mm``: a stored-image pixel, as --pixel-size) the
    resolution is map pixels per centimetre (ResolutionUnit 3; HALCON, ImageJ and GIMP read
    the scale) and XPosition / YPosition the ROI's corner in cm; without one the unit is one
    stored-image pixel (ResolutionUnit 1, NONE): resolution 1 / K, position (x0, y0)."""
    k = frame.downscale
    if image_pixel_size_mm is None:
        unit, per_unit, position_scale = "NONE", 1.0 / k, 1.0
    else:
        cm = image_pixel_size_mm / 10.0  # a stored-image pixel in cm
        unit, per_unit, position_scale = "CENTIMETER", 1.0 / (k * cm), cm

    def rational(value: float) -> tuple[int, int]:
        f = Fraction(value).limit_denominator(1 << 20)
        return f.numerator, f.denominator

    x0, y0 = frame.origin_xy
    return {
        "resolution": (per_unit, per_unit),
        "resolutionunit": unit,
        "extratags": [
            (286, 5, 1, rational(x0 * position_scale), True),  # XPosition, RATIONAL
            (287, 5, 1, rational(y0 * position_scale), True),  # YPosition
        ],
    }


def gradients(
    normals: np.ndarray, valid: np.ndarray, min_nz: float = 0.05
) -> tuple[np.ndarray, np.ndarray]:
    """(p, q) = (dz/dcol, dz/drow) of (H, W, 3) unit normals (x right, y up, z to the camera),
    float32, NaN outside ``valid``; nz is clipped at ``min_nz`` (slopes bounded by 1/min_nz)."""
    # float32 throughout (the maps are float32): no float64 H x W temporaries
    nz = np.maximum(normals[..., 2], min_nz).astype(np.float32)
    p = np.divide(normals[..., 0], nz, dtype=np.float32)
    np.negative(p, out=p)
    q = np.divide(normals[..., 1], nz, dtype=np.float32)  # rows down: dz/drow = ny / nz
    del nz
    p[~valid] = np.nan
    q[~valid] = np.nan
    return p, q


class _Moments:
    """Gaussian-weighted moments sum_d g(d) (dx/s)^a (dy/s)^b src(p + d) of a few (H, W) float64
    maps at every pixel p: separable filters for small kernels, one FFT per map for large ones
    (the cost then stops growing with the kernel)."""

    def __init__(self, sigma: float, shape: tuple[int, int], max_power: int) -> None:
        h, w = shape
        reach = math.ceil(TREND_TRUNCATE * sigma)
        # no offset along an axis exceeds the map's extent there: each axis's kernel ends at
        # that or at 4 sigma (one radius for both padded a 40 x 3000 strip to 3000 x 3000)
        self.radius = (int(min(reach, h - 1)), int(min(reach, w - 1)))  # rows, columns
        # offsets in units of the window actually seen: the moments stay O(1), so the ridge
        # below means the same whatever sigma is (one unit for both axes)
        unit = min(sigma, max(*self.radius, 1) / 2.0)
        self.kernels: list[list[np.ndarray]] = []  # [axis][power], axis 0: rows
        for r in self.radius:
            offsets = np.arange(-r, r + 1, dtype=np.float64)
            weight = np.exp(-0.5 * (offsets / sigma) ** 2)
            self.kernels.append([weight * (offsets / unit) ** a for a in range(max_power + 1)])
        self.shape = shape
        self.fft = max(self.radius) > TREND_FFT_RADIUS
        if self.fft:
            from scipy import fft

            self._fft = fft
            # h + radius samples keep the circular wrap out of the rows kept (and w + radius
            # the columns): the kernel spans 2 radius + 1, the output h
            self._padded = (
                fft.next_fast_len(h + self.radius[0], real=True),
                fft.next_fast_len(w + self.radius[1], real=True),
            )
            self._rows = [fft.fft(k, self._padded[0]) for k in self.kernels[0]]
            self._cols = [fft.rfft(k, self._padded[1]) for k in self.kernels[1]]

    def of(self, src: np.ndarray) -> Callable[[int, int], np.ndarray]:
        """A function (a, b) -> the moment of ``src`` with column power a and row power b."""
        rows, cols = self.kernels
        if not self.fft:
            return lambda a, b: cv2.sepFilter2D(
                src, cv2.CV_64F, cols[a], rows[b], borderType=cv2.BORDER_CONSTANT
            )
        fft, padded, (ry, rx) = self._fft, self._padded, self.radius
        h, w = self.shape
        spectrum = fft.rfft2(src, padded)

        def moment(a: int, b: int) -> np.ndarray:
            full = fft.irfft2(spectrum * self._rows[b][:, None] * self._cols[a][None, :], padded)
            # the FFT convolves; a kernel of odd total power changes sign when mirrored
            sign = -1.0 if (a + b) % 2 else 1.0
            return sign * full[ry : ry + h, rx : rx + w]

        return moment


def local_trend(
    values: np.ndarray, valid: np.ndarray, sigma: float, degree: int = TREND_DEGREE
) -> np.ndarray:
    """At each valid pixel, the value there of the polynomial of ``degree`` (1: a plane, 2: a
    quadric) fitted to the ``valid`` neighbours with Gaussian weights of ``sigma`` px (local
    polynomial regression, i.e. higher-order normalised convolution). A plain masked Gaussian
    is off by about slope x sigma at the mask's edge and by curvature x sigma^2 / 2 on a bowed
    part (as deep as the scratches looked for); a local quadric follows tilt and bow alike.
    NaN outside ``valid``.

    The polynomial is written in offsets from the pixel, so its constant term is the trend
    there and every normal equation is a Gaussian-weighted moment of the mask or of the
    masked values: one filter each, on the mask's bounding box only. The trend is linear in
    the values' moments, with weights that depend on the mask alone (:func:`_trend_weights`,
    kept for the next call with the same mask: a station's parts share their fixture's)."""
    if values.shape != valid.shape or values.ndim != 2:
        raise ValueError(f"heights {values.shape} and mask {valid.shape}: expected one (H, W)")
    h, w = values.shape
    out = np.full((h, w), np.nan, np.float32)
    box = mask_box(valid)
    if box is None:
        return out
    ok = valid[box]
    z = np.where(ok, np.nan_to_num(values[box]), 0.0).astype(np.float64)
    # a constant is in the fit: take the mean out for precision, put it back at the end
    level = float(z[ok].mean())
    z -= level
    z *= ok
    filters = _Moments(sigma, (int(ok.shape[0]), int(ok.shape[1])), 2 * degree)
    weights = _trend_weights(ok, sigma, degree, filters)
    of_values = filters.of(z)
    del z
    trend = np.zeros(weights.shape[1])
    for row, (a, b) in zip(weights, _powers(degree), strict=True):
        trend += row * of_values(a, b)[ok]
    out[box][ok] = trend + level
    return out


def _powers(degree: int) -> list[tuple[int, int]]:
    """The polynomial's terms as (x power, y power): 1, x, y, x^2, xy, y^2, ..."""
    return [(a, d - a) for d in range(degree + 1) for a in range(d, -1, -1)]


class _TrendCache:
    """The last mask's trend weights (one entry, up to TREND_CACHE_PIXELS pixels)."""

    lock = threading.Lock()
    key: tuple[float, int] | None = None
    mask: np.ndarray | None = None
    weights: np.ndarray | None = None


def _trend_weights(ok: np.ndarray, sigma: float, degree: int, filters: _Moments) -> np.ndarray:
    """(K, P) float64: per mask pixel, the first row of the inverse of its K x K normal
    equations (Gaussian-weighted moments of the mask), so that the trend there is that row
    times the K moments of the values."""
    key = (float(sigma), degree)
    with _TrendCache.lock:
        held, kept = _TrendCache.mask, _TrendCache.weights
        same = held is not None and held.shape == ok.shape and np.array_equal(held, ok)
        if same and _TrendCache.key == key and kept is not None:
            return kept
    powers = _powers(degree)
    k = len(powers)
    of_mask = filters.of(ok.astype(np.float64))
    # each moment once, at the mask's pixels only (8 B a pixel each); the K x K systems are
    # then built and solved a chunk of pixels at a time
    sums = [(ai + aj, bi + bj) for ai, bi in powers for aj, bj in powers]
    of_m = {key: of_mask(*key)[ok] for key in dict.fromkeys(sums)}
    pixels = len(next(iter(of_m.values())))
    weights = np.empty((k, pixels))
    first = np.zeros((1, k, 1))
    first[0, 0, 0] = 1.0
    for start in range(0, pixels, TREND_CHUNK):
        part = slice(start, start + TREND_CHUNK)
        a = np.stack([of_m[key][part] for key in sums], axis=-1).reshape(-1, k, k)
        # a ridge on the non-constant terms: a one-pixel strip has no slope across it
        ridge = 1e-6 * a[:, 0, 0]
        for i in range(1, k):
            a[:, i, i] += ridge
        # the systems are symmetric: the inverse's first column is its first row
        weights[:, part] = np.linalg.solve(a, np.broadcast_to(first, (len(a), k, 1)))[..., 0].T
    if pixels <= TREND_CACHE_PIXELS and ok.size <= 4 * TREND_CACHE_PIXELS:
        with _TrendCache.lock:
            _TrendCache.key, _TrendCache.mask, _TrendCache.weights = key, ok.copy(), weights
    return weights


def local_shape(height: np.ndarray, valid: np.ndarray, size_px: float) -> np.ndarray:
    """Height minus its trend at the characteristic size ``size_px`` (see module notes; the
    trend is :func:`local_trend`, so a tilted or bowed part reads flat up to its edges); at
    most the map's longer side (:func:`check_local_size`)."""
    if not (np.isfinite(size_px) and size_px > 0):
        raise ValueError(f"local shape size must be a positive number of px, got {size_px}")
    check_local_size(size_px, (int(height.shape[0]), int(height.shape[1])))
    ok = valid & np.isfinite(height)
    trend = local_trend(height, ok, size_px)
    return np.where(ok, height - trend, np.nan).astype(np.float32)


def write_tiff(
    path: Path, data: np.ndarray, description: str = "", placement: dict[str, Any] | None = None
) -> None:
    """A float32 TIFF, (H, W) or (H, W, C) as RGB-like samples, uncompressed; ``placement``:
    :func:`tiff_placement`'s resolution and position tags."""
    import tifffile

    arr = np.ascontiguousarray(data, np.float32)
    photometric = "rgb" if arr.ndim == 3 and arr.shape[2] == 3 else "minisblack"
    note = description or None
    tifffile.imwrite(
        path, arr, photometric=photometric, description=note, metadata=None, **(placement or {})
    )


def read_tiff(path: Path) -> np.ndarray:
    """A TIFF written by :func:`write_tiff` (or any real-valued TIFF) as float32; complex
    samples are refused (a cast would keep the real part without a word)."""
    import tifffile

    image_header(path)  # the size from the header first: a few KB can declare 3600 MP
    data = np.asarray(tifffile.imread(path))
    if data.dtype.kind not in "fiub":
        raise InputError(f"expected real numbers, found {data.dtype}", path)
    return data.astype(np.float32, copy=False)


def described_png(png: bytes, note: str) -> bytes:
    """PNG bytes with ``note`` as a Description text chunk right after the header (a viewer's
    image properties show it: what the grey levels or colours mean)."""
    import zlib

    data = b"Description\0" + note.encode("latin-1", "replace")
    chunk = len(data).to_bytes(4, "big") + b"tEXt" + data
    chunk += zlib.crc32(b"tEXt" + data).to_bytes(4, "big")
    end = 8 + 25  # the signature, then the IHDR chunk (4 + 4 + 13 + 4 bytes)
    return png[:end] + chunk + png[end:]


def grey16_view(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(H, W) uint16: the values' range inside ``valid`` stretched to 1..65535, 0 outside."""
    ok = valid & np.isfinite(values)
    out = np.zeros(values.shape, np.uint16)
    if not ok.any():
        return out
    lo, hi = float(np.min(values[ok])), float(np.max(values[ok]))
    scale = 65534.0 / (hi - lo) if hi > lo else 0.0
    out[ok] = np.rint(1.0 + (values[ok] - lo) * scale).astype(np.uint16)
    return out


def signed_view(values: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, float]:
    """(H, W, 3) uint8 RGB of a signed map on a blue-white-red palette centred on 0 (red
    positive), range +-r with r the VIEW_PERCENTILE of |values|; grey outside ``valid``.
    Returns the picture and r."""
    ok = valid & np.isfinite(values)
    out = np.full((*values.shape, 3), 128, np.uint8)
    if not ok.any():
        return out, 0.0
    top = float(np.percentile(np.abs(values[ok]), VIEW_PERCENTILE))
    top = top if top > 0 else 1e-12
    t = np.clip(np.nan_to_num(values) / top, -1.0, 1.0)
    pos, neg = np.clip(t, 0, 1), np.clip(-t, 0, 1)
    # white at 0, pure red at +r, pure blue at -r
    rgb = 255.0 * np.stack([1.0 - neg, 1.0 - pos - neg, 1.0 - pos], axis=-1)
    out[ok] = np.rint(rgb[ok]).astype(np.uint8)
    return out, top


__all__ = [
    "DEFAULT_LOCAL_SIZE_PX",
    "Frame",
    "Units",
    "check_local_size",
    "described_png",
    "gradients",
    "grey16_view",
    "local_shape",
    "local_trend",
    "read_tiff",
    "signed_view",
    "tiff_placement",
    "write_tiff",
]
