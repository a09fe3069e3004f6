"""Robust least squares: plain least squares where every light fits, shadows and highlights
dropped where a few lights break the model, and a residual that says where even that fails."""

from __future__ import annotations

import numpy as np
import pytest
from _runtime_helpers import ring_lights

from msfnet.runtime.infer.least_squares import least_squares_normals
from msfnet.runtime.infer.robust_least_squares import robust_least_squares, tukey_fit
from msfnet.runtime.stack import Stack
from msfnet.runtime.stack.readers import unit_normals


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a, b = a.astype(np.float64), b.astype(np.float64)
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    return np.degrees(np.arctan2(cross, np.sum(a * b, axis=-1)))


def _normals(seed: int, h: int = 24, w: int = 32) -> np.ndarray:
    rng = np.random.default_rng(seed)
    n = rng.normal(0, 0.12, (h, w, 3)).astype(np.float32)
    n[..., 2] += 1.0
    return unit_normals(n)


def _stack(shading: np.ndarray, lights: np.ndarray) -> Stack:
    return Stack.from_arrays(np.repeat(shading[..., None], 3, axis=3).astype(np.float32), lights)


def test_equals_plain_least_squares_where_every_light_fits() -> None:
    n, lights = _normals(1), ring_lights()
    shading = np.einsum("hwc,nc->nhw", n, lights) * 0.6  # every light lit: no clamping
    assert shading.min() > 0
    stack = _stack(shading, lights)
    fit = robust_least_squares(stack)
    plain = least_squares_normals(stack)
    assert _angle(fit.normals, plain).max() < 1e-3
    assert _angle(fit.normals, n).max() < 1e-3
    assert fit.residual.max() < 1e-5


def test_highlight_and_cast_shadow_drop_out() -> None:
    n, lights = _normals(2), ring_lights()
    shading = np.einsum("hwc,nc->nhw", n, lights) * 0.5
    shading[3, :, :16] += 0.8  # a highlight under light 4 on the left half
    shading[7, 8:, :] = 0.0  # a cast shadow under light 8 on the lower rows
    stack = _stack(shading, lights)
    plain = _angle(least_squares_normals(stack), n)
    fit = robust_least_squares(stack)
    robust = _angle(fit.normals, n)
    assert plain[:, :16].mean() > 5.0 and plain[8:, 16:].mean() > 1.0  # the plain fit tilts
    assert robust.max() < 0.05  # the robust one drops the two bad lights
    assert fit.residual.max() < 1e-3


def test_residual_is_high_where_the_model_fails_and_one_on_black() -> None:
    rng = np.random.default_rng(3)
    grey = rng.uniform(0.0, 1.0, (12, 500))  # no normal explains these
    _, residual = tukey_fit(grey, ring_lights().astype(np.float64))
    assert np.median(residual) > 0.15
    n, lights = _normals(4, 8, 8), ring_lights()
    shading = np.einsum("hwc,nc->nhw", n, lights) * 0.5
    shading[:, 0, 0] = 0.0  # black under every light
    fit = robust_least_squares(_stack(shading, lights))
    assert fit.residual[0, 0] == 1.0 and not fit.normals[0, 0].any()
    assert fit.residual[1:, 1:].max() < 1e-5


