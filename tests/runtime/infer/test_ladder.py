"""The speed ladder's rungs as estimators, with a fake network (no model is run here)."""

from __future__ import annotations

import numpy as np
import pytest
from _runtime_helpers import sphere_stack, tiny_msfnet_onnx

from msfnet.common.errors import InputError
from msfnet.common.vocabulary import speaking_as
from msfnet.runtime.engines.method import RunMethod
from msfnet.runtime.evaluate.metrics import normal_metrics
from msfnet.runtime.infer.detail_fusion import DetailFusionEstimator
from msfnet.runtime.infer.estimators import Estimate, LeastSquaresEstimator, TilingOptions
from msfnet.runtime.infer.ladder import (
    FAST_LIGHTS,
    RUNGS,
    grow_normals,
    reduced_network,
    rung,
    shrink_stack,
)
from msfnet.runtime.instrument import StageTimer


class FakeNetwork:
    """Least squares standing in for the network; records what it was given."""

    method = "msf"
    engine = None
    reason = ""

    def __init__(self) -> None:
        self.seen: list[tuple[int, tuple[int, int]]] = []

    def describe(self) -> RunMethod:
        return RunMethod(method="msf", engine="fake")

    def estimate(self, stack, tiling, timer, progress=False) -> Estimate:
        self.seen.append((stack.num_lights, stack.shape))
        return LeastSquaresEstimator().estimate(stack, tiling, timer)


def run(step: str, stack, net: FakeNetwork | None = None):
    """The rung as Model runs it: the reduced network inside the detail fusion."""
    net = net or FakeNetwork()
    est = DetailFusionEstimator(reduced_network(net, step))  # type: ignore[arg-type]
    return est.estimate(stack, TilingOptions(), StageTimer()).normals, net


def test_rung_names() -> None:
    assert list(RUNGS) == ["full", "balanced", "fast"]
    assert rung(" Balanced ").scale == 2.5 and rung("fast").scale == 3
    assert rung("fast").max_lights == FAST_LIGHTS
    with (
        speaking_as("msf-run"),
        pytest.raises(InputError, match=r"^--speed 'turbo': expected one of full, balanced, fast$"),
    ):
        rung("turbo")
    with pytest.raises(InputError, match=r"^speed='turbo': expected one of"):
        rung("turbo")


def test_full_is_the_network_itself() -> None:
    from msfnet.runtime.infer.ladder import ReducedNetwork

    net = FakeNetwork()
    assert reduced_network(net, None) is net  # type: ignore[arg-type]
    assert reduced_network(net, "full") is net  # type: ignore[arg-type]
    assert isinstance(reduced_network(net, "fast"), ReducedNetwork)  # type: ignore[arg-type]


def test_shrink_stack_halves_any_size_and_keeps_the_dtype() -> None:
    stack = sphere_stack(n=5, h=37, w=44, seed=3)
    stack = stack.__class__.from_arrays(
        (stack.images / 40000 * 65535).astype(np.uint16), stack.lights, mask=stack.mask
    )
    small = shrink_stack(stack, 2)
    assert small.images.shape == (5, 19, 22, 3) and small.images.dtype == np.uint16
    np.testing.assert_array_equal(small.lights, stack.lights)
    # a 2x2 block of object pixels is object, one of background is background
    assert small.mask[9, 11] and not small.mask[0, 0]
    assert shrink_stack(stack, 1) is stack


@pytest.mark.parametrize(
    ("step", "lights", "shape"), [("balanced", 12, (39, 44)), ("fast", FAST_LIGHTS, (32, 36))]
)
def test_reduced_rungs_run_the_network_small_and_stay_accurate(
    step: str, lights: int, shape: tuple[int, int]
) -> None:
    stack = sphere_stack(n=12, h=96, w=108, seed=4)
    normals, net = run(step, stack)
    # the network saw 2/5 / a third of the resolution (and the fast rung's light budget) ...
    assert net.seen == [(lights, shape)]
    # ... and the result is full size, unit on the mask, zero outside, and as accurate as the
    # full rung (the fake network is least squares: both err only where lights are in
    # attached shadow, 3.7 deg MAE; elsewhere the reduced-resolution shape with full-resolution
    # detail is exact: measured median 0.09 / 0.15 deg)
    assert normals.shape == (96, 108, 3)
    np.testing.assert_allclose(np.linalg.norm(normals[stack.mask], axis=1), 1.0, atol=1e-5)
    assert not normals[~stack.mask].any()
    assert stack.normals_gt is not None
    full, _ = run("full", stack)
    mae = normal_metrics(normals, stack.normals_gt, stack.mask).mae_deg
    assert mae == pytest.approx(normal_metrics(full, stack.normals_gt, stack.mask).mae_deg, abs=0.2)
    err = np.degrees(np.arccos(np.clip(np.sum(normals * stack.normals_gt, axis=2), -1, 1)))
    assert np.median(err[stack.mask]) < 0.3


