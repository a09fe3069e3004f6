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
from msfnet.common.vocabulary import declare, opt
from msfnet.runtime.contract import METADATA_KEYS, TRAIN_LIGHTS
from msfnet.runtime.infer.normalise import network_input
from msfnet.runtime.stack import Stack, load_stack

# msf-export's --calib (also declared by export.variants, which this module does not import)
declare("calib", "--calib")

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
        raise InputError(f"{opt('calib')}: give at least one stack to calibrate on", option="calib")
    for s in stacks:
        if s.num_lights < MIN_CALIB_LIGHTS:
            raise InputError(
                f"{opt('calib')}: {s.num_lights} lights; int8 calibration needs at least "
                f"{MIN_CALIB_LIGHTS} per stack",
                s.source or s.name,
                option="calib",
            )
    pixels = sum(int(np.count_nonzero(s.mask)) for s in stacks)
    if pixels < MIN_CALIB_PIXELS:
        sizes = ", ".join(f"{s.name} {s.shape[1]}x{s.shape[0]}" for s in stacks)
        raise InputError(
            f"{opt('calib')}: {pixels} object pixel(s) in all ({sizes}); int8 calibration needs at "
            f"least {MIN_CALIB_PIXELS} (a {MIN_CALIB_SIDE} x {MIN_CALIB_SIDE} patch of object)",
            option="calib",
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
    """(feeds, mask (t, t), stack name) per tile: network feeds {'images': (1,N,3,t,t),
    'lights': (1,N,3)} from real stacks.

    Normalisation is per pixel, so normalising a crop equals cropping the normalised image.
    Each stack gives tiles at up to three light counts (``lights``, 32 and 8, capped by the
    stack's count) so the calibrated ranges cover the sqrt(N / 32) scaling the runtime applies.
    """
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


def calibration_samples(stacks: Sequence[Stack], **options: int) -> Iterator[dict[str, np.ndarray]]:
    """The feeds of :func:`calibration_tiles` (same options), without masks and names."""
    return (feeds for feeds, _mask, _name in calibration_tiles(stacks, **options))


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


# "percentile" (default): each activation's int8 range from the ACTIVATION_PERCENTILE-th
# percentile of its values over the calibration tiles (both tails), set by msfnet itself on the
# min/max-calibrated graph (ONNX Runtime's own percentile and entropy calibrators fail on tiles
# of different light counts). Stacks of many lights reach activations 2-3x larger than few-light
# stacks in a few pixels (a highlight normalised against many dark lights) while the bulk does
# not move (docs/export.md): min/max ranges wide enough for those pixels quantise the bulk of a
# 12-light stack coarsely (its deviation from fp32 doubled), narrower ones clip them.
# "minmax": the extremes of the calibration tiles.
CALIBRATION_METHODS = ("percentile", "minmax")
ACTIVATION_PERCENTILE = 99.9995
# Values of one activation per calibration tile that the percentile is taken over: a seeded
# random draw (a 96-light tile's activation holds up to 50 M values; an evenly strided subset
# lines up with the tile's rows and reads only a few columns)
PERCENTILE_SUBSAMPLE = 400_000
# Activations fetched per pass over a tile: each is up to 200 MB at 96 lights (64 px tiles),
# and every pass runs the graph again (fewer, larger passes are faster)
RANGES_PER_PASS = 12

# Calibration must see many-light stacks (see above); when no stack given has MANY_LIGHTS, these
# rendered ones are added (msfnet.synth; seeded, so every export calibrates on the same ones).
MANY_LIGHTS = 48
RENDERED_CALIB_OBJECTS = 6
RENDERED_CALIB_LIGHTS = 96
RENDERED_CALIB_SIZE = 128
RENDERED_CALIB_SEED = 101


def with_many_light_stacks(stacks: Sequence[Stack]) -> list[Stack]:
    """``stacks``, plus rendered 96-light objects where none of them has MANY_LIGHTS lights."""
    if max((s.num_lights for s in stacks), default=0) >= MANY_LIGHTS:
        return list(stacks)
    from msfnet.synth.render import SHAPES, RenderOptions, render_set

    options = RenderOptions(size=RENDERED_CALIB_SIZE, lights=RENDERED_CALIB_LIGHTS)
    rendered = render_set(RENDERED_CALIB_SEED, RENDERED_CALIB_OBJECTS, options, shapes=SHAPES)
    return [*stacks, *rendered]


def activation_inputs(qmodel: onnx.ModelProto) -> list[str]:
    """The fp32 tensors a QDQ graph quantises that are activations (not weights)."""
    constants = {i.name for i in qmodel.graph.initializer}
    names = [
        n.input[0]
        for n in qmodel.graph.node
        if n.op_type == "QuantizeLinear" and n.input[0] not in constants
    ]
    return list(dict.fromkeys(names))


def ranged_quantisers(qmodel: onnx.ModelProto, fp32: onnx.ModelProto) -> int:
    """How many activation QuantizeLinear nodes of ``qmodel`` read a tensor that the fp32
    graph computes: those whose ranges the percentile step sets (what ``quantize_model``
    records as ranges_from_percentiles; after mixed precision took layers back to fp32,
    fewer are left)."""
    known = {o for n in fp32.graph.node for o in n.output}
    constants = {i.name for i in qmodel.graph.initializer}
    return sum(
        1
        for n in qmodel.graph.node
        if n.op_type == "QuantizeLinear" and n.input[0] in known and n.input[0] not in constants
    )


def _tails(values: np.ndarray, keep: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``keep`` smallest and largest of ``values`` (all of them when fewer)."""
    if values.size <= 2 * keep:
        return values, values
    part = np.partition(values, (keep, values.size - keep - 1))
    return part[:keep], part[-keep:]


def activation_ranges(
    fp32: onnx.ModelProto,
    samples: Sequence[dict[str, np.ndarray]],
    names: Sequence[str],
    percentile: float = ACTIVATION_PERCENTILE,
) -> dict[str, tuple[float, float]]:
    """(low, high) of each tensor ``names`` of the fp32 graph over ``samples``: the
    ``100 - percentile`` and ``percentile`` percentiles of a seeded random draw of each tile's
    values (zero always inside, as the quantiser requires). Only the tails are kept per tile,
    so memory does not grow with the number of tiles."""
    import onnxruntime as ort

    if not names:  # (ONNX Runtime would read an empty list of outputs as "all of them")
        return {}
    probe = onnx.ModelProto()
    probe.CopyFrom(fp32)
    have = {o.name for o in probe.graph.output}
    for name in names:
        if name not in have:
            probe.graph.output.append(onnx.helper.make_empty_tensor_value_info(name))
    session = ort.InferenceSession(probe.SerializeToString(), providers=["CPUExecutionProvider"])
    tail = 1.0 - percentile / 100.0
    keep = int(np.ceil(len(samples) * PERCENTILE_SUBSAMPLE * tail)) + 1
    lows: dict[str, list[np.ndarray]] = {n: [] for n in names}
    highs: dict[str, list[np.ndarray]] = {n: [] for n in names}
    counts = dict.fromkeys(names, 0)
    rng = np.random.default_rng(0)
    groups = [list(names[i : i + RANGES_PER_PASS]) for i in range(0, len(names), RANGES_PER_PASS)]
    for feeds in samples:
        for group in groups:  # a few activations a pass bounds the memory; costs passes
            for name, value in zip(group, session.run(group, feeds), strict=True):
                flat = value.ravel()
                if flat.size > PERCENTILE_SUBSAMPLE:
                    flat = flat[rng.integers(0, flat.size, PERCENTILE_SUBSAMPLE)]
                low, high = _tails(flat, keep)
                lows[name].append(low)
                highs[name].append(high)
                counts[name] += flat.size
    out = {}
    for name in names:
        rank = min(int(counts[name] * tail), keep - 1)  # values beyond the range, each tail
        low = np.sort(np.concatenate(lows[name]))[rank]
        high = np.sort(np.concatenate(highs[name]))[::-1][rank]
        out[name] = (min(0.0, float(low)), max(0.0, float(high)))
    return out


def set_activation_ranges(
    qmodel: onnx.ModelProto,
    ranges: dict[str, tuple[float, float]],
    fp32: onnx.ModelProto | None = None,
) -> int:
    """Give each activation QuantizeLinear of a QDQ graph the range ``ranges`` names for its
    input (its DequantizeLinear shares the scale and zero point); returns how many changed.
    The convs' int32 biases are quantised again at their new scale, from the fp32 graph's
    biases where ``fp32`` is given (else from their old int32 values, one old step coarser)."""
    from onnx import numpy_helper

    constants = {i.name: i for i in qmodel.graph.initializer}
    changed = 0
    for node in qmodel.graph.node:
        if node.op_type != "QuantizeLinear" or node.input[0] not in ranges:
            continue
        low, high = ranges[node.input[0]]
        scale_t, zero_t = constants[node.input[1]], constants[node.input[2]]
        kind = numpy_helper.to_array(zero_t).dtype
        if kind == np.uint8:
            scale = max(high - low, 1e-12) / 255.0
            zero = int(np.clip(round(-low / scale), 0, 255))
        else:  # int8, symmetric
            scale = max(abs(low), abs(high), 1e-12) / 127.0
            zero = 0
        scale_t.CopyFrom(numpy_helper.from_array(np.array(scale, np.float32), scale_t.name))
        zero_t.CopyFrom(numpy_helper.from_array(np.array(zero, kind), zero_t.name))
        changed += 1
    originals = {} if fp32 is None else {i.name: i for i in fp32.graph.initializer}
    _requantise_biases(qmodel, originals)
    return changed


def _requantise_biases(qmodel: onnx.ModelProto, originals: dict[str, onnx.TensorProto]) -> None:
    """Keep each quantised Conv's int32 bias at scale = input scale x weight scale: ONNX
    Runtime fuses DequantizeLinear -> Conv -> QuantizeLinear into its int8 kernel only then (a
    bias left at the old scale silently runs that conv in fp32, half the speed)."""
    from onnx import numpy_helper

    constants = {i.name: i for i in qmodel.graph.initializer}
    dq = {n.output[0]: n for n in qmodel.graph.node if n.op_type == "DequantizeLinear"}

    def array(name: str) -> np.ndarray:
        return numpy_helper.to_array(constants[name])

    for conv in qmodel.graph.node:
        if conv.op_type != "Conv" or len(conv.input) < 3:
            continue
        x, w, b = (dq.get(conv.input[i]) for i in range(3))
        if x is None or w is None or b is None or b.input[0] not in constants:
            continue
        bias_int = array(b.input[0])
        if bias_int.dtype != np.int32:
            continue
        # ONNX Runtime names a quantised bias "<fp32 name>_quantized"
        source = originals.get(b.input[0].removesuffix("_quantized"))
        if source is not None:
            bias = numpy_helper.to_array(source).astype(np.float64)
        else:
            bias = bias_int.astype(np.float64) * array(b.input[1]).astype(np.float64)
        scale = (array(x.input[1]).astype(np.float64) * array(w.input[1])).astype(np.float32)
        requantised = np.clip(np.rint(bias / scale), -(2**31), 2**31 - 1).astype(np.int32)
        for name, value in ((b.input[0], requantised), (b.input[1], scale)):
            constants[name].CopyFrom(numpy_helper.from_array(value, name))


def quantize_model(
    model: onnx.ModelProto,
    stacks: Sequence[Stack],
    scratch: Path,
    *,
    method: str = "percentile",
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

    method: 'percentile' (default) or 'minmax' (see CALIBRATION_METHODS). Stacks with fewer
    than MANY_LIGHTS lights are calibrated together with rendered many-light objects
    (``with_many_light_stacks``; named in the summary).
    reduce_range: 7-bit weights; default: where this CPU lacks VNNI (ONNX Runtime's int8
    kernels saturate full-range weights there, so the export's own check could not pass, and
    7-bit weights compute exactly on every CPU; see CpuInfo.int8_full_range). Recorded in the
    summary, which the runtime reads before running the model on a CPU without VNNI.
    """
    _check_quantisable(model, method)
    check_calibration(stacks)
    given = [s.name for s in stacks]
    stacks = with_many_light_stacks(stacks)
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
    qmodel = _quantize_static(model, samples, scratch, reduce_range)
    ranged = 0
    if method == "percentile":
        ranged = _set_percentile_ranges(model, qmodel, samples)
    summary: dict[str, object] = {
        "calibration_samples": len(samples),
        "calibration_stacks": given,
        "rendered_stacks": len(stacks) - len(given),
        "method": method,
        "percentile": ACTIVATION_PERCENTILE if method == "percentile" else None,
        "ranges_from_percentiles": ranged,
        "tile": tile,
        "lights": lights,
        "reduce_range": reduce_range,
        "fp32_convs": fp32_conv_names(model),
    }
    return qmodel, summary


def _check_quantisable(model: onnx.ModelProto, method: str) -> None:
    """Refuse an unknown calibration method, and a graph whose transposed convs are not yet
    rewritten (``rewrite.rewrite_deconvs``)."""
    if method not in CALIBRATION_METHODS:
        raise InputError(
            f"calibration method {method!r}: expected one of {', '.join(CALIBRATION_METHODS)}"
        )
    if any(n.op_type == "ConvTranspose" for n in model.graph.node):
        raise ValueError("rewrite the transposed convolutions first (rewrite.rewrite_deconvs)")


def _quantize_static(
    model: onnx.ModelProto, samples: list[dict[str, np.ndarray]], scratch: Path, reduce_range: bool
) -> onnx.ModelProto:
    """ONNX Runtime's quantize_static on ``model`` (min/max ranges over ``samples``), through
    files in ``scratch``: the QDQ graph it writes, loaded back."""
    from onnxruntime.quantization import (
        CalibrationDataReader,
        CalibrationMethod,
        QuantFormat,
        QuantType,
        quantize_static,
    )

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
            calibrate_method=CalibrationMethod.MinMax,  # percentile ranges are set below
            nodes_to_exclude=fp32_conv_names(model),
            reduce_range=reduce_range,
        )
        return onnx.load(str(dst))
    finally:
        tempfile.tempdir = old_tempdir
        root.setLevel(level)


def _set_percentile_ranges(
    model: onnx.ModelProto, qmodel: onnx.ModelProto, samples: list[dict[str, np.ndarray]]
) -> int:
    """Replace the min/max ranges of ``qmodel``'s activations that the fp32 ``model`` computes
    by their ACTIVATION_PERCENTILE ranges over ``samples``; returns how many changed."""
    known = {o for n in model.graph.node for o in n.output}
    names = [n for n in activation_inputs(qmodel) if n in known]
    ranges = activation_ranges(model, samples, names, ACTIVATION_PERCENTILE)
    return set_activation_ranges(qmodel, ranges, model)
