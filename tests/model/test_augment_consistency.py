"""The training augmentation (model.data.rotate_flip) against rendering the turned scene.

Rotating / mirroring a rendered sample (images, ground-truth normals, mask, lights) must give
what the renderer gives for the turned scene itself (height field, materials and rig turned).
The turn of directions is written out here independently of the code under test."""

from __future__ import annotations

import math
from dataclasses import fields

import numpy as np
import pytest

pytest.importorskip("torch", reason="needs torch: the [train] extra")

from msfnet.model.data import rotate_flip
from msfnet.synth.lights import rig_lights
from msfnet.synth.materials import ALL_KINDS, MaterialMap, material_map, shade
from msfnet.synth.render import cast_shadow_mask
from msfnet.synth.shapes import make_shape, normals_from_height

TURNS = [(k, flip) for flip in (False, True) for k in range(4)]


def _image(a: np.ndarray, k: int, flip: bool) -> np.ndarray:
    """Turn an (H, W, ...) field k quarter turns counter-clockwise on screen, then mirror."""
    a = np.rot90(a, k, axes=(0, 1))
    return np.ascontiguousarray(a[:, ::-1] if flip else a)


def _directions(v: np.ndarray, k: int, flip: bool) -> np.ndarray:
    """x right, y up: a counter-clockwise turn by k x 90 deg, then x -> -x."""
    c, s = round(math.cos(k * math.pi / 2)), round(math.sin(k * math.pi / 2))
    x, y = c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]
    return np.stack([-x if flip else x, y, v[..., 2]], axis=-1).astype(np.float32)


def _render(height, mask, mat, lights):
    normals = normals_from_height(height, mask).astype(np.float32)
    radiance = shade(normals, lights, mat) * cast_shadow_mask(height, mask, lights)[..., None]
    radiance[:, ~mask] = 0.0
    return radiance, normals


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(11)
    height, mask = make_shape("bumps", 32, rng)
    mat = material_map(32, rng, 3, ALL_KINDS)
    lights = rig_lights(6, rng)
    return height, mask, mat, lights


@pytest.mark.parametrize(("k", "flip"), TURNS)
def test_augmented_sample_is_the_rendered_turned_scene(scene, k: int, flip: bool) -> None:
    height, mask, mat, lights = scene
    images, normals = _render(height, mask, mat, lights)
    aug_images, aug_normals, aug_mask, aug_lights = rotate_flip(
        images, normals, mask, lights, k, flip
    )
    turned_mat = MaterialMap(
        **{
            f.name: None if getattr(mat, f.name) is None else _image(getattr(mat, f.name), k, flip)
            for f in fields(MaterialMap)
        }
    )
    turned_lights = _directions(lights, k, flip)
    ref_images, ref_normals = _render(
        _image(height, k, flip), _image(mask, k, flip), turned_mat, turned_lights
    )
    np.testing.assert_allclose(aug_lights, turned_lights, atol=1e-6)
    np.testing.assert_array_equal(aug_mask, _image(mask, k, flip))
    np.testing.assert_allclose(aug_normals, ref_normals, atol=1e-5)
    # Shading agrees to float rounding; the cast-shadow ray march rounds sample positions to
    # pixels, so a handful of pixels on shadow edges may flip (ties round the other way).
    close = np.isclose(aug_images, ref_images, rtol=1e-4, atol=1e-5).all(axis=-1)
    assert close.mean() > 0.995
    # Turned samples keep the image statistics (mean, share of dark pixels) of the original.
    assert abs(float(aug_images.mean()) - float(images.mean())) < 1e-6 * max(images.mean(), 1)
