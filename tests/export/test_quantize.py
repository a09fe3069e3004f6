"""Static int8 QDQ export: every conv of the stages quantised, dynamic N, bounded deviation."""

from __future__ import annotations

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from _runtime_helpers import as_float32

from msfnet.export.pipeline import export_variant
from msfnet.export.quantize import (
    MANY_LIGHTS,
    RENDERED_CALIB_LIGHTS,
    RENDERED_CALIB_OBJECTS,
    activation_inputs,
    activation_ranges,
    calibration_samples,
    calibration_tiles,
    set_activation_ranges,
    tile_origins,
    with_many_light_stacks,
)
from msfnet.export.variants import ExportOptions
from msfnet.model.checkpoint import save_checkpoint
from msfnet.model.network import MSFNet
from msfnet.runtime.evaluate.metrics import angular_error_deg
from msfnet.runtime.stack import load_stack


def test_tile_origins_are_aligned_and_inside(rng):
    mask = np.zeros((50, 70), bool)
    mask[10:30, 40:60] = True
    for y0, x0 in tile_origins(mask, 16, 5):
        assert y0 % 4 == 0 and x0 % 4 == 0
        assert 0 <= y0 <= 50 - 16 and 0 <= x0 <= 70 - 16


def test_calibration_tiles_of_a_16bit_stack_equal_the_float32_ones(ball_dir):
    """int8 calibration reads real (16-bit) stacks: only each crop is gathered and cast."""
    held = load_stack(ball_dir, max_lights=40)
    assert held.images.dtype == np.uint16
    pairs = zip(
        calibration_tiles([held], tiles_per_stack=3),
        calibration_tiles([as_float32(held)], tiles_per_stack=3),
        strict=True,
    )
    for (got, mask, _), (want, want_mask, _) in pairs:
        np.testing.assert_array_equal(mask, want_mask)
        for key in ("images", "lights"):
            np.testing.assert_array_equal(got[key], want[key])


@pytest.fixture(scope="module")
def quantised(tmp_path_factory, ball_dir):
    """msf-export's int8 variant (torch export -> metadata -> deconv rewrite -> quantisation,
    written once and verified) of a random-weight network, calibrated on ballPNG tiles."""
    torch.manual_seed(0)
    net = MSFNet().eval()
    tmp = tmp_path_factory.mktemp("q")
    save_checkpoint(net, tmp / "rand.pth")
    stack = load_stack(ball_dir, max_lights=12)
    result = export_variant(
        tmp / "rand.pth",
        "int8",
        tmp / "int8.onnx",
        calib=[stack],
        options=ExportOptions(
            checks=((3, 8, 8),), calib_tile=32, calib_lights=8, calib_tiles_per_stack=2
        ),
    )
    summary = result.notes["quantization"]
    assert isinstance(summary, dict)
    return net, tmp, stack, summary


def test_int8_graph_has_no_fp32_deconv(quantised):
    _, tmp, _, summary = quantised
    model = onnx.load(str(tmp / "int8.onnx"))
    ops = [n.op_type for n in model.graph.node]
    assert summary["deconvs_rewritten"] == 3
    assert "ConvTranspose" not in ops
    # the extractors' convs are quantised; fusion gates, first conv and regressor stay fp32
    weights_q = sum(
        1 for n in model.graph.node if n.op_type == "DequantizeLinear" and "weight" in n.input[0]
    )
    convs = sum(1 for n in model.graph.node if n.op_type == "Conv")
    assert convs >= 18 and weights_q == convs - len(summary["fp32_convs"]) >= 9
    meta = {p.key: p.value for p in model.metadata_props}
    assert meta["msfnet.precision"] == "int8-qdq"


def test_int8_runs_any_light_count_close_to_fp32(quantised):
    net, tmp, stack, _ = quantised
    sess = ort.InferenceSession(str(tmp / "int8.onnx"), providers=["CPUExecutionProvider"])
    for n in (5, 12):
        sub = stack.subset(range(n))
        (feed,) = calibration_samples([sub], tile=32, lights=n, tiles_per_stack=1, seed=9)
        (out,) = sess.run(["normals"], feed)
        with torch.no_grad():
            ref = net(torch.from_numpy(feed["images"]), torch.from_numpy(feed["lights"])).numpy()
        assert out.shape == ref.shape
        mask = np.abs(feed["images"][0]).sum(axis=(0, 1)) > 0
        d = angular_error_deg(out[0].transpose(1, 2, 0), ref[0].transpose(1, 2, 0))[mask]
        # random weights: numerics only; measured mean ~0.2-0.3 deg on ballPNG tiles
        assert d.mean() < 2.0
        assert np.isfinite(out).all()


