"""Real-camera inputs: linearisation, auto-mask, ROI and downscale against known answers."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from _runtime_helpers import sphere_stack

from msfnet.common.errors import InputError
from msfnet.runtime.api import Model
from msfnet.runtime.stack import (
    LoadOptions,
    Stack,
    load_stack,
    parse_roi,
    prepare_stack,
    save_stack,
)
from msfnet.runtime.stack.transforms import (
    Transforms,
    area_downscale,
    auto_mask,
    srgb_to_linear,
)
from msfnet.synth import RenderOptions, render_stack


def _srgb_encode(lin: np.ndarray) -> np.ndarray:
    """The inverse of the sRGB EOTF (what a camera's JPEG/PNG output applies)."""
    return np.where(lin <= 0.0031308, lin * 12.92, 1.055 * np.power(lin, 1 / 2.4) - 0.055)


def _saved(stack: Stack, folder: Path, bit_depth: int = 16) -> Path:
    return save_stack(stack, folder, bit_depth=bit_depth)


def test_srgb_formula_round_trips() -> None:
    v = np.linspace(0, 1, 1001)
    np.testing.assert_allclose(srgb_to_linear(_srgb_encode(v).astype(np.float32)), v, atol=2e-6)


def test_srgb_8bit_render_linearised_gives_the_linear_render(tmp_path: Path) -> None:
    lin_stack = sphere_stack(n=6, h=40, w=48)
    lin = lin_stack.images / 65535.0  # linear radiance, 0..~0.75 of full scale
    encoded = np.rint(_srgb_encode(lin) * 255.0)
    folder = _saved(
        replace(lin_stack, images=encoded.astype(np.float32)), tmp_path / "s", bit_depth=8
    )
    got = load_stack(folder, srgb=True).images / 255.0
    # 8-bit quantisation: half a step of 1/255 times the EOTF's largest slope (2.28 at 1.0)
    err = np.abs(got - lin).max()
    assert err < 0.5 / 255 * 2.3, err
    raw = load_stack(folder).images / 255.0  # not linearised: far off (the test can fail)
    assert np.abs(raw - lin).max() > 0.1


def test_gamma_16bit_render_linearised_gives_the_linear_render(tmp_path: Path) -> None:
    lin_stack = sphere_stack(n=6, h=40, w=48)
    lin = lin_stack.images / 65535.0
    encoded = np.rint(np.power(lin, 1 / 2.2) * 65535.0)
    folder = _saved(replace(lin_stack, images=encoded.astype(np.float32)), tmp_path / "g")
    got = load_stack(folder, gamma=2.2).images / 65535.0
    assert np.abs(got - lin).max() < 0.5 / 65535 * 2.2 * 1.01
    # ...and least squares on it recovers the sphere as from the linear render
    l2 = Model.least_squares()(load_stack(folder, gamma=2.2))
    assert l2.metrics is not None and l2.metrics.median_deg < 0.05
    wrong = Model.least_squares()(load_stack(folder))
    assert wrong.metrics is not None and wrong.metrics.median_deg > 2


def _object_on_dark_backdrop(folder: Path) -> tuple[Path, np.ndarray]:
    """A rendered object on a dark noisy backdrop saved as 16-bit PNGs (mask.png all ones),
    and its true mask."""
    rng = np.random.default_rng(5)
    stack = render_stack(7, RenderOptions(size=96, lights=16, noise=False), shape="blob")
    # a dark, noisy, unevenly lit backdrop (0.2-0.6 % of full scale, where the object's
    # darkest peaks are ~1.5 %)
    h, w = stack.shape
    backdrop = (0.002 + 0.004 * np.linspace(0, 1, w)[None, :]) * 65535.0
    noise = rng.normal(0, 0.001 * 65535.0, stack.images.shape)
    images = np.where(
        stack.mask[None, :, :, None], stack.images, backdrop[None, :, :, None] + noise
    )
    images = np.clip(images, 0, 65535).astype(np.float32)
    return _saved(replace(stack, images=images, mask=np.ones((h, w), bool)), folder), stack.mask


def test_auto_mask_matches_a_rendered_object_on_a_dark_background(tmp_path: Path) -> None:
    folder, truth = _object_on_dark_backdrop(tmp_path / "o")
    got = load_stack(folder, auto_mask=True).mask
    iou = (got & truth).sum() / (got | truth).sum()
    print(f"auto-mask IoU {iou:.4f} ({truth.sum()} true px)")
    assert iou > 0.95
    # the folder's own mask.png (all ones here) is what a plain load reads
    assert load_stack(folder).mask.all()


def test_auto_mask_of_a_16bit_stack_equals_its_float32_copy(tmp_path: Path) -> None:
    folder, _ = _object_on_dark_backdrop(tmp_path / "o")
    held = load_stack(folder, auto_mask=True)
    assert held.images.dtype == np.uint16
    np.testing.assert_array_equal(auto_mask(held.images.astype(np.float32)), held.mask)
    np.testing.assert_array_equal(auto_mask(held.images), held.mask)


def test_transforms_keep_the_type_only_when_no_value_changes() -> None:
    rng = np.random.default_rng(0)
    img = rng.integers(0, 65536, (20, 24, 3)).astype(np.uint16)
    crop = Transforms(roi=(2, 3, 16, 12)).image(img)
    assert crop.dtype == np.uint16
    np.testing.assert_array_equal(crop, img[3:15, 2:18])
    for t in (Transforms(downscale=2), Transforms(gamma=2.2), Transforms(srgb=True)):
        out = t.image(img)
        assert out.dtype == np.float32
        white = Transforms(t.roi, t.downscale, t.srgb, t.gamma, 65535.0)
        np.testing.assert_array_equal(out, white.image(img.astype(np.float32)))
    assert Transforms().image(img.astype(np.float64)).dtype == np.float32


def test_roi_crops_images_mask_and_ground_truth_alike(tmp_path: Path) -> None:
    folder = _saved(sphere_stack(n=5, h=40, w=48), tmp_path / "r")
    full = load_stack(folder)
    x, y, w, h = roi = parse_roi("7,5,30,21")
    part = load_stack(folder, roi=roi)
    assert part.shape == (h, w)
    np.testing.assert_array_equal(part.images, full.images[:, y : y + h, x : x + w])
    np.testing.assert_array_equal(part.mask, full.mask[y : y + h, x : x + w])
    assert full.normals_gt is not None and part.normals_gt is not None
    np.testing.assert_array_equal(part.normals_gt, full.normals_gt[y : y + h, x : x + w])
    # ROI first, then the downscale: 30x21 -> 15x10 (the odd last row is dropped)
    both = load_stack(folder, roi=roi, downscale=2)
    assert both.shape == (10, 15)
    np.testing.assert_allclose(
        both.images[2], area_downscale(full.images[2, y : y + h, x : x + w], 2), rtol=1e-6
    )
    with pytest.raises(InputError, match="past the 48x40 image"):
        load_stack(folder, roi=(40, 0, 10, 10))


def _unshadowed_sphere(h: int, w: int, n: int = 12) -> Stack:
    """A Lambertian sphere whose masked part faces every light (slant < 55 deg, lights within
    30 deg of the view axis): least squares is exact on it, so any error left after a
    downscale comes from how images, mask and ground truth were reduced."""
    rng = np.random.default_rng(3)
    tilt, az = np.radians(rng.uniform(10, 30, n)), rng.uniform(0, 2 * np.pi, n)
    lights = np.stack([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)], 1)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    r = 0.45 * min(h, w)
    x, y = (xx - w / 2 + 0.5) / r, -(yy - h / 2 + 0.5) / r
    mask = x**2 + y**2 < np.sin(np.radians(55)) ** 2
    normals = np.dstack([x, y, np.sqrt(np.clip(1 - x**2 - y**2, 0, None))]) * mask[..., None]
    images = 50000.0 * np.clip(np.einsum("hwc,nc->nhw", normals, lights), 0, None)
    return Stack.from_arrays(
        np.repeat(images[..., None], 3, 3).astype(np.float32),
        lights,
        mask=mask,
        normals_gt=normals.astype(np.float32),
        name="sphere",
    )


