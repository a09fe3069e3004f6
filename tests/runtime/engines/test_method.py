"""RunMethod: what ran, one record built layer by layer; its as_json is profile.json's entries,
whose keys and order the files keep."""

from __future__ import annotations

from dataclasses import replace

import pytest
from _runtime_helpers import sphere_stack

from msfnet.runtime.api import Model, default_model_path
from msfnet.runtime.engines.method import RunMethod

FUSION = "robust least squares where its Lambertian residual r is small (detail weight "


def test_least_squares_says_what_ran_in_the_profiles_order() -> None:
    said = Model.least_squares(maps=None).describe().as_json()
    assert list(said.items()) == [
        ("method", "l2"),
        ("model", None),
        ("engine", "numpy"),
        ("precision", "fp64"),
        ("threads", None),
        ("choice", None),
    ]
    profile = Model.least_squares(maps=None)(sphere_stack(n=6, h=20, w=24, seed=1)).profile()
    assert [k for k in profile if k in said] == list(said)  # profile.json holds it, in order
    assert {k: profile[k] for k in said} == said


def test_the_bundled_network_says_what_ran_in_the_profiles_order() -> None:
    model = Model(engine="onnxruntime", precision="fp32", threads=1, maps=None)
    said = model.describe().as_json()
    assert list(said) == [
        "method", "model", "engine", "precision", "provider", "threads", "graph", "chunk",
        "choice", "edge_context", "detail_fusion",
    ]  # fmt: skip
    assert {k: said[k] for k in ("method", "model", "engine", "precision", "provider")} == {
        "method": "msf",
        "model": str(default_model_path()),
        "engine": "onnxruntime",
        "precision": "fp32",
        "provider": "CPUExecutionProvider",
    }
    assert (said["threads"], said["graph"], said["edge_context"]) == (1, "staged", True)
    assert isinstance(said["chunk"], int) and str(said["choice"]).startswith("onnxruntime fp32")
    assert str(said["detail_fusion"]).startswith(FUSION)
    # the engine's own record, as msf-bench writes it: no method, model or choice
    engine = model.estimator.network.engine  # type: ignore[attr-defined]
    assert list(engine.describe().as_json()) == [
        "engine", "precision", "provider", "threads", "graph", "chunk",
    ]  # fmt: skip


def test_each_layer_adds_its_own_field_in_its_place() -> None:
    said = Model(engine="onnxruntime", threads=1, maps=None, speed="fast", tta=4).describe()
    assert list(said.as_json())[-5:] == [
        "edge_context", "speed", "speed_rung", "tta", "detail_fusion",
    ]  # fmt: skip
    assert (said.speed, said.tta) == ("fast", 4) and "8 lights" in str(said.speed_rung)
    plain = Model(engine="onnxruntime", threads=1, maps=None, detail_fusion=False).describe()
    assert plain.detail_fusion is None and "detail_fusion" not in plain.as_json()
    assert replace(plain, model="elsewhere.onnx").as_json()["model"] == "elsewhere.onnx"


def test_openvino_says_its_device_and_version() -> None:
    pytest.importorskip("openvino")
    said = Model(engine="openvino", precision="fp32", threads=1, maps=None).describe()
    assert list(said.as_json())[:9] == [
        "method", "model", "engine", "precision", "device", "threads", "openvino", "graph",
        "chunk",
    ]  # fmt: skip
    assert said.provider is None and said.device == "CPU" and said.openvino


def test_a_record_says_null_only_where_the_profile_did() -> None:
    assert RunMethod(engine="torch", precision="fp32").as_json() == {
        "engine": "torch",
        "precision": "fp32",
        "threads": None,
    }
    assert "chunk" in RunMethod(graph="monolithic").as_json()  # None: all lights in one call
