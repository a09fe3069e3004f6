"""The photometric stack: the one type every loader returns and every consumer takes."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from msfnet.common.errors import InputError
from msfnet.common.vocabulary import opt

# The fewest lights photometric stereo can work with: a normal and an albedo are three unknowns
# per pixel, so fewer images leave them undetermined. The one minimum of every command (stacks,
# --max-lights, least-squares trimming, training batches, captures).
MIN_LIGHTS = 3
# Light sets whose 3 x 3 moment matrix is worse conditioned than this cannot separate the normal's
# components (e.g. all lights nearly parallel): least squares and the network both degrade.
MAX_LIGHT_CONDITION = 1e4
INTENSITY_RANGE = (1e-6, 1e6)  # relative to the median intensity
# The brightest image value divided by its light's intensity must lie in this range: above it,
# squares summed over the lights overflow float32 in the network's normalisation (inf -> NaN
# normals); below it, the normalisation's +1e-10 dominates and the network sees a dimmed input.
# Pixel values and intensities each pass their own checks and still break it together
# (intensities of 1e-40: every one equal, so none is out of line with the others).
SIGNAL_RANGE = (1e-6, 1e15)
# Integer images a stack keeps as decoded: 1 or 2 bytes a value instead of float32's 4 (a
# 96-light 16-bit DiLiGenT ball holds 172 MB instead of 344). Their values are exact in float32,
# so consumers cast a tile or a light at a time and get the numbers a float32 stack gives.
INTEGER_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16))
# An image whose mean inside the mask (per unit light intensity) is below this fraction of a
# typical image's (the stack's 75th percentile) is taken for a dead light or a missed trigger:
# its pixels say "black" where the surface is lit, and every normal bends away from that light.
# The darkest images of DiLiGenT and psmImages (grazing lights, shadows) are at 0.6 or more.
DARK_IMAGE = 0.02
# The values a float image stands at when it is clipped: see float_full_scale.
FLOAT_FULL_SCALES = (1.0, 255.0, 1023.0, 4095.0, 16383.0, 65535.0)


def held_dtype(dtype: np.dtype | type) -> np.dtype:
    """The type a stack holds images stored as ``dtype`` in: uint8 and uint16 as they are,
    anything else (float16/64, other integers, bool) as float32."""
    dtype = np.dtype(dtype)
    return dtype if dtype in INTEGER_DTYPES else np.dtype(np.float32)


def as_held(images: np.ndarray) -> np.ndarray:
    """``images`` in their :func:`held_dtype` (no copy when already so)."""
    return images.astype(held_dtype(images.dtype), copy=False)


@dataclass
class Stack:
    """N images of one static object, each lit by one distant light.

    images:       (N, H, W, 3) linear RGB as stored (not yet divided by intensity): uint8 or
                  uint16 as stored when loading changed no value (ROI and selection only),
                  else float32 (see :func:`held_dtype`; loaders and ``from_arrays`` give no
                  other type). Consumers cast to float a tile or a light at a time, never the
                  integers themselves into arithmetic (a uint16 square overflows).
    lights:       (N, 3) float32 unit directions, camera frame: x right, y up, z to the camera
    intensities:  (N, 3) float32 RGB light intensities (ones when unknown)
    mask:         (H, W) bool object mask (all True when unknown)
    normals_gt:   (H, W, 3) float32 ground-truth unit normals, or None
    """

    name: str
    images: np.ndarray
    lights: np.ndarray
    intensities: np.ndarray
    mask: np.ndarray
    normals_gt: np.ndarray | None = None
    filenames: list[str] = field(default_factory=list)
    source: Path | None = None
    # what validate() found suspicious but usable (an image black among lit ones): one line
    # each, for the commands to print and keep in the profile
    warnings: list[str] = field(default_factory=list, compare=False)
    # what loading found (an automatic mask far from the folder's own): validate() keeps
    # these at the head of ``warnings``
    load_warnings: tuple[str, ...] = field(default=(), compare=False)
    # (y0, y1, x0, x1) of the requested --roi inside a crop grown by a halo
    # (LoadOptions.roi_halo): the estimators run on the grown crop (context for the ROI's
    # edges) and Model crops every output back to the box (:meth:`inner`). None: the stack
    # is what was asked for.
    roi_box: tuple[int, int, int, int] | None = None

    @classmethod
    def from_arrays(
        cls,
        images: npt.ArrayLike,
        lights: npt.ArrayLike,
        *,
        mask: npt.ArrayLike | None = None,
        intensities: npt.ArrayLike | None = None,
        normals_gt: npt.ArrayLike | None = None,
        name: str = "stack",
    ) -> Stack:
        """A validated stack from plain arrays (or nested lists): images (N, H, W, 3) or
        (N, H, W) grey, lights (N, 3) any length; mask and intensities optional. uint8/uint16
        images are kept as they are, any other type becomes float32."""
        images = as_held(real_array(images, "images", name))
        if images.ndim == 3:
            images = np.repeat(images[..., None], 3, axis=3)
        if images.ndim != 4:
            raise InputError(f"images must be N x H x W (x 3), got shape {images.shape}", name)
        n, h, w = images.shape[:3]

        def f32(values: object, what: str) -> np.ndarray:
            return real_array(values, what, name).astype(np.float32)

        lights = unit_lights(f32(lights, "light directions"), name)
        ones = np.ones((n, 3), np.float32)
        ints = ones if intensities is None else f32(intensities, "light intensities")
        mask = np.ones((h, w), bool) if mask is None else as_mask(mask, name)
        gt = None if normals_gt is None else f32(normals_gt, "ground-truth normals")
        return cls(name, images, lights, ints, mask, gt).validate()

    def __repr__(self) -> str:
        """One line (the dataclass's own printed every array: ~330 lines for a small stack)."""
        try:
            return self._summary()
        except (AttributeError, IndexError, TypeError, ValueError):  # not validated, malformed
            return f"Stack({self.name!r}, not a valid stack)"

    def _summary(self) -> str:
        h, w = self.shape
        pixels = int(np.count_nonzero(self.mask))
        parts = [repr(self.name), f"{self.num_lights} lights", f"{w}x{h}", str(self.images.dtype)]
        parts.append(f"mask_px={pixels}")
        if self.normals_gt is not None:
            parts.append("ground truth")
        if self.roi_box is not None:
            parts.append(f"roi_box={self.roi_box}")
        if self.source is not None:
            parts.append(f"source={str(self.source)!r}")
        return f"Stack({', '.join(parts)})"

    @property
    def num_lights(self) -> int:
        return int(self.images.shape[0])

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.images.shape[1]), int(self.images.shape[2])

    def subset(self, indices: Sequence[int]) -> Stack:
        idx = list(indices)
        names = [self.filenames[i] for i in idx] if self.filenames else []
        return replace(
            self,
            images=self.images[idx],
            lights=self.lights[idx],
            intensities=self.intensities[idx],
            filenames=names,
        )

    def inner(self) -> Stack:
        """The stack cropped to ``roi_box`` (images, mask, ground truth; views, no copy):
        exactly the requested ROI. Itself when there is no box."""
        if self.roi_box is None:
            return self
        y0, y1, x0, x1 = self.roi_box
        gt = self.normals_gt
        return replace(
            self,
            images=self.images[:, y0:y1, x0:x1],
            mask=self.mask[y0:y1, x0:x1],
            normals_gt=None if gt is None else gt[y0:y1, x0:x1],
            roi_box=None,
        )

    def validate(self) -> Stack:
        """Check shapes and values; raise InputError naming the source. Usable oddities are
        (re)listed in ``warnings``, the only thing it changes."""
        src = self.source if self.source is not None else self.name
        if self.images.ndim != 4 or self.images.shape[3] != 3:
            raise InputError(f"images must be N x H x W x 3, got {self.images.shape}", src)
        real_array(self.lights, "light directions", src)
        real_array(self.intensities, "light intensities", src)
        n = self.images.shape[0]
        if n < MIN_LIGHTS:
            raise InputError(f"photometric stereo needs at least {MIN_LIGHTS} lights, got {n}", src)
        if self.lights.ndim != 2 or self.lights.shape[1] != 3:
            raise InputError(
                f"light directions must have 3 numbers per row, got shape {self.lights.shape}", src
            )
        if self.lights.shape[0] != n:
            raise InputError(f"{n} images but {self.lights.shape[0]} light directions", src)
        if self.intensities.shape != (n, 3):
            raise InputError(
                f"{n} images but light intensities of shape "
                f"{self.intensities.shape} (expected {n} x 3)",
                src,
            )
        check_lights(self.lights, src)
        check_intensities(self.intensities, src)
        if self.mask.shape != self.shape:
            raise InputError(f"mask is {self.mask.shape} but images are {self.shape}", src)
        if not self.mask.any():
            raise InputError("mask is empty", src)
        if self.roi_box is not None:
            y0, y1, x0, x1 = self.roi_box
            if not (0 <= y0 < y1 <= self.shape[0] and 0 <= x0 < x1 <= self.shape[1]):
                raise InputError(f"ROI box {self.roi_box} lies outside the {self.shape} stack", src)
        if self.normals_gt is not None and self.normals_gt.shape != (*self.shape, 3):
            raise InputError(
                f"ground-truth normals are {self.normals_gt.shape}, images {self.shape}", src
            )
        if self.mask.dtype != np.bool_:
            raise InputError(f"mask must be boolean, got {self.mask.dtype}", src)
        self._check_pixels(src)
        if self.normals_gt is not None:
            gt = self.normals_gt
            unit = np.isfinite(gt).all(axis=-1) & (
                np.abs(np.linalg.norm(np.nan_to_num(gt), axis=-1) - 1) < 0.05
            )
            if not (unit & self.mask).any():
                raise InputError(
                    "the ground-truth normals hold no unit vector inside the mask "
                    "(all zero, or not normals): nothing to score against",
                    src,
                )
        return self

    def _check_pixels(self, src: str | Path | None) -> None:
        """Values the estimators cannot use: NaN/inf, negatives, a stack that is black or
        saturated inside the mask (every normal would be a guess) or outside SIGNAL_RANGE; a
        black image among lit ones becomes a warning. One light at a time, so the check needs
        no stack-sized temporary. Unsigned images can hold neither NaN nor negatives, and their
        extremes are taken in their own type (a max cannot overflow)."""
        kind = self.images.dtype.kind
        if kind not in "biuf":
            raise InputError(f"images have dtype {self.images.dtype}; expected numbers", src)
        n = self.num_lights
        peak, low, mean = np.zeros(n), np.zeros(n), np.zeros(n)
        # OpenCV's masked extremes and mean need no gathered copy (a station checks every part)
        fast = self.images.dtype in (np.uint8, np.uint16, np.float32)
        mask3 = np.repeat(self.mask, 3, axis=1).view(np.uint8) if fast else None
        for i, img in enumerate(self.images):
            if kind == "f" and not np.isfinite(img).all():
                raise InputError(
                    f"images contain NaN or infinite pixel values (image {i + 1})", src
                )
            if kind in "fi" and img.min() < 0:
                raise InputError(
                    f"images contain negative pixel values (image {i + 1}; "
                    "expected linear intensities >= 0)",
                    src,
                )
            peak[i], low[i], mean[i] = _masked_extremes(img, self.mask, mask3)
        if not peak.any():
            raise InputError(
                "every image is black (zero) inside the mask: nothing to estimate normals from", src
            )
        # integer images: at the type's full scale; float ones: one value everywhere, and that
        # value a full scale (see float_full_scale). A clipped stack after --downscale or
        # --srgb is one; a flat part under a ring light (one value in every image, 0.4 say) is
        # not, and its normals are well determined.
        full = full_scale(self.images.dtype)
        if full is None:
            full = float_full_scale(float(peak.max()))
        if full is not None and (low >= full).all():
            raise InputError(
                f"every image is saturated inside the mask (all pixels at {full:g})"
                ": no shading to estimate normals from; lower the exposure",
                src,
            )
        top = float((peak[:, None] / self.intensities.astype(np.float64)).max())
        lo, hi = SIGNAL_RANGE
        if not lo <= top <= hi:
            raise InputError(
                f"brightest pixel / light intensity is {top:.3g}, outside "
                f"{lo:g}..{hi:g}: rescale the images or check the intensities' "
                "units",
                src,
            )
        self.warnings = [
            *self.load_warnings,
            *self._dark_images(mean / self.intensities.astype(np.float64).mean(axis=1), src),
            *self._unshaded(peak, low, mean),
        ]

    def _unshaded(self, peak: np.ndarray, low: np.ndarray, mean: np.ndarray) -> list[str]:
        """A warning where every image is the same inside the mask: no shading between the
        lights (they did not switch, or one frame was saved N times). Compared in full only
        where each image's extremes and mean agree, which almost never happens otherwise."""
        if np.ptp(peak) or np.ptp(low) or np.ptp(mean):
            return []
        first = self.images[0][self.mask]
        if any(not np.array_equal(img[self.mask], first) for img in self.images[1:]):
            return []
        return [
            "every image is the same inside the mask: no shading between the lights (did "
            "they switch?); the normals are a guess unless the lights lie on one cone around "
            "the view, as a ring light over a flat part"
        ]

    def _dark_images(self, brightness: np.ndarray, src: str | Path | None) -> list[str]:
        """One warning per image far darker than the stack's typical one (see DARK_IMAGE)."""
        typical = float(np.percentile(brightness, 75))
        if typical <= 0:  # most images black: compare with the brightest instead
            typical = float(brightness.max())
        out = []
        for i in np.flatnonzero(brightness < DARK_IMAGE * typical):
            where = (
                f"{src}/{self.filenames[i]}"
                if self.filenames and isinstance(src, Path) and src.is_dir()
                else f"{src}: image {i + 1}"
            )
            out.append(
                f"{where}: (nearly) black inside the mask ({brightness[i] / typical:.1%} "
                "of a typical image's brightness): a dead light or a missed trigger? "
                f"It is used as it is (leave it out with {opt('select')})"
            )
        return out


