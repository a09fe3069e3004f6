"""Pictures: ranges, colour conventions, layout (size, colour bar, ticks, background),
degenerate inputs; drawn without matplotlib."""

from __future__ import annotations

import subprocess
import sys

import cv2
import numpy as np
import pytest

from msfnet.runtime.results.maps import pictures


def test_nice_ceiling_and_error_range() -> None:
    assert pictures.nice_ceiling(3.2) == 5.0
    assert pictures.nice_ceiling(11.0) == 20.0
    assert pictures.nice_ceiling(0.021) == pytest.approx(0.025)
    assert pictures.nice_ceiling(2.0) == 2.0
    mask = np.ones((20, 50), bool)
    err = np.full((20, 50), 1.0)
    assert pictures.error_range(err, mask) == 5.0  # never below the minimum range
    err[:] = np.linspace(0, 17, 1000).reshape(20, 50)
    assert pictures.error_range(err, mask) == 20.0  # 99th percentile 16.8 rounded up
    err[0, 0] = 1e4  # a single outlier does not stretch the scale
    assert pictures.error_range(err, mask) == 20.0


def test_legend_sphere_follows_the_normal_colour_convention() -> None:
    rgb, disc = pictures.legend_sphere(32)
    right, top = rgb[16, 30], rgb[1, 16]
    assert right[0] > 0.9 and top[1] > 0.9  # red grows to the right, green upward
    assert rgb[16, 16, 2] > 0.95  # the centre faces the camera: blue
    assert not disc[0, 0]


def _is_picture(img: np.ndarray) -> None:
    assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
    assert img.shape[0] > 100 and img.shape[1] > 100
    assert img.std() > 5, "a blank picture"


def test_pictures_draw_with_colour_bars(surfaces) -> None:
    z, mask, n = surfaces["sphere_cap"](h=40, w=48, radius=24.0, cap=18.0)
    err = np.where(mask, np.hypot(*np.mgrid[0:40, 0:48]) / 5, 0.0)
    curv = np.where(mask, np.linspace(-1, 1, 48)[None, :] * 0.02, np.nan)
    albedo = np.where(mask[..., None], 0.5, 0.0) * np.array([1.0, 0.8, 0.6])
    images = np.random.default_rng(0).uniform(0, 1000, size=(5, 40, 48, 3)).astype(np.float32)
    curv_img = pictures.curvature_picture(curv, mask)
    for img in (
        pictures.error_picture(err, mask),
        pictures.normals_picture(n, mask),
        pictures.height_picture(z, mask),
        curv_img,
        pictures.albedo_picture(albedo, mask),
        pictures.inputs_picture(images, mask),
    ):
        _is_picture(img)
    # diverging and centred on zero: flat is white, concave blue, convex red, and the range is
    # symmetric so equal magnitudes get equally strong colours
    top = pictures.symmetric_range(curv[mask], 99.0)
    assert top == pytest.approx(np.percentile(np.abs(curv[mask]), 99))
    row = pictures._colour(np.nan_to_num(curv), pictures.CURVATURE_CMAP, -top, top)[20] / 255.0
    flat, concave, convex = row[np.argmin(np.abs(curv[20]))], row[14], row[33]
    assert flat.min() > 0.9
    assert concave[2] > concave[0] + 0.2 and convex[0] > convex[2] + 0.2
    assert np.allclose(concave[::-1], convex, atol=0.25)  # RdBu is near mirror-symmetric
    png = pictures.png_bytes(curv_img)
    decoded = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)[..., ::-1]
    assert np.array_equal(decoded, curv_img)


