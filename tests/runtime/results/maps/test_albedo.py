"""Albedo: exact on a rendered Lambertian object, robust to shadows and clipped highlights;
clipped means at the image's full scale, and an albedo with no observation is NaN."""

from __future__ import annotations

import numpy as np
import pytest

from msfnet.common.errors import InputError
from msfnet.runtime.results.maps.albedo import checked_albedo, default_saturation
from msfnet.runtime.results.maps.validate import check_normals


def albedo_map(images, lights, intensities, mask, normals, **options) -> np.ndarray:
    """The albedo of normals over a mask, as the maps compute it."""
    unit, valid = check_normals(normals, mask)
    return checked_albedo(np.asarray(images), lights, intensities, valid, unit, **options)


def _render(surfaces, n_lights: int = 12, seed: int = 3, full_scale: float = 40000.0):
    """A textured Lambertian sphere cap under coloured lights from the upper hemisphere,
    some of them low enough to leave part of the object in attached shadow."""
    rng = np.random.default_rng(seed)
    _, mask, normals = surfaces["sphere_cap"](h=40, w=44, radius=22.0, cap=19.0)
    lights = rng.normal(size=(n_lights, 3))
    lights[:, 2] = np.abs(lights[:, 2]) + 0.3
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    ints = rng.uniform(0.4, 1.6, size=(n_lights, 3))
    albedo = rng.uniform(0.15, 0.95, size=(*mask.shape, 3))
    albedo[~mask] = 0
    shading = np.clip(np.einsum("hwc,nc->nhw", normals, lights), 0, None)
    images = full_scale * albedo[None] * ints[:, None, None, :] * shading[..., None]
    return images.astype(np.float32), lights, ints, mask, normals, full_scale * albedo


def test_lambertian_albedo_within_one_percent(surfaces) -> None:
    images, lights, ints, mask, normals, truth = _render(surfaces)
    est = albedo_map(images, lights, ints, mask, normals)
    assert est.shape == truth.shape and est.dtype == np.float32
    rel = np.abs(est[mask] / truth[mask] - 1)
    assert rel.max() < 0.01, f"worst pixel {100 * rel.max():.3f} %"
    assert np.isnan(est[~mask]).all()  # unknown outside the mask, not black


@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_clipped_highlights_are_left_out(surfaces, dtype: type) -> None:
    """A 16-bit sensor saturates at 65535, a float one (as a camera SDK writes it) at 1.0:
    those observations are dropped by default, whatever the stack's maximum."""
    images, lights, ints, mask, normals, truth = _render(surfaces)
    full = 65535.0 if dtype == np.uint16 else 1.0
    gain = full / np.percentile(images[:, mask], 97)  # 3 % of the object's values clip
    clipped = np.minimum(images * gain, full)
    if dtype == np.uint16:
        clipped = np.floor(clipped)  # no rounding up to full scale below it
    clipped = clipped.astype(dtype)
    truth = truth * gain
    naive = albedo_map(clipped, lights, ints, mask, normals, saturation=np.inf)
    robust = albedo_map(clipped, lights, ints, mask, normals)  # default: the full scale
    worst_naive = np.abs(naive[mask] / truth[mask] - 1).max()
    worst = np.abs(robust[mask] / truth[mask] - 1).max()
    assert worst_naive > 0.02, "the test needs clipping that biases the plain fit"
    assert worst < 0.01


def test_default_saturation_is_the_full_scale() -> None:
    """Integer images: the type's full scale (the robust fit's rule); float images: their
    maximum only when that is a full scale (1.0, 255, 65535), else nothing is clipped. Never
    a fraction of the maximum (99 % of it dropped an evenly lit part's every observation)."""
    assert default_saturation(np.full((2, 3, 3, 3), 200, np.uint8)) == 255.0
    assert default_saturation(np.full((2, 3, 3, 3), 9000, np.uint16)) == 65535.0
    assert default_saturation(np.full((2, 3, 3, 3), 0.49, np.float32)) == np.inf
    for top in (1.0, 255.0, 65535.0):  # clipped floats: a float camera, 8 / 16-bit downscaled
        images = np.zeros((2, 3, 3, 3), np.float32)
        images[0, 0, 0] = top
        assert default_saturation(images) == top


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_an_evenly_lit_flat_keeps_its_albedo(dtype: type) -> None:
    """A flat part facing the camera under a ring of lights reads one value, the stack's
    largest, in every image: every observation is kept (was: all dropped, albedo 0)."""
    n, h, w = 12, 8, 9
    az = 2 * np.pi * np.arange(n) / n
    el = np.radians(45.0)
    lights = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.full(n, np.sin(el))], 1)
    normals = np.zeros((h, w, 3))
    normals[..., 2] = 1.0
    mask = np.ones((h, w), bool)
    value = {np.uint8: 200, np.uint16: 50000, np.float32: 0.49}[dtype]
    images = np.full((n, h, w, 3), value, dtype)
    est = albedo_map(images, lights, np.ones((n, 3)), mask, normals)
    np.testing.assert_allclose(est, float(value) / np.sin(el), rtol=1e-5)
    # at full scale every observation is clipped: the albedo is unknown, NaN, not 0
    top = {np.uint8: 255, np.uint16: 65535, np.float32: 1.0}[dtype]
    est = albedo_map(np.full_like(images, top), lights, np.ones((n, 3)), mask, normals)
    assert np.isnan(est).all()


def test_dark_lights_are_left_out(surfaces) -> None:
    """With shading below min_shading dropped, a pixel lit by no kept light gets NaN."""
    images, lights, ints, mask, normals, _ = _render(surfaces)
    est = albedo_map(images, lights, ints, mask, normals, min_shading=1.1)  # cos never > 1.1
    assert np.isnan(est).all()


def test_albedo_bad_input(surfaces) -> None:
    images, lights, ints, mask, normals, _ = _render(surfaces, n_lights=4)
    with pytest.raises(InputError, match="lights and intensities"):
        albedo_map(images, lights[:3], ints, mask, normals)
    with pytest.raises(InputError, match="N x H x W x 3"):
        albedo_map(images[..., 0], lights, ints, mask, normals)
    with pytest.raises(InputError, match="normals are"):
        albedo_map(images, lights, ints, mask[:-1, :-1], normals[:-1, :-1])
    bad = normals.copy()
    bad[mask.nonzero()[0][0], mask.nonzero()[1][0]] = np.nan
    with pytest.raises(InputError, match="NaN"):
        albedo_map(images, lights, ints, mask, bad)
    empty = albedo_map(images, lights, ints, np.zeros_like(mask), normals)
    assert np.isnan(empty).all()


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_integer_images_give_the_float32_albedo(surfaces, dtype: type) -> None:
    """Each chunk of an integer stack is cast to float64 before any arithmetic, and the default
    clipping level is its full scale, which these values stay below: the float32 copy's
    albedo exactly."""
    images, lights, ints, mask, normals, _ = _render(
        surfaces, full_scale=200.0 if dtype == np.uint8 else 40000.0
    )
    held = np.rint(images).astype(dtype)
    est = albedo_map(held, lights, ints, mask, normals)
    np.testing.assert_array_equal(
        est, albedo_map(held.astype(np.float32), lights, ints, mask, normals)
    )
    assert est[mask].min() > 0
