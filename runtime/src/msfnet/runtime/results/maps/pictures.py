"""Pictures for a person: colour maps with colour bars, units and sensible automatic ranges.

Every function returns an (h, w, 3) uint8 RGB array (``png_bytes`` encodes one). Drawing uses
numpy and OpenCV for the pixels and Pillow for the text only: no plotting library, so a fresh
``msf-run`` does not pay ~1 s importing and driving one, and there is no global state to
disturb in a host program. Pictures are ~500 px wide (readable side by side in a report),
cropped to the object's bounding box plus a margin; pixels outside the mask are drawn light
grey. An empty mask gives a picture that says so instead of a blank or NaN one.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from msfnet.runtime.results.maps.albedo import display_level
from msfnet.runtime.results.maps.curvature import symmetric_range
from msfnet.runtime.results.maps.extent import mask_box

if TYPE_CHECKING:
    from PIL import Image, ImageFont

    _Font = ImageFont.FreeTypeFont | ImageFont.ImageFont

BACKGROUND = (0.88, 0.88, 0.88)
WIDTH_PX = 500  # pictures are ~500 px wide, readable side by side in a report
ERROR_PERCENTILE = 99.0
ERROR_MIN_RANGE_DEG = 5.0

# layout, in pixels
_MARGIN = 10  # left, right and below the image
_TITLE_H = 35  # band above the image for the title
_MIN_BOX_H, _MAX_BOX_H = 120, 1000  # the image's box: a thin object still gets a colour bar
_BAR_W, _TICK_LEN = 18, 4
_TITLE_PX, _TICK_PX, _LABEL_PX, _SMALL_PX = 14, 12, 13, 10
_INK = (0, 0, 0)
_BACKGROUND_U8 = tuple(round(255 * c) for c in BACKGROUND)


# ----------------------------------------------------------------------------- helpers


@functools.cache
def can_draw() -> bool:
    """Whether the pictures can be drawn: they need only Pillow (a base dependency) for their
    text. Kept so that a broken install still writes every other output (data, registered
    maps, mesh, profile) and says once why the figures are missing."""
    try:
        from PIL import Image, ImageDraw, ImageFont  # noqa: F401
    except ImportError:
        return False
    return True


def missing_note() -> str:
    """The one line saying that figures were not drawn and how to get them."""
    return "figures not drawn (they need Pillow): pip install 'pillow>=10'"


def nice_ceiling(value: float) -> float:
    """Round up to 1, 2, 2.5 or 5 times a power of ten (0 stays 0)."""
    if not math.isfinite(value) or value <= 0:
        return 0.0
    exp = math.floor(math.log10(value))
    for step in (1.0, 2.0, 2.5, 5.0, 10.0):
        top = step * 10.0**exp
        if top >= value * (1 - 1e-12):
            return top
    return 10.0 ** (exp + 1)


# finer than nice_ceiling's 1-2-2.5-5: a colour scale should end near the data (a 99th
# percentile of 109 deg drawn on 0..200 is mostly near-black)
_SCALE_STEPS = (1.0, 1.2, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0)


def scale_ceiling(value: float) -> float:
    """Round up to one of 1, 1.2, 1.5, 2, 2.5, 3, 4, 5, 6, 8 times a power of ten (at most
    25 % above ``value``; 0 stays 0)."""
    if not math.isfinite(value) or value <= 0:
        return 0.0
    exp = math.floor(math.log10(value))
    return next(
        round(s * 10.0**exp, 12) for s in _SCALE_STEPS if s * 10.0**exp >= value * (1 - 1e-12)
    )


def error_range(
    err_deg: np.ndarray,
    mask: np.ndarray,
    percentile: float = ERROR_PERCENTILE,
    minimum: float = ERROR_MIN_RANGE_DEG,
) -> float:
    """Upper end of the error colour scale in degrees: the ``percentile`` of the errors in the
    mask rounded up by :func:`scale_ceiling`, at least ``minimum``, at most 180."""
    vals = err_deg[mask & np.isfinite(err_deg)]
    top = float(np.percentile(vals, percentile)) if vals.size else 0.0
    return min(180.0, max(minimum, scale_ceiling(top)))


def colorbar_ticks(vmin: float, vmax: float) -> list[float]:
    """4 to 7 round values (steps of 1, 2, 2.5 or 5 times a power of ten) within
    [vmin, vmax], preferring a set that ends on ``vmax`` (an error scale's top is round)."""
    span = vmax - vmin
    if not (math.isfinite(span) and span > 0):
        return [vmin]
    found: list[list[float]] = []
    for parts in (5, 4, 6, 7, 3, 8, 9, 10):
        step = nice_ceiling(span / parts)
        first = math.ceil(vmin / step - 1e-9)
        last = math.floor(vmax / step + 1e-9)
        if 4 <= last - first + 1 <= 7:
            ticks = [round(k * step, 12) + 0.0 for k in range(first, last + 1)]  # no -0.0
            if math.isclose(ticks[-1], vmax, rel_tol=1e-9, abs_tol=1e-12 * span):
                return ticks
            found.append(ticks)
    if found:
        return found[0]
    return [vmin + span * k / 4 for k in range(5)]


def tick_label(value: float, ticks: list[float]) -> str:
    """A tick value with as many decimals as the ticks' spacing needs (all alike)."""
    step = abs(ticks[1] - ticks[0]) if len(ticks) > 1 else abs(value)
    if step == 0 or not math.isfinite(step):
        return f"{value:g}"
    if step < 1e-4 or step >= 1e6:
        return f"{value:.3g}"
    decimals = 0
    while decimals < 6 and abs(step * 10**decimals - round(step * 10**decimals)) > 1e-6:
        decimals += 1
    text = f"{value:.{decimals}f}"
    return "0" if float(text) == 0 else text


SHOWN_PX = 1000  # samples shown along a picture's longer side: twice its ~500 px width


def crop_box(mask: np.ndarray, margin: float = 0.06) -> tuple[slice, slice]:
    """Row and column slices of the mask's bounding box grown by ``margin`` of its size,
    every k-th pixel where the box is longer than SHOWN_PX: a picture ~500 px wide shows no
    more, and drawing a full-resolution crop held several float copies of a large image
    (hundreds of MB beyond --max-memory)."""
    box = mask_box(mask)
    if box is None:
        return slice(None), slice(None)
    rows, cols = box
    h, w = mask.shape
    pad_r = math.ceil(margin * float(rows.stop - rows.start)) + 1
    pad_c = math.ceil(margin * float(cols.stop - cols.start)) + 1
    r0, r1 = max(rows.start - pad_r, 0), min(rows.stop + pad_r, h)
    c0, c1 = max(cols.start - pad_c, 0), min(cols.stop + pad_c, w)
    step = max(1, math.ceil(max(r1 - r0, c1 - c0) / SHOWN_PX))
    return slice(int(r0), int(r1), step), slice(int(c0), int(c1), step)


# ----------------------------------------------------------------------------- colours


def _cv2_lut(code: int) -> np.ndarray:
    """OpenCV's 256-entry colour map as a (256, 3) uint8 RGB table."""
    ramp = np.arange(256, dtype=np.uint8).reshape(256, 1)
    return np.ascontiguousarray(cv2.applyColorMap(ramp, code)[:, 0, ::-1])


def _anchor_lut(anchors: list[tuple[float, tuple[float, float, float]]]) -> np.ndarray:
    """A (256, 3) uint8 RGB table interpolated linearly between (position, rgb) anchors."""
    pos = np.array([p for p, _ in anchors])
    rgb = np.array([c for _, c in anchors])
    t = np.linspace(0.0, 1.0, 256)
    table = np.stack([np.interp(t, pos, rgb[:, k]) for k in range(3)], -1)
    return np.clip(np.rint(table * 255), 0, 255).astype(np.uint8)


# diverging, blue concave .. near-white flat .. red convex; mirror-like in lightness so equal
# magnitudes of either sign read equally strong
_DIVERGING_ANCHORS = [
    (0.00, (0.03, 0.19, 0.40)),
    (0.20, (0.18, 0.43, 0.71)),
    (0.38, (0.60, 0.79, 0.89)),
    (0.50, (0.97, 0.97, 0.97)),
    (0.62, (0.96, 0.73, 0.62)),
    (0.80, (0.79, 0.29, 0.26)),
    (1.00, (0.42, 0.01, 0.12)),
]


@functools.cache
def _lut(name: str) -> np.ndarray:
    opencv = {"inferno": cv2.COLORMAP_INFERNO, "viridis": cv2.COLORMAP_VIRIDIS}
    if name in opencv:
        return _cv2_lut(opencv[name])
    if name == "diverging":
        return _anchor_lut(_DIVERGING_ANCHORS)
    raise ValueError(name)


def _levels(values: np.ndarray, vmin: float, vmax: float) -> np.ndarray:
    """Values scaled onto the 256 table entries (NaN as vmin), as uint8 indices."""
    span = vmax - vmin if vmax > vmin else 1.0
    shifted = np.nan_to_num(values.astype(np.float32), nan=vmin) - np.float32(vmin)
    return np.clip(shifted * np.float32(255.0 / span) + 0.5, 0, 255).astype(np.uint8)


def _colour(values: np.ndarray, cmap: str, vmin: float, vmax: float) -> np.ndarray:
    """(..., 3) uint8 RGB of ``values`` on the named table."""
    return _lut(cmap)[_levels(values, vmin, vmax)]


def _u8(rgb: np.ndarray) -> np.ndarray:
    """Float RGB in [0, 1] to uint8 (NaN as black)."""
    scaled = np.nan_to_num(rgb.astype(np.float32)) * np.float32(255.0)
    return np.clip(scaled + 0.5, 0, 255).astype(np.uint8)


def _on_background(rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """uint8 RGB with the pixels outside ``mask`` light grey (a copy)."""
    out = np.array(rgb, np.uint8)
    out[~mask] = _BACKGROUND_U8
    return out


def _fit(rgb: np.ndarray, box_w: int, box_h: int) -> np.ndarray:
    """``rgb`` (uint8) scaled to fit the box, its aspect kept: whole samples when enlarging
    (each pixel stays a crisp square), area averages when shrinking."""
    h, w = rgb.shape[:2]
    size = _shown_size((h, w), box_w, box_h)
    scale = size[0] / w
    if size == (w, h):
        return np.ascontiguousarray(rgb)
    how = cv2.INTER_NEAREST if scale >= 1 else cv2.INTER_AREA
    return cv2.resize(np.ascontiguousarray(rgb), size, interpolation=how)


# ----------------------------------------------------------------------------- text and layout


@functools.cache
def _font(size: int) -> _Font:
    """Pillow's own scalable font (Pillow >= 10.1 with FreeType; it has the degree sign the
    titles use, not Greek: keep units in Latin letters), else its fixed bitmap font: one
    size, but legible."""
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except (TypeError, OSError, ImportError):  # Pillow 10.0, or no FreeType
        return ImageFont.load_default()


def _text_size(text: str, font: _Font) -> tuple[int, int]:
    left, top, right, bottom = font.getbbox(text)
    return math.ceil(right - left), math.ceil(bottom - top)


def _fitting_font(text: str, size: int, width: int) -> _Font:
    """The largest font up to ``size`` px in which ``text`` is at most ``width`` wide (a long
    title is made smaller, not clipped)."""
    font = _font(size)
    while size > 8 and _text_size(text, font)[0] > width:
        size -= 1
        font = _font(size)
    return font


def _put_text(
    canvas: Image.Image,
    text: str,
    font: _Font,
    x: float,
    y: float,
    *,
    align: str = "left",
    valign: str = "top",
) -> None:
    """Draw ``text`` with its ink box's left/centre/right edge at ``x`` and top/middle edge at
    ``y``, kept inside the canvas (positions from the ink box: the bitmap fallback font
    has no anchors)."""
    from PIL import ImageDraw

    left, top, right, bottom = font.getbbox(text)
    w, h = right - left, bottom - top
    x0 = x - (w / 2 if align == "center" else w if align == "right" else 0)
    y0 = y - (h / 2 if valign == "middle" else 0)
    x0 = min(max(x0, 1), canvas.width - w - 1)
    y0 = min(max(y0, 1), canvas.height - h - 1)
    ImageDraw.Draw(canvas).text((x0 - left, y0 - top), text, fill=_INK, font=font)


def _centred(canvas: Image.Image, text: str, font: _Font, x: float, y: float) -> None:
    """``text`` centred on (x, y)."""
    _put_text(canvas, text, font, x, y, align="center", valign="middle")


def _put_vertical_text(canvas: Image.Image, text: str, font: _Font, x: int, y_mid: float) -> None:
    """``text`` reading upward, its left ink edge at ``x``, centred on ``y_mid``: drawn level
    into a mask and turned a quarter (exact, so it stays as crisp as level text)."""
    from PIL import Image, ImageDraw

    left, top, right, bottom = font.getbbox(text)
    w, h = math.ceil(right - left), math.ceil(bottom - top)
    level = Image.new("L", (w + 2, h + 2), 0)
    ImageDraw.Draw(level).text((1 - left, 1 - top), text, fill=255, font=font)
    upright = level.transpose(Image.Transpose.ROTATE_90)
    y0 = round(min(max(y_mid - upright.height / 2, 0), canvas.height - upright.height))
    x = min(x, canvas.width - upright.width)
    canvas.paste(_INK, (x, y0, x + upright.width, y0 + upright.height), upright)


@dataclass(frozen=True)
class _Bar:
    """A colour bar: its table, range, ticks and label."""

    cmap: str
    vmin: float
    vmax: float
    label: str

    def ticks(self) -> list[float]:
        return colorbar_ticks(self.vmin, self.vmax)

    def width(self) -> int:
        """Pixels it takes right of the image: bar, ticks, their labels, the rotated label."""
        ticks = self.ticks()
        labels = max(_text_size(tick_label(t, ticks), _font(_TICK_PX))[0] for t in ticks)
        return 25 + _BAR_W + _TICK_LEN + 4 + labels + 10 + _text_size("Ag", _font(_LABEL_PX))[1]

    def draw(self, canvas: Image.Image, x: int, y: int, h: int) -> None:
        """Draw the bar at (x, y), ``h`` high (top = vmax), with its ticks and labels."""
        from PIL import Image, ImageDraw

        ramp = np.linspace(255, 0, h).astype(np.uint8)  # top row: the table's last entry
        colours = np.repeat(_lut(self.cmap)[ramp][:, None, :], _BAR_W, axis=1)
        canvas.paste(Image.fromarray(np.ascontiguousarray(colours)), (x, y))
        draw = ImageDraw.Draw(canvas)
        draw.rectangle((x - 1, y - 1, x + _BAR_W, y + h), outline=_INK)
        ticks = self.ticks()
        span = self.vmax - self.vmin
        font = _font(_TICK_PX)
        right = x + _BAR_W + _TICK_LEN + 4
        widest = 0
        for t in ticks:
            ty = y + (h - 1) * (1 - (t - self.vmin) / span) if span > 0 else y + h / 2
            draw.line((x + _BAR_W, round(ty), x + _BAR_W + _TICK_LEN, round(ty)), fill=_INK)
            text = tick_label(t, ticks)
            widest = max(widest, _text_size(text, font)[0])
            _put_text(canvas, text, font, right, ty, valign="middle")
        # a thin picture's short bar: the label may run past the bar, within the picture
        label = _fitting_font(self.label, _LABEL_PX, canvas.height - 4)
        _put_vertical_text(canvas, self.label, label, right + widest + 10, y + h / 2)


def _box_size(shape: tuple[int, int], box_w: int) -> tuple[int, int]:
    """The image's box: ``box_w`` wide, as high as the picture's aspect asks within limits."""
    h, w = shape
    return box_w, int(min(max(round(box_w * h / max(w, 1)), _MIN_BOX_H), _MAX_BOX_H))


def _shown_size(shape: tuple[int, int], box_w: int, box_h: int) -> tuple[int, int]:
    """(w, h) of a ``shape`` picture fitted into the box, its aspect kept."""
    h, w = shape
    scale = min(box_w / w, box_h / h)
    return max(1, round(w * scale)), max(1, round(h * scale))


def _titled(
    rgb: np.ndarray, title: str, *, bar: _Bar | None = None, reserve: int = 0
) -> tuple[Image.Image, tuple[int, int, int, int]]:
    """A white canvas ~500 px wide with ``rgb`` (uint8) fitted into the image box under the
    title, and ``bar`` (or ``reserve`` free pixels) beside it. Also returns the box (x, y, w,
    h) of the image as drawn."""
    from PIL import Image

    side = bar.width() if bar is not None else reserve
    # with a bar the image takes ~74 % of the width; without one, nearly all
    room = WIDTH_PX - 2 * _MARGIN - side
    box_w, box_h = _box_size(rgb.shape[:2], min(room, 370) if bar else room)
    width = max(WIDTH_PX, _MARGIN + box_w + side + _MARGIN)
    canvas = Image.new("RGB", (width, _TITLE_H + box_h + _MARGIN), "white")
    shown = _fit(rgb, box_w, box_h)
    sh, sw = shown.shape[:2]
    x0 = _MARGIN + (box_w - sw) // 2
    y0 = _TITLE_H + (box_h - sh) // 2
    canvas.paste(Image.fromarray(shown), (x0, y0))
    _centred(
        canvas,
        title,
        _fitting_font(title, _TITLE_PX, width - 2 * _MARGIN),
        _MARGIN + box_w / 2,
        _TITLE_H / 2,
    )
    if bar is not None:
        bar_h = max(int(0.8 * box_h), 40)
        bar.draw(canvas, _MARGIN + box_w + 25, _TITLE_H + (box_h - bar_h) // 2, bar_h)
    return canvas, (x0, y0, sw, sh)


def _array(canvas: Image.Image) -> np.ndarray:
    return np.array(canvas.convert("RGB"), dtype=np.uint8)


def _empty(title: str) -> np.ndarray:
    """The picture of a map without object pixels: its title and a grey box that says so."""
    from PIL import Image, ImageDraw

    box_w, box_h = WIDTH_PX - 2 * _MARGIN, 240
    canvas = Image.new("RGB", (WIDTH_PX, _TITLE_H + box_h + _MARGIN), "white")
    ImageDraw.Draw(canvas).rectangle(
        (_MARGIN, _TITLE_H, _MARGIN + box_w - 1, _TITLE_H + box_h - 1), fill=_BACKGROUND_U8
    )
    _centred(canvas, title, _font(_TITLE_PX), WIDTH_PX / 2, _TITLE_H / 2)
    note = "no object pixels (empty mask)"
    _centred(canvas, note, _font(_TITLE_PX), WIDTH_PX / 2, _TITLE_H + box_h / 2)
    return _array(canvas)


def _scalar_picture(
    values: np.ndarray,
    mask: np.ndarray,
    *,
    cmap: str,
    vmin: float,
    vmax: float,
    title: str,
    label: str,
    rgb: np.ndarray | None = None,
) -> np.ndarray:
    """Colour-mapped (or precomputed uint8 ``rgb``, of the ``crop_box(mask)`` crop only)
    picture of a scalar map with a colour bar."""
    rs, cs = crop_box(mask)
    m = mask[rs, cs]
    shown = _colour(values[rs, cs], cmap, vmin, vmax) if rgb is None else rgb
    canvas, _ = _titled(_on_background(shown, m), title, bar=_Bar(cmap, vmin, vmax, label))
    return _array(canvas)


# ----------------------------------------------------------------------------- pictures


def error_picture(
    err_deg: np.ndarray, mask: np.ndarray, *, vmax: float | None = None
) -> np.ndarray:
    """Angular error map (deg) with a colour bar; range 0..vmax, automatic by default
    (:func:`error_range`). The title gives mean and median over the mask."""
    if not mask.any():
        return _empty("angular error")
    top = error_range(err_deg, mask) if vmax is None else float(vmax)
    vals = err_deg[mask & np.isfinite(err_deg)]  # pixels without ground truth are not scored
    if not vals.size:
        return _empty("angular error")
    title = f"angular error: mean {vals.mean():.2f}°, median {np.median(vals):.2f}°"
    return _scalar_picture(
        err_deg, mask, cmap="inferno", vmin=0.0, vmax=top, title=title, label="angular error (deg)"
    )


def legend_sphere(size: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """A unit sphere's normals coloured like the normal map: (size, size, 3) RGB in [0, 1] and
    its (size, size) bool disc mask."""
    t = (np.arange(size) + 0.5) / size * 2 - 1
    x, y = np.meshgrid(t, -t)  # y up: the top of the disc is y = +1
    disc = x**2 + y**2 < 1
    z = np.sqrt(np.clip(1 - x**2 - y**2, 0, None))
    rgb = np.empty((size, size, 3), np.float32)  # display values: float32 is plenty
    rgb[:] = BACKGROUND
    rgb[disc] = np.clip((np.stack([x, y, z], -1)[disc] + 1) / 2, 0.0, 1.0)
    return rgb, disc


_SPHERE_MIN, _SPHERE_MAX = 48, 96  # the sphere inset's side


def _sphere_inset(canvas: Image.Image, left: int, top: int, side: int) -> None:
    """The colour-convention sphere in a framed ``side`` square at (left, top), labelled
    "sphere" above; drawn 3x finer and averaged down, so its rim is smooth."""
    from PIL import Image, ImageDraw

    sphere, _ = legend_sphere(3 * side)
    small = cv2.resize(_u8(sphere), (side, side), interpolation=cv2.INTER_AREA)
    canvas.paste(Image.fromarray(small), (left, top))
    ImageDraw.Draw(canvas).rectangle((left - 1, top - 1, left + side, top + side), outline=_INK)
    label = _font(_SMALL_PX)
    y = top - _text_size("sphere", label)[1] - 3
    _put_text(canvas, "sphere", label, left + side / 2, y, align="center")


def normals_picture(normals: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Normal map as RGB = (n + 1) / 2 with a reference sphere inset showing the convention
    (red: x right, green: y up, blue: z toward the camera)."""
    if not mask.any():
        return _empty("normals")
    rs, cs = crop_box(mask)
    m = mask[rs, cs]
    rgb = _on_background(_u8((np.nan_to_num(normals[rs, cs].astype(np.float32)) + 1.0) / 2.0), m)
    title = "normals: RGB = (n + 1) / 2, x right, y up, z to camera"
    room = WIDTH_PX - 2 * _MARGIN
    sw, sh = _shown_size(m.shape, *_box_size(m.shape, room))
    label_h = _text_size("sphere", _font(_SMALL_PX))[1] + 3
    if sh >= 2 * _SPHERE_MIN + label_h:  # in the image's top right corner, as a legend
        canvas, (x0, y0, sw, sh) = _titled(rgb, title)
        side = int(min(max(0.19 * min(sw, sh), _SPHERE_MIN), _SPHERE_MAX))
        _sphere_inset(canvas, x0 + sw - side - 4, y0 + 4 + label_h, side)
    else:  # a flat object: beside the image, covering none of it
        canvas, _ = _titled(rgb, title, reserve=_SPHERE_MIN + 12)
        _sphere_inset(canvas, canvas.width - _MARGIN - _SPHERE_MIN, _TITLE_H + label_h, _SPHERE_MIN)
    return _array(canvas)


def _hill_shade(crop: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """Brightness in [0, 1] of a height crop lit from the upper left, 45 deg above the
    picture: 0.5 where the surface is level, brighter where it faces the light."""
    gy, gx = np.gradient(crop.astype(np.float32), dy, dx)
    # normal (-dz/dx, -dz/drow, 1) in picture coordinates (rows go down); the light comes
    # from -x and -row (upper left), elevation 45 deg
    lx = ly = -0.5
    lz = math.sqrt(0.5)
    lit = (-gx * lx - gy * ly + lz) / np.sqrt(gx * gx + gy * gy + 1.0)
    return np.clip(0.5 + 0.7 * (lit - lz), 0.0, 1.0)  # 0.7: shaded sides keep their colour


def height_picture(height: np.ndarray, mask: np.ndarray, *, units: str = "px") -> np.ndarray:
    """Hill-shaded, colour-mapped height (light from the upper left) with a colour bar."""
    valid = mask & np.isfinite(height)
    if not valid.any():
        return _empty("height")
    vals = height[valid]
    lo, hi = float(vals.min()), float(vals.max())
    if hi - lo <= 1e-9:
        hi = lo + 1.0  # a flat (or one-pixel) object: any range shows it in one colour
    rs, cs = crop_box(valid)
    crop = np.where(valid[rs, cs], height[rs, cs], lo)
    colours = _colour(crop, "viridis", lo, hi)
    if min(crop.shape) >= 2:  # hill shading needs a slope: one row or column is just coloured
        # a subsampled crop: slopes per original pixel
        light = _hill_shade(crop, float(cs.step or 1), float(rs.step or 1))[..., None]
        base = colours.astype(np.float32) / np.float32(255.0)
        # a soft-light blend: mid grey keeps the colour, light brightens and shade darkens it
        # without washing it out, so the colour bar still reads
        blended = (1 - 2 * light) * base * base + 2 * light * base
        colours = _u8(blended)
    return _scalar_picture(
        height,
        valid,
        cmap="viridis",
        vmin=lo,
        vmax=hi,
        rgb=colours,
        title=f"height (hill-shaded), range {hi - lo:.1f} {units}",
        label=f"height toward camera ({units})",
    )


CURVATURE_CMAP = "diverging"  # blue concave, near-white flat, red convex


def _diverging_picture(
    values: np.ndarray, mask: np.ndarray, percentile: float, what: str, title: str, unit: str
) -> np.ndarray:
    """``values`` on the diverging map centred on 0, symmetric range from the ``percentile``
    of their magnitude in the mask, with a colour bar labelled ``what (unit)``."""
    valid = mask & np.isfinite(values)
    if not valid.any():
        return _empty(what)
    top = symmetric_range(values[valid], percentile)
    return _scalar_picture(
        values,
        valid,
        cmap=CURVATURE_CMAP,
        vmin=-top,
        vmax=top,
        title=title,
        label=f"{what} ({unit})",
    )


def curvature_picture(
    mean: np.ndarray, mask: np.ndarray, *, percentile: float = 99.0
) -> np.ndarray:
    """Mean curvature on a diverging map centred on 0 (red convex, blue concave), symmetric
    range from the ``percentile`` of |H|, with a colour bar in 1/px."""
    title = "mean curvature (red convex, blue concave)"
    return _diverging_picture(mean, mask, percentile, "mean curvature", title, "1/px")


def local_shape_picture(
    local: np.ndarray, mask: np.ndarray, size_px: float, *, percentile: float = 99.0
) -> np.ndarray:
    """The local shape (height less its trend at ``size_px``: what msf-inspect's --depth
    judges) on the curvature's diverging map (red up, blue down), symmetric range from the
    ``percentile`` of its magnitude, with a colour bar in px."""
    title = f"local shape at {size_px:g} px (red up, blue down)"
    return _diverging_picture(local, mask, percentile, "local shape", title, "px")


def albedo_picture(albedo: np.ndarray, mask: np.ndarray, percentile: float = 99.5) -> np.ndarray:
    """Albedo as a colour picture, scaled so the ``percentile`` of the brightest channel is
    white (relative: the absolute values are in albedo.npy)."""
    if not mask.any():
        return _empty("albedo")
    top = display_level(albedo, mask, percentile)
    rs, cs = crop_box(mask)
    scaled = np.nan_to_num(albedo[rs, cs].astype(np.float32)) / np.float32(top if top > 0 else 1.0)
    rgb = _u8(np.clip(scaled, 0, 1) ** np.float32(1 / 2.2))
    title = f"albedo (display gamma 2.2, white = {top:.4g})"
    canvas, _ = _titled(_on_background(rgb, mask[rs, cs]), title)
    return _array(canvas)


_PANEL_W = 240  # each panel of the inputs picture


def inputs_picture(
    images: np.ndarray, mask: np.ndarray | None = None, count: int = 3
) -> np.ndarray:
    """The per-pixel maximum over all N images beside ``count`` evenly spaced inputs, each
    scaled by the 99.5th percentile of the maximum image and shown with gamma 2.2."""
    from PIL import Image

    n = images.shape[0]
    m = np.ones(images.shape[1:3], bool) if mask is None or not mask.any() else mask
    rs, cs = crop_box(m)
    top_img = images[:, rs, cs].max(axis=0)
    top = float(np.percentile(top_img, 99.5)) or 1.0
    picks = sorted(set(np.rint(np.linspace(0, n - 1, min(count, n))).astype(int).tolist()))
    panels = [("max of all", top_img)] + [(f"image {i + 1}", images[i, rs, cs]) for i in picks]
    h, w = top_img.shape[:2]
    box_w = _PANEL_W - 10
    box_h = int(min(max(round(_PANEL_W * h / max(w, 1)), 20), 2 * _PANEL_W))
    canvas = Image.new("RGB", (_PANEL_W * len(panels), box_h + _TITLE_H), "white")
    font = _font(_TICK_PX)
    for k, (name, img) in enumerate(panels):
        # shrink first, then scale and gamma: the arithmetic runs on the shown pixels only
        scale = min(box_w / w, box_h / h)
        size = (max(1, round(w * scale)), max(1, round(h * scale)))
        how = cv2.INTER_NEAREST if scale >= 1 else cv2.INTER_AREA
        small = cv2.resize(np.ascontiguousarray(img), size, interpolation=how)
        small = small.reshape(size[1], size[0], -1)
        shown = np.clip(small.astype(np.float32) / np.float32(top), 0, 1) ** np.float32(1 / 2.2)
        shown = np.broadcast_to(shown, (*shown.shape[:2], 3))  # a grey stack shows grey
        x0 = k * _PANEL_W + 5 + (box_w - size[0]) // 2
        canvas.paste(Image.fromarray(_u8(shown)), (x0, _TITLE_H - 5 + (box_h - size[1]) // 2))
        _centred(canvas, name, font, k * _PANEL_W + _PANEL_W / 2, _TITLE_H / 2 - 3)
    return _array(canvas)


def png_bytes(rgb: np.ndarray) -> bytes:
    """Encode an (h, w, 3) uint8/uint16 RGB (or (h, w) grey) array as PNG bytes."""
    arr = np.ascontiguousarray(rgb[..., ::-1] if rgb.ndim == 3 else rgb)
    ok, buf = cv2.imencode(".png", arr)
    if not ok:
        raise ValueError("PNG encoding failed")
    return buf.tobytes()


__all__ = [
    "albedo_picture",
    "can_draw",
    "colorbar_ticks",
    "crop_box",
    "curvature_picture",
    "error_picture",
    "error_range",
    "height_picture",
    "inputs_picture",
    "legend_sphere",
    "missing_note",
    "nice_ceiling",
    "normals_picture",
    "png_bytes",
    "scale_ceiling",
    "tick_label",
]
