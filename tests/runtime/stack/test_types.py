"""Stack.validate on integer stacks: the checks that matter for them, exact and cheap."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from _runtime_helpers import sphere_stack

from msfnet.common.errors import InputError
from msfnet.runtime.api import Model
from msfnet.runtime.stack import Stack, as_held, held_dtype, load_stack, save_stack


def _int_stack(dtype: type, scale: float = 1.0) -> Stack:
    ref = sphere_stack(n=5)
    top = np.iinfo(dtype).max
    images = np.clip(np.rint(ref.images * np.float32(scale)), 0, top).astype(dtype)
    return replace(ref, images=images)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_integer_stacks_validate(dtype: type) -> None:
    scale = 255 / 65535 if dtype == np.uint8 else 1.0
    stack = _int_stack(dtype, scale)
    assert stack.validate() is stack and stack.images.dtype == dtype


def _nearly_full(stack: Stack) -> Stack:
    """Every pixel at 65535 but one inside the mask (all of them: refused as saturated)."""
    images = np.full_like(stack.images, 65535)
    r, c = np.argwhere(stack.mask)[0]
    images[0, r, c] = 1000
    return replace(stack, images=images)


def test_signal_range_uses_the_integer_maximum_without_overflow() -> None:
    """Pixels at 65535: the peak is read in uint16 (a max cannot overflow) and the ratio to
    the intensity is taken in float64."""
    stack = _int_stack(np.uint16)
    full = _nearly_full(stack)
    full.validate()
    tiny = np.full_like(stack.intensities, 65535 / 2e15)  # brightest / intensity = 2e15
    with pytest.raises(InputError, match=r"brightest pixel / light intensity is 2e\+15"):
        replace(full, intensities=tiny).validate()
    dim = np.full_like(stack.intensities, 1e7)  # 65535 / 1e7 = 6.55e-3: inside the range
    replace(full, intensities=dim).validate()


def test_black_integer_stack_is_refused() -> None:
    stack = _int_stack(np.uint8)
    with pytest.raises(InputError, match="every image is black"):
        replace(stack, images=np.zeros_like(stack.images)).validate()


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_saturated_stack_is_refused(dtype: type) -> None:
    """Every pixel inside the mask at the white level: no shading, every normal a guess (it
    ran with exit 0: 53 deg with least squares on a DiLiGenT crop). Outside the mask may be
    anything; one pixel below full scale is enough to run."""
    stack = _int_stack(dtype)
    top = np.iinfo(dtype).max
    images = np.where(stack.mask[None, :, :, None], top, 0).astype(dtype)
    images = np.repeat(images, stack.num_lights, axis=0).repeat(3, axis=3)
    with pytest.raises(InputError, match=f"every image is saturated.*at {top}"):
        replace(stack, images=images).validate()
    r, c = np.argwhere(stack.mask)[0]
    images[2, r, c] = top - 1
    replace(stack, images=images).validate()


@pytest.mark.parametrize("full", [1.0, 255.0, 4095.0, 65535.0])
def test_saturated_float_stack_is_refused(full: float) -> None:
    """Float images carry no white level: one full-scale value everywhere (1.0, or an integer
    scale kept through --downscale or --srgb) is what a clipped stack becomes, and holds no
    shading either."""
    stack = sphere_stack(n=5)
    with pytest.raises(InputError, match=f"saturated inside the mask .*at {full:g}"):
        replace(stack, images=np.full_like(stack.images, full)).validate()
    srgb = np.float32(full) * np.float32(1.0000001)  # float32 rounding of a linearised clip
    with pytest.raises(InputError, match="saturated"):
        replace(stack, images=np.full_like(stack.images, srgb)).validate()


@pytest.mark.parametrize("value", [0.4, 0.7, 100.0, 1000.0])
def test_a_flat_float_stack_below_full_scale_is_no_saturated_one(value: float) -> None:
    """A flat, face-on part under a ring light (every image one value, 0.4 of full scale) was
    refused as "saturated ... lower the exposure"; its normals are (0, 0, 1)."""
    n = 8
    az = np.linspace(0, 2 * np.pi, n, endpoint=False)
    lights = np.stack([np.cos(az) * 0.6, np.sin(az) * 0.6, np.full(n, 0.8)], 1)
    images = np.full((n, 16, 16), value, np.float32)
    stack = Stack.from_arrays(images, lights)
    normals = Model.least_squares(maps=None)(stack).normals
    np.testing.assert_allclose(normals.reshape(-1, 3), [[0, 0, 1]] * 256, atol=1e-5)


def test_ragged_arrays_are_refused_as_such() -> None:
    """A list of images of different sizes raised numpy's own ValueError ("inhomogeneous
    shape"), where every other bad shape is an InputError."""
    stack = sphere_stack(n=5)
    images = [*stack.images[:2], stack.images[2][:10], *stack.images[3:]]
    with pytest.raises(InputError, match=r"images are ragged: .* the same shape"):
        Stack.from_arrays(images, stack.lights)
    with pytest.raises(InputError, match="light intensities are ragged"):
        Stack.from_arrays(stack.images, stack.lights, intensities=[[1, 1, 1], [1, 1]] * 3)


