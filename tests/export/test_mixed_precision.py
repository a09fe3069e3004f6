"""Mixed precision on a tiny int8 QDQ conv graph: layers back to fp32 by graph surgery, their
sensitivity, and the greedy choice (no msfnet model is exported here)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
from onnx import TensorProto, helper, numpy_helper  # noqa: E402

from msfnet.common.errors import InputError  # noqa: E402
from msfnet.export.mixed_precision import (  # noqa: E402
    _outputs,
    keep_fp32,
    mean_deviation,
    mixed_precision,
    quantised_convs,
)

H = W = 12


def tiny_graph(seed: int = 0) -> onnx.ModelProto:
    """images (1, 4, H, W) -> conv a -> relu -> conv b -> relu -> conv c (1x1, 3 ch) -> unit
    normals; conv b has one output channel 200x larger than the rest, so its int8 activation
    scale is coarse for the others: the sensitive layer."""
    rng = np.random.default_rng(seed)
    wa = rng.normal(0, 0.3, (8, 4, 3, 3)).astype(np.float32)
    wb = rng.normal(0, 0.3, (8, 8, 3, 3)).astype(np.float32)
    wb[0] *= 200.0
    wc = rng.normal(0, 0.3, (3, 8, 1, 1)).astype(np.float32)
    wc[:, 0] /= 200.0
    wc[2] += 0.5  # normals mostly towards the camera
    inits = [
        numpy_helper.from_array(wa, "wa"),
        numpy_helper.from_array(wb, "wb"),
        numpy_helper.from_array(wc, "wc"),
        numpy_helper.from_array(np.full(3, 0.5, np.float32), "bc"),
    ]
    nodes = [
        helper.make_node("Conv", ["images", "wa"], ["a"], name="conv_a", pads=[1, 1, 1, 1]),
        helper.make_node("Relu", ["a"], ["ra"], name="relu_a"),
        helper.make_node("Conv", ["ra", "wb"], ["b"], name="conv_b", pads=[1, 1, 1, 1]),
        helper.make_node("Relu", ["b"], ["rb"], name="relu_b"),
        helper.make_node("Conv", ["rb", "wc", "bc"], ["c"], name="conv_c"),
        helper.make_node("LpNormalization", ["c"], ["normals"], name="unit", axis=1, p=2),
    ]
    graph = helper.make_graph(
        nodes,
        "tiny",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 4, H, W])],
        [helper.make_tensor_value_info("normals", TensorProto.FLOAT, [1, 3, H, W])],
        inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    return model


def samples(n: int, seed: int) -> list[dict[str, np.ndarray]]:
    rng = np.random.default_rng(seed)
    return [{"images": rng.uniform(0, 1, (1, 4, H, W)).astype(np.float32)} for _ in range(n)]


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory) -> tuple[onnx.ModelProto, onnx.ModelProto]:
    from onnxruntime.quantization import (
        CalibrationDataReader,
        QuantFormat,
        QuantType,
        quantize_static,
    )

    folder: Path = tmp_path_factory.mktemp("mixed")
    fp32 = tiny_graph()
    onnx.save(fp32, str(folder / "fp32.onnx"))

    class Reader(CalibrationDataReader):
        def __init__(self) -> None:
            self.it = iter(samples(4, seed=1))

        def get_next(self):  # type: ignore[no-untyped-def]
            return next(self.it, None)

    quantize_static(
        str(folder / "fp32.onnx"),
        str(folder / "int8.onnx"),
        Reader(),
        quant_format=QuantFormat.QDQ,
        per_channel=True,
        activation_type=QuantType.QUInt8,
        weight_type=QuantType.QInt8,
        op_types_to_quantize=["Conv"],
    )
    return fp32, onnx.load(str(folder / "int8.onnx"))


def deviation(model, ref_model, feeds) -> float:  # type: ignore[no-untyped-def]
    masks = [np.ones((H, W), bool)] * len(feeds)
    return mean_deviation(_outputs(model, feeds, 1), _outputs(ref_model, feeds, 1), masks)


def test_every_conv_back_in_fp32_is_the_fp32_graph(pair) -> None:
    fp32, q = pair
    assert quantised_convs(q) == ["conv_a", "conv_b", "conv_c"]
    held_out = samples(3, seed=7)
    assert deviation(q, fp32, held_out) > 0.05  # int8 differs measurably ...
    back = keep_fp32(q, quantised_convs(q), fp32)
    assert quantised_convs(back) == []
    assert deviation(back, fp32, held_out) < 1e-3  # ... and all-fp32 is the fp32 graph again
    # without the fp32 graph the weights are the dequantised int8 ones: close, not equal
    dequantised = keep_fp32(q, quantised_convs(q))
    assert 0 < deviation(dequantised, fp32, held_out) < deviation(q, fp32, held_out)
    onnx.checker.check_model(back)


def test_one_layer_back_leaves_the_others_int8(pair) -> None:
    fp32, q = pair
    part = keep_fp32(q, ["conv_b"], fp32)
    assert quantised_convs(part) == ["conv_a", "conv_c"]
    with pytest.raises(InputError, match="no quantised Conv named conv_x"):
        keep_fp32(q, ["conv_x"])


def test_the_sensitive_layer_is_chosen_first(pair) -> None:
    fp32, q = pair
    feeds = samples(3, seed=11)  # held out: not the calibration samples
    masks = [np.ones((H, W), bool)] * 3
    mixed, report = mixed_precision(fp32, q, feeds, masks, target_deg=0.0, max_layers=1)
    assert report.quantised == 3
    # conv_b's input scale is set by conv_a's outputs, fine; its *output* channel 0 is 200x the
    # others, so conv_c's int8 input rounds the other channels away: conv_c gains most
    assert report.fp32_layers == (max(report.sensitivity, key=report.sensitivity.get),)
    assert report.mixed_mean_deg < report.int8_mean_deg
    assert report.steps[0][1] == pytest.approx(report.mixed_mean_deg)
    assert deviation(mixed, fp32, feeds) == pytest.approx(report.mixed_mean_deg, rel=1e-4)
    # a generous target keeps everything int8
    _, loose = mixed_precision(fp32, q, feeds, masks, target_deg=180.0)
    assert loose.fp32_layers == () and loose.mixed_mean_deg == loose.int8_mean_deg


def test_layers_back_in_fp32_leave_fewer_ranged_quantisers(pair) -> None:
    """The metadata's count of percentile-ranged activations is recounted after mixed
    precision (the int8-mixed pass): the quantisers of a layer back in fp32 go with it."""
    from msfnet.export.quantize import ranged_quantisers

    fp32, q = pair
    every = ranged_quantisers(q, fp32)
    # the convs' inputs that other nodes compute: ra, rb (the graph's input images is not
    # ranged by the percentile step), and the int8 outputs of the convs before their ReLUs
    assert every >= 2
    assert ranged_quantisers(keep_fp32(q, ["conv_b"], fp32), fp32) < every
    assert ranged_quantisers(keep_fp32(q, quantised_convs(q), fp32), fp32) == 0
