"""The network's normalisation (the core contract with the exported model), tested directly."""

from __future__ import annotations

import numpy as np

from msfnet.runtime.contract import TRAIN_LIGHTS
from msfnet.runtime.infer.normalise import normalise


def test_normalise_follows_the_four_steps(rng: np.random.Generator) -> None:
    n, h, w = 7, 5, 6
    images = rng.uniform(0, 1000, (n, h, w, 3)).astype(np.float32)
    ints = rng.uniform(0.5, 2.0, (n, 3)).astype(np.float32)
    mask = rng.random((h, w)) > 0.3
    x = normalise(images, ints, mask, TRAIN_LIGHTS)
    assert x.shape == (n, 3, h, w) and x.dtype == np.float32
    # by hand, in float64: divide by intensity, L2 over lights, sqrt(N / 32), mask
    ref = images.astype(np.float64) / ints[:, None, None, :]
    ref /= np.sqrt((ref**2).sum(axis=0, keepdims=True)) + 1e-10
    ref *= np.sqrt(n / TRAIN_LIGHTS) * mask[None, :, :, None]
    np.testing.assert_allclose(x, ref.transpose(0, 3, 1, 2), rtol=2e-6, atol=1e-7)
    # per pixel and channel the N values have norm sqrt(N / 32) inside the mask, 0 outside
    norms = np.linalg.norm(x, axis=0)  # (3, H, W)
    np.testing.assert_allclose(norms[:, mask], np.sqrt(n / 32), rtol=1e-5)
    assert np.all(norms[:, ~mask] == 0)


def test_normalise_is_per_pixel_so_tiles_equal_crops(rng: np.random.Generator) -> None:
    images = rng.uniform(0, 1, (4, 12, 10, 3)).astype(np.float32)
    ints = np.ones((4, 3), np.float32)
    mask = np.ones((12, 10), bool)
    whole = normalise(images, ints, mask)
    tile = normalise(images[:, 3:9, 2:7], ints, mask[3:9, 2:7])
    np.testing.assert_array_equal(tile, whole[:, :, 3:9, 2:7])


def test_normalise_is_invariant_to_exposure_and_light_brightness(rng: np.random.Generator) -> None:
    images = rng.uniform(1, 100, (5, 4, 4, 3)).astype(np.float32)
    ints = rng.uniform(0.5, 2.0, (5, 3)).astype(np.float32)
    mask = np.ones((4, 4), bool)
    base = normalise(images, ints, mask)
    # a brighter exposure of the whole stack changes nothing; so does a light that is 3x
    # brighter when its intensity says so
    np.testing.assert_allclose(normalise(images * 7, ints, mask), base, rtol=1e-5)
    brighter, ints3 = images.copy(), ints.copy()
    brighter[2] *= 3
    ints3[2] *= 3
    np.testing.assert_allclose(normalise(brighter, ints3, mask), base, rtol=1e-5)


def test_integer_tiles_give_the_float32_input_bit_for_bit(rng: np.random.Generator) -> None:
    """A stack held as uint8/uint16 is cast per tile: the same network input as its float32
    copy, even at full scale over 96 lights, where uint16 squares summed would overflow."""
    ints = rng.uniform(0.5, 2.0, (96, 3)).astype(np.float32)
    mask = rng.random((6, 7)) > 0.2
    mask[0, 0] = True
    for dtype in (np.uint8, np.uint16):
        top = np.iinfo(dtype).max
        images = rng.integers(0, top + 1, (96, 6, 7, 3)).astype(dtype)
        images[:, 0, 0] = top  # 96 x 65535^2 = 4e11: beyond even uint32
        x = normalise(images, ints, mask)
        assert x.dtype == np.float32 and np.isfinite(x).all()
        np.testing.assert_array_equal(x, normalise(images.astype(np.float32), ints, mask))
        np.testing.assert_allclose(
            np.linalg.norm(x[:, :, 0, 0], axis=0), np.sqrt(96 / 32), rtol=1e-5
        )


def test_network_input_is_the_crop_of_the_normalised_stack_padded_with_zeros() -> None:
    """One function assembles a crop's network input (runtime tiles, int8 calibration, bench
    workloads, export checks): the crop of the normalised images, zero-padded, unit lights."""
    from _runtime_helpers import sphere_stack

    from msfnet.runtime.infer.normalise import network_input, network_lights

    stack = sphere_stack(n=7, h=30, w=26, seed=4)
    full = normalise(stack.images, stack.intensities, stack.mask)
    rows, cols = slice(20, 30), slice(5, 26)
    x, lights = network_input(stack, rows, cols, shape=(12, 24))
    assert x.shape == (1, 7, 3, 12, 24) and lights.shape == (1, 7, 3)
    np.testing.assert_array_equal(x[0, :, :, :10, :21], full[:, :, rows, cols])
    assert not x[0, :, :, 10:].any() and not x[0, :, :, :, 21:].any()
    np.testing.assert_array_equal(lights[0], network_lights(stack.lights))
    pick = [0, 3, 6]
    sub, sub_lights = network_input(stack, lights=pick, train_lights=16)
    np.testing.assert_array_equal(
        sub[0], normalise(stack.images[pick], stack.intensities[pick], stack.mask, 16)
    )
    np.testing.assert_array_equal(sub_lights[0], network_lights(stack.lights[pick]))