def test_lights_all_pointing_away_from_the_camera_are_refused() -> None:
    """A z-away light file (every z < 0) spans 3-D and passed every check, then gave normals
    55-90 deg off with exit 0."""
    stack = sphere_stack(n=6)
    away = stack.lights * np.array([1, 1, -1], np.float32)
    with pytest.raises(InputError, match="no light direction points toward the camera"):
        replace(stack, lights=away).validate()
    some = away.copy()
    some[0, 2] = 0.3  # one light in front is a (poor but) valid rig
    replace(stack, lights=some / np.linalg.norm(some, axis=1, keepdims=True)).validate()


def test_one_black_image_is_a_warning_naming_it(tmp_path: Path) -> None:
    """A dead light or a missed trigger: the stack still runs (the other lights may suffice),
    but the image is named; the rest of a good stack gives no warning."""
    stack = save_stack(sphere_stack(n=8), tmp_path / "s")
    assert load_stack(stack).warnings == []
    cv2.imwrite(str(stack / "005.png"), np.zeros((36, 44, 3), np.uint16))
    warnings = load_stack(stack).warnings
    assert len(warnings) == 1 and str(stack / "005.png") in warnings[0]
    assert "black" in warnings[0] and "\n" not in warnings[0]
    arrays = sphere_stack(n=8)
    arrays.images[2] *= 0.001  # from arrays: named by position
    assert "image 3" in Stack.from_arrays(arrays.images, arrays.lights).warnings[0]
    # a grazing light leaves most of the object dark: not a dead one
    dim = sphere_stack(n=8)
    dim.images[1] *= 0.05
    assert dim.validate().warnings == []


def test_held_types() -> None:
    assert held_dtype(np.uint8) == np.uint8 and held_dtype(np.uint16) == np.uint16
    for other in (
        np.float16,
        np.float32,
        np.float64,
        np.int8,
        np.int16,
        np.int32,
        np.uint32,
        np.bool_,
    ):
        assert held_dtype(other) == np.float32
    a = np.zeros((2, 2), np.uint16)
    assert as_held(a) is a  # no copy
    assert as_held(a.astype(np.float64)).dtype == np.float32


@pytest.mark.slow
def test_real_benchmarks_load_without_warnings(ball_dir: Path, psm_dir: Path) -> None:
    """The new checks (saturation, lights behind, black images) leave real data alone: every
    DiLiGenT object (bear without its 20 corrupted images) and every psmImages object."""
    diligent = ball_dir.parent
    for name in ("ballPNG", "bearPNG", "harvestPNG"):
        stack = load_stack(diligent / name, select="21-96" if name == "bearPNG" else None)
        assert stack.warnings == [], name
    for folder in sorted(p for p in psm_dir.iterdir() if p.is_dir()):
        stack = load_stack(folder, lights=psm_dir / "lights.txt")
        assert stack.warnings == [], folder.name


def test_repr_is_one_line_of_what_the_stack_is() -> None:
    """repr(Stack) printed every array: ~330 lines for a small stack (issue #49)."""
    text = repr(sphere_stack(n=8, h=36, w=44))
    assert "\n" not in text and len(text) < 200
    assert text == "Stack('sphere', 8 lights, 44x36, float32, mask_px=788, ground truth)"
    broken = Stack("x", np.zeros((4, 5)), np.zeros((1, 3)), np.ones((1, 3)), np.ones((4, 5), bool))
    assert repr(broken) == "Stack('x', not a valid stack)"  # repr runs in debuggers too


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32, np.float64])
def test_masked_extremes_agree_with_numpy_for_every_held_type(dtype) -> None:
    from msfnet.runtime.stack.types import _masked_extremes

    rng = np.random.default_rng(1)
    img = (rng.random((40, 50, 3)) * 200).astype(dtype)
    mask = rng.random((40, 50)) > 0.4
    fast = dtype in (np.uint8, np.uint16, np.float32)
    mask3 = np.repeat(mask, 3, axis=1).view(np.uint8) if fast else None
    inside = img[mask]
    want = (inside.max(), inside.min(), inside.mean(dtype=np.float64))
    assert _masked_extremes(img, mask, mask3) == pytest.approx(want, rel=1e-12, abs=1e-9)
