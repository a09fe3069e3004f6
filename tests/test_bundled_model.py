"""The bundled default model: an msfnet ONNX file that the README's main command runs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from msfnet.runtime.cli import main as run_main
from msfnet.runtime.run import default_model_path
from msfnet.runtime.session import create_session


def test_bundled_model_is_an_msfnet_model_with_dynamic_lights() -> None:
    path = default_model_path()
    if not path.is_file():
        pytest.fail(f"bundled model missing at {path}")
    session = create_session(path, threads=1)
    assert session.info.train_lights == 32 and session.info.static_shape is None
    rng = np.random.default_rng(0)
    for n in (3, 11):
        images = rng.random((1, n, 3, 16, 20), dtype=np.float32) * 0.2
        lights = rng.normal(size=(1, n, 3)).astype(np.float32)
        lights[..., 2] = np.abs(lights[..., 2]) + 1
        lights /= np.linalg.norm(lights, axis=-1, keepdims=True)
        out = session.run(images, lights)
        assert out.shape == (1, 3, 16, 20)
        np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-4)


def test_demo_main_job_writes_outputs_and_metrics(tmp_path: Path, capsys) -> None:
    out = tmp_path / "demo"
    assert run_main(["--demo", "-o", str(out), "--threads", "2"]) == 0
    printed = capsys.readouterr().out
    assert "MAE" in printed and "least squares on the same stack" in printed
    metrics = json.loads((out / "metrics.json").read_text())
    assert 0 <= metrics["mae_deg"] <= 180 and metrics["pixels"] > 1000
    normals = np.load(out / "normals.npy")
    assert normals.shape == (128, 128, 3)
