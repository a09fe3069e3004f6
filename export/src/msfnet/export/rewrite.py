"""Rewrite 4x4 stride-2 transposed convolutions as Conv (4x channels) + DepthToSpace.

Why: ONNX Runtime's static int8 path has no quantised ConvTranspose, so those layers stay fp32
and dominate the int8 run time. A ConvTranspose(k=4, s=2, p=1) is exactly a 3x3 convolution
(pad 1) over the *input* grid that produces the 4 output phases (row parity a, column parity b)
as 4x the channels, followed by a pixel shuffle (DepthToSpace, CRD mode). Every layer then
becomes a plain Conv that quantises.

Derivation (1-D, per axis): ConvTranspose writes y[2*i' - 1 + k] += x[i'] * w[k]. For output
row 2*i + a the contributing input rows are i' = i + d with d in {-1, 0, 1}:
  a = 0: d = 0 -> k = 1, d = -1 -> k = 3        a = 1: d = 0 -> k = 2, d = +1 -> k = 0
Taps that do not exist are zero in the 3x3 kernel (the rewrite does 9/4 of the useful MACs on
those layers, a price int8 repays several times).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import onnx
from onnx import helper, numpy_helper

# KERNEL_TAP[a][d + 1]: which 4x4 kernel index feeds output phase a from input offset d (-1: none)
KERNEL_TAP = ((3, 1, -1), (-1, 2, 0))


def deconv_weight_as_conv(weight: np.ndarray) -> np.ndarray:
    """ConvTranspose weight (Cin, Cout, 4, 4) -> Conv weight (4*Cout, Cin, 3, 3), CRD order.

    Output channel co*4 + a*2 + b holds phase (a, b) of transposed-conv channel co, which is
    the channel order DepthToSpace(mode="CRD") (= torch PixelShuffle) expects.
    """
    cin, cout, kh, kw = weight.shape
    if (kh, kw) != (4, 4):
        raise ValueError(f"expected a 4x4 kernel, got {kh}x{kw}")
    out = np.zeros((cout, 2, 2, cin, 3, 3), dtype=weight.dtype)
    wt = weight.transpose(1, 0, 2, 3)  # (Cout, Cin, 4, 4)
    for a in range(2):
        for b in range(2):
            for u in range(3):
                ky = KERNEL_TAP[a][u]
                if ky < 0:
                    continue
                for v in range(3):
                    kx = KERNEL_TAP[b][v]
                    if kx >= 0:
                        out[:, a, b, :, u, v] = wt[:, :, ky, kx]
    return out.reshape(cout * 4, cin, 3, 3)


# PHASE_TAPS[a]: 4x4 kernel rows feeding output phase a from its 2x2 input window
# (window starts at offset -1 for a = 0 and 0 for a = 1; see the derivation above)
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


def rewrite_deconvs(model: onnx.ModelProto, mode: str = "conv3x3") -> tuple[onnx.ModelProto, int]:
    """Return a copy of ``model`` with every rewritable ConvTranspose replaced; and the count.

    mode "conv3x3": one 3x3 conv to 4*Cout channels + DepthToSpace (CRD): fewest nodes, 9/4
    of the MACs. mode "phases": four 2x2 convs + Concat + DepthToSpace (DCR): exact MACs.
    Bias-free ConvTranspose only in "phases" mode (this network's deconvs have no bias).
    """
    if mode not in ("conv3x3", "phases"):
        raise ValueError(f"rewrite mode {mode!r}: expected conv3x3 or phases")
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
        base = node.name or f"deconv{count}"
        if mode == "phases" and not (len(node.input) > 2 and node.input[2]):
            new_nodes.extend(_phase_nodes(node, weight, graph, base))
            continue
        wname = f"{node.input[1]}_as_conv"
        graph.initializer.append(numpy_helper.from_array(deconv_weight_as_conv(weight), wname))
        mid = f"{node.output[0]}_phases"
        conv_inputs = [node.input[0], wname]
        if len(node.input) > 2 and node.input[2]:
            # per-channel bias repeats over the 4 phases of each output channel
            bias = numpy_helper.to_array(inits[node.input[2]])
            bname = f"{node.input[2]}_as_conv"
            graph.initializer.append(numpy_helper.from_array(np.repeat(bias, 4), bname))
            conv_inputs.append(bname)
        new_nodes.append(
            helper.make_node(
                "Conv",
                conv_inputs,
                [mid],
                name=f"{base}_conv",
                kernel_shape=[3, 3],
                pads=[1, 1, 1, 1],
                strides=[1, 1],
            )
        )
        new_nodes.append(
            helper.make_node(
                "DepthToSpace",
                [mid],
                list(node.output),
                name=f"{base}_d2s",
                blocksize=2,
                mode="CRD",
            )
        )
    del graph.node[:]
    graph.node.extend(new_nodes)
    # drop the now unused ConvTranspose weights
    used = {i for n in graph.node for i in n.input}
    keep = [t for t in graph.initializer if t.name in used]
    del graph.initializer[:]
    graph.initializer.extend(keep)
    onnx.checker.check_model(model)
    return model, count