def full_scale(dtype: np.dtype) -> float | None:
    """The value at which an observation stored as ``dtype`` is clipped: an integer type's
    full scale (255, 65535); None for floats, whose type says nothing of the sensor's range.
    The robust fit and the albedo both drop such observations."""
    dtype = np.dtype(dtype)
    return float(np.iinfo(dtype).max) if dtype.kind in "ui" else None


def float_full_scale(value: float) -> float | None:
    """``value`` when it is a full scale float images are held at, else None: 1.0 (float
    images), 255 / 65535 (8 / 16-bit images after --downscale, --srgb, --gamma), 1023 / 4095
    / 16383 (a camera's 10 / 12 / 14 raw bits). Only a float stack at one of them everywhere
    is saturated."""
    return next((f for f in FLOAT_FULL_SCALES if math.isclose(value, f, rel_tol=1e-5)), None)


def real_array(values: object, what: str, src: str | Path | None = None) -> np.ndarray:
    """``values`` as an array of real numbers (bool, integers or floats); complex numbers,
    strings and objects refused (a cast would drop an imaginary part without a word), and so
    are ragged lists (rows or images of different sizes)."""
    try:
        arr = np.asarray(values)
    except ValueError as exc:  # numpy: "setting an array element with a sequence ..."
        raise InputError(
            f"{what} are ragged: a list of arrays (or rows) of different shapes; every "
            "element must have the same shape",
            src,
        ) from exc
    if arr.dtype.kind not in "biuf":
        raise InputError(f"{what} have dtype {arr.dtype}; expected real numbers", src)
    return arr