@pytest.mark.slow
def test_int8_of_the_trained_model_stays_within_half_a_degree(tmp_path, ball_dir):
    """The accuracy bound with real weights and real data: a trained network's activations
    span ~50x between mask boundary and interior, which random weights do not show (the old
    recipe passed with random weights and failed here at 1.7 deg mean). Calibrated on the stack
    it is scored on: this bounds the quantisation itself; across stacks the current model is
    further off (dispatch.MEASURED; the bundled int8 twin's own figures are in
    docs/export.md)."""
    from dataclasses import replace

    from msfnet.model.checkpoint import default_checkpoint_path
    from msfnet.runtime.engines.ort_session import create_session
    from msfnet.runtime.infer.tiled import infer_normals
    from msfnet.runtime.infer.tiling import plan_tiles

    options = ExportOptions(checks=((3, 8, 8),), calib_tiles_per_stack=3)
    export_variant(default_checkpoint_path(), "fp32", tmp_path / "fp32.onnx", options=options)
    # calibrated on all 96 lights of the ball: its own many-light activations, with no rendered
    # objects added (16 lights took six, which made the export 4x slower); scored at 16 lights
    stack = load_stack(ball_dir, max_lights=16)
    calib = [load_stack(ball_dir)]
    result = export_variant(
        default_checkpoint_path(), "int8", tmp_path / "int8.onnx", calib=calib, options=options
    )
    summary = result.notes["quantization"]
    assert isinstance(summary, dict)
    assert any("regressor" in n for n in summary["fp32_convs"])
    ys, xs = np.nonzero(stack.mask)
    y0, x0 = int(ys.mean()) - 100, int(xs.mean()) - 100  # the ball's upper-left rim + interior
    crop = replace(
        stack,
        images=stack.images[:, y0 : y0 + 96, x0 : x0 + 96],
        mask=stack.mask[y0 : y0 + 96, x0 : x0 + 96],
        normals_gt=None,
    )
    plan = plan_tiles(crop.mask, None)
    ref = infer_normals(create_session(tmp_path / "fp32.onnx", threads=2), crop, plan).normals
    out = infer_normals(create_session(tmp_path / "int8.onnx", threads=2), crop, plan).normals
    d = angular_error_deg(out, ref)[crop.mask]
    print(f"int8 vs fp32 on a ballPNG crop: mean {d.mean():.3f} deg, max {d.max():.2f}")
    assert d.mean() < 0.5


def test_many_light_stacks_are_added_only_when_missing(ball_dir):
    """Calibration must see many-light activations (they reach 2-3x further than few-light
    ones): rendered 96-light objects join stacks that lack them, the same ones every time."""
    few = load_stack(ball_dir, max_lights=12)
    got = with_many_light_stacks([few])
    assert got[0] is few and len(got) == 1 + RENDERED_CALIB_OBJECTS
    assert all(s.num_lights == RENDERED_CALIB_LIGHTS for s in got[1:])
    again = with_many_light_stacks([few])
    np.testing.assert_array_equal(got[1].images, again[1].images)  # seeded
    many = load_stack(ball_dir, max_lights=MANY_LIGHTS)
    assert with_many_light_stacks([few, many]) == [few, many]


def _two_convs() -> onnx.ModelProto:
    """x (1, 3, 8, 8) -> Conv 3x3 + bias -> LeakyRelu -> Conv 3x3 + bias -> y."""
    from onnx import TensorProto, helper, numpy_helper

    r = np.random.default_rng(3)
    inits = [
        numpy_helper.from_array(r.normal(size=(4, 3, 3, 3)).astype(np.float32), "w1"),
        numpy_helper.from_array(r.normal(size=4).astype(np.float32), "b1"),
        numpy_helper.from_array(r.normal(size=(4, 4, 3, 3)).astype(np.float32) / 4, "w2"),
        numpy_helper.from_array(r.normal(size=4).astype(np.float32), "b2"),
    ]
    nodes = [
        helper.make_node("Conv", ["x", "w1", "b1"], ["c1"], pads=[1, 1, 1, 1]),
        helper.make_node("LeakyRelu", ["c1"], ["a1"], alpha=0.1),
        helper.make_node("Conv", ["a1", "w2", "b2"], ["y"], pads=[1, 1, 1, 1]),
    ]
    graph = helper.make_graph(
        nodes,
        "two",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, 8, 8])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 4, 8, 8])],
        inits,
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])