def test_downscale_2_of_a_sphere_keeps_least_squares_accurate(tmp_path: Path) -> None:
    stack = _unshadowed_sphere(96, 112)
    folder = _saved(stack, tmp_path / "d")
    full = Model.least_squares()(load_stack(folder))
    small = load_stack(folder, downscale=2)
    assert small.shape == (48, 56)
    assert abs(small.mask.sum() * 4 - stack.mask.sum()) < 0.05 * stack.mask.sum()
    result = Model.least_squares()(small)
    assert full.metrics is not None and result.metrics is not None
    print(
        f"least squares MAE: full size {full.metrics.mae_deg:.4f} deg, downscaled 2x "
        f"{result.metrics.mae_deg:.4f} deg"
    )
    assert result.metrics.mae_deg < 1.0
    # the same images with the ground truth shifted by one block: the test can fail
    assert small.normals_gt is not None
    shifted = replace(small, normals_gt=np.roll(small.normals_gt, 1, axis=1))
    off = Model.least_squares()(shifted).metrics
    assert off is not None and off.mae_deg > 1.0


def test_in_memory_stack_gets_the_same_treatment(tmp_path: Path) -> None:
    stack = sphere_stack(n=6, h=40, w=48)
    stack = replace(stack, images=np.rint(stack.images))  # what a 16-bit save keeps
    opts = LoadOptions(roi=(4, 2, 40, 36), downscale=2, gamma=2.2, white_level=65535.0)
    from_disk = load_stack(_saved(stack, tmp_path / "m"), opts)
    in_memory = prepare_stack(stack, opts)
    np.testing.assert_allclose(in_memory.images, from_disk.images, rtol=1e-6)
    np.testing.assert_array_equal(in_memory.mask, from_disk.mask)
    assert stack.shape == (40, 48)  # the caller's stack is left alone


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (dict(srgb=True, gamma=2.2), "give one of them"),
        (dict(gamma=-1.0), "positive"),
        (dict(downscale=0), "positive integer"),
        (dict(auto_mask=True, mask=Path("m.png")), "choose one"),
    ],
)
def test_contradictory_options_are_refused(options: dict, message: str) -> None:
    with pytest.raises(InputError, match=message):
        LoadOptions(**options)


def test_roi_argument_type() -> None:
    assert parse_roi("1,2,3,4") == (1, 2, 3, 4)
    for bad in ("1,2,3", "a,b,c,d", "0,0,0,5", "-1,0,4,4"):
        with pytest.raises(argparse.ArgumentTypeError):
            parse_roi(bad)


def test_float_images_need_a_white_level_to_be_linearised() -> None:
    stack = sphere_stack(n=4, h=20, w=20)  # float values up to ~48000
    with pytest.raises(InputError, match=r"value \(white_level\) to linearise"):
        prepare_stack(stack, LoadOptions(srgb=True))
    out = prepare_stack(stack, LoadOptions(srgb=True, white_level=65535.0))
    assert out.images.max() < stack.images.max()  # the EOTF lowers every value below white