def as_mask(mask: object, src: str | Path | None = None) -> np.ndarray:
    """A boolean mask from booleans or from numbers that are exactly 0 or 1; any other value
    (0.05, 255, NaN) is refused rather than read as "inside" (a grey image is not a mask: use
    :func:`msfnet.common.imageio.read_mask` for mask images)."""
    arr = real_array(mask, "mask values", src)
    if arr.dtype == np.bool_:
        return arr
    odd = (arr != 0) & (arr != 1)
    if odd.any():
        value = arr[odd].flat[0].item()  # a plain number in the message, not np.float64(...)
        raise InputError(
            f"mask holds {value!r} ({int(odd.sum())} value(s) other than 0 and 1): a mask is "
            "boolean, or numbers that are exactly 0 or 1",
            src,
        )
    return arr.astype(bool)


def unit_lights(lights: np.ndarray, src: str | Path | None = None) -> np.ndarray:
    """Light directions scaled to unit length (float32); zero or non-finite rows refused."""
    lights = np.asarray(lights, np.float64)
    if lights.ndim != 2 or lights.shape[1] != 3:
        raise InputError(
            f"light directions must have 3 numbers per row, got shape {lights.shape}", src
        )
    if not np.all(np.isfinite(lights)):
        raise InputError("light directions contain NaN or infinite values", src)
    norms = np.linalg.norm(lights, axis=1)
    if np.any(norms < 1e-6):
        bad = np.flatnonzero(norms < 1e-6) + 1
        raise InputError(f"zero-length light direction(s) at row(s) {bad.tolist()}", src)
    return (lights / norms[:, None]).astype(np.float32)


