"""Whether the CPU engines' int8 convolutions are exact with full-range (8-bit) weights here.

    python scripts/int8_saturation.py
    python -m msfnet.bench.cpu_proxy avx2 -- python scripts/int8_saturation.py   # as AVX2 only

Builds a one-layer QDQ convolution (u8 activations near 255, s8 weights near 127, so adjacent
products summed in 16 bits overflow: 255 x 127 x 2 > 32767), runs it on OpenVINO and ONNX
Runtime, and prints each engine's largest error against an exact integer reference, for 8-bit
and for 7-bit weights. Without VNNI both engines saturate the 8-bit case (docs/benchmark.md):
this is why a full-range int8 file is refused on such CPUs (engines.base.check_int8_exact) and
msf-export can write 7-bit weights.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

C, K, S = 64, 32, 16  # channels in, out; image side
X_SCALE, W_SCALE, Y_SCALE, Y_ZERO = 1.0 / 255, 0.01, 6.0, 128


def model(weights: np.ndarray) -> bytes:
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    def const(value: object, name: str, dtype: type) -> onnx.TensorProto:
        return numpy_helper.from_array(np.array(value, dtype), name)

    nodes = [
        helper.make_node("QuantizeLinear", ["x", "xs", "xz"], ["xq"]),
        helper.make_node("DequantizeLinear", ["xq", "xs", "xz"], ["xd"]),
        helper.make_node("DequantizeLinear", ["wq", "ws", "wz"], ["wd"]),
        helper.make_node("Conv", ["xd", "wd"], ["yc"], pads=[1, 1, 1, 1]),
        helper.make_node("QuantizeLinear", ["yc", "ys", "yz"], ["yq"]),
        helper.make_node("DequantizeLinear", ["yq", "ys", "yz"], ["y"]),
    ]
    inits = [
        const(X_SCALE, "xs", np.float32),
        const(0, "xz", np.uint8),
        numpy_helper.from_array(weights, "wq"),
        const(W_SCALE, "ws", np.float32),
        const(0, "wz", np.int8),
        const(Y_SCALE, "ys", np.float32),
        const(Y_ZERO, "yz", np.uint8),
    ]
    graph = helper.make_graph(
        nodes,
        "saturation",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, C, S, S])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, K, S, S])],
        inits,
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]).SerializeToString()


def exact(xq: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The quantised output computed in int64: the convolution, then the output's QDQ."""
    padded = np.pad(xq[0].astype(np.int64), ((0, 0), (1, 1), (1, 1)))
    acc = np.zeros((K, S, S), np.int64)
    for dy in range(3):
        for dx in range(3):
            window = padded[:, dy : dy + S, dx : dx + S]
            acc += np.einsum("kc,cyx->kyx", weights[:, :, dy, dx].astype(np.int64), window)
    real = acc * (X_SCALE * W_SCALE)
    q = np.clip(np.round(real / Y_SCALE) + Y_ZERO, 0, 255)
    return ((q - Y_ZERO) * Y_SCALE)[None].astype(np.float64)


def main() -> int:
    import onnxruntime as ort
    import openvino as ov

    rng = np.random.default_rng(0)
    x = rng.uniform(0.9, 1.0, size=(1, C, S, S)).astype(np.float32)
    xq = np.clip(np.round(x / X_SCALE), 0, 255)
    core = ov.Core()
    print("OpenVINO CPU capabilities:", core.get_property("CPU", "OPTIMIZATION_CAPABILITIES"))
    for bits in (8, 7):
        top = 2 ** (bits - 1)
        weights = rng.integers(top - 28, top, size=(K, C, 3, 3)).astype(np.int8)
        ref = exact(xq, weights)
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "m.onnx"
            path.write_bytes(model(weights))
            compiled = core.compile_model(
                core.read_model(str(path)), "CPU", {"INFERENCE_PRECISION_HINT": "f32"}
            )
            got_ov = compiled([x])[0]
            session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
            got_ort = session.run(None, {"x": x})[0]
        print(
            f"{bits}-bit weights: largest |error| OpenVINO {np.abs(got_ov - ref).max():.1f}, "
            f"ONNX Runtime {np.abs(got_ort - ref).max():.1f}, of outputs up to "
            f"{np.abs(ref).max():.1f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
