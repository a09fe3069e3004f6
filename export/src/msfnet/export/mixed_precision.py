"""Accuracy-aware mixed precision: an int8 QDQ graph with its most sensitive convolutions back
in fp32, until it is within a bound of the fp32 graph on held-out data.

Why: the trained network's int8 export (quantize.py) is 0.67-0.92 deg mean from fp32 on
DiLiGenT crops, above the 0.5 deg bound for defaults; a few layers carry most of that error.
How, without re-running the quantiser per layer:

1. ``keep_fp32`` takes named Convs of the int8 graph back to fp32 by graph surgery: an
   activation input read through QuantizeLinear -> DequantizeLinear reads the fp32 tensor
   again, a constant weight or bias read through DequantizeLinear is the fp32 graph's own
   again, and the rounding of the layer's output goes (unless an int8 Conv reads it directly).
2. ``sensitivity``: each quantised Conv alone back in fp32; how much the mean deviation from
   the fp32 graph drops over the held-out samples.
3. ``mixed_precision``: the most sensitive first, re-measured after each (a layer that does
   not lower the deviation on top of those already chosen stays int8), until the mean
   deviation is within ``target_deg`` (or ``max_layers`` are back in fp32).

The held-out samples must be no validation data (the caller's choice: psmImages objects other
than the calibration ones, or synthetic stacks). ``mixed_precision`` runs the three steps on
in-memory graphs; nothing is written here.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import onnx
from onnx import numpy_helper

from msfnet.common.errors import InputError

DEFAULT_TARGET_DEG = 0.3  # on held-out tiles: leaves room below the 0.5 deg bound on real data
DEFAULT_MAX_LAYERS = 8


@dataclass(frozen=True)
class MixedPrecisionReport:
    """What was kept fp32 and why: the deviation before, after and at each step."""

    int8_mean_deg: float  # every quantisable conv in int8
    mixed_mean_deg: float  # with ``fp32_layers`` back in fp32
    fp32_layers: tuple[str, ...]
    steps: tuple[tuple[str, float], ...]  # (layer added, mean deg after)
    sensitivity: dict[str, float] = field(default_factory=dict)  # layer -> deg gained alone
    quantised: int = 0  # convs quantised in the int8 graph

    def as_dict(self) -> dict[str, object]:
        return {
            "int8_mean_deg": self.int8_mean_deg,
            "mixed_mean_deg": self.mixed_mean_deg,
            "fp32_layers": list(self.fp32_layers),
            "steps": [list(s) for s in self.steps],
            "quantised_convs": self.quantised,
        }


def _producers(graph: onnx.GraphProto) -> dict[str, onnx.NodeProto]:
    return {out: n for n in graph.node for out in n.output}


def quantised_convs(model: onnx.ModelProto) -> list[str]:
    """Convs whose weight is read through DequantizeLinear (the ones running int8)."""
    prod = _producers(model.graph)
    out = []
    for n in model.graph.node:
        if n.op_type == "Conv" and len(n.input) > 1:
            src = prod.get(n.input[1])
            if src is not None and src.op_type == "DequantizeLinear":
                out.append(n.name)
    return out


def _constant(model: onnx.ModelProto, name: str) -> np.ndarray | None:
    for init in model.graph.initializer:
        if init.name == name:
            return numpy_helper.to_array(init)
    for n in model.graph.node:
        if n.op_type == "Constant" and n.output[0] == name:
            for a in n.attribute:
                if a.name == "value":
                    return numpy_helper.to_array(a.t)
    return None


def _dequantised(model: onnx.ModelProto, dq: onnx.NodeProto) -> np.ndarray | None:
    """The fp32 value of a DequantizeLinear over constants, or None if an input is not one."""
    values = [_constant(model, i) for i in dq.input]
    if any(v is None for v in values[:2]):
        return None
    q, scale = values[0], values[1]
    zero = values[2] if len(values) > 2 and values[2] is not None else np.zeros_like(scale)
    assert q is not None and scale is not None and zero is not None
    axis = next((a.i for a in dq.attribute if a.name == "axis"), 1)
    shape = [1] * q.ndim
    if scale.ndim == 1 and scale.size > 1:
        shape[axis % q.ndim] = scale.size
    return ((q.astype(np.float64) - zero.reshape(shape)) * scale.reshape(shape)).astype(np.float32)


def _prune(graph: onnx.GraphProto) -> None:
    """Drop nodes and initializers nothing reads any more (the bypassed QDQ pairs)."""
    outputs = {o.name for o in graph.output}
    while True:
        used = {i for n in graph.node for i in n.input} | outputs
        dead = [n for n in graph.node if not any(o in used for o in n.output)]
        if not dead:
            break
        for n in dead:
            graph.node.remove(n)
    used = {i for n in graph.node for i in n.input}
    for init in [i for i in graph.initializer if i.name not in used]:
        graph.initializer.remove(init)


def _fp32_inputs(fp32_model: onnx.ModelProto | None) -> dict[tuple[str, int], np.ndarray]:
    """(conv name, input index) -> the fp32 graph's constant there (weights, biases): the
    quantiser keeps node names, so a Conv's original parameters are found by its name."""
    if fp32_model is None:
        return {}
    out = {}
    for n in fp32_model.graph.node:
        if n.op_type == "Conv":
            for k, name in enumerate(n.input[1:], start=1):
                value = _constant(fp32_model, name)
                if value is not None:
                    out[(n.name, k)] = value
    return out


