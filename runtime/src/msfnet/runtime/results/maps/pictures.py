"""Pictures for a person: colour maps with colour bars, units and sensible automatic ranges.

Every function returns an (h, w, 3) uint8 RGB array (``png_bytes`` encodes one). Matplotlib is
imported only when a picture is drawn, and only its object-oriented Agg canvas is used (no
pyplot, no global backend switch), so drawing is safe inside any host program and without a
display. Pictures are cropped to the object's bounding box plus a margin; pixels outside the mask
are drawn light grey. An empty mask gives a picture that says so instead of a blank or NaN one.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import cv2
import numpy as np

from msfnet.runtime.results.maps.curvature import symmetric_range

BACKGROUND = (0.88, 0.88, 0.88)
WIDTH_IN = 5.0  # inches at DPI: pictures are ~500 px wide, readable side by side in a report
DPI = 100
ERROR_PERCENTILE = 99.0
ERROR_MIN_RANGE_DEG = 5.0


# ----------------------------------------------------------------------------- helpers


@functools.cache
def can_draw() -> bool:
    """Whether matplotlib (the ``[pictures]`` extra) can be imported. Without it the figures
    are skipped and every other output (data, registered maps, mesh, profile) is still
    written: a headless station does not need 65 MB of plotting library to measure."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


def missing_note() -> str:
    """The one line saying that figures were not drawn and how to get them."""
    from msfnet.common.cli import install_hint

    return f"figures not drawn (they need matplotlib): {install_hint('matplotlib')}"


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


# finer than nice_ceiling's 1-2-2.5-5: a colour scale should end near the data (harvest's
# least-squares errors, 99th percentile 109 deg, were drawn on 0..200, most of it near-black)
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


SHOWN_PX = 1000  # samples shown along a picture's longer side: twice its ~500 px width


def crop_box(mask: np.ndarray, margin: float = 0.06) -> tuple[slice, slice]:
    """Row and column slices of the mask's bounding box grown by ``margin`` of its size,
    every k-th pixel where the box is longer than SHOWN_PX: a picture ~500 px wide shows no
    more, and drawing a full-resolution crop held several float64 copies of a large image
    (hundreds of MB beyond --max-memory)."""
    if not mask.any():
        return slice(None), slice(None)
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    h, w = mask.shape
    pad_r = math.ceil(margin * float(rows[-1] - rows[0] + 1)) + 1
    pad_c = math.ceil(margin * float(cols[-1] - cols[0] + 1)) + 1
    r0, r1 = max(rows[0] - pad_r, 0), min(rows[-1] + pad_r + 1, h)
    c0, c1 = max(cols[0] - pad_c, 0), min(cols[-1] + pad_c + 1, w)
    step = max(1, math.ceil(max(r1 - r0, c1 - c0) / SHOWN_PX))
    return slice(int(r0), int(r1), step), slice(int(c0), int(c1), step)


