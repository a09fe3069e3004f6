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
    calibration_samples,
    calibration_tiles,
    tile_origins,
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
    further off (dispatch.MEASURED), which is why int8 is no default."""
    from dataclasses import replace

    from msfnet.model.checkpoint import default_checkpoint_path
    from msfnet.runtime.engines.ort_session import create_session
    from msfnet.runtime.infer.tiled import infer_normals
    from msfnet.runtime.infer.tiling import plan_tiles

    options = ExportOptions(checks=((3, 8, 8),), calib_tiles_per_stack=3)
    export_variant(default_checkpoint_path(), "fp32", tmp_path / "fp32.onnx", options=options)
    stack = load_stack(ball_dir, max_lights=16)
    result = export_variant(
        default_checkpoint_path(), "int8", tmp_path / "int8.onnx", calib=[stack], options=options
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
