"""The passes a variant applies, in order, to one in-memory ``onnx.ModelProto``.

Each pass takes the model so far (None before the first) and the export's context, and returns
the next model. None of them writes the output: ``pipeline.run_export`` does that once.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import onnx

from msfnet.common.files import scratch_folder
from msfnet.common.version import installed_version
from msfnet.export.onnx_export import (
    export_proto,
    export_staged_proto,
    set_metadata,
    simplify,
    store_weights_fp16,
)
from msfnet.export.variants import ExportOptions, Variant
from msfnet.model.checkpoint import sha256_of
from msfnet.model.network import MSFNet
from msfnet.runtime.contract import METADATA_KEYS, model_metadata
from msfnet.runtime.stack import Stack

PRECISION_LABELS = {
    "fp32": "fp32",
    "fp16-weights": "fp32 (fp16-stored weights)",
    "int8": "int8-qdq",
}


@dataclass
class PassContext:
    """What the passes share: the torch network (already fp16-rounded for fp16 variants), the
    request, calibration stacks, the output path (scratch files go beside it) and notes for the
    result."""

    model: MSFNet
    variant: Variant
    options: ExportOptions
    checkpoint: Path
    output: Path
    stacks: list[Stack] = field(default_factory=list)
    notes: dict[str, object] = field(default_factory=dict)


PassFn = Callable[[onnx.ModelProto | None, PassContext], onnx.ModelProto]


@dataclass(frozen=True)
class Pass:
    """``lossy``: changes the numbers beyond float32 rounding; the pipeline verifies the model
    as it stands before the first lossy pass against PyTorch, and uses it as the reference."""

    name: str
    run: PassFn
    lossy: bool = False


def _torch_export(_: onnx.ModelProto | None, ctx: PassContext) -> onnx.ModelProto:
    return export_proto(ctx.model, ctx.options.opset, ctx.options.static)


def _torch_export_staged(_: onnx.ModelProto | None, ctx: PassContext) -> onnx.ModelProto:
    return export_staged_proto(ctx.model, ctx.options.opset)


def _metadata(proto: onnx.ModelProto | None, ctx: PassContext) -> onnx.ModelProto:
    """The contract's metadata (``runtime.contract.model_metadata``, the variant's name
    included) in place of whatever the torch export left."""
    assert proto is not None
    static = ctx.options.static
    set_metadata(
        proto,
        model_metadata(
            train_lights=ctx.options.train_lights,
            checkpoint_sha256=sha256_of(ctx.checkpoint),
            version=installed_version(),
            static_shape=None if static is None else (static.lights, static.height, static.width),
            precision=PRECISION_LABELS[ctx.variant.precision],
            staged=ctx.variant.graph == "staged",
            variant=ctx.variant.name,
        ),
        replace_all=True,
    )
    proto.doc_string = "MSF-Net photometric stereo (msfnet): images + lights -> unit normals"
    return proto


def _simplify(proto: onnx.ModelProto | None, _: PassContext) -> onnx.ModelProto:
    assert proto is not None
    return simplify(proto)


def _fp16_storage(proto: onnx.ModelProto | None, _: PassContext) -> onnx.ModelProto:
    assert proto is not None
    return store_weights_fp16(proto)


def _rewrite_deconvs(proto: onnx.ModelProto | None, ctx: PassContext) -> onnx.ModelProto:
    """ConvTranspose -> four 2x2 phase convs + DepthToSpace (exact in fp32), so they quantise
    (docs/benchmark.md, "Measurements behind the code's rules")."""
    from msfnet.export.rewrite import rewrite_deconvs

    assert proto is not None
    rewritten, count = rewrite_deconvs(proto)
    ctx.notes["deconvs_rewritten"] = count
    return rewritten


def _quantise_int8(proto: onnx.ModelProto | None, ctx: PassContext) -> onnx.ModelProto:
    from msfnet.export.quantize import quantize_model

    assert proto is not None
    o = ctx.options
    with scratch_folder(ctx.output) as scratch:
        qmodel, summary = quantize_model(
            proto,
            ctx.stacks,
            scratch,
            tile=o.calib_tile,
            lights=o.calib_lights,
            tiles_per_stack=o.calib_tiles_per_stack,
            train_lights=o.train_lights,
            reduce_range=o.reduce_range,
        )
    summary = {
        "deconvs_rewritten": ctx.notes.get("deconvs_rewritten", 0),
        **summary,
        "rewrite": "phases",
    }
    ctx.notes["quantization"] = summary
    set_metadata(
        qmodel,
        {
            METADATA_KEYS["precision"]: PRECISION_LABELS["int8"],
            METADATA_KEYS["quantization"]: json.dumps(summary),
        },
    )
    return qmodel


def _quantise_int8_mixed(proto: onnx.ModelProto | None, ctx: PassContext) -> onnx.ModelProto:
    """int8, then the most sensitive convs back in fp32 until the graph is within
    mixed_precision.DEFAULT_TARGET_DEG of fp32 on held-out tiles of the calibration stacks
    (other tiles than the calibration's own; never validation data unless given as --calib)."""
    from msfnet.export.mixed_precision import DEFAULT_TARGET_DEG, mixed_precision
    from msfnet.export.quantize import calibration_tiles, ranged_quantisers

    assert proto is not None
    qmodel = _quantise_int8(proto, ctx)
    o = ctx.options
    tiles = list(
        calibration_tiles(
            ctx.stacks,
            tile=o.calib_tile,
            lights=min(o.calib_lights, 32),  # sensitivity, not ranges: 8 and 32 lights suffice
            tiles_per_stack=o.calib_tiles_per_stack,
            train_lights=o.train_lights,
            # other tiles than the calibration's (seed 0) and the verification's (seed 1000, in
            # verify.py), so the written file is checked on tiles the selection never saw
            seed=2000,
        )
    )
    mixed, report = mixed_precision(
        proto, qmodel, [t[0] for t in tiles], [t[1] for t in tiles], target_deg=DEFAULT_TARGET_DEG
    )
    prior = ctx.notes["quantization"]
    assert isinstance(prior, dict)
    summary = {**prior, "mixed_precision": report.as_dict()}
    if prior.get("ranges_from_percentiles"):
        # the quantisers of the layers back in fp32 went with them: count what is left
        summary["ranges_from_percentiles"] = ranged_quantisers(mixed, proto)
    ctx.notes["quantization"] = summary
    set_metadata(mixed, {METADATA_KEYS["quantization"]: json.dumps(summary)})
    return mixed


PASSES: dict[str, Pass] = {
    p.name: p
    for p in (
        Pass("torch-export", _torch_export),
        Pass("torch-export-staged", _torch_export_staged),
        Pass("metadata", _metadata),
        Pass("simplify", _simplify),
        Pass("fp16-storage", _fp16_storage),
        Pass("rewrite-deconvs", _rewrite_deconvs),
        Pass("quantise-int8", _quantise_int8, lossy=True),
        Pass("quantise-int8-mixed", _quantise_int8_mixed, lossy=True),
    )
}

__all__ = ["PASSES", "PRECISION_LABELS", "Pass", "PassContext"]