def test_small_stacks_are_not_shrunk() -> None:
    stack = sphere_stack(n=12, h=40, w=44, seed=5)  # 2/5 would be under 32 px a side
    _, net = run("balanced", stack)
    assert net.seen == [(12, (40, 44))]


def test_grow_normals_fills_the_rim_the_small_mask_lost() -> None:
    h, w = 16, 16
    small = np.zeros((8, 8, 3), np.float32)
    small_mask = np.zeros((8, 8), bool)
    small_mask[2:6, 2:6] = True
    small[small_mask] = [0.0, 0.6, 0.8]
    mask = np.zeros((h, w), bool)
    mask[3:13, 3:13] = True  # one pixel wider on every side than the small mask covers
    big = grow_normals(small, small_mask, (h, w), mask)
    np.testing.assert_allclose(
        big[mask], np.broadcast_to([0.0, 0.6, 0.8], (mask.sum(), 3)), atol=1e-5
    )
    assert not big[~mask].any()


def test_describe_names_the_rung() -> None:
    d = reduced_network(FakeNetwork(), "balanced").describe()  # type: ignore[arg-type]
    assert d.speed == "balanced" and "2/5 of the resolution" in str(d.speed_rung)


def test_speed_and_device_options_refuse_contradictions() -> None:
    from msfnet.runtime.options import ModelOptions

    with pytest.raises(InputError, match=r"^speed / device choose .*; method='l2' has no network"):
        ModelOptions(method="l2", speed="fast")
    with (
        speaking_as("msf-run"),
        pytest.raises(
            InputError, match=r"^--speed / --device choose .*; --method l2 has no network$"
        ),
    ):
        ModelOptions(method="l2", device="cuda")
    with pytest.raises(InputError, match="choose one"):
        ModelOptions(speed="balanced", fine_detail=True)
    with pytest.raises(InputError, match=r"both pick where ONNX Runtime runs: use device$"):
        ModelOptions(device="cuda", provider="cuda")
    with pytest.raises(InputError, match="expected full, balanced or fast"):
        ModelOptions(speed="turbo")


def test_model_runs_a_rung_and_says_so(tmp_path) -> None:
    from msfnet.runtime.api import Model

    random_onnx = tiny_msfnet_onnx(tmp_path / "tiny.onnx")
    stack = sphere_stack(n=12, h=72, w=80, seed=6)
    result = Model(random_onnx, speed="fast", threads=1, maps=None, engine="onnxruntime")(stack)
    assert result.normals.shape == (72, 80, 3)
    np.testing.assert_allclose(np.linalg.norm(result.normals[stack.mask], axis=1), 1.0, atol=1e-5)
    described = Model(random_onnx, speed="fast", threads=1, maps=None).describe()
    assert described.speed == "fast" and "8 lights" in str(described.speed_rung)


@pytest.mark.parametrize("device", ["cuda", "tensorrt", "gpu", "npu"])
def test_absent_devices_are_refused_by_model_and_msf_run(device, tmp_path, capfd):
    from msfnet.runtime.api import Model
    from msfnet.runtime.cli.run import main
    from msfnet.runtime.engines.dispatch import resolve_device
    from msfnet.runtime.stack import save_stack

    try:
        resolve_device(device)
    except InputError:
        pass
    else:
        pytest.skip(f"a {device} device is present here")
    random_onnx = tiny_msfnet_onnx(tmp_path / "tiny.onnx")
    # the API words it as a keyword (device=...), the command as a flag
    with pytest.raises(InputError, match=rf"device='{device}': .* here"):
        Model(random_onnx, device=device)
    src = save_stack(sphere_stack(n=6, h=24, w=28, seed=2), tmp_path / "s")
    capfd.readouterr()
    code = main(
        [str(src), "--onnx", str(random_onnx), "--device", device, "-o", str(tmp_path / "o")]
    )
    err = capfd.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith(f"msf-run: error: --device {device}")
    assert not (tmp_path / "o").exists()
