"""Pixel-registered maps: float32 TIFFs that round-trip, same-size views, gradients, local shape
and physical units."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from _runtime_helpers import sphere_stack

from msfnet.runtime.results.maps import MapOptions, registered, stack_maps, write_maps
from msfnet.runtime.results.maps.registered import (
    gradients,
    grey16_view,
    local_shape,
    local_trend,
    read_tiff,
    signed_view,
    write_tiff,
)


def _plane_normals(h: int, w: int, p: float, q: float) -> np.ndarray:
    """Normals of z = p * col + q * row (rows down; y up: dz/dy = -q)."""
    n = np.array([-p, q, 1.0]) / np.sqrt(1 + p * p + q * q)
    return np.broadcast_to(n, (h, w, 3)).astype(np.float32).copy()


def test_tiff_round_trip_is_exact(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    grey = rng.normal(size=(17, 23)).astype(np.float32)
    grey[3, 4] = np.nan
    rgb = rng.normal(size=(17, 23, 3)).astype(np.float32)
    write_tiff(tmp_path / "g.tif", grey, "test")
    write_tiff(tmp_path / "c.tif", rgb)
    back = read_tiff(tmp_path / "g.tif")
    assert back.dtype == np.float32 and back.shape == grey.shape
    assert np.array_equal(back, grey, equal_nan=True)
    assert np.array_equal(read_tiff(tmp_path / "c.tif"), rgb)
    # OpenCV reads the same floats (three samples in its BGR order)
    cv = cv2.imread(str(tmp_path / "c.tif"), cv2.IMREAD_UNCHANGED)
    assert cv.dtype == np.float32 and np.array_equal(cv[..., ::-1], rgb)


def test_gradients_of_a_plane() -> None:
    n = _plane_normals(8, 9, 0.3, -0.2)
    valid = np.ones((8, 9), bool)
    valid[0] = False
    p, q = gradients(n, valid)
    assert np.allclose(p[valid], 0.3, atol=1e-6) and np.allclose(q[valid], -0.2, atol=1e-6)
    assert np.isnan(p[0]).all() and np.isnan(q[0]).all()


def test_local_shape_ignores_tilt_and_bow_and_keeps_a_dent() -> None:
    h, w = 80, 100
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    trend = 0.08 * cols - 0.05 * rows + 0.002 * (cols - 50) ** 2 + 0.001 * (rows - 40) ** 2
    r = np.hypot(rows - 40, cols - 30)
    dent = -0.5 * np.where(r < 4, 0.5 * (1 + np.cos(np.pi * r / 4)), 0.0)
    valid = np.ones((h, w), bool)
    valid[:, 90:] = False  # a mask edge: the trend must follow the tilt up to it
    local = local_shape(trend + dent, valid, 12.0)
    away = valid & (r > 20)  # beyond the dent's pull on the trend
    assert np.nanmax(np.abs(local[away])) < 0.01  # px: tilt and bow gone, edges included
    assert local[40, 30] == pytest.approx(-0.5, abs=0.08)
    assert np.isnan(local[~valid]).all()


def _weighted_quadric_at_each_pixel(z: np.ndarray, valid: np.ndarray, sigma: float) -> np.ndarray:
    """The trend by definition: a weighted least-squares quadric per pixel, untruncated."""
    rows, cols = np.nonzero(valid)
    out = np.full(z.shape, np.nan)
    for r, c in zip(rows, cols, strict=True):
        u, v = (cols - c) / sigma, (rows - r) / sigma
        root_w = np.exp(-0.25 * (u * u + v * v))
        basis = np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], axis=1)
        coef = np.linalg.lstsq(basis * root_w[:, None], z[valid] * root_w, rcond=None)[0]
        out[r, c] = coef[0]
    return out


@pytest.mark.parametrize("sigma", [1.5, 4.0, 12.0, 200.0])
def test_local_trend_is_the_weighted_quadric_fit(sigma: float) -> None:
    # sigma 12 and 200 take the FFT path (kernel radius above TREND_FFT_RADIUS), 1.5 and 4 not
    h, w = 40, 48
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    z = 50 + 0.01 * (cols - 20) ** 2 + 0.3 * np.sin(cols / 2.5) + 0.2 * np.cos(rows / 3)
    valid = np.hypot(rows - 21, cols - 26) < 17
    valid[20:23, 12:40] = False  # a slot through the part
    expected = _weighted_quadric_at_each_pixel(z, valid, sigma)
    got = local_trend(z.astype(np.float32), valid, sigma)
    assert np.isnan(got[~valid]).all()
    # the kernel ends at 4 sigma: weights below exp(-8) of the centre's are left out
    assert np.max(np.abs(got[valid] - expected[valid])) < 2e-3


def test_the_fft_and_the_direct_filters_agree(monkeypatch: pytest.MonkeyPatch) -> None:
    # odd, thin and wide boxes: the FFT's padding must keep the circular wrap out
    rng = np.random.default_rng(0)
    for _ in range(12):
        h, w = (int(n) for n in rng.integers(1, 70, 2))
        z = (10 * rng.normal(size=(h, w))).astype(np.float32)
        valid = rng.random((h, w)) > 0.3
        sigma = float(rng.uniform(0.7, 40))
        monkeypatch.setattr(registered, "TREND_FFT_RADIUS", 10**9)
        direct = local_trend(z, valid, sigma)
        monkeypatch.setattr(registered, "TREND_FFT_RADIUS", -1)
        by_fft = local_trend(z, valid, sigma)
        np.testing.assert_allclose(by_fft[valid], direct[valid], rtol=0, atol=1e-4)


@pytest.mark.parametrize("shape", [(30, 2000), (2000, 30)])
def test_a_thin_strip_with_a_wide_size_stays_small(shape: tuple[int, int]) -> None:
    # each axis's kernel ends at the map's extent along it: one radius for both padded the
    # short axis to the long one (a 30 x 2000 strip at size 2000 took ~0.5 GB)
    import tracemalloc

    z = np.random.default_rng(0).normal(size=shape).astype(np.float32)
    tracemalloc.start()
    try:
        out = local_trend(z, np.ones(shape, bool), 2000.0)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert np.isfinite(out).all()
    assert peak < 100 * 2**20  # measured 53 MB (30 x 2000) and 39 MB (2000 x 30)


def test_heights_and_mask_of_other_shapes_are_refused() -> None:
    with pytest.raises(ValueError, match="expected one"):
        local_trend(np.zeros((4, 5), np.float32), np.ones((5, 4), bool), 2.0)


def test_local_trend_uses_only_the_masks_box() -> None:
    # the same part anywhere in a larger image gives the same trend
    rng = np.random.default_rng(3)
    z = rng.normal(size=(30, 30)).astype(np.float32)
    valid = rng.random((30, 30)) > 0.2
    alone = local_trend(z, valid, 6.0)
    big = np.full((90, 120), 7.0, np.float32)
    big_valid = np.zeros((90, 120), bool)
    big[50:80, 20:50], big_valid[50:80, 20:50] = z, valid
    placed = local_trend(big, big_valid, 6.0)
    np.testing.assert_allclose(placed[50:80, 20:50][valid], alone[valid], atol=1e-5)
    assert np.isnan(placed[~big_valid]).all()


def test_views_have_the_input_size() -> None:
    values = np.linspace(-1, 2, 30, dtype=np.float32).reshape(5, 6)
    valid = np.ones((5, 6), bool)
    valid[0, 0] = False
    g = grey16_view(values, valid)
    assert g.dtype == np.uint16 and g.shape == (5, 6) and g[0, 0] == 0
    assert g[valid].min() == 1 and g[valid].max() == 65535
    rgb, top = signed_view(values, valid)
    assert rgb.dtype == np.uint8 and rgb.shape == (5, 6, 3) and top > 0
    assert tuple(rgb[-1, -1]) == (255, 0, 0)  # the largest positive value: red


def test_write_maps_registered_files_and_units(tmp_path: Path) -> None:
    stack = sphere_stack(n=8, h=36, w=44)
    opts = MapOptions(maps=("albedo", "height", "curvature"), pixel_size_mm=0.05)
    maps = stack_maps(stack, stack.normals_gt, opts)
    write_maps(tmp_path, maps, report=False)
    h, w = stack.shape
    for name in ("height", "local_shape", "curvature", "gaussian_curvature", "gradient_p"):
        data = read_tiff(tmp_path / f"{name}.tif")
        assert data.shape == (h, w) and data.dtype == np.float32
        assert np.array_equal(np.isfinite(data), stack.mask)
    assert not (tmp_path / "normals.tif").exists()  # normals.npy holds them: no second copy
    # physical units: heights x pixel size, curvature / pixel size
    height = read_tiff(tmp_path / "height.tif")
    m = stack.mask
    assert np.allclose(height[m], maps.height[m] * 0.05, rtol=1e-6)
    curv = read_tiff(tmp_path / "curvature.tif")
    assert np.allclose(curv[m], maps.curvature[m] / 0.05, rtol=1e-5)
    units = json.loads((tmp_path / "maps.json").read_text())["registered"]
    assert units["height"] == "mm" and units["curvature"] == "1/mm"
    # the viewing PNGs are registered too: the input's size, not a figure's
    for name, dtype, shape in (
        ("height.png", np.uint16, (h, w)),
        ("curvature.png", np.uint8, (h, w, 3)),
        ("local_shape.png", np.uint8, (h, w, 3)),
    ):
        img = cv2.imread(str(tmp_path / name), cv2.IMREAD_UNCHANGED)
        assert img.dtype == dtype and img.shape == shape


def test_map_options_refuse_bad_numbers() -> None:
    from msfnet.common.errors import InputError

    for bad in ({"pixel_size_mm": float("nan")}, {"local_size_px": 0.0}, {"curvature_sigma": -1}):
        with pytest.raises(InputError, match="must be a positive number"):
            MapOptions(**bad)  # type: ignore[arg-type]


def test_the_trend_weights_kept_for_a_mask_give_what_a_fresh_fit_gives() -> None:
    """A station's parts share a mask: the second trend reuses the first's weights, exactly;
    another mask of the same shape gets its own."""
    from msfnet.runtime.results.maps import registered

    rng = np.random.default_rng(3)
    valid = np.ones((80, 90), bool)
    valid[60:] = False
    other = valid.copy()
    other[:, :5] = False
    z1, z2 = rng.normal(size=(2, 80, 90)).cumsum(axis=2)

    def fresh(z: np.ndarray, mask: np.ndarray) -> np.ndarray:
        registered._TrendCache.mask = None
        return registered.local_trend(z, mask, 6.0)

    first, second = fresh(z1, valid), registered.local_trend(z2, valid, 6.0)
    assert registered._TrendCache.mask is not None  # kept, and used for z2
    np.testing.assert_array_equal(second, fresh(z2, valid))
    np.testing.assert_array_equal(first, fresh(z1, valid))
    moved = registered.local_trend(z2, other, 6.0)
    np.testing.assert_array_equal(moved, fresh(z2, other))
    assert np.isnan(moved[:, :5]).all()
