"""Detail fusion: the pure function's limits, the Lambertian validity, and the default path on
the rendered plates (edge error, scratch contrast, glossy error)."""

from __future__ import annotations

import numpy as np
import pytest
from _runtime_helpers import ring_lights
from scipy import ndimage

from msfnet.common.errors import InputError
from msfnet.runtime.infer.detail_fusion import FusionOptions, fuse_detail, validity
from msfnet.runtime.infer.robust_least_squares import RobustFit, robust_least_squares
from msfnet.runtime.stack import Stack
from msfnet.runtime.stack.readers import unit_normals


def _field(seed: int, h: int = 40, w: int = 48) -> np.ndarray:
    rng = np.random.default_rng(seed)
    n = rng.normal(0, 0.15, (h, w, 3)).astype(np.float32)
    n[..., 2] += 1.0
    return unit_normals(n)


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Degrees between unit vectors, atan2 in float64 (arccos of a float32 dot product alone
    reads 0.03 deg for identical vectors)."""
    a, b = a.astype(np.float64), b.astype(np.float64)
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    return np.degrees(np.arctan2(cross, np.sum(a * b, axis=-1)))


def test_weights_zero_keep_the_network_and_one_take_least_squares() -> None:
    net, ls = _field(1), _field(2)
    mask = np.ones(net.shape[:2], bool)
    mask[:, :5] = False
    zero = np.zeros(mask.shape, np.float32)
    one = np.ones(mask.shape, np.float32)
    kept = fuse_detail(net, ls, zero, mask)
    assert _angle(kept, net)[mask].max() < 1e-3  # low + high of the same map: the map
    taken = fuse_detail(net, ls, one, mask, shape_weights=one)
    assert _angle(taken, ls)[mask].max() < 1e-3
    assert not kept[~mask].any() and not taken[~mask].any()
    # detail only: the result's high-pass is least squares', its low-pass the network's
    mixed = fuse_detail(net, ls, one, mask)
    assert _angle(mixed, net)[mask].mean() > 1.0 and _angle(mixed, ls)[mask].mean() > 1.0
    norms = np.linalg.norm(mixed[mask], axis=1)
    assert np.allclose(norms, 1.0, atol=1e-5)


def test_shapes_are_checked() -> None:
    net = _field(1)
    mask = np.ones(net.shape[:2], bool)
    with pytest.raises(InputError, match="shapes differ"):
        fuse_detail(net, net[:, :-1], np.ones(mask.shape), mask)
    with pytest.raises(InputError, match="weights"):
        fuse_detail(net, net, np.ones((3, 3)), mask)
    with pytest.raises(InputError, match="sigma"):
        FusionOptions(sigma=float("nan"))


def _lambertian_stack(broken: bool) -> Stack:
    n = _field(5, 32, 32)
    lights = ring_lights()
    shading = np.clip(np.einsum("hwc,nc->nhw", n, lights), 0, None) * 0.5
    shading[3, :, :16] += 0.8  # a highlight under one light: the robust fit drops it
    if broken:  # the left half unlike any Lambertian surface: nothing to trust there
        shading[:, :, :16] = np.random.default_rng(6).uniform(0.0, 1.0, (12, 32, 16))
    images = np.repeat(shading[..., None], 3, axis=3).astype(np.float32)
    return Stack.from_arrays(images, lights)


def test_validity_trusts_the_robust_fit_and_not_a_broken_model() -> None:
    stack = _lambertian_stack(broken=False)
    v = validity(robust_least_squares(stack), stack.mask)
    assert v.detail.min() > 0.99  # the highlight is dropped, not distrusted
    stack = _lambertian_stack(broken=True)
    v = validity(robust_least_squares(stack), stack.mask)
    assert v.detail[:, :12].mean() < 0.15 and v.detail[:, :12].max() < 0.3
    assert v.detail[:, 20:].min() > 0.99
    assert v.shape[:, :12].max() < 0.05 and v.shape[:, :12].max() <= v.detail[:, :12].max()
    # the trust rises over a few pixels out of the broken half (no switch from 0 to 1 at the
    # boundary), while a broken pixel never borrows its good neighbours' weight
    assert v.detail[:, 16].max() < 0.75 and v.detail[:, 17].max() < 0.9
    assert v.detail[:, 18].min() > 0.9


def test_detail_weight_is_flat_at_a_few_per_cent_and_falls_fast_beyond() -> None:
    """Uniform residual maps through validity(): the detail weight stays near 1 at the residuals
    a mild gloss leaves (psmImages horse: median 0.065) and is gone where a fit breaks (harvest's
    shadowed folds: 0.3-0.4), the two ends a Gaussian weight could not serve at once."""
    mask = np.ones((24, 24), bool)

    def weights(r: float) -> tuple[float, float]:
        fit = RobustFit(np.zeros((24, 24, 3), np.float32), np.full((24, 24), r, np.float32))
        v = validity(fit, mask)
        return float(v.detail.mean()), float(v.shape.mean())

    assert weights(0.065)[0] == pytest.approx(np.exp(-((0.065 / 0.19) ** 4)), abs=1e-4)
    assert weights(0.065)[0] > 0.98 and weights(0.13)[0] > 0.75
    assert weights(0.3)[0] < 0.005 and weights(0.4)[0] < 1e-8
    # the shape weight falls off far sooner than the detail weight
    assert weights(0.03)[1] == pytest.approx(np.exp(-1.0), abs=1e-4)
    assert weights(0.065)[1] < 0.01
    # what profile.json / report.html record names the weights the code uses
    from types import SimpleNamespace

    from msfnet.runtime.engines.method import RunMethod
    from msfnet.runtime.infer.detail_fusion import DetailFusionEstimator

    net = SimpleNamespace(describe=lambda: RunMethod(method="msf"))
    said = DetailFusionEstimator(net).describe().detail_fusion  # type: ignore[arg-type]
    assert "exp(-(r/0.19)^4)" in str(said) and "exp(-(r/0.03)^2)" in str(said)


@pytest.mark.slow
def test_default_path_keeps_least_squares_detail_on_psm_images(psm_dir) -> None:
    """The issue's target on real 12-light captures: detail ratio (high-pass energy against
    plain least squares) >= 0.9 on cat, owl and horse with the default path (measured 0.99 /
    0.98 / 0.92; the network alone 0.61 / 0.58 / 0.65)."""
    from msfnet.runtime.api import Model
    from msfnet.runtime.evaluate.detail_ratio import detail_ratio
    from msfnet.runtime.stack import LoadOptions

    load = LoadOptions(lights=psm_dir / "lights.txt")
    fused, ls = Model(threads=2, maps=None), Model.least_squares(maps=None)
    for name in ("cat", "owl", "horse"):
        a, b = fused(psm_dir / name, load), ls(psm_dir / name, load)
        assert detail_ratio(a.normals, b.normals, a.stack.mask) >= 0.9, name


@pytest.mark.slow
@pytest.mark.parametrize("glossy", [False, True])
def test_default_path_on_the_plates(glossy: bool) -> None:
    """The issue's targets on a plate cut by the mask (bundled model, default path): the error
    within 4 px of the mask edge <= 1.5x the interior's; matte: the scratch curvature contrast
    at least 0.8x least squares'; glossy: mean error below least squares'. (Measured: matte
    0.05 deg with a ratio ~0.96 and contrast 1.0x; glossy 1.98 vs 2.10 deg, ratio ~1.14.)"""
    from msfnet.runtime.api import Model
    from msfnet.runtime.results.maps.curvature import curvature_maps
    from msfnet.synth.plates import PlateOptions, render_plate

    p = render_plate(PlateOptions(glossy=glossy))
    st = p.stack
    m = st.mask
    fused = Model(threads=2, maps=None)(st).normals
    ls = Model.least_squares(maps=None)(st).normals
    err_f, err_l = _angle(fused, p.normals), _angle(ls, p.normals)
    cols = np.arange(st.shape[1])[None, :].repeat(st.shape[0], 0)
    edge = m & (cols >= p.options.mask_edge - 4)
    inner = ndimage.distance_transform_edt(m) > 12
    assert err_f[edge].mean() <= 1.5 * err_f[inner].mean()
    if glossy:
        assert err_f[m].mean() < err_l[m].mean()
        return
    background = inner & (ndimage.distance_transform_edt(p.defects == 0) > 6)
    background &= ~ndimage.binary_dilation(p.marks, iterations=4)
    scratches = (p.defects >= 1) & (p.defects <= 3) & inner

    def contrast(n: np.ndarray) -> float:
        c = curvature_maps(n, m, sigma=1.0).mean
        return abs(np.nanmean(c[scratches]) - np.nanmean(c[background])) / np.nanstd(c[background])

    assert contrast(fused) >= 0.8 * contrast(ls)


def _noisy_stack(seed: int, h: int = 96, w: int = 80) -> tuple[Stack, np.ndarray]:
    """A gently curved Lambertian part with 1-2 px relief, 12 ring lights, 1 % noise."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    z = 0.002 * ((x - w / 2) ** 2 + (y - h / 2) ** 2) + 0.6 * np.sin(x / 1.3) * np.sin(y / 1.7)
    gy, gx = np.gradient(z)
    n = unit_normals(np.dstack([-gx, -gy, np.ones_like(z)]).astype(np.float32))
    lights = ring_lights()
    shading = np.clip(np.einsum("hwc,nc->nhw", n, lights), 0, None) * 0.5
    shading += 0.005 * rng.normal(size=shading.shape)
    images = np.repeat(np.clip(shading, 0, None)[..., None], 3, axis=3).astype(np.float32)
    return Stack.from_arrays(images, lights), n


