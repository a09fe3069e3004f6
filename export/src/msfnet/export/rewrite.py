"""Rewrite 4x4 stride-2 transposed convolutions as four 2x2 Convs + Concat + DepthToSpace.

Why: ONNX Runtime's static int8 path has no quantised ConvTranspose, so those layers stay fp32
and dominate the int8 run time. A ConvTranspose(k=4, s=2, p=1) is exactly four 2x2
convolutions over the *input* grid, one per output phase (row parity a, column parity b),
interleaved by a pixel shuffle (Concat, then DepthToSpace in DCR mode). Every layer then
becomes a plain Conv that quantises, doing only the useful multiply-adds (one 3x3 convolution
to 4x the channels would do 9/4 of them, and ran int8 slower: docs/benchmark.md).

Derivation (1-D, per axis): ConvTranspose writes y[2*i' - 1 + k] += x[i'] * w[k]. For output
row 2*i + a the contributing input rows are i' = i + d with d in {-1, 0, 1}:
  a = 0: d = 0 -> k = 1, d = -1 -> k = 3        a = 1: d = 0 -> k = 2, d = +1 -> k = 0
so phase 0 reads a 2x2 window starting at offset -1 through taps (3, 1), phase 1 one starting
at offset 0 through taps (2, 0).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import onnx
from onnx import helper, numpy_helper

# PHASE_TAPS[a]: 4x4 kernel rows feeding output phase a from its 2x2 input window
# (starting at offset -1 for a = 0 and 0 for a = 1: the derivation above)
PHASE_TAPS = ((3, 1), (2, 0))


def deconv_weight_as_phases(weight: np.ndarray) -> list[np.ndarray]:
    """ConvTranspose weight (Cin, Cout, 4, 4) -> four 2x2 Conv weights (Cout, Cin, 2, 2),
    phase order (a, b) = (0,0), (0,1), (1,0), (1,1): no zero taps, the useful MACs only."""
    wt = weight.transpose(1, 0, 2, 3)
    return [
        np.ascontiguousarray(wt[:, :, list(PHASE_TAPS[a])][:, :, :, list(PHASE_TAPS[b])])
        for a in range(2)
        for b in range(2)
    ]


def _attrs(node: onnx.NodeProto) -> dict[str, Any]:
    return {a.name: helper.get_attribute_value(a) for a in node.attribute}


def _is_rewritable(node: onnx.NodeProto, inits: dict[str, onnx.TensorProto]) -> bool:
    if node.op_type != "ConvTranspose" or len(node.input) < 2 or node.input[1] not in inits:
        return False
    if len(node.input) > 2 and node.input[2]:  # a bias (this network's deconvs have none)
        return False
    at = _attrs(node)
    shape = list(inits[node.input[1]].dims)
    return (
        len(shape) == 4
        and shape[2:] == [4, 4]
        and list(at.get("strides", [1, 1])) == [2, 2]
        and list(at.get("pads", [0] * 4)) == [1, 1, 1, 1]
        and at.get("group", 1) == 1
        and list(at.get("dilations", [1, 1])) == [1, 1]
        and not any(at.get("output_padding", []))
        and "output_shape" not in at
        and at.get("auto_pad", b"NOTSET") in (b"NOTSET", "NOTSET")
    )


def _phase_nodes(
    node: onnx.NodeProto, weight: np.ndarray, graph: onnx.GraphProto, base: str
) -> list[onnx.NodeProto]:
    """Four 2x2 convs (asymmetric pads pick each phase's window) -> Concat -> DCR shuffle."""
    nodes, outs = [], []
    for p, w in enumerate(deconv_weight_as_phases(weight)):
        a, b = divmod(p, 2)
        wname = f"{node.input[1]}_phase{p}"
        graph.initializer.append(numpy_helper.from_array(w, wname))
        out = f"{node.output[0]}_phase{p}"
        outs.append(out)
        nodes.append(
            helper.make_node(
                "Conv",
                [node.input[0], wname],
                [out],
                name=f"{base}_phase{p}",
                kernel_shape=[2, 2],
                pads=[1 - a, 1 - b, a, b],
                strides=[1, 1],
            )
        )
    cat = f"{node.output[0]}_phases"
    nodes.append(helper.make_node("Concat", outs, [cat], name=f"{base}_cat", axis=1))
    nodes.append(
        helper.make_node(
            "DepthToSpace", [cat], list(node.output), name=f"{base}_d2s", blocksize=2, mode="DCR"
        )
    )
    return nodes


def rewrite_deconvs(model: onnx.ModelProto) -> tuple[onnx.ModelProto, int]:
    """Return a copy of ``model`` with every rewritable (bias-free 4x4 stride-2) ConvTranspose
    replaced by its phase convolutions; and how many were."""
    model = onnx.ModelProto.FromString(model.SerializeToString())
    graph = model.graph
    inits = {t.name: t for t in graph.initializer}
    new_nodes: list[onnx.NodeProto] = []
    count = 0
    for node in graph.node:
        if not _is_rewritable(node, inits):
            new_nodes.append(node)
            continue
        count += 1
        weight = numpy_helper.to_array(inits[node.input[1]])
        new_nodes.extend(_phase_nodes(node, weight, graph, node.name or f"deconv{count}"))
    del graph.node[:]
    graph.node.extend(new_nodes)
    # drop the now unused ConvTranspose weights
    used = {i for n in graph.node for i in n.input}
    keep = [t for t in graph.initializer if t.name in used]
    del graph.initializer[:]
    graph.initializer.extend(keep)
    onnx.checker.check_model(model)
    return model, count
