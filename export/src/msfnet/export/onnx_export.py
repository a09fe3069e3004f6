"""Checkpoint -> ONNX model in memory: torch export, metadata, fp16 storage, simplification.

The ONNX contract (also in the README):
  inputs   images  float32 (B, N, 3, H, W)  normalised as msfnet.runtime.infer.normalise.normalise
           lights  float32 (B, N, 3)        unit directions, x right, y up, z to the camera
  output   normals float32 (B, 3, H, W)     unit normals, same frame
  N, H, W (and B) are dynamic unless exported --static; H and W must be multiples of 4.

Every function here works on an ``onnx.ModelProto`` in memory; only ``pipeline.export_variant``
writes a file (once, after all passes) and verifies that file (``verify.py``).
"""

from __future__ import annotations

import io
import warnings
from typing import Any

import numpy as np
import onnx
import torch

from msfnet.common.errors import InputError
from msfnet.common.vocabulary import opt
from msfnet.export.variants import StaticShape
from msfnet.model.network import MSFNet

EXAMPLE_SHAPE = (2, 4, 24, 20)  # B, N, H, W of the tracing example: differs from every check
STAGED_CHECK_CHUNK = 3  # verification chunk: uneven splits of every checked light count


def random_inputs(
    batch: int, lights: int, height: int, width: int, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Plausible network inputs: positive normalised images and upper-hemisphere unit lights."""
    rng = np.random.default_rng(seed)
    images = rng.random((batch, lights, 3, height, width), dtype=np.float32)
    images *= np.float32(np.sqrt(1.0 / 32.0))  # about the scale normalise() produces
    dirs = rng.normal(size=(batch, lights, 3))
    dirs[..., 2] = np.abs(dirs[..., 2]) + 0.5
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    return images, dirs.astype(np.float32)


def rendered_inputs(
    batch: int, lights: int, height: int, width: int, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Network inputs from rendered non-Lambertian objects, normalised exactly as the runtime
    does, and their object masks (B, H, W): what a real stack looks like to the network.

    Only object pixels are compared: in the empty background a trained network's raw output is
    a near-zero vector whose direction is ill-conditioned (measured: ~0.5 against a median of
    ~100 before normalisation), and the runtime zeroes those pixels anyway."""
    from msfnet.runtime.infer.normalise import network_input
    from msfnet.synth.render import RenderOptions, render_stack

    images = np.empty((batch, lights, 3, height, width), np.float32)
    dirs = np.empty((batch, lights, 3), np.float32)
    masks = np.empty((batch, height, width), bool)
    options = RenderOptions(size=max(height, width), lights=lights)
    for b in range(batch):
        stack = render_stack(np.random.default_rng([seed, b]), options)
        x, lit = network_input(stack, slice(0, height), slice(0, width))
        images[b], dirs[b] = x[0], lit[0]
        masks[b] = stack.mask[:height, :width]
    return images, dirs, masks


def _export_bytes(
    module: torch.nn.Module, args: tuple[torch.Tensor, ...], **kwargs: Any
) -> onnx.ModelProto:
    """TorchScript export (dynamo=False: opset 17 and lower, GELU as Erf) into memory."""
    buffer = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # TorchScript exporter deprecation chatter
        # torch accepts a BytesIO here (its annotation says path only)
        torch.onnx.export(
            module,
            args,
            buffer,  # type: ignore[arg-type]
            do_constant_folding=True,
            dynamo=False,
            **kwargs,
        )
    return onnx.load_from_string(buffer.getvalue())


def export_staged_proto(model: MSFNet, opset: int) -> onnx.ModelProto:
    """The staged graph (see ``staged.py``): each entry point with its own dynamic axes, so a
    call can feed small placeholders to the entry points it does not use."""
    from msfnet.export.staged import StagedGraph
    from msfnet.runtime.engines.staged_loop import FEATURES, STAGE_INPUTS, STAGE_OUTPUTS

    _, n, h, w = EXAMPLE_SHAPE
    images, lights = (torch.from_numpy(a) for a in random_inputs(1, n, h, w))
    # Tracing example: every light count > 1 and every size distinct, or the exporter
    # specialises size-1 axes (measured: a placeholder-sized example broke the fusion reshape).
    gen = torch.Generator().manual_seed(0)
    example = {"images": images, "lights": lights}
    c = FEATURES
    for name, shape in (
        ("feat1_in", (3, c, 6, 5)),
        ("max1", (1, c, 6, 5)),
        ("feat2_in", (2, c, 5, 7)),
        ("max2", (1, c, 5, 7)),
        ("max3", (1, c, 6, 4)),
    ):
        example[name] = torch.rand(shape, generator=gen)
    feat = {0: "lights", 2: "half_height", 3: "half_width"}
    pooled = {2: "half_height", 3: "half_width"}
    dynamic = {
        "images": {1: "lights1", 3: "height", 4: "width"},
        "lights": {1: "lights1"},
        "feat1": {0: "lights1", 2: "height_2", 3: "width_2"},
        "feat1_in": {k: f"{v}_s2" for k, v in feat.items()},
        "max1": {k: f"{v}_s2" for k, v in pooled.items()},
        "feat2": {k: f"{v}_s2" for k, v in feat.items()},
        "feat2_in": {k: f"{v}_s3" for k, v in feat.items()},
        "max2": {k: f"{v}_s3" for k, v in pooled.items()},
        "feat3": {k: f"{v}_s3" for k, v in feat.items()},
        "max3": {2: "half_height_r", 3: "half_width_r"},
        "normals": {2: "out_height", 3: "out_width"},
    }
    # eval() first: export restores the wrapper's mode afterwards, and a fresh module is in
    # training mode, which would leave the network's BatchNorms training for verification
    proto = _export_bytes(
        StagedGraph(model).eval(),
        tuple(example[k] for k in STAGE_INPUTS),
        input_names=list(STAGE_INPUTS),
        output_names=list(STAGE_OUTPUTS),
        dynamic_axes=dynamic,
        opset_version=opset,
    )
    _declare_dims(proto, "normals", [1, 3, "out_height", "out_width"])
    return proto


def _declare_dims(proto: onnx.ModelProto, output: str, dims: list[int | str]) -> None:
    """Name an output's axes plainly: the exporter calls fixed ones 'Divnormals_dim_1', which
    onnxslim then resolves to numbers (and --simplify refused the changed axes)."""
    value = next(o for o in proto.graph.output if o.name == output)
    for dim, want in zip(value.type.tensor_type.shape.dim, dims, strict=True):
        if isinstance(want, int):
            dim.dim_value = want
        else:
            dim.dim_param = want


def export_proto(model: torch.nn.Module, opset: int, static: StaticShape | None) -> onnx.ModelProto:
    """The monolithic graph: dynamic B, N, H, W, or fixed shapes (batch 1) for ``static``."""
    if static is None:
        b, n, h, w = EXAMPLE_SHAPE
        dynamic = {
            "images": {0: "batch", 1: "lights", 3: "height", 4: "width"},
            "lights": {0: "batch", 1: "lights"},
            "normals": {0: "batch", 2: "height", 3: "width"},
        }
    else:
        b, n, h, w = 1, static.lights, static.height, static.width
        dynamic = None
    images, lights = (torch.from_numpy(a) for a in random_inputs(b, n, h, w))
    proto = _export_bytes(
        model,
        (images, lights),
        input_names=["images", "lights"],
        output_names=["normals"],
        dynamic_axes=dynamic,
        opset_version=opset,
    )
    _declare_dims(
        proto,
        "normals",
        ["batch", 3, "height", "width"] if static is None else [1, 3, static.height, static.width],
    )
    return proto


def set_metadata(
    proto: onnx.ModelProto, values: dict[str, str], *, replace_all: bool = False
) -> None:
    """Update (or with ``replace_all`` replace) metadata_props in place, keys kept in order."""
    current = {} if replace_all else {p.key: p.value for p in proto.metadata_props}
    current.update(values)
    del proto.metadata_props[:]
    for key, value in current.items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value


def store_weights_fp16(proto: onnx.ModelProto) -> onnx.ModelProto:
    """Store float32 weights as float16 (half the file), each followed by a Cast back to float32.

    ONNX Runtime folds the Casts when it loads the model, so it computes in float32 exactly as a
    float32 file holding the fp16-rounded weights would. Pair it with a network whose weights
    are fp16-rounded (the verification reference of the fp16 variants) and parity is exact.
    """
    from onnx import TensorProto, helper, numpy_helper

    casts = []
    for init in proto.graph.initializer:
        if init.data_type != TensorProto.FLOAT or int(np.prod(init.dims)) < 16:
            continue  # keep scalars and shape constants as they are
        half = numpy_helper.from_array(
            numpy_helper.to_array(init).astype(np.float16), f"{init.name}__fp16"
        )
        casts.append(
            helper.make_node(
                "Cast", [half.name], [init.name], to=TensorProto.FLOAT, name=f"{init.name}__to_fp32"
            )
        )
        init.CopyFrom(half)
    nodes = [*casts, *proto.graph.node]
    del proto.graph.node[:]
    proto.graph.node.extend(nodes)
    return proto


def _dims(proto: onnx.ModelProto) -> dict[str, list[str | int]]:
    return {
        v.name: [d.dim_param or d.dim_value for d in v.type.tensor_type.shape.dim]
        for v in [*proto.graph.input, *proto.graph.output]
    }


def simplify(proto: onnx.ModelProto) -> onnx.ModelProto:
    """Simplify the graph with onnxslim; refuse if any declared axis changed."""
    try:
        import onnxslim
    except ImportError as exc:
        raise InputError(
            f"{opt('simplify')} needs the onnxslim package: pip install onnxslim", option="simplify"
        ) from exc
    simplified = onnxslim.slim(proto)
    if _dims(simplified) != _dims(proto):
        raise InputError(
            f"simplification changed the input/output axes {_dims(proto)} -> {_dims(simplified)}"
        )
    return simplified


def default_checks(static: StaticShape | None) -> list[tuple[int, int, int]]:
    """Light counts unlike the tracing example, two of them at non-square sizes."""
    if static is not None:
        return [(static.lights, static.height, static.width)]
    return [(3, 32, 32), (7, 28, 44), (32, 16, 24)]


__all__ = [
    "EXAMPLE_SHAPE",
    "STAGED_CHECK_CHUNK",
    "default_checks",
    "export_proto",
    "export_staged_proto",
    "random_inputs",
    "rendered_inputs",
    "set_metadata",
    "simplify",
    "store_weights_fp16",
]