def test_bands_give_the_whole_image_fusion() -> None:
    from msfnet.runtime.infer.detail_fusion import fuse_in_bands

    stack, truth = _noisy_stack(11)
    fit = robust_least_squares(stack)
    net = _masked_smooth_field(truth, stack.mask)
    whole = fuse_in_bands(net, fit, stack.mask)
    for rows in (7, 32):
        banded = fuse_in_bands(net, fit, stack.mask, rows=rows)
        assert _angle(banded, whole)[stack.mask].max() < 1e-3


def _masked_smooth_field(n: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """A network stand-in: the truth without its fine relief (a Gaussian of 3 px)."""
    import cv2

    return unit_normals(cv2.GaussianBlur(n, (0, 0), 3.0) * mask[..., None])


def test_default_split_passes_the_detail_band_whole() -> None:
    """With every pixel valid, the fused map keeps the detail check's band (2 px) of the robust
    fit: at least 0.9 of its high-pass energy at the default 3 px split. A split at the check's
    own scale (2 px) hands over only part of the band (measured 0.84-0.90 on psmImages)."""
    from msfnet.runtime.evaluate.detail_ratio import highpass_energy

    stack, truth = _noisy_stack(12)
    fit = robust_least_squares(stack)
    net = _masked_smooth_field(truth, stack.mask)
    one = np.ones(stack.mask.shape, np.float32)
    ref = highpass_energy(fit.normals, stack.mask)
    default = fuse_detail(net, fit.normals, one, stack.mask, FusionOptions().sigma)
    narrow = fuse_detail(net, fit.normals, one, stack.mask, 2.0)
    assert highpass_energy(default, stack.mask) >= 0.9 * ref
    assert highpass_energy(narrow, stack.mask) < highpass_energy(default, stack.mask) - 0.02 * ref


def test_a_failed_fit_lends_no_trust_to_its_pixel() -> None:
    """A speck black under every light (fit residual 1) inside a well-fitted part: the weights
    there stay ~0 (smoothing does not lift them) and the fused normal is the network's."""
    stack, truth = _noisy_stack(13)
    images = stack.images.copy()
    images[:, 40, 40] = 0.0
    stack = Stack.from_arrays(images, stack.lights)
    fit = robust_least_squares(stack)
    v = validity(fit, stack.mask)
    assert fit.residual[40, 40] == 1.0
    assert v.detail[40, 40] < 1e-3 and v.shape[40, 40] < 1e-3
    assert np.median(v.detail[stack.mask]) > 0.5  # the rest of the part is trusted
    net = _masked_smooth_field(truth, stack.mask)
    fused = fuse_detail(net, fit.normals, v.detail, stack.mask, 3.0, v.shape)
    assert _angle(fused[40:41, 40:41], net[40:41, 40:41]).max() < 2.0


def test_bands_span_only_the_masks_columns_and_change_nothing() -> None:
    """A band is computed on its mask pixels' columns and their context only: an object on a
    small part of a wide image fuses to the whole-image result (validity + fuse_detail on the
    full width), with noise and residuals everywhere so that a lost column of context shows."""
    from msfnet.runtime.infer.detail_fusion import (
        above_floor,
        fuse_in_bands,
        residual_floor,
        validity,
    )
    from msfnet.runtime.infer.robust_least_squares import RobustFit

    rng = np.random.default_rng(5)
    UP = np.array([0.0, 0.0, 2.0], np.float32)  # tilted around +z: valid normals
    h, w = 90, 240
    yy, xx = np.mgrid[:h, :w]
    mask = ((yy - 40) ** 2 + (xx - 60) ** 2 < 25**2) | ((yy - 70) ** 2 + (xx - 200) ** 2 < 9**2)
    net = unit_normals(rng.normal(size=(h, w, 3)).astype(np.float32) + UP)
    ls = unit_normals(rng.normal(size=(h, w, 3)).astype(np.float32) + UP)
    fit = RobustFit(ls, rng.uniform(0.0, 0.4, (h, w)).astype(np.float32))
    floor = residual_floor(fit.residual, mask)
    v = validity(RobustFit(ls, above_floor(fit.residual, floor)), mask)
    whole = fuse_detail(net, ls, v.detail, mask, FusionOptions().sigma, v.shape)
    for rows in (None, 16):
        banded = fuse_in_bands(net, fit, mask, rows=rows)
        np.testing.assert_allclose(banded, whole, atol=1e-6)
        assert not banded[~mask].any()


@pytest.mark.parametrize("broken", [np.nan, 0.0])
def test_pixels_the_network_gave_no_normal_keep_none(broken: float) -> None:
    """A model returning NaN or zeros was fused into least squares' normals and scored ~11
    deg instead of the 180 deg a non-unit prediction scores."""
    net, ls = _field(1), _field(2)
    net[:4] = broken
    mask = np.ones(net.shape[:2], bool)
    one = np.ones(mask.shape, np.float32)
    fused = fuse_detail(net, ls, one, mask, shape_weights=one)
    assert not fused[:4].any()
    assert np.allclose(np.linalg.norm(fused[4:], axis=-1), 1.0, atol=1e-5)


def test_the_weights_read_the_residual_above_the_parts_floor() -> None:
    """A calibration error lifts every pixel's residual: the floor comes off in quadrature, up
    to FLOOR_CAP (above it the floor is the material's and stays); failed fits stay failed."""
    from msfnet.runtime.infer.detail_fusion import FLOOR_CAP, above_floor, residual_floor

    rng = np.random.default_rng(3)
    mask = np.ones((40, 50), bool)
    own = rng.uniform(0.0005, 0.002, mask.shape).astype(np.float32)
    own[10:14, 20:30] = 0.3  # a highlight
    lifted = np.sqrt(own**2 + 0.012**2)  # LED intensities a few per cent off
    got = above_floor(lifted, residual_floor(lifted, mask))
    assert np.abs(got - own)[own < 0.01].max() < 0.0025
    assert (got[10:14, 20:30] > 0.28).all()  # a highlight stays one
    matte = np.full(mask.shape, 0.05, np.float32)  # a floor that is the material's
    assert np.allclose(
        above_floor(matte, residual_floor(matte, mask)), np.sqrt(0.05**2 - FLOOR_CAP**2), atol=1e-6
    )
    failed = own.copy()
    failed[0, :5] = 1.0
    assert (above_floor(failed, residual_floor(failed, mask))[0, :5] == 1.0).all()


@pytest.mark.slow
@pytest.mark.parametrize(("plate", "gains"), [(0, 47), (1, 47), (0, (0, 47, 1))])
def test_led_intensities_off_by_two_per_cent_cost_no_more_than_least_squares(
    plate: int, gains: int | tuple[int, ...]
) -> None:
    """LED intensities +-2 % off what the tool is told (a matte plate cut by its mask): the
    robust fit within 5 % of plain least squares (it used to drop the lights the calibration got
    most wrong: 0.56 / 0.65 against 0.41 deg on the first two), and the default path within
    1.15x least squares inside and 0.3 deg of it at the mask's edge, where it used to take the
    network's rim (measured: inside 0.409 / 0.429 / 0.103 against 0.412 / 0.411 / 0.094 deg, edge
    0.429 / 0.503 / 0.289 against 0.406 / 0.421 / 0.087; the network alone 19-20 deg there)."""
    from dataclasses import replace

    from msfnet.runtime.api import Model
    from msfnet.synth.plates import PlateOptions, render_plate

    p = render_plate(PlateOptions(seed=plate))
    gain = 1.0 + np.random.default_rng(gains).uniform(-0.02, 0.02, p.stack.num_lights)
    images = p.stack.images.astype(np.float32) * gain[:, None, None, None].astype(np.float32)
    st = replace(p.stack, images=images)
    m = st.mask
    edge = m & (ndimage.distance_transform_edt(m) <= 4)
    inner = m & ~edge
    fused = _angle(Model(threads=2, maps=None)(st).normals, p.normals)
    fit = _angle(robust_least_squares(st).normals, p.normals)
    plain = _angle(Model.least_squares(maps=None)(st).normals, p.normals)
    assert fit[inner].mean() <= 1.05 * plain[inner].mean()
    assert fused[inner].mean() <= 1.15 * plain[inner].mean()
    assert fused[edge].mean() <= plain[edge].mean() + 0.3
