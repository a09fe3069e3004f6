"""Staged export + light-chunked runtime: same normals as the monolithic graph, less memory."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from _runtime_helpers import sphere_stack

from msfnet.common.errors import InputError
from msfnet.runtime.engines.ort_session import create_session
from msfnet.runtime.engines.staged_loop import DEFAULT_CHUNK, STAGE_INPUTS, STAGE_OUTPUTS
from msfnet.runtime.evaluate.metrics import angular_error_deg
from msfnet.runtime.infer.tiled import choose_plan, infer_normals
from msfnet.runtime.infer.tiling import plan_tiles, tile_size_for_memory


def test_staged_model_declares_itself(staged_onnx, sensitive_onnx) -> None:
    model = create_session(staged_onnx, threads=1)
    assert model.info.staged and model.info.metadata["msfnet.graph"] == "staged"
    # arena on by default for staged graphs only (see create_session)
    assert model.session.get_session_options().enable_cpu_mem_arena
    mono = create_session(sensitive_onnx, threads=1)
    assert not mono.info.staged and not mono.session.get_session_options().enable_cpu_mem_arena
    assert [i.name for i in model.session.get_inputs()] == list(STAGE_INPUTS)
    assert [o.name for o in model.session.get_outputs()] == list(STAGE_OUTPUTS)


@pytest.mark.parametrize("chunk", [1, 3, 13])
def test_chunked_run_equals_monolithic(staged_onnx, sensitive_onnx, chunk) -> None:
    """Same weights, 13 lights: every chunking (1 per call, uneven 3s, all at once) gives the
    monolithic graph's normals. The model is He-initialised, so a wrong max (e.g. over one chunk
    only) would move them by degrees."""
    stack = sphere_stack(n=13, h=36, w=44, seed=4)
    mono = create_session(sensitive_onnx, threads=2)
    staged = replace(create_session(staged_onnx, threads=2), lights_per_call=chunk)
    plan = plan_tiles(stack.mask, None)
    want = infer_normals(mono, stack, plan).normals
    got = infer_normals(staged, stack, plan).normals
    diff = angular_error_deg(got[stack.mask], want[stack.mask])
    assert diff.max() < 0.01, diff.max()
    # a stack with the last light dropped gives different normals: the comparison can fail
    fewer = replace(
        stack,
        images=stack.images[:-1],
        lights=stack.lights[:-1],
        intensities=stack.intensities[:-1],
    )
    other = infer_normals(staged, fewer, plan).normals
    assert angular_error_deg(other[stack.mask], want[stack.mask]).mean() > 0.05


def test_staged_tiles_are_larger_for_the_same_memory(staged_onnx) -> None:
    mono_tile = tile_size_for_memory(2048, 96)
    staged_tile = tile_size_for_memory(2048, 96, chunk=DEFAULT_CHUNK)  # what msf-run feeds
    assert staged_tile > 2 * mono_tile
    stack = sphere_stack(n=96, h=200, w=200, seed=1)
    model = create_session(staged_onnx, threads=1)
    plan = choose_plan(stack, model, max_memory_mb=2048)
    assert plan.tile_size is not None and plan.tile_size > 2 * mono_tile


def test_staged_and_static_do_not_combine(tmp_path) -> None:
    pytest.importorskip("torch")
    from msfnet.export.pipeline import export_variant
    from msfnet.export.variants import ExportOptions, StaticShape

    with pytest.raises(InputError, match="staged=True and static do"):
        export_variant(
            tmp_path / "none.pth",
            "staged",
            tmp_path / "x.onnx",
            options=ExportOptions(static=StaticShape(8, 32, 32)),
        )
    assert not (tmp_path / "x.onnx").exists()


@pytest.mark.slow
def test_tiled_staged_run_matches_untiled(staged_onnx) -> None:
    stack = sphere_stack(n=6, h=100, w=96, seed=2)
    model = create_session(staged_onnx, threads=2)
    untiled = infer_normals(model, stack, plan_tiles(stack.mask, None)).normals
    plan = plan_tiles(stack.mask, 64)
    assert len(plan.tiles) >= 4
    tiled = infer_normals(model, stack, plan).normals
    assert angular_error_deg(tiled[stack.mask], untiled[stack.mask]).max() < 0.01
    assert np.all(tiled[~stack.mask] == 0)
