"""Matrix-multiply peaks of this machine, measured in the benchmark's own run.

Each precision's peak is measured with the kernels of the engine that runs it, so a variant's
"share of its own peak" compares like with like: a constant-weight MatMul graph through ONNX
Runtime (fp32 MatMul; int8 MatMulInteger, u8 x s8 -> i32, the QGEMM that QLinearConv uses) and
through OpenVINO (the fp32 graph with INFERENCE_PRECISION_HINT f32 and bf16; int8 as a QDQ
MatMul, which OpenVINO runs as an int8 matmul). torch's fp32/bf16 matmul is kept for the
PyTorch variants (field notes: torch's fp32 matmul under-reads the machine on Zen 5, so it is not
"the" fp32 peak).

The size grows until one product takes long enough to time (bf16 without hardware support is
~100x slower than fp32, so a fixed 4096^3 product could take a minute there).
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from msfnet.common.cpu import CpuInfo, check_threads, detect_cpu

MIN_SECONDS = 0.15
MAX_SIZE = 4096


def _grow_and_time(
    make: Callable[[int], Callable[[], object]],
    min_seconds: float,
    max_size: int,
    repeats: int,
    start: int = 256,
) -> tuple[int, list[float], dict[int, float]]:
    """Double n until one call takes ``min_seconds`` (or n = max_size), timing ``repeats`` calls
    at every n from 1024 up (smaller products are too short to reach the peak). Returns the
    size whose fastest call was fastest per FLOP, its call times, and the best time per size."""
    n = start
    per_size: dict[int, list[float]] = {}
    while True:
        call = make(n)
        call()  # warm-up (packing, thread pool, lazy compilation)
        t0 = time.perf_counter()
        call()
        times = [time.perf_counter() - t0]
        last = times[0] >= min_seconds or n >= max_size
        if n >= 1024 or last:
            for _ in range(repeats - 1):
                t0 = time.perf_counter()
                call()
                times.append(time.perf_counter() - t0)
            per_size[n] = times
        if last:
            break
        n = min(max_size, n * 2)
    best_n = max(per_size, key=lambda k: k**3 / max(min(per_size[k]), 1e-9))
    return best_n, per_size[best_n], {k: min(v) for k, v in per_size.items()}


def _result(
    engine: str, dtype: str, threads: int, n: int, times: list[float], per_size: dict[int, float]
) -> dict[str, object]:
    """``gflops`` is the fastest call's rate: a peak is what the machine can do, and on a shared
    machine other jobs only ever slow a call down (the median is kept as ``median_gflops``)."""
    ops = 2.0 * n**3  # multiply-adds count 2 (int8: operations, reported as "gflops" too)
    return {
        "engine": engine,
        "dtype": dtype,
        "threads": threads,
        "size": n,
        "gflops": ops / max(min(times), 1e-9) / 1e9,
        "median_gflops": ops / statistics.median(times) / 1e9,
        "by_size": {str(k): 2.0 * k**3 / max(t, 1e-9) / 1e9 for k, t in sorted(per_size.items())},
    }


def matmul_peak_gflops(
    dtype: str = "fp32",
    threads: int = 2,
    min_seconds: float = MIN_SECONDS,
    max_size: int = 3072,
    repeats: int = 5,
) -> dict[str, object]:
    """torch: median GFLOP/s of square matmuls in ``dtype`` ('fp32' or 'bf16') at ``threads``."""
    import torch

    check_threads(threads)

    torch.set_num_threads(threads)
    tdtype = {"fp32": torch.float32, "bf16": torch.bfloat16}[dtype]
    gen = torch.Generator().manual_seed(0)

    def make(n: int) -> Callable[[], object]:
        a = torch.randn(n, n, generator=gen).to(tdtype)
        b = torch.randn(n, n, generator=gen).to(tdtype)
        return lambda: a @ b

    return _result("torch", dtype, threads, *_grow_and_time(make, min_seconds, max_size, repeats))


def int8_weight_limit(cpu: CpuInfo | None = None) -> int:
    """The largest |weight| of the int8 graphs: 127 where ONNX Runtime's u8 x s8 kernels are
    exact with full-range weights (VNNI), else 63 (7 bits, as reduce_range quantises: the
    16-bit pair sums of the AVX2 kernels cannot saturate, 255 * 64 * 2 < 32768). The speed is
    the same; the products stay right, so a peak is never timed on wrong arithmetic."""
    cpu = cpu or detect_cpu()
    return 127 if cpu.int8_full_range else 63


def matmul_onnx(n: int, dtype: str, cpu: CpuInfo | None = None) -> bytes:
    """A one-node ONNX graph Y = A @ B with B a constant (like conv weights, pre-packed by the
    engine): fp32 MatMul, 'int8' MatMulInteger (A uint8, B int8), or 'qdq' (fp32 A quantised
    and dequantised, int8 B dequantised, then MatMul: the pattern QDQ exports use). int8
    weights lie within :func:`int8_weight_limit` for ``cpu`` (default: this one)."""
    from onnx import TensorProto, helper, numpy_helper

    rng = np.random.default_rng(0)
    top = int8_weight_limit(cpu) if dtype in ("int8", "qdq") else 127
    f32 = TensorProto.FLOAT
    if dtype == "fp32":
        inits = [numpy_helper.from_array(rng.standard_normal((n, n)).astype(np.float32), "B")]
        nodes = [helper.make_node("MatMul", ["A", "B"], ["Y"])]
        a_type, y_type = f32, f32
    elif dtype == "int8":
        inits = [numpy_helper.from_array(rng.integers(-top, top + 1, (n, n), dtype=np.int8), "B")]
        nodes = [helper.make_node("MatMulInteger", ["A", "B"], ["Y"])]
        a_type, y_type = TensorProto.UINT8, TensorProto.INT32
    elif dtype == "qdq":
        inits = [
            numpy_helper.from_array(rng.integers(-top, top + 1, (n, n), dtype=np.int8), "Bq"),
            numpy_helper.from_array(np.array(0.01, np.float32), "b_scale"),
            numpy_helper.from_array(np.array(0, np.int8), "b_zero"),
            numpy_helper.from_array(np.array(0.02, np.float32), "a_scale"),
            numpy_helper.from_array(np.array(128, np.uint8), "a_zero"),
        ]
        nodes = [
            helper.make_node("QuantizeLinear", ["A", "a_scale", "a_zero"], ["Aq"]),
            helper.make_node("DequantizeLinear", ["Aq", "a_scale", "a_zero"], ["Ad"]),
            helper.make_node("DequantizeLinear", ["Bq", "b_scale", "b_zero"], ["Bd"]),
            helper.make_node("MatMul", ["Ad", "Bd"], ["Y"]),
        ]
        a_type, y_type = f32, f32
    else:
        raise ValueError(f"dtype {dtype!r}: expected fp32, int8 or qdq")
    graph = helper.make_graph(
        nodes,
        f"matmul_{dtype}_{n}",
        [helper.make_tensor_value_info("A", a_type, [n, n])],
        [helper.make_tensor_value_info("Y", y_type, [n, n])],
        inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8  # readable by every onnxruntime / openvino this project supports
    return model.SerializeToString()


def _input(n: int, dtype: str) -> np.ndarray:
    rng = np.random.default_rng(1)
    if dtype == "int8":
        return rng.integers(0, 256, (n, n), dtype=np.uint8)
    return rng.standard_normal((n, n)).astype(np.float32)


def ort_matmul_peak(
    dtype: str = "fp32",
    threads: int = 2,
    min_seconds: float = MIN_SECONDS,
    max_size: int = MAX_SIZE,
    repeats: int = 5,
) -> dict[str, object]:
    """ONNX Runtime CPU: GFLOP/s (fp32) or GOP/s (int8, MatMulInteger) of its own GEMM."""
    import onnxruntime as ort

    check_threads(threads)

    def make(n: int) -> Callable[[], object]:
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        opts.log_severity_level = 3
        sess = ort.InferenceSession(matmul_onnx(n, dtype), opts, providers=["CPUExecutionProvider"])
        feed = {"A": _input(n, dtype)}
        return lambda: sess.run(None, feed)

    return _result(
        "onnxruntime", dtype, threads, *_grow_and_time(make, min_seconds, max_size, repeats)
    )


def ov_matmul_peak(
    dtype: str = "fp32",
    threads: int = 2,
    min_seconds: float = MIN_SECONDS,
    max_size: int = MAX_SIZE,
    repeats: int = 5,
) -> dict[str, object]:
    """OpenVINO CPU: fp32 / bf16 (the fp32 graph with the bf16 hint) / int8 (QDQ MatMul)."""
    from msfnet.runtime.engines.openvino import import_openvino

    ov = import_openvino()
    check_threads(threads)

    core = ov.Core()
    hint = "bf16" if dtype == "bf16" else "f32"

    def make(n: int) -> Callable[[], object]:
        model = core.read_model(matmul_onnx(n, "qdq" if dtype == "int8" else "fp32"), b"")
        compiled = core.compile_model(
            model,
            "CPU",
            {
                "INFERENCE_PRECISION_HINT": hint,
                "INFERENCE_NUM_THREADS": threads,
                "NUM_STREAMS": 1,
                "PERFORMANCE_HINT": "LATENCY",
            },
        )
        request = compiled.create_infer_request()
        feed = {"A": _input(n, "fp32")}
        return lambda: request.infer(feed)

    return _result(
        "openvino", dtype, threads, *_grow_and_time(make, min_seconds, max_size, repeats)
    )


def engine_peaks(
    threads: list[int], engines: set[str], torch_peaks: bool = True
) -> list[dict[str, object]]:
    """Every (engine, precision) peak at every thread count, in this process."""
    for t in threads:  # all refused before the first measurement, not after minutes of them
        check_threads(t)
    out: list[dict[str, object]] = []
    for t in threads:
        if torch_peaks:
            out += [matmul_peak_gflops(d, t) for d in ("fp32", "bf16")]
        out += [ort_matmul_peak(d, t) for d in ("fp32", "int8")]
        if "openvino" in engines:
            out += [ov_matmul_peak(d, t) for d in ("fp32", "bf16", "int8")]
    return out


def merge_peaks(*runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The best of several measurements of each (engine, dtype, threads): msf-bench measures
    before and after the cells, so a busy moment on a shared machine does not set the peak."""
    best: dict[tuple, dict[str, Any]] = {}
    seen: dict[tuple, list[float]] = {}
    for run in runs:
        for p in run:
            key = (p["engine"], p["dtype"], p["threads"])
            seen.setdefault(key, []).append(float(p["gflops"]))
            if key not in best or p["gflops"] > best[key]["gflops"]:
                best[key] = p
    return [{**p, "runs": seen[key]} for key, p in best.items()]


__all__ = [
    "engine_peaks",
    "int8_weight_limit",
    "matmul_onnx",
    "matmul_peak_gflops",
    "merge_peaks",
    "ort_matmul_peak",
    "ov_matmul_peak",
]