def keep_fp32(
    model: onnx.ModelProto, names: Sequence[str], fp32_model: onnx.ModelProto | None = None
) -> onnx.ModelProto:
    """A copy of the int8 QDQ ``model`` with the Convs ``names`` computing in fp32 (see the
    module notes): weights and biases from ``fp32_model`` (the graph that was quantised) when
    given, else dequantised from the int8 graph. InputError for a name that is no quantised
    Conv of the graph."""
    known = set(quantised_convs(model))
    missing = [n for n in names if n not in known]
    if missing:
        raise InputError(f"mixed precision: no quantised Conv named {', '.join(missing)}")
    out = onnx.ModelProto()
    out.CopyFrom(model)
    graph = out.graph
    prod = _producers(graph)
    wanted = set(names)
    originals = _fp32_inputs(fp32_model)
    for node in graph.node:
        if node.name not in wanted:
            continue
        for k, name in enumerate(node.input):
            dq = prod.get(name)
            if dq is None or dq.op_type != "DequantizeLinear":
                continue
            q = prod.get(dq.input[0])
            if q is not None and q.op_type == "QuantizeLinear":
                node.input[k] = q.input[0]  # the activation before rounding
                continue
            value = originals.get((node.name, k))
            if value is None:
                value = _dequantised(out, dq)
            if value is not None:
                fresh = f"{node.name}_fp32_input{k}"
                graph.initializer.append(numpy_helper.from_array(value, fresh))
                node.input[k] = fresh
    # The layer's output rounding (QuantizeLinear -> DequantizeLinear after the Conv) goes too,
    # except where an int8 Conv reads it directly: that conv's input stays quantised.
    int8_convs = set(quantised_convs(model)) - wanted
    readers: dict[str, list[onnx.NodeProto]] = {}
    for n in graph.node:
        for name in n.input:
            readers.setdefault(name, []).append(n)
    for node in [n for n in graph.node if n.name in wanted]:
        for q in [r for r in readers.get(node.output[0], []) if r.op_type == "QuantizeLinear"]:
            for dq in [r for r in readers.get(q.output[0], []) if r.op_type == "DequantizeLinear"]:
                for reader in readers.get(dq.output[0], []):
                    if reader.name in int8_convs:
                        continue
                    for k, name in enumerate(reader.input):
                        if name == dq.output[0]:
                            reader.input[k] = node.output[0]
    _prune(graph)
    return out


def _outputs(model: onnx.ModelProto | bytes, samples: Sequence[dict], threads: int) -> list:
    from msfnet.export.verify import cpu_session

    data = model if isinstance(model, bytes) else model.SerializeToString()
    sess = cpu_session(data, threads)
    return [sess.run(["normals"], feeds)[0] for feeds in samples]


def mean_deviation(
    outs: Sequence[np.ndarray], refs: Sequence[np.ndarray], masks: Sequence[np.ndarray]
) -> float:
    """Mean angle (deg) over every sample's mask pixels, samples weighted by their pixels."""
    from msfnet.runtime.evaluate.metrics import deviation_deg

    total = weight = 0.0
    for out, ref, mask in zip(outs, refs, masks, strict=True):
        mean, _ = deviation_deg(out, ref, mask)
        total += mean * float(mask.sum())
        weight += float(mask.sum())
    return total / max(weight, 1.0)


def sensitivity(
    qmodel: onnx.ModelProto,
    fp32_model: onnx.ModelProto | None,
    samples: Sequence[dict],
    masks: Sequence[np.ndarray],
    refs: Sequence[np.ndarray],
    threads: int = 1,
) -> tuple[float, dict[str, float]]:
    """(int8 mean deg, {conv: deg gained with that conv alone back in fp32}); ``refs``: the
    fp32 graph's outputs on ``samples``."""
    base = mean_deviation(_outputs(qmodel, samples, threads), refs, masks)
    gains = {}
    for name in quantised_convs(qmodel):
        trial = keep_fp32(qmodel, [name], fp32_model)
        gains[name] = base - mean_deviation(_outputs(trial, samples, threads), refs, masks)
    return base, gains


def mixed_precision(
    fp32_model: onnx.ModelProto,
    qmodel: onnx.ModelProto,
    samples: Sequence[dict],
    masks: Sequence[np.ndarray],
    *,
    target_deg: float = DEFAULT_TARGET_DEG,
    max_layers: int = DEFAULT_MAX_LAYERS,
    threads: int = 1,
) -> tuple[onnx.ModelProto, MixedPrecisionReport]:
    """The int8 graph with the fewest sensitive Convs back in fp32 that brings it within
    ``target_deg`` mean of ``fp32_model`` on ``samples`` (network feeds with their ``masks``),
    at most ``max_layers`` of them (then the best reached, which the report shows)."""
    if not samples or len(samples) != len(masks):
        raise InputError("mixed precision needs held-out samples, one mask each")
    refs = _outputs(fp32_model, samples, threads)
    base, gains = sensitivity(qmodel, fp32_model, samples, masks, refs, threads)
    order = sorted(gains, key=lambda n: gains[n], reverse=True)
    chosen: list[str] = []
    steps: list[tuple[str, float]] = []
    best, dev = qmodel, base
    for name in order:
        if dev <= target_deg or len(chosen) >= max_layers or gains[name] <= 0:
            break
        trial = keep_fp32(qmodel, [*chosen, name], fp32_model)
        trial_dev = mean_deviation(_outputs(trial, samples, threads), refs, masks)
        if trial_dev >= dev:  # helped alone, not on top of the others: stays int8
            continue
        chosen.append(name)
        steps.append((name, trial_dev))
        best, dev = trial, trial_dev
    report = MixedPrecisionReport(
        base, dev, tuple(chosen), tuple(steps), gains, len(quantised_convs(qmodel))
    )
    return best, report


__all__ = [
    "DEFAULT_MAX_LAYERS",
    "DEFAULT_TARGET_DEG",
    "MixedPrecisionReport",
    "keep_fp32",
    "mean_deviation",
    "mixed_precision",
    "quantised_convs",
    "sensitivity",
]
