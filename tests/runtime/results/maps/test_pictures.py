"""Pictures: ranges, colour conventions, degenerate inputs; no global matplotlib state."""

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
    rgb, top = pictures.curvature_colors(curv, mask)
    assert top == pytest.approx(np.percentile(np.abs(curv[mask]), 99))
    row = rgb[20]
    flat, concave, convex = row[np.argmin(np.abs(curv[20]))], row[14], row[33]
    assert flat.min() > 0.9
    assert concave[2] > concave[0] + 0.2 and convex[0] > convex[2] + 0.2
    assert np.allclose(concave[::-1], convex, atol=0.25)  # RdBu is near mirror-symmetric
    png = pictures.png_bytes(curv_img)
    decoded = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)[..., ::-1]
    assert np.array_equal(decoded, curv_img)


def test_pictures_never_import_pyplot() -> None:
    """Drawing must not touch pyplot's global state (a fresh interpreter: other tests may have
    imported pyplot into this one)."""
    code = (
        "import sys, numpy as np\n"
        "from msfnet.runtime.results.maps import pictures\n"
        "m = np.ones((8, 8), bool)\n"
        "pictures.error_picture(np.zeros((8, 8)), m)\n"
        "assert 'matplotlib.pyplot' not in sys.modules\n"
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