def _int8_convs(model: onnx.ModelProto, tmp_path) -> int:
    """How many convs ONNX Runtime runs with its int8 kernel (fused QLinearConv)."""
    options = ort.SessionOptions()
    options.optimized_model_filepath = str(tmp_path / "optimised.onnx")
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED
    ort.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])
    return sum(
        n.op_type == "QLinearConv" for n in onnx.load(options.optimized_model_filepath).graph.node
    )


def test_percentile_ranges_keep_the_int8_kernels(tmp_path):
    from onnx import numpy_helper
    from onnxruntime.quantization import (
        CalibrationDataReader,
        QuantFormat,
        QuantType,
        quantize_static,
    )

    fp32 = _two_convs()
    r = np.random.default_rng(4)
    samples = [{"x": r.normal(size=(1, 3, 8, 8)).astype(np.float32)} for _ in range(6)]
    samples[2]["x"][0, 0, 0, 0] = 40.0  # one extreme value: min/max follows it, a percentile not

    class Reader(CalibrationDataReader):
        def __init__(self) -> None:
            self.it = iter(samples)

        def get_next(self):
            return next(self.it, None)

    onnx.save(fp32, str(tmp_path / "fp32.onnx"))
    quantize_static(
        str(tmp_path / "fp32.onnx"),
        str(tmp_path / "int8.onnx"),
        Reader(),
        quant_format=QuantFormat.QDQ,
        per_channel=True,
        activation_type=QuantType.QUInt8,  # as the export quantises
        weight_type=QuantType.QInt8,
    )
    q = onnx.load(str(tmp_path / "int8.onnx"))
    assert _int8_convs(q, tmp_path) == 2
    # inputs of both convs, and the conv outputs ORT quantises too (the graph output renamed)
    known = {"x", "c1", "a1", "y"}
    names = [n for n in activation_inputs(q) if n in known]
    assert {"x", "a1"} <= set(names)
    ranges = activation_ranges(fp32, samples, names, percentile=99.0)
    # against numpy on the same values (each tile's 384 / 256 values, all kept)
    values = {"x": np.concatenate([s["x"].ravel() for s in samples])}
    assert ranges["x"][1] == pytest.approx(np.percentile(values["x"], 99.0), rel=0.05)
    assert ranges["x"][1] < 10.0  # the extreme value is outside the range
    assert set_activation_ranges(q, ranges, fp32) == len(names)
    consts = {i.name: numpy_helper.to_array(i) for i in q.graph.initializer}
    for node in q.graph.node:
        if node.op_type == "QuantizeLinear" and node.input[0] in ranges:
            low, high = ranges[node.input[0]]
            assert float(consts[node.input[1]]) == pytest.approx((high - low) / 255.0, rel=1e-6)
    # the int32 biases follow the new input scales: still two int8 convs, same bias values
    assert _int8_convs(q, tmp_path) == 2
    biases = [n for n in q.graph.node if n.op_type == "DequantizeLinear" and "b" in n.input[0]]
    for dq, want in zip(sorted(biases, key=lambda n: n.input[0]), ("b1", "b2"), strict=True):
        got = consts[dq.input[0]].astype(np.float64) * consts[dq.input[1]]
        np.testing.assert_allclose(
            got,
            numpy_helper.to_array(fp32.graph.initializer[["w1", "b1", "w2", "b2"].index(want)]),
            atol=float(np.max(consts[dq.input[1]])) / 2 + 1e-7,  # half a step of the new scale
        )


def test_percentile_ranges_see_every_column_of_a_subsampled_tensor(monkeypatch):
    """A tile's values are drawn at random when there are more than the subsample: an evenly
    strided draw lined up with the rows and read only a few columns (review, 2026-12-02)."""
    import msfnet.export.quantize as quantize

    monkeypatch.setattr(quantize, "PERCENTILE_SUBSAMPLE", 100)  # of 192 values a tile
    r = np.random.default_rng(5)
    samples = []
    for _ in range(6):
        x = (0.1 * r.normal(size=(1, 3, 8, 8))).astype(np.float32)
        x[..., 3] = 5.0  # one column in eight: 12.5 % of the values
        samples.append({"x": x})
    low, high = activation_ranges(_two_convs(), samples, ["x"], percentile=95.0)["x"]
    assert high == pytest.approx(5.0, abs=1e-6)
    assert -0.5 < low < 0.0