def light_condition(lights: np.ndarray) -> float:
    """Condition number of the light set's 3 x 3 moment matrix (1 = ideal, inf = rank < 3)."""
    lights = np.asarray(lights, np.float64)
    s = np.linalg.svd(lights, compute_uv=False)
    return float(s[0] / s[-1]) if s[-1] > 1e-12 * max(s[0], 1e-300) else float("inf")


def check_lights(lights: np.ndarray, src: str | Path | None = None) -> None:
    if not np.all(np.isfinite(lights)):
        raise InputError("light directions contain NaN or infinite values", src)
    norms = np.linalg.norm(lights, axis=1)
    if np.any(np.abs(norms - 1) > 1e-3):
        raise InputError("light directions must be unit vectors (loaders normalise them)", src)
    cond = light_condition(lights)
    if not cond < MAX_LIGHT_CONDITION:
        what = "rank < 3" if not np.isfinite(cond) else f"condition number {cond:.3g}"
        raise InputError(
            f"the light directions do not span 3-D ({what}; e.g. all lights "
            "equal or in one plane): normals cannot be recovered",
            src,
        )
    if not (lights[:, 2] > 0).any():
        # z is toward the camera: lights all behind the object light nothing the camera sees
        # (typically a file in the z-away convention); the normals would be nonsense
        raise InputError(
            "no light direction points toward the camera (every z <= 0; "
            "expected x right, y up, z toward the camera): flip the sign of z",
            src,
        )


