"""Test-time augmentation: dihedral transforms of stacks and normals, and the wrapper."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from msfnet.runtime.evaluate.metrics import normal_metrics
from msfnet.runtime.infer.estimators import LeastSquaresEstimator, TilingOptions
from msfnet.runtime.infer.tta import (
    Dihedral,
    TTAEstimator,
    normals_back,
    transform_stack,
    tta_transforms,
)
from msfnet.runtime.instrument import StageTimer
from msfnet.synth.render import RenderOptions, render_stack

ALL = tta_transforms(8)


@pytest.fixture(scope="module")
def stack():
    # not square, so a quarter turn that forgot to swap H and W would fail
    s = render_stack(3, RenderOptions(size=40, lights=12, cast_shadows=False, noise=False))
    assert s.normals_gt is not None
    cols = slice(4, 35)
    return replace(
        s,
        images=np.ascontiguousarray(s.images[:, :, cols]),
        mask=np.ascontiguousarray(s.mask[:, cols]),
        normals_gt=np.ascontiguousarray(s.normals_gt[:, cols]),
    ).validate()


def test_groups() -> None:
    assert len(set(ALL)) == 8
    assert tta_transforms(4) == ALL[:4]
    assert tta_transforms(1) == (Dihedral(),)
    with pytest.raises(ValueError):
        tta_transforms(2)
    for t in tta_transforms(4):  # the 4-copy set keeps the image's shape
        assert t.image(np.zeros((3, 5)), (0, 1)).shape == (3, 5)


@pytest.mark.parametrize("t", ALL)
def test_round_trip(t: Dihedral) -> None:
    rng = np.random.default_rng(0)
    field = rng.normal(size=(5, 7, 3)).astype(np.float32)
    moved = np.ascontiguousarray(t.vectors(t.image(field, (0, 1))))
    np.testing.assert_allclose(normals_back(moved, t), field, atol=1e-6)
    m = t.matrix()
    np.testing.assert_allclose(m @ m.T, np.eye(2), atol=1e-12)


def test_quarter_turn_convention() -> None:
    """On screen (rows down), a pixel right of the centre goes above it, and the direction
    pointing right (+x) then points up (+y)."""
    img = np.zeros((3, 3))
    img[1, 2] = 1.0  # right of the centre
    t = Dihedral(1)
    assert t.image(img, (0, 1))[0, 1] == 1.0  # now above the centre
    np.testing.assert_allclose(t.vectors(np.array([1.0, 0.0, 0.5])), [0.0, 1.0, 0.5], atol=1e-7)
    np.testing.assert_allclose(
        Dihedral(0, True).vectors(np.array([0.3, 0.4, 0.5])), [-0.3, 0.4, 0.5], atol=1e-7
    )


@pytest.mark.parametrize("t", ALL)
def test_transformed_gt_matches_its_image(stack, t: Dihedral) -> None:
    """Least squares on the turned stack finds the turned ground truth (lights turned right)."""
    moved = transform_stack(stack, t)
    est = LeastSquaresEstimator().estimate(moved, TilingOptions(), StageTimer())
    assert moved.normals_gt is not None
    err = normal_metrics(est.normals, moved.normals_gt, moved.mask).mae_deg
    plain = LeastSquaresEstimator().estimate(stack, TilingOptions(), StageTimer())
    assert stack.normals_gt is not None
    ref = normal_metrics(plain.normals, stack.normals_gt, stack.mask).mae_deg
    assert abs(err - ref) < 1e-3


def test_tta_of_least_squares_is_plain(stack) -> None:
    plain = LeastSquaresEstimator().estimate(stack, TilingOptions(), StageTimer())
    for count in (4, 8):
        est = TTAEstimator(LeastSquaresEstimator(), count)
        assert est.describe().tta == count
        out = est.estimate(stack, TilingOptions(), StageTimer())
        assert out.normals.shape == plain.normals.shape
        np.testing.assert_allclose(out.normals, plain.normals, atol=2e-5)
        assert not out.normals[~stack.mask].any()


def test_model_option() -> None:
    from msfnet.common.errors import InputError
    from msfnet.runtime.api import Model
    from msfnet.runtime.options import ModelOptions

    with pytest.raises(InputError, match="1 \\(off\\), 4 or 8"):
        ModelOptions(tta=2)
    with pytest.raises(InputError, match="least squares"):
        ModelOptions(method="l2", tta=4)
    model = Model(tta=4, maps=None, detail_fusion=False, threads=1)
    assert model.describe().tta == 4
    assert Model(maps=None, detail_fusion=False, threads=1).describe().tta is None


def test_flag_parses() -> None:
    import argparse

    from msfnet.runtime.options import tta_count

    assert tta_count("8") == 8
    with pytest.raises(argparse.ArgumentTypeError):
        tta_count("3")


def test_model_tta_on_a_rendered_stack(stack) -> None:
    """The bundled network with TTA-4: as accurate as the plain pass or better on a rendered
    object, and its first copy is the plain pass (same result as without TTA for count 1)."""
    from msfnet.runtime.api import Model

    plain = Model(maps=None, detail_fusion=False, threads=1)(stack)
    tta = Model(tta=4, maps=None, detail_fusion=False, threads=1)(stack)
    assert plain.metrics is not None and tta.metrics is not None
    assert tta.normals.shape == plain.normals.shape
    assert tta.metrics.mae_deg < plain.metrics.mae_deg + 0.5
    moved = np.degrees(np.arccos(np.clip((tta.normals * plain.normals).sum(-1), -1, 1)))
    assert 0 < float(moved[stack.mask].mean()) < 10  # averaging changed something, not much
