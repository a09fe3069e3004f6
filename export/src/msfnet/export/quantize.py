"""Static int8 (QDQ, per-channel weights) quantisation calibrated on real photometric stacks.

Pipeline: fp32 ONNX -> ConvTranspose rewrite (so every layer is a Conv that quantises, see
``rewrite.py``) -> onnxruntime.quantization.quantize_static with a CalibrationDataReader that
feeds normalised tiles cut from real stacks (inside their masks), exactly as the runtime feeds
the network. Only the per-light convolutions of the three extractors are quantised (all but
the first 6-channel one): they are >99 % of the work at 32 lights. Everything else stays fp32:
- the regressor (once per pixel, not per light: 0.5 % of the work at 32 lights). Its
  activations span ~50x between the mask boundary and the interior of a trained model, so one
  per-tensor int8 scale wipes out the boundary;
- LeakyRelu and DepthToSpace outputs (quantising them costs accuracy for little speed);
- the fusion's GELU / sigmoid gate and the max over lights (cheap, and their inputs span ranges
  int8 handles poorly).
What each choice cost or saved, and the recipe's deviation from fp32 and speed: docs/export.md
("int8 export") and docs/benchmark.md ("Measurements behind the code's rules").
"""

from __future__ import annotations

import logging
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import onnx

from msfnet.common.errors import InputError
from msfnet.runtime.contract import METADATA_KEYS, TRAIN_LIGHTS
from msfnet.runtime.infer.normalise import network_input
from msfnet.runtime.stack import Stack, load_stack

CALIB_TILE = 64
# Up to 96 lights: the max over more lights reaches larger feature values, so a calibration at
# few lights only leaves many-light stacks further from fp32 (docs/benchmark.md)
CALIB_LIGHTS = 96
CALIB_TILES_PER_STACK = 3
# Convs only: quantised LeakyRelu / DepthToSpace outputs cost accuracy (see the module notes)
QUANT_OPS = ["Conv"]
# The least calibration an int8 export accepts: object pixels over all stacks (a 32 x 32 patch;
# a 1 x 1 stack calibrated every activation range on one value and the tiles' zero padding)
# and lights per stack (the fewest a calibration tile uses, see calibration_tiles).
MIN_CALIB_SIDE = 32
MIN_CALIB_PIXELS = MIN_CALIB_SIDE * MIN_CALIB_SIDE
MIN_CALIB_LIGHTS = 8


def check_calibration(stacks: Sequence[Stack]) -> None:
    """Refuse calibration stacks too small to set int8 ranges from, naming the minimum."""
    if not stacks:
        raise InputError("--calib: give at least one stack to calibrate on")
    for s in stacks:
        if s.num_lights < MIN_CALIB_LIGHTS:
            raise InputError(
                f"--calib: {s.num_lights} lights; int8 calibration needs at least "
                f"{MIN_CALIB_LIGHTS} per stack",
                s.source or s.name,
            )
    pixels = sum(int(np.count_nonzero(s.mask)) for s in stacks)
    if pixels < MIN_CALIB_PIXELS:
        sizes = ", ".join(f"{s.name} {s.shape[1]}x{s.shape[0]}" for s in stacks)
        raise InputError(
            f"--calib: {pixels} object pixel(s) in all ({sizes}); int8 calibration needs at "
            f"least {MIN_CALIB_PIXELS} (a {MIN_CALIB_SIDE} x {MIN_CALIB_SIDE} patch of object)"
        )


def evenly(n: int, k: int) -> list[int]:
    """k indices spread over range(n) (all of them when k >= n)."""
    if k >= n:
        return list(range(n))
    return [int(v) for v in np.rint(np.linspace(0, n - 1, k))]