def check_intensities(intensities: np.ndarray, src: str | Path | None = None) -> None:
    if not np.all(np.isfinite(intensities)) or np.any(intensities <= 0):
        bad = np.flatnonzero(~np.all(np.isfinite(intensities) & (intensities > 0), axis=1)) + 1
        raise InputError(
            f"light intensities must be positive and finite; bad row(s) {bad.tolist()}", src
        )
    ref = float(np.median(intensities))
    lo, hi = INTENSITY_RANGE
    ratio = intensities / ref
    if np.any(ratio < lo) or np.any(ratio > hi):
        bad = np.flatnonzero(np.any((ratio < lo) | (ratio > hi), axis=1)) + 1
        raise InputError(
            f"light intensities span more than {hi / lo:.0e}x (row(s) "
            f"{bad.tolist()[:5]}): probably a unit or parsing error",
            src,
        )


def _masked_extremes(
    img: np.ndarray, mask: np.ndarray, mask3: np.ndarray | None
) -> tuple[float, float, float]:
    """Max, min and mean of an (H, W, 3) image's values inside ``mask``; ``mask3``: the mask
    repeated per colour as uint8 (H, 3W), for OpenCV (None: numpy, any dtype)."""
    if mask3 is None:
        inside = img[mask]
        return float(inside.max()), float(inside.min()), float(inside.mean(dtype=np.float64))
    flat = np.ascontiguousarray(img).reshape(img.shape[0], -1)
    low, peak, _, _ = cv2.minMaxLoc(flat, mask3)
    return float(peak), float(low), float(cv2.mean(flat, mask3)[0])
