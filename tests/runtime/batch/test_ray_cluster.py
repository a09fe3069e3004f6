"""msf-run --ray's worker side without Ray: what a worker builds and returns must match a
local run (Ray only moves these objects between processes)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _runtime_helpers import sphere_stack

from msfnet.common.errors import InputError
from msfnet.runtime.api import Model
from msfnet.runtime.batch.ray_cluster import ModelSpec, StackWorker
from msfnet.runtime.options import ModelOptions
from msfnet.runtime.stack import LoadOptions, save_stack


def test_a_worker_builds_the_engine_and_precision_asked_for(random_onnx: Path) -> None:
    spec = ModelSpec.of(
        ModelOptions(random_onnx, engine="onnxruntime", precision="fp32", threads=1)
    )
    described = StackWorker(spec).model.describe()
    assert described["engine"] == "onnxruntime" and described["precision"] == "fp32"


def test_a_worker_returns_what_a_local_run_gives(random_onnx: Path, tmp_path: Path) -> None:
    path = save_stack(sphere_stack(n=6, h=24, w=28, seed=3), tmp_path / "s")
    worker = StackWorker(ModelSpec.of(ModelOptions(random_onnx, engine="onnxruntime", threads=1)))
    got = worker.run("s", str(path), LoadOptions())
    assert "error" not in got
    local = Model(random_onnx, engine="onnxruntime", threads=1)(path)
    np.testing.assert_allclose(got["result"].normals, local.normals, atol=1e-6, rtol=0)
    assert got["result"].method["model"] == str(random_onnx)  # the driver's name, not a copy
    assert got["result"].stack.images.size == 0  # no images shipped back


def test_a_worker_reports_a_bad_stack_as_text(random_onnx: Path, tmp_path: Path) -> None:
    worker = StackWorker(ModelSpec.of(ModelOptions(random_onnx, threads=1)))
    got = worker.run("missing", str(tmp_path / "nothing"), LoadOptions())
    assert "nothing" in got["error"]


@pytest.mark.parametrize("options", [{"engine": "openvino"}, {"precision": "bf16"}])
def test_least_squares_refuses_engine_options_before_any_work(options: dict[str, str]) -> None:
    with pytest.raises(InputError, match="--method l2 has no network"):
        ModelSpec.of(ModelOptions(method="l2", **options))
    with pytest.raises(InputError, match="method='l2' has no network"):  # the API's words
        Model(method="l2", **options)


def test_least_squares_refuses_a_model_file(random_onnx: Path) -> None:
    with pytest.raises(InputError, match="needs no model"):
        ModelSpec.of(ModelOptions(random_onnx, method="l2"))
