"""Tiled inference on integer stacks: each tile is cast to float32 in the normaliser, so the
network sees (and returns) exactly what the float32 copy of the stack gives; the tile planner
counts the stack's bytes as held."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _runtime_helpers import as_float32, png_stack

from msfnet.runtime.api import Model, default_model_path
from msfnet.runtime.engines.ort_session import create_session
from msfnet.runtime.evaluate.metrics import angular_error_deg
from msfnet.runtime.infer import tiled as infer
from msfnet.runtime.infer.tiled import choose_plan, infer_normals
from msfnet.runtime.infer.tiling import plan_tiles
from msfnet.runtime.stack import Stack, load_stack

MAX_DIFF_DEG = 1e-4  # float32 rounding; the inputs themselves are bit-identical


@pytest.fixture(scope="module")
def bundled():
    return create_session(default_model_path(), threads=1)


def _assert_same_normals(model, held: Stack, tile: int | None) -> None:
    plan = plan_tiles(held.mask, tile)
    got = infer_normals(model, held, plan).normals
    want = infer_normals(model, as_float32(held), plan).normals
    m = held.mask
    diff = angular_error_deg(got[m], want[m])
    print(f"{held.images.dtype} vs float32: max {diff.max():.2e} deg over {m.sum()} px")
    assert diff.max() <= MAX_DIFF_DEG
    assert np.all(got[~m] == 0)


# 16-bit (the real data's depth) by default, 8-bit (the same check) with -m slow
@pytest.mark.parametrize("bits", [pytest.param(8, marks=pytest.mark.slow), 16])
def test_network_normals_of_an_integer_stack(bundled, tmp_path: Path, bits: int) -> None:
    held = load_stack(png_stack(tmp_path / "s", bits, n=8, h=60, w=70))
    assert held.images.dtype == (np.uint8 if bits == 8 else np.uint16)
    _assert_same_normals(bundled, held, tile=None)
    _assert_same_normals(bundled, held, tile=64)  # tile slices of the integer array


def test_network_normals_on_a_ball_crop(bundled, ball_dir: Path) -> None:
    """DiLiGenT ballPNG (16-bit PNG): the ball's top-left quarter with its rim, 8 lights."""
    held = load_stack(ball_dir, roi=(236, 192, 96, 96), max_lights=8)
    assert held.images.dtype == np.uint16 and 0 < held.mask.mean() < 1
    _assert_same_normals(bundled, held, tile=None)


def test_tile_planner_counts_the_bytes_held(
    bundled, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    held = load_stack(png_stack(tmp_path / "s", 16, n=8, h=60, w=70))
    seen: list[float] = []
    real = infer.tile_size_for_memory

    def spy(*args, stack_mb: float = 0.0, **kwargs):
        seen.append(stack_mb)
        return real(*args, stack_mb=stack_mb, **kwargs)

    monkeypatch.setattr(infer, "tile_size_for_memory", spy)
    choose_plan(held, bundled, None, 2048)
    choose_plan(as_float32(held), bundled, None, 2048)
    assert seen == [held.images.nbytes / 2**20, 2 * held.images.nbytes / 2**20]


def test_model_results_of_an_integer_stack(tmp_path: Path) -> None:
    """The whole pipeline (normals, metrics, albedo map) on a 16-bit stack and on its float32
    copy."""
    held = load_stack(png_stack(tmp_path / "s", 16, n=8, h=60, w=70))
    model = Model(threads=1)
    got, want = model(held), model(as_float32(held))
    m = held.mask
    assert angular_error_deg(got.normals[m], want.normals[m]).max() <= MAX_DIFF_DEG
    assert got.metrics is not None and want.metrics is not None
    assert got.metrics.mae_deg == pytest.approx(want.metrics.mae_deg, abs=1e-5)
    assert got.maps is not None and want.maps is not None
    assert got.maps.albedo is not None and want.maps.albedo is not None
    np.testing.assert_allclose(got.maps.albedo, want.maps.albedo, rtol=1e-5, atol=1e-6)
    l2 = Model.least_squares(maps=None)
    np.testing.assert_array_equal(l2(held).normals, l2(as_float32(held)).normals)


def test_an_engine_failure_quotes_openvinos_cause_not_its_location_lines() -> None:
    from msfnet.runtime.infer.tiled import _cause

    text = (
        "Exception from src/inference/src/cpp/infer_request.cpp:223:\n"
        "Exception from src/plugins/intel_cpu/src/memory.cpp:91:\n"
        "Cannot allocate 4096 MB"
    )
    assert _cause("openvino", RuntimeError(text)) == "Cannot allocate 4096 MB"
    assert _cause("onnxruntime", RuntimeError("bad alloc\nmore")) == "bad alloc"