def test_a_fresh_process_draws_without_matplotlib() -> None:
    """The written pictures need no plotting library: a fresh interpreter drawing the normals
    and error pictures never imports matplotlib (it cost ~1 s of a fresh msf-run)."""
    code = (
        "import sys, numpy as np\n"
        "from msfnet.runtime.results.maps import pictures\n"
        "m = np.zeros((40, 50), bool); m[5:35, 8:40] = True\n"
        "n = np.zeros((40, 50, 3)); n[..., 2] = 1\n"
        "pictures.png_bytes(pictures.normals_picture(n, m))\n"
        "pictures.png_bytes(pictures.error_picture(np.ones((40, 50)), m))\n"
        "assert pictures.can_draw()\n"
        "assert 'matplotlib' not in sys.modules, sorted(sys.modules)\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_degenerate_inputs_still_give_readable_pictures() -> None:
    empty = np.zeros((20, 20), bool)
    nan = np.full((20, 20), np.nan)
    for img in (
        pictures.height_picture(nan, empty),
        pictures.curvature_picture(nan, empty),
        pictures.error_picture(np.zeros((20, 20)), empty),
        pictures.normals_picture(np.zeros((20, 20, 3)), empty),
        pictures.albedo_picture(np.zeros((20, 20, 3)), empty),
    ):
        _is_picture(img)  # a picture that says "empty mask", not an all-NaN one
    one = np.zeros((20, 20), bool)
    one[5, 5] = True
    flat = np.where(one, 0.0, np.nan)
    _is_picture(pictures.height_picture(flat, one))
    _is_picture(pictures.curvature_picture(np.where(one, 0.0, np.nan), one))


GREY = np.array(pictures._BACKGROUND_U8, np.uint8)  # outside the mask


def _disc(h: int = 60, w: int = 80) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w]
    return (yy - h / 2) ** 2 + (xx - w / 2) ** 2 < (0.4 * h) ** 2


def _bar(img: np.ndarray, lut: np.ndarray) -> tuple[int, int, int]:
    """(column, top row, bottom row) of the colour bar: a column right of the image whose
    top is the table's last colour and bottom its first."""
    w = img.shape[1]
    for x in range(int(0.6 * w), w):
        col = img[:, x].astype(int)
        hi = np.flatnonzero(np.abs(col - lut[255]).max(axis=1) <= 8)
        lo = np.flatnonzero(np.abs(col - lut[0]).max(axis=1) <= 8)
        if hi.size >= 2 and lo.size >= 2 and hi[0] < lo[-1]:
            return x, int(hi[0]), int(lo[-1])
    raise AssertionError("no colour bar")