def _figure(shape: tuple[int, int], colorbar: bool) -> tuple[Any, Any, Any]:
    """A figure sized to the picture, with fixed axes (faster than a layout engine): the image
    axes, and the colour-bar axes (None without one)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    h, w = shape
    img_w = WIDTH_IN * (0.74 if colorbar else 0.96)
    img_h = min(max(img_w * h / max(w, 1), 1.2), 2.0 * WIDTH_IN)
    title = 0.35  # inches above the image for the title
    height = img_h + title + 0.1
    fig = Figure(figsize=(WIDTH_IN, height), dpi=DPI)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0.02, 0.05 / height, img_w / WIDTH_IN, img_h / height))
    ax.set_axis_off()
    cax = None
    if colorbar:
        cax = fig.add_axes((0.80, (0.05 + 0.1 * img_h) / height, 0.035, 0.8 * img_h / height))
    return fig, ax, cax


def _render(fig: Any) -> np.ndarray:
    fig.canvas.draw()
    rgb = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    # a figure's artists form reference cycles that keep the arrays they show (float64
    # frames) until a garbage collection: dropped now, within --max-memory
    fig.clear()
    return rgb


def _empty(title: str) -> np.ndarray:
    fig, ax, _ = _figure((240, 320), colorbar=False)
    ax.set_title(title)
    ax.text(
        0.5, 0.5, "no object pixels (empty mask)", ha="center", va="center", transform=ax.transAxes
    )
    return _render(fig)


def _rgb_on_background(rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
    out = np.empty(rgb.shape, np.float32)  # display values: float32 is plenty
    out[:] = BACKGROUND
    out[mask] = np.clip(rgb[mask], 0.0, 1.0)
    return out


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
    """Colour-mapped (or precomputed ``rgb``, of the ``crop_box(mask)`` crop only) picture of
    a scalar map with a colour bar."""
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    rs, cs = crop_box(mask)
    m = mask[rs, cs]
    norm = Normalize(vmin=vmin, vmax=vmax)
    cm = colormaps[cmap]
    rgb = cm(norm(np.nan_to_num(values[rs, cs])))[..., :3] if rgb is None else rgb
    fig, ax, cax = _figure(m.shape, colorbar=True)
    ax.imshow(_rgb_on_background(rgb, m), interpolation="nearest")
    ax.set_title(title, fontsize=10)
    bar = fig.colorbar(ScalarMappable(norm=norm, cmap=cm), cax=cax)
    bar.set_label(label)
    return _render(fig)


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
    rgb = (np.stack([x, y, z], -1) + 1) / 2
    return _rgb_on_background(rgb, disc), disc


def normals_picture(normals: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Normal map as RGB = (n + 1) / 2 with a reference sphere inset showing the convention
    (red: x right, green: y up, blue: z toward the camera)."""
    if not mask.any():
        return _empty("normals")
    rs, cs = crop_box(mask)
    m = mask[rs, cs]
    rgb = (np.nan_to_num(normals[rs, cs]) + 1.0) / 2.0
    fig, ax, _ = _figure(m.shape, colorbar=False)
    ax.imshow(_rgb_on_background(rgb, m), interpolation="nearest")
    ax.set_title("normals: RGB = (n + 1) / 2, x right, y up, z to camera", fontsize=10)
    inset = ax.inset_axes((0.80, 0.80, 0.19, 0.19))
    sphere, _ = legend_sphere()
    inset.imshow(sphere, interpolation="bilinear")
    inset.set_xticks([])
    inset.set_yticks([])
    inset.set_title("sphere", fontsize=7, pad=2)
    return _render(fig)


def height_picture(height: np.ndarray, mask: np.ndarray, *, units: str = "px") -> np.ndarray:
    """Hill-shaded, colour-mapped height (light from the upper left) with a colour bar."""
    from matplotlib import colormaps
    from matplotlib.colors import LightSource, Normalize

    valid = mask & np.isfinite(height)
    if not valid.any():
        return _empty("height")
    vals = height[valid]
    lo, hi = float(vals.min()), float(vals.max())
    if hi - lo <= 1e-9:
        hi = lo + 1.0  # a flat (or one-pixel) object: any range shows it in one colour
    rs, cs = crop_box(valid)
    crop = np.where(valid[rs, cs], height[rs, cs], lo)
    if min(crop.shape) < 2:  # hill shading needs a slope: one row or column is just coloured
        shade = colormaps["viridis"](Normalize(lo, hi)(crop))[..., :3]
    else:
        shade = LightSource(
            azdeg=315, altdeg=45
        ).shade(
            crop,
            cmap=colormaps["viridis"],
            norm=Normalize(lo, hi),
            blend_mode="soft",
            vert_exag=1.0,
            dx=float(cs.step or 1),  # a subsampled crop: slopes per original pixel
            dy=float(rs.step or 1),
        )[..., :3]
    return _scalar_picture(
        height,
        valid,
        cmap="viridis",
        vmin=lo,
        vmax=hi,
        rgb=shade,
        title=f"height (hill-shaded), range {hi - lo:.1f} {units}",
        label=f"height toward camera ({units})",
    )


CURVATURE_CMAP = "RdBu_r"  # diverging: blue concave, white flat, red convex