def test_bands_give_the_same_fit_and_nothing_outside_the_mask(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import msfnet.runtime.infer.robust_least_squares as robust

    asked: list[int] = []

    def eight_rows(
        budget: float, stack: Stack, bytes_per_pixel_light: int, **counted: object
    ) -> int:
        asked.append(bytes_per_pixel_light)
        assert counted["output_bytes_per_pixel"] == 16  # normals and residual, whole image
        return 8

    n, lights = _normals(5, 64, 48), ring_lights()
    shading = np.einsum("hwc,nc->nhw", n, lights) * 0.5 + 0.02 * np.random.default_rng(5).random(
        (12, 64, 48)
    )
    mask = np.ones((64, 48), bool)
    mask[:, :6] = False
    stack = Stack.from_arrays(
        np.repeat(shading[..., None], 3, axis=3).astype(np.float32), lights, mask=mask
    )
    whole = robust_least_squares(stack)
    monkeypatch.setattr(robust, "rows_for_memory", eight_rows)
    banded = robust_least_squares(stack, max_memory_mb=500)  # 8 bands of 8 rows
    # the per-pixel part (the 3 x 3 systems) spread over the lights: 72 + ceil(400 / 12)
    assert asked == [robust.BYTES_PER_PIXEL_LIGHT + 34]
    assert np.allclose(whole.normals, banded.normals, atol=1e-6)
    assert np.allclose(whole.residual, banded.residual, atol=1e-6)
    assert not whole.normals[~mask].any() and not whole.residual[~mask].any()


def test_no_redundancy_is_no_trust() -> None:
    """Three lights fit any three values exactly: a residual of 0 would claim a perfect fit,
    so a pixel without a fourth usable observation gets residual 1."""
    n = _normals(6, 8, 8)
    lights = ring_lights(3)
    shading = np.einsum("hwc,nc->nhw", n, lights) * 0.5
    fit = robust_least_squares(_stack(shading, lights))
    assert np.all(fit.residual == 1.0)
    four = ring_lights(4)
    shading = np.einsum("hwc,nc->nhw", n, four) * 0.5
    fit = robust_least_squares(_stack(shading, four))
    assert fit.residual.max() < 1e-4  # exact data with one spare light: trusted


def test_clipped_observations_are_not_used() -> None:
    """uint8 pixels at 255 under some lights: the fit uses the others; a patch clipped under
    every light has no usable observation and no fit."""
    n, lights = _normals(7, 16, 16), ring_lights()
    shading = np.einsum("hwc,nc->nhw", n, lights) * 200.0
    shading[2, :, :8] = 255.0  # clipped under one light on the left half
    shading[:, 12:, 12:] = 255.0  # clipped under every light
    images = np.repeat(np.clip(np.round(shading), 0, 255)[..., None], 3, axis=3).astype(np.uint8)
    fit = robust_least_squares(Stack.from_arrays(images, lights))
    err = _angle(fit.normals, n)
    assert err[:12, :8].max() < 0.6  # only 8-bit rounding left
    assert np.all(fit.residual[12:, 12:] == 1.0) and not fit.normals[12:, 12:].any()


def test_attached_shadows_fit_the_clamped_model() -> None:
    """Normals tilted so that several ring lights are behind the surface (zero shading): the
    clamped model explains them, so the fit is exact and its residual small."""
    rng = np.random.default_rng(8)
    n = rng.normal(0, 0.08, (16, 16, 3)).astype(np.float32)
    n[..., 0] += 0.9
    n[..., 2] += 0.5
    n = unit_normals(n)
    lights = ring_lights(12, 60.0)
    shading = np.clip(np.einsum("hwc,nc->nhw", n, lights), 0, None) * 0.5
    assert (shading == 0).sum(axis=0).min() >= 2  # every pixel has attached shadows
    fit = robust_least_squares(_stack(shading, lights))
    assert _angle(fit.normals, n).max() < 0.05
    assert fit.residual.max() < 1e-3
    plain = _angle(least_squares_normals(_stack(shading, lights)), n)
    assert plain.mean() > 2.0  # what the unclamped plain fit makes of them


def test_plain_noise_stays_plain_least_squares_noise() -> None:
    """Gaussian noise, every light lit, no outlier: the robust fit's normals scatter as plain
    least squares' do (a weighted solve alone would add its weights' own noise: ~9 % more
    high-pass energy at 12 lights)."""
    from msfnet.runtime.evaluate.detail_ratio import highpass_energy

    rng = np.random.default_rng(9)
    lights = ring_lights()
    y, x = np.mgrid[0:96, 0:96]
    n = np.dstack([(x - 48) / 300, (y - 48) / 300, np.ones((96, 96))]).astype(np.float32)
    n = unit_normals(n)
    mask = np.ones((96, 96), bool)
    for noise in (0.005, 0.02):
        shading = np.einsum("hwc,nc->nhw", n, lights) * 0.6
        shading = shading + noise * rng.normal(size=shading.shape)
        stack = _stack(shading.astype(np.float32), lights)
        ratio = highpass_energy(robust_least_squares(stack).normals, mask) / highpass_energy(
            least_squares_normals(stack), mask
        )
        assert 0.97 < ratio < 1.05, (noise, ratio)


def test_split_among_cores_gives_the_serial_fit(monkeypatch: pytest.MonkeyPatch) -> None:
    import msfnet.runtime.infer.robust_least_squares as robust

    rng = np.random.default_rng(10)
    lights = ring_lights().astype(np.float64)
    grey = np.abs(rng.normal(0.5, 0.2, (12, 3 * robust.MIN_PIXELS_PER_WORKER)))
    usable = rng.random(grey.shape) > 0.05
    monkeypatch.setattr(robust, "usable_cores", lambda: 3)
    g, res = robust._fit_parallel(grey, lights, 0.01, usable)
    g1, res1 = robust.tukey_fit(grey, lights, 0.01, usable)
    # equal up to rounding: numpy's SIMD loops split the columns differently per worker (bitwise
    # equal with AVX-512 kernels; 2e-8 apart with AVX2 ones, the cpuid proxy's avx2 class)
    np.testing.assert_allclose(g, g1, rtol=0, atol=1e-6)
    np.testing.assert_allclose(res, res1, rtol=0, atol=1e-6)


@pytest.mark.parametrize("shadowed", [2, 3, 4])
def test_two_to_four_cast_shadowed_lights_of_twelve_drop_out(shadowed: int) -> None:
    """A boss beside the pixel hides ``shadowed`` neighbouring LEDs of a 12-LED ring (ambient
    only there): plain least squares tilts by 26-47 deg; the robust fit, started from each
    pixel's brighter observations, stays within 0.5 deg (measured 0.11 / 0.12 / 0.17 mean; from
    the plain solve it was 26-47 deg too)."""
    rng = np.random.default_rng(shadowed)
    n, lights = _normals(shadowed), ring_lights()
    shading = np.clip(np.einsum("hwc,nc->nhw", n, lights), 0, None) * 0.6
    first = rng.integers(0, len(lights), n.shape[:2])
    for k in range(shadowed):
        hidden = (first + k) % len(lights)
        np.put_along_axis(
            shading, hidden[None], np.take_along_axis(shading, hidden[None], 0) * 0.02, 0
        )
    shading += rng.normal(0, 1e-3, shading.shape)
    stack = _stack(shading.astype(np.float32), lights)
    assert _angle(least_squares_normals(stack), n).mean() > 10
    assert _angle(robust_least_squares(stack).normals, n).mean() < 0.5
