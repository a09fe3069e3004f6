"""Albedo: exact on a rendered Lambertian object, robust to shadows and clipped highlights."""

from __future__ import annotations

import numpy as np
import pytest

from msfnet.common.errors import InputError
from msfnet.runtime.results.maps.albedo import albedo_map


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
    assert np.all(est[~mask] == 0)


def test_clipped_highlights_are_left_out(surfaces) -> None:
    images, lights, ints, mask, normals, truth = _render(surfaces)
    level = np.percentile(images[:, mask], 97)
    clipped = np.minimum(images, level)  # a sensor that saturates at `level`
    naive = albedo_map(clipped, lights, ints, mask, normals, saturation=np.inf)
    robust = albedo_map(clipped, lights, ints, mask, normals)  # default: 99 % of the maximum
    worst_naive = np.abs(naive[mask] / truth[mask] - 1).max()
    worst = np.abs(robust[mask] / truth[mask] - 1).max()
    assert worst_naive > 0.02, "the test needs clipping that biases the plain fit"
    assert worst < 0.01


def test_dark_lights_are_left_out(surfaces) -> None:
    """With shading below min_shading dropped, a pixel lit by no kept light gets 0."""
    images, lights, ints, mask, normals, _ = _render(surfaces)
    est = albedo_map(images, lights, ints, mask, normals, min_shading=1.1)  # cos never > 1.1
    assert np.all(est == 0)


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
    assert not empty.any()


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_integer_images_give_the_float32_albedo(surfaces, dtype: type) -> None:
    """Each chunk of an integer stack is cast to float64 before any arithmetic, and the default
    clipping level comes from its maximum as stored: the float32 copy's albedo exactly."""
    images, lights, ints, mask, normals, _ = _render(
        surfaces, full_scale=200.0 if dtype == np.uint8 else 40000.0
    )
    held = np.rint(images).astype(dtype)
    est = albedo_map(held, lights, ints, mask, normals)
    np.testing.assert_array_equal(
        est, albedo_map(held.astype(np.float32), lights, ints, mask, normals)
    )
    assert est[mask].min() > 0
