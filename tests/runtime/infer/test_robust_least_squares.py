"""Robust least squares: plain least squares where every light fits, shadows and highlights
dropped where a few lights break the model, and a residual that says where even that fails."""

from __future__ import annotations

import numpy as np
import pytest

from msfnet.runtime.infer.least_squares import least_squares_normals
from msfnet.runtime.infer.robust_least_squares import robust_least_squares, tukey_fit
from msfnet.runtime.stack import Stack
from msfnet.runtime.stack.readers import unit_normals


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a, b = a.astype(np.float64), b.astype(np.float64)
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    return np.degrees(np.arctan2(cross, np.sum(a * b, axis=-1)))


def _ring(n: int = 12, tilt_deg: float = 35.0) -> np.ndarray:
    k = np.arange(n)
    th = np.radians(tilt_deg)
    return np.stack(
        [
            np.sin(th) * np.cos(2 * np.pi * k / n),
            np.sin(th) * np.sin(2 * np.pi * k / n),
            np.full(n, np.cos(th)),
        ],
        axis=1,
    ).astype(np.float32)


def _normals(seed: int, h: int = 24, w: int = 32) -> np.ndarray:
    rng = np.random.default_rng(seed)
    n = rng.normal(0, 0.12, (h, w, 3)).astype(np.float32)
    n[..., 2] += 1.0
    return unit_normals(n)


def _stack(shading: np.ndarray, lights: np.ndarray) -> Stack:
    return Stack.from_arrays(np.repeat(shading[..., None], 3, axis=3).astype(np.float32), lights)


def test_equals_plain_least_squares_where_every_light_fits() -> None:
    n, lights = _normals(1), _ring()
    shading = np.einsum("hwc,nc->nhw", n, lights) * 0.6  # every light lit: no clamping
    assert shading.min() > 0
    stack = _stack(shading, lights)
    fit = robust_least_squares(stack)
    plain = least_squares_normals(stack)
    assert _angle(fit.normals, plain).max() < 1e-3
    assert _angle(fit.normals, n).max() < 1e-3
    assert fit.residual.max() < 1e-5


def test_highlight_and_cast_shadow_drop_out() -> None:
    n, lights = _normals(2), _ring()
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
    _, residual = tukey_fit(grey, _ring().astype(np.float64))
    assert np.median(residual) > 0.15
    n, lights = _normals(4, 8, 8), _ring()
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

    def eight_rows(budget: float, stack: Stack, bytes_per_pixel_light: int) -> int:
        asked.append(bytes_per_pixel_light)
        return 8

    n, lights = _normals(5, 64, 48), _ring()
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
    assert asked == [robust.BYTES_PER_PIXEL_LIGHT]
    assert np.allclose(whole.normals, banded.normals, atol=1e-6)
    assert np.allclose(whole.residual, banded.residual, atol=1e-6)
    assert not whole.normals[~mask].any() and not whole.residual[~mask].any()