def tile_origins(mask: np.ndarray, tile: int, count: int, seed: int = 0) -> list[tuple[int, int]]:
    """Top-left corners (multiples of 4) of tiles centred on random mask pixels."""
    h, w = mask.shape
    ys, xs = np.nonzero(mask)
    rng = np.random.default_rng(seed)
    picks = rng.choice(len(ys), size=min(count, len(ys)), replace=False)
    out = []
    for p in picks:
        y0 = int(np.clip(ys[p] - tile // 2, 0, max(h - tile, 0))) // 4 * 4
        x0 = int(np.clip(xs[p] - tile // 2, 0, max(w - tile, 0))) // 4 * 4
        out.append((y0, x0))
    return out


def calibration_tiles(
    stacks: Sequence[Stack],
    *,
    tile: int = CALIB_TILE,
    lights: int = CALIB_LIGHTS,
    tiles_per_stack: int = CALIB_TILES_PER_STACK,
    train_lights: int = TRAIN_LIGHTS,
    seed: int = 0,
) -> Iterator[tuple[dict[str, np.ndarray], np.ndarray, str]]:
    """(feeds, mask (t, t), stack name) per tile; see ``calibration_samples``."""
    for si, stack in enumerate(stacks):
        counts = sorted({min(k, stack.num_lights) for k in (lights, 32, 8)})
        for ti, (y0, x0) in enumerate(tile_origins(stack.mask, tile, tiles_per_stack, seed + si)):
            n = counts[ti % len(counts)]
            idx = evenly(stack.num_lights, n)
            rows, cols = slice(y0, y0 + tile), slice(x0, x0 + tile)
            x, dirs = network_input(
                stack, rows, cols, lights=idx, train_lights=train_lights, shape=(tile, tile)
            )
            mask = np.zeros((tile, tile), bool)
            crop = stack.mask[rows, cols]
            mask[: crop.shape[0], : crop.shape[1]] = crop
            yield {"images": x, "lights": dirs}, mask, stack.name


def calibration_samples(
    stacks: Sequence[Stack],
    *,
    tile: int = CALIB_TILE,
    lights: int = CALIB_LIGHTS,
    tiles_per_stack: int = CALIB_TILES_PER_STACK,
    train_lights: int = TRAIN_LIGHTS,
    seed: int = 0,
) -> Iterator[dict[str, np.ndarray]]:
    """Network feeds {'images': (1,N,3,t,t), 'lights': (1,N,3)} from real stacks.

    Normalisation is per pixel, so normalising a crop equals cropping the normalised image.
    Each stack gives tiles at up to three light counts (``lights``, 32 and 8, capped by the
    stack's count) so the calibrated ranges
    cover the sqrt(N / 32) scaling the runtime applies.
    """
    for feeds, _mask, _name in calibration_tiles(
        stacks,
        tile=tile,
        lights=lights,
        tiles_per_stack=tiles_per_stack,
        train_lights=train_lights,
        seed=seed,
    ):
        yield feeds


def load_calibration_stacks(paths: Sequence[str | Path], max_lights: int = 96) -> list[Stack]:
    """Load each calibration stack; a psmImages-style object folder finds ../lights.txt."""
    stacks = []
    for p in paths:
        p = Path(p)
        lights = None
        if p.is_dir() and not any((p / n).exists() for n in ("light_directions.txt", "lights.txt")):
            parent = p.parent / "lights.txt"
            lights = parent if parent.is_file() else None
        stacks.append(load_stack(p, lights=lights, max_lights=max_lights))
    check_calibration(stacks)
    return stacks


def _is_staged(model: onnx.ModelProto) -> bool:
    return any(
        p.key == METADATA_KEYS["graph"] and p.value == "staged" for p in model.metadata_props
    )


def staged_samples(
    src: str | Path | bytes, samples: list[dict[str, np.ndarray]]
) -> list[dict[str, np.ndarray]]:
    """Feeds for a staged graph: each entry point gets its real input, i.e. what the fp32
    graph (a file or its serialised bytes) produces in its earlier stages on the same tile
    (placeholders would calibrate nothing)."""
    import onnxruntime as ort

    from msfnet.runtime.engines.staged_loop import run_staged

    session = ort.InferenceSession(
        src if isinstance(src, bytes) else str(src), providers=["CPUExecutionProvider"]
    )
    out = []
    for feeds in samples:
        keep: dict[str, np.ndarray] = {}
        run_staged(
            session, feeds["images"], feeds["lights"], chunk=feeds["images"].shape[1], keep=keep
        )
        out.append(keep)
    return out


class _Reader:
    """onnxruntime.quantization.CalibrationDataReader over precomputed samples."""

    def __init__(self, samples: list[dict[str, np.ndarray]]) -> None:
        self._it = iter(samples)

    def get_next(self) -> dict[str, np.ndarray] | None:
        return next(self._it, None)

    def rewind(self) -> None:  # pragma: no cover - ORT calls it only for some methods
        pass


def fp32_conv_names(model: onnx.ModelProto) -> list[str]:
    """Convs kept in fp32: the fusion's 1x1 gate (its channel sum feeds a sigmoid, so int8
    error there flips the blend), the first conv (6 input channels: cheap, touches the raw
    input) and the whole regressor (see the module notes)."""
    convs = [n.name for n in model.graph.node if n.op_type == "Conv"]
    keep = [n for n in convs if "fusion" in n or "regressor" in n]
    return [*keep, convs[0]] if convs and convs[0] not in keep else keep


CALIBRATION_METHODS = ("minmax", "percentile", "entropy")


def quantize_model(
    model: onnx.ModelProto,
    stacks: Sequence[Stack],
    scratch: Path,
    *,
    method: str = "minmax",
    tile: int = CALIB_TILE,
    lights: int = CALIB_LIGHTS,
    tiles_per_stack: int = CALIB_TILES_PER_STACK,
    train_lights: int = TRAIN_LIGHTS,
    reduce_range: bool | None = None,
) -> tuple[onnx.ModelProto, dict[str, object]]:
    """An fp32 msfnet graph whose transposed convs are already rewritten (``rewrite.py``) ->
    int8 QDQ graph, and a summary. onnxruntime's quantiser works on files: they go to
    ``scratch`` (a private folder the caller removes). The ``quantise-int8`` pass
    (``passes.py``) records the int8 precision and this summary in the metadata.

    method: 'minmax' (default; robust for this ReLU-like network) or 'percentile' / 'entropy'.
    reduce_range: 7-bit weights; default: where this CPU lacks VNNI (ONNX Runtime's int8
    kernels saturate full-range weights there, so the export's own check could not pass, and
    7-bit weights compute exactly on every CPU; see CpuInfo.int8_full_range). Recorded in the
    summary, which the runtime reads before running the model on a CPU without VNNI.
    """
    from onnxruntime.quantization import (
        CalibrationDataReader,
        CalibrationMethod,
        QuantFormat,
        QuantType,
        quantize_static,
    )

    methods = {
        "minmax": CalibrationMethod.MinMax,
        "percentile": CalibrationMethod.Percentile,
        "entropy": CalibrationMethod.Entropy,
    }
    if method not in methods:
        raise InputError(f"calibration method {method!r}: expected one of {', '.join(methods)}")
    if any(n.op_type == "ConvTranspose" for n in model.graph.node):
        raise ValueError("rewrite the transposed convolutions first (rewrite.rewrite_deconvs)")
    check_calibration(stacks)
    if reduce_range is None:
        from msfnet.common.cpu import detect_cpu

        reduce_range = not detect_cpu().int8_full_range
    samples = list(
        calibration_samples(
            stacks,
            tile=tile,
            lights=lights,
            tiles_per_stack=tiles_per_stack,
            train_lights=train_lights,
        )
    )
    if _is_staged(model):
        samples = staged_samples(model.SerializeToString(), samples)

    class Reader(_Reader, CalibrationDataReader):
        pass

    src, dst = scratch / "fp32.onnx", scratch / "int8.onnx"
    onnx.save(model, str(src))
    root = logging.getLogger()
    level = root.level
    root.setLevel(logging.ERROR)  # ORT's "consider pre-processing" advice is not for our users
    # ORT makes its own temporary folders ("ort.quant.*", augmented model, calibration data):
    # inside scratch (files.scratch_folder) they go with it, even after a SIGKILL
    old_tempdir = tempfile.tempdir
    tempfile.tempdir = str(scratch)
    try:
        quantize_static(
            str(src),
            str(dst),
            Reader(samples),
            quant_format=QuantFormat.QDQ,
            per_channel=True,
            activation_type=QuantType.QUInt8,
            weight_type=QuantType.QInt8,
            op_types_to_quantize=QUANT_OPS,
            calibrate_method=methods[method],
            nodes_to_exclude=fp32_conv_names(model),
            reduce_range=reduce_range,
            extra_options={"CalibPercentile": 99.999} if method == "percentile" else {},
        )
        qmodel = onnx.load(str(dst))
    finally:
        tempfile.tempdir = old_tempdir
        root.setLevel(level)
    summary: dict[str, object] = {
        "calibration_samples": len(samples),
        "calibration_stacks": [s.name for s in stacks],
        "method": method,
        "tile": tile,
        "lights": lights,
        "reduce_range": reduce_range,
        "fp32_convs": fp32_conv_names(model),
    }
    return qmodel, summary