def curvature_colors(
    mean: np.ndarray, mask: np.ndarray, percentile: float = 99.0, *, top: float | None = None
) -> tuple[np.ndarray, float]:
    """(H, W, 3) RGB in [0, 1] of a mean-curvature map on the diverging map centred on 0, and
    the symmetric range r used (-r .. +r, the ``percentile`` of |H| in the mask, or ``top``)."""
    from matplotlib import colormaps

    if top is None:
        valid = mask & np.isfinite(mean)
        top = symmetric_range(mean[valid], percentile)
    scaled = np.clip(np.nan_to_num(mean) / top, -1.0, 1.0) * 0.5 + 0.5
    return colormaps[CURVATURE_CMAP](scaled)[..., :3], top


def curvature_picture(
    mean: np.ndarray, mask: np.ndarray, *, percentile: float = 99.0
) -> np.ndarray:
    """Mean curvature on a diverging map centred on 0 (red convex, blue concave), symmetric
    range from the ``percentile`` of |H|, with a colour bar in 1/px."""
    valid = mask & np.isfinite(mean)
    if not valid.any():
        return _empty("mean curvature")
    top = symmetric_range(mean[valid], percentile)
    rs, cs = crop_box(valid)
    rgb, _ = curvature_colors(mean[rs, cs], valid[rs, cs], percentile, top=top)
    return _scalar_picture(
        mean,
        valid,
        cmap=CURVATURE_CMAP,
        vmin=-top,
        vmax=top,
        rgb=rgb,
        title="mean curvature (red convex, blue concave)",
        label="mean curvature (1/px)",
    )


def albedo_picture(albedo: np.ndarray, mask: np.ndarray, percentile: float = 99.5) -> np.ndarray:
    """Albedo as a colour picture, scaled so the ``percentile`` of the brightest channel is
    white (relative: the absolute values are in albedo.npy)."""
    if not mask.any():
        return _empty("albedo")
    vals = albedo[mask].max(axis=1)
    top = float(np.percentile(vals, percentile))
    rs, cs = crop_box(mask)
    rgb = np.nan_to_num(albedo[rs, cs]) / (top if top > 0 else 1.0)
    fig, ax, _ = _figure(rgb.shape[:2], colorbar=False)
    ax.imshow(_rgb_on_background(rgb ** (1 / 2.2), mask[rs, cs]), interpolation="nearest")
    ax.set_title(f"albedo (display gamma 2.2, white = {top:.4g})", fontsize=10)
    return _render(fig)


def inputs_picture(
    images: np.ndarray, mask: np.ndarray | None = None, count: int = 3
) -> np.ndarray:
    """The per-pixel maximum over all N images beside ``count`` evenly spaced inputs, each
    scaled by the 99.5th percentile of the maximum image and shown with gamma 2.2."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    n = images.shape[0]
    m = np.ones(images.shape[1:3], bool) if mask is None or not mask.any() else mask
    rs, cs = crop_box(m)
    top_img = images[:, rs, cs].max(axis=0)
    top = float(np.percentile(top_img, 99.5)) or 1.0
    picks = sorted(set(np.rint(np.linspace(0, n - 1, min(count, n))).astype(int).tolist()))
    panels = [("max of all", top_img)] + [(f"image {i + 1}", images[i, rs, cs]) for i in picks]
    h, w = top_img.shape[:2]
    cols = len(panels)
    panel_h = min(2.4 * h / max(w, 1), 4.8)
    height = panel_h + 0.35
    fig = Figure(figsize=(2.4 * cols, height), dpi=DPI)
    FigureCanvasAgg(fig)
    for k, (name, img) in enumerate(panels):
        ax = fig.add_axes((k / cols + 0.01, 0.05 / height, 1 / cols - 0.02, panel_h / height))
        shown = np.clip(img.astype(np.float32) / np.float32(top), 0, 1, dtype=np.float32)
        ax.imshow(shown ** np.float32(1 / 2.2), interpolation="nearest")
        ax.set_title(name, fontsize=9)
        ax.set_axis_off()
    return _render(fig)


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
    "crop_box",
    "curvature_colors",
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
]
