"""Engine matmul peaks: the graphs compute a matmul, and the timing loop sizes itself."""

from __future__ import annotations

import time

import numpy as np
import pytest

from msfnet.bench.peak import matmul_onnx, ort_matmul_peak, ov_matmul_peak
from msfnet.runtime.engines import installed_engines


@pytest.mark.parametrize("dtype", ["fp32", "int8", "qdq"])
def test_matmul_graphs_compute_a_matmul(dtype: str) -> None:
    pytest.importorskip("onnx", reason="needs onnx: the [bench] extra")
    import onnxruntime as ort
    from onnx import load_from_string, numpy_helper

    n = 32
    model = matmul_onnx(n, dtype)
    weights = {t.name: numpy_helper.to_array(t) for t in load_from_string(model).graph.initializer}
    rng = np.random.default_rng(0)
    a = (
        rng.integers(0, 256, (n, n), dtype=np.uint8)
        if dtype == "int8"
        else rng.standard_normal((n, n)).astype(np.float32)
    )
    sess = ort.InferenceSession(model, providers=["CPUExecutionProvider"])
    y = sess.run(None, {"A": a})[0]
    if dtype == "qdq":  # A quantised with scale 0.02 / zero 128, B dequantised with 0.01
        aq = np.clip(np.round(a / 0.02) + 128, 0, 255)
        want = ((aq - 128) * 0.02) @ (weights["Bq"].astype(np.float64) * 0.01)
        np.testing.assert_allclose(y, want, rtol=1e-4, atol=1e-3)
    else:
        b = weights["B"]
        want = a.astype(np.int64) @ b.astype(np.int64) if dtype == "int8" else a @ b
        np.testing.assert_allclose(y, want, rtol=1e-4, atol=1e-3)


def test_ort_peaks_are_measured_at_a_timeable_size() -> None:
    pytest.importorskip("onnx", reason="needs onnx: the [bench] extra")  # builds the graph
    for dtype in ("fp32", "int8"):
        p = ort_matmul_peak(dtype, threads=1, min_seconds=0.005, max_size=512, repeats=2)
        assert p["engine"] == "onnxruntime" and p["dtype"] == dtype
        assert 256 <= p["size"] <= 512 and p["gflops"] > 0.1


@pytest.mark.skipif("openvino" not in installed_engines(), reason="openvino not installed")
def test_openvino_peak_runs() -> None:
    pytest.importorskip("onnx", reason="needs onnx: the [bench] extra")  # builds the graph
    p = ov_matmul_peak("fp32", threads=1, min_seconds=0.005, max_size=256, repeats=2)
    assert p["engine"] == "openvino" and p["size"] == 256 and p["gflops"] > 0.1


def test_merged_peak_is_the_best_measurement() -> None:
    from msfnet.bench.peak import merge_peaks

    before = [
        {"engine": "onnxruntime", "dtype": "fp32", "threads": 2, "gflops": 40.0},
        {"engine": "openvino", "dtype": "bf16", "threads": 2, "gflops": 900.0},
    ]
    after = [
        {"engine": "onnxruntime", "dtype": "fp32", "threads": 2, "gflops": 290.0},
        {"engine": "openvino", "dtype": "bf16", "threads": 2, "gflops": 150.0},
    ]
    merged = {(p["engine"], p["dtype"]): p for p in merge_peaks(before, after)}
    assert merged[("onnxruntime", "fp32")]["gflops"] == 290.0
    assert merged[("openvino", "bf16")]["gflops"] == 900.0
    assert merged[("openvino", "bf16")]["runs"] == [900.0, 150.0]


def test_growth_stops_at_a_slow_small_size_and_keeps_the_fastest_size() -> None:
    from msfnet.bench.peak import _grow_and_time

    def slow(n: int):  # every call "takes" long: the first size is the last
        return lambda: time.sleep(0.02)

    n, times, per_size = _grow_and_time(slow, min_seconds=0.01, max_size=4096, repeats=2)
    assert n == 256 and len(times) == 2 and list(per_size) == [256]
    n, _, per_size = _grow_and_time(lambda n: lambda: None, 1.0, 2048, 2)
    assert list(per_size) == [1024, 2048] and n in per_size