def test_layout_size_colour_bar_ticks_and_background() -> None:
    mask = _disc()
    err = np.where(mask, np.linspace(0, 7.3, 80)[None, :], 0.0)
    img = pictures.error_picture(err, mask, vmax=8.0)  # as msf-eval: one range for all
    assert img.shape[1] == pictures.WIDTH_PX and img.shape[2] == 3
    # crop 54 x 62 px of a 60 x 80 frame: ~370 px wide box, about as high, plus the title
    assert 360 <= img.shape[0] <= 440
    lut = pictures._lut("inferno")
    x, top, bottom = _bar(img, lut)
    assert x > 350 and bottom - top > 200  # right of the image, most of its height
    # the bar runs through the table: its middle is the table's middle colour
    mid = img[(top + bottom) // 2, x].astype(int)
    assert np.abs(mid - lut[128]).max() <= 12, mid
    # 0..8: ticks 0, 2, 4, 6, 8, each with a label (dark text) right of its tick mark
    ticks = pictures.colorbar_ticks(0.0, 8.0)
    assert ticks == [0.0, 2.0, 4.0, 6.0, 8.0]
    for t in ticks:
        row = round(top + (bottom - top) * (1 - t / 8.0))
        right = img[row - 3 : row + 4, x + 15 : x + 45]
        assert (right.max(axis=2) < 100).sum() >= 3, t
    # outside the mask: light grey, exactly; inside: no grey at all on this colour ramp
    grey = (img == GREY).all(axis=2)
    assert grey.sum() > 0.1 * 370 * 370
    rows = np.flatnonzero(grey.sum(axis=1) > 50)  # (anti-aliased text has a grey pixel or so)
    assert rows.min() >= 25  # under the title band
    assert not grey[rows.min() :, x - 2 : x + 3].any()  # the bar is not background


def test_colorbar_ticks_are_round_and_four_to_seven() -> None:
    assert pictures.colorbar_ticks(0.0, 5.0) == [0, 1, 2, 3, 4, 5]
    assert pictures.colorbar_ticks(0.0, 120.0) == [0, 20, 40, 60, 80, 100, 120]  # ends on top
    assert pictures.colorbar_ticks(0.0, 1.2) == pytest.approx([0, 0.2, 0.4, 0.6, 0.8, 1.0, 1.2])
    sym = pictures.colorbar_ticks(-0.0123, 0.0123)
    assert sym == pytest.approx([-0.01, -0.005, 0.0, 0.005, 0.01])
    assert [pictures.tick_label(t, sym) for t in sym] == ["-0.010", "-0.005", "0", "0.005", "0.010"]
    assert [pictures.tick_label(t, [0.0, 50.0]) for t in (0.0, 150.0)] == ["0", "150"]
    rng = np.random.default_rng(1)
    for _ in range(300):
        lo = float(rng.uniform(-1e3, 1e3)) * 10.0 ** rng.integers(-6, 4)
        hi = lo + float(rng.uniform(1e-3, 1e3)) * 10.0 ** rng.integers(-5, 4)
        ticks = pictures.colorbar_ticks(lo, hi)
        assert 4 <= len(ticks) <= 7, (lo, hi, ticks)
        span = hi - lo
        assert lo - 1e-9 * span <= ticks[0] and ticks[-1] <= hi + 1e-9 * span
        steps = np.diff(ticks)
        assert np.allclose(steps, steps[0], rtol=1e-6)
        mantissa = steps[0] / 10.0 ** np.floor(np.log10(steps[0]))
        assert min(abs(mantissa - m) for m in (1, 2, 2.5, 5, 10)) < 1e-6, (lo, hi, ticks)
    assert pictures.colorbar_ticks(3.0, 3.0) == [3.0]  # no range: one tick, no error


def test_normals_picture_keeps_the_width_and_a_sphere_legend() -> None:
    mask = _disc(90, 60)
    n = np.zeros((90, 60, 3))
    n[..., 2] = 1.0
    img = pictures.normals_picture(n, mask)
    assert img.shape[1] == pictures.WIDTH_PX and img.shape[0] > 480  # a tall object: taller
    sphere = (img[..., 0] > 200) & (img[..., 1] < 140) & (img[..., 2] > 200)  # magenta: bottom
    assert sphere[:, 300:].any(), "no sphere legend at the right"
    # n = (0, 0, 1) everywhere in the mask: its 83 x 60 crop is shown 8x (480 px wide), every
    # object pixel an 8 x 8 block, less the legend's corner
    facing = np.abs(img.astype(int) - [128, 128, 255]).max(axis=2) <= 1
    assert facing.sum() == pytest.approx(mask.sum() * 64, rel=0.02)


@pytest.mark.parametrize("shape", [(1, 30), (30, 1), (2, 2)])
def test_thin_objects_give_whole_pictures(shape: tuple[int, int]) -> None:
    mask = np.zeros((40, 50), bool)
    mask[10 : 10 + shape[0], 5 : 5 + shape[1]] = True
    values = np.where(mask, np.linspace(0.0, 3.0, 50)[None, :], np.nan)
    n = np.zeros((40, 50, 3))
    n[..., 2] = 1.0
    imgs = [
        pictures.error_picture(np.nan_to_num(values) * 4, mask),
        pictures.height_picture(values, mask),
        pictures.curvature_picture(values - 1.5, mask),
        pictures.normals_picture(n, mask),
        pictures.albedo_picture(np.repeat(np.nan_to_num(values)[..., None], 3, 2), mask),
    ]
    for img in imgs:
        _is_picture(img)
        assert img.shape[1] == pictures.WIDTH_PX
        assert 150 <= img.shape[0] <= 1100
        assert (img[-1] == 255).all() and (img[:, -1] == 255).all()  # a white edge: no clipping
    # the flat normals picture's legend sits beside the image, not over the object
    assert (np.abs(imgs[3].astype(int) - [128, 128, 255]).max(axis=2) <= 1).any()


def test_nan_errors_inside_the_mask_are_not_scored() -> None:
    mask = _disc()
    err = np.where(mask, 2.0, 0.0)
    err[:30] = np.nan  # no ground truth in the top half
    _is_picture(pictures.error_picture(err, mask))
    assert pictures.error_range(err, mask) == 5.0
    all_nan = np.full(mask.shape, np.nan)
    empty = pictures.error_picture(all_nan, mask)  # nothing to score: says so
    assert empty.shape == pictures.error_picture(all_nan, np.zeros_like(mask)).shape


def test_empty_picture_says_so_on_grey() -> None:
    img = pictures.normals_picture(np.zeros((20, 20, 3)), np.zeros((20, 20), bool))
    assert img.shape[1] == pictures.WIDTH_PX
    middle = img[img.shape[0] // 2 - 12 : img.shape[0] // 2 + 12, 100:400]
    assert (middle == GREY).all(axis=2).mean() > 0.5  # the grey box
    assert (middle.max(axis=2) < 90).sum() > 50  # and its dark text


def test_inputs_picture_panels_and_scaling() -> None:
    images = np.zeros((5, 30, 40, 3), np.uint16)
    images[:, 5:25, 10:30] = np.arange(1, 6, dtype=np.uint16)[:, None, None, None] * 10000
    img = pictures.inputs_picture(images, np.ones((30, 40), bool), count=3)
    assert img.shape[1] == 4 * 240  # max of all + images 1, 3, 5
    # each panel is scaled by the maximum image: the brightest input is white, the first
    # (a fifth of it) dark grey: (1/5) ** (1 / 2.2) = 0.48
    row = img[img.shape[0] // 2 + 15]
    centres = [row[k * 240 + 120] for k in range(4)]
    assert centres[0].min() >= 250 and centres[3].min() >= 250
    assert centres[1] == pytest.approx([123, 123, 123], abs=3)
    single = pictures.inputs_picture(images[:1], None)
    assert single.shape[1] == 2 * 240  # max of all and the one image


def test_bitmap_font_fallback_still_draws(monkeypatch: pytest.MonkeyPatch) -> None:
    """Without FreeType (or with Pillow 10.0) load_default takes no size: the fixed bitmap font
    is used and the pictures still draw."""
    from PIL import ImageFont

    # Pillow >= 10.1's load_default() is itself FreeType where FreeType is there: the bitmap
    # font a Pillow without FreeType gives is load_default_imagefont()
    real = getattr(ImageFont, "load_default_imagefont", ImageFont.load_default)

    def no_sizes(size: float | None = None) -> object:
        if size is not None:
            raise TypeError("load_default() got an unexpected keyword argument 'size'")
        return real()

    monkeypatch.setattr(ImageFont, "load_default", no_sizes)
    pictures._font.cache_clear()
    try:
        assert not isinstance(pictures._font(14), ImageFont.FreeTypeFont)
        mask = _disc()
        _is_picture(pictures.error_picture(np.where(mask, 3.0, 0.0), mask))
        _is_picture(pictures.normals_picture(np.dstack([mask * 0.0] * 2 + [mask * 1.0]), mask))
        ramp = np.where(mask, np.linspace(-0.3, 0.3, mask.shape[1])[None, :], np.nan)
        _is_picture(pictures.curvature_picture(ramp, mask))  # negative tick labels
    finally:
        pictures._font.cache_clear()


def test_the_scalable_font_has_the_signs_the_titles_use() -> None:
    from PIL import features

    if not features.check("freetype2"):
        pytest.skip("Pillow without FreeType: the bitmap font is used")
    font = pictures._font(14)
    missing = bytes(font.getmask("\ue000"))  # a private-use code point: the missing glyph
    assert bytes(font.getmask("°")) != missing  # the error picture's title and tick units


def test_hill_shading_lights_the_upper_left() -> None:
    yy, xx = np.mgrid[0:41, 0:41].astype(np.float64)
    dome = np.sqrt(np.clip(30.0**2 - (yy - 20) ** 2 - (xx - 20) ** 2, 0, None))
    shade = pictures._hill_shade(dome, 1.0, 1.0)
    assert shade[20, 20] == pytest.approx(0.5, abs=1e-6)  # level: the colour is kept
    assert shade[8, 8] > 0.6 and shade[32, 32] < 0.4  # facing the light / away from it
    assert shade[8, 32] == pytest.approx(shade[32, 8], abs=1e-6)  # across the light: alike
    assert np.allclose(pictures._hill_shade(np.full((5, 5), 7.0), 2.0, 2.0), 0.5)
