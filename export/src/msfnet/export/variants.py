"""The export variants as one table (run by ``pipeline.export_variant``: checkpoint -> ONNX).

Each row of :data:`VARIANTS` names a graph form (dynamic, static or staged) and a precision
(fp32, fp16-stored weights, int8), the passes that build it and the rule its written file must
pass. The CLI (``msf-export --variant NAME`` or the flags), the benchmark and the tests all go
through this table.

The pipeline works on one in-memory ``onnx.ModelProto``: torch export -> metadata -> (simplify)
-> (fp16 storage | deconv rewrite -> int8 quantisation), then ONE write to a temporary sibling
of the target (``common/files.py``'s ``write_atomic``, as every msfnet output), verification of
exactly that file as ONNX Runtime loads it, and only then an atomic rename into place. Nothing
of a failed, interrupted or unverified export is left behind.

msf-export's flags are declared here, once, on the types that hold them (:class:`ExportOptions`,
:class:`ExportRequest`; common.vocabulary): the command's parser is built from them, and the
messages of this table name them through the same vocabulary.

This module imports no torch, onnx or onnxruntime at import time, so the CLI's argument
parsing and ``--list-variants`` stay instant; they load when an export starts.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from msfnet.common.cli import int_range, path_arg, positive_float, positive_int
from msfnet.common.vocabulary import flag, opt, options_type, verbatim
from msfnet.runtime.contract import TRAIN_LIGHTS

Graph = Literal["dynamic", "static", "staged"]
Precision = Literal["fp32", "fp16-weights", "int8"]
Reference = Literal["pytorch", "pytorch-fp16-weights", "fp32-graph"]

DEFAULT_OPSET = 17  # TorchScript exporter: GELU as Erf, runs on older runtimes (OpenVINO 2022)
# Measured with torch 2.13: opset 7 has no Expand, 8 gives a graph ORT rejects; 20 is the
# TorchScript exporter's highest (torch.onnx._constants.ONNX_TORCHSCRIPT_EXPORTER_MAX_OPSET).
MIN_OPSET, MAX_OPSET = 9, 20
MIN_INT8_OPSET = 13  # per-channel QuantizeLinear / DequantizeLinear (axis attribute)
TOLERANCE_DEG = 0.01
# int8 vs the fp32 graph, mean over held-out 64 px calibration tiles: between the shipped
# recipe (~1 deg) and the known failure mode, the regressor quantised (~2.5 deg; the figures:
# docs/benchmark.md, "Measurements behind the code's rules").
INT8_MEAN_LIMIT_DEG = 1.5
# A trained network's normals leave its final L2 normalisation with |n| = 1 to ~1e-7; an
# all-zero or dead network gives |n| = 0 there, which an angle check alone cannot see
# (atan2(0, 0) = 0 deg "agrees" perfectly with an equally dead PyTorch reference).
UNIT_NORM_TOL = 1e-3


@dataclass(frozen=True)
class StaticShape:
    """N, H, W of a fixed-shape export (batch 1)."""

    lights: int
    height: int
    width: int

    @classmethod
    def parse(cls, text: str) -> StaticShape:
        """'32,128,128' -> StaticShape; ValueError with the problem otherwise."""
        try:
            n, h, w = (int(v) for v in text.split(","))
        except ValueError:
            raise ValueError(f"{text!r}: expected N,H,W such as 32,128,128") from None
        if n < 1 or h < 4 or w < 4 or h % 4 or w % 4:
            raise ValueError(f"{text!r}: need N >= 1 and H, W positive multiples of 4")
        return cls(n, h, w)

    def __str__(self) -> str:
        return f"{self.lights},{self.height},{self.width}"


def static_shape(text: str) -> StaticShape:
    """The ``--static`` value: :meth:`StaticShape.parse`, refused as a usage error."""
    try:
        return StaticShape.parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


@dataclass(frozen=True)
class VerifyRule:
    """What the written file is compared with, on what inputs, and the bound it must meet.

    statistic "max": the largest angle over all object pixels of all checks; "mean": the
    pixel-weighted mean angle over all of them (the max is still reported). Every check also
    needs unit normals (| |n| - 1 | <= unit_norm_tol) on every object pixel.
    """

    reference: Reference
    inputs: Literal["rendered", "calibration-tiles"]
    statistic: Literal["max", "mean"]
    limit_deg: float
    unit_norm_tol: float = UNIT_NORM_TOL

    def describe(self, limit_deg: float | None = None) -> str:
        ref = {
            "pytorch": "PyTorch",
            "pytorch-fp16-weights": "PyTorch with fp16-rounded weights",
            "fp32-graph": "the verified fp32 graph",
        }[self.reference]
        inputs = {
            "rendered": "rendered non-Lambertian objects",
            "calibration-tiles": "held-out tiles of the calibration stacks",
        }[self.inputs]
        limit = self.limit_deg if limit_deg is None else limit_deg
        return f"{self.statistic} <= {limit:g} deg vs {ref}, object pixels of {inputs}"


FP32_RULE = VerifyRule("pytorch", "rendered", "max", TOLERANCE_DEG)
FP16_RULE = VerifyRule("pytorch-fp16-weights", "rendered", "max", TOLERANCE_DEG)
INT8_RULE = VerifyRule("fp32-graph", "calibration-tiles", "mean", INT8_MEAN_LIMIT_DEG)


@dataclass(frozen=True)
class Variant:
    """One row of the table: a graph form, a precision, its passes and its verification rule.

    ``passes`` name entries of ``msfnet.export.passes.PASSES``, run in order on the in-memory
    model (``simplify`` is inserted after ``metadata`` when asked for)."""

    name: str
    summary: str
    graph: Graph
    precision: Precision
    passes: tuple[str, ...]
    rule: VerifyRule

    @property
    def needs_calibration(self) -> bool:
        return self.precision == "int8"

    @property
    def needs_shape(self) -> bool:
        return self.graph == "static"

    def effective_passes(self, simplify: bool = False) -> tuple[str, ...]:
        if not simplify:
            return self.passes
        i = self.passes.index("metadata") + 1
        return (*self.passes[:i], "simplify", *self.passes[i:])


_EXPORT = ("torch-export", "metadata")
_STAGED = ("torch-export-staged", "metadata")
_INT8 = ("rewrite-deconvs", "quantise-int8")

VARIANTS: tuple[Variant, ...] = (
    Variant("fp32", "dynamic N, H, W; float32", "dynamic", "fp32", _EXPORT, FP32_RULE),
    Variant(
        "fp16",
        "weights stored in float16 (half the file), computed in float32",
        "dynamic",
        "fp16-weights",
        (*_EXPORT, "fp16-storage"),
        FP16_RULE,
    ),
    Variant(
        "static",
        "fixed N, H, W (batch 1) for NPU / OpenVINO / OAK compilers",
        "static",
        "fp32",
        _EXPORT,
        FP32_RULE,
    ),
    Variant(
        "static-fp16",
        "fixed shapes, weights stored in float16",
        "static",
        "fp16-weights",
        (*_EXPORT, "fp16-storage"),
        FP16_RULE,
    ),
    Variant(
        "staged",
        "cut at the three max-over-lights steps; msf-run feeds a few lights a call",
        "staged",
        "fp32",
        _STAGED,
        FP32_RULE,
    ),
    Variant(
        "staged-fp16",
        "staged graph, weights stored in float16",
        "staged",
        "fp16-weights",
        (*_STAGED, "fp16-storage"),
        FP16_RULE,
    ),
    Variant(
        "int8",
        "static int8 QDQ of the extractors' convs, calibrated on real stacks",
        "dynamic",
        "int8",
        (*_EXPORT, *_INT8),
        INT8_RULE,
    ),
    Variant(
        "int8-mixed",
        "int8 with the convs most sensitive on held-out calibration tiles back in fp32 "
        "(export/mixed_precision.py)",
        "dynamic",
        "int8",
        (*_EXPORT, "rewrite-deconvs", "quantise-int8-mixed"),
        INT8_RULE,
    ),
    Variant(
        "staged-int8",
        "staged graph, int8 QDQ (each entry point calibrated on the fp32 "
        "graph's own stage outputs)",
        "staged",
        "int8",
        (*_STAGED, *_INT8),
        INT8_RULE,
    ),
)

VARIANT_NAMES = tuple(v.name for v in VARIANTS)


def get_variant(name: str | Variant) -> Variant:
    """The table row called ``name`` (a Variant is returned as it is)."""
    if isinstance(name, Variant):
        return name
    for v in VARIANTS:
        if v.name == name:
            return v
    raise ValueError(f"unknown export variant {name!r} (one of {', '.join(VARIANT_NAMES)})")


def variant_for(
    *,
    static: bool = False,
    staged: bool = False,
    plain: bool = False,
    fp16_weights: bool = False,
    int8: bool = False,
) -> Variant:
    """The row the flags (--static, --plain, --staged, --fp16-weights, --int8) describe.

    The graph is staged unless --static or --plain asks for one graph: msf-run runs the staged
    graph light-chunked, in a fraction of the memory at many lights and as fast or faster on
    whole images; other runtimes need the single graph. ``staged`` is the default, kept so
    older command lines stay valid."""
    from msfnet.common.errors import InputError

    if staged and static:
        raise InputError(
            f"{opt('staged')} and {opt('static')} do not combine (the staged graph's entry "
            "points need dynamic shapes)",
            option="staged",
        )
    if staged and plain:
        raise InputError(
            f"{opt('staged')} and {opt('plain')} contradict each other", option="staged"
        )
    if int8 and fp16_weights:
        raise InputError(
            f"{opt('int8')} and {opt('fp16_weights')} do not combine (int8 stores its own weights)",
            option="int8",
        )
    graph: Graph = "static" if static else "dynamic" if plain else "staged"
    precision: Precision = "int8" if int8 else "fp16-weights" if fp16_weights else "fp32"
    for v in VARIANTS:
        if v.graph == graph and v.precision == precision:
            return v
    raise InputError(
        f"no export variant has a {graph} graph in {precision} (static int8: "
        "calibration feeds tiles at several light counts, which a fixed-shape "
        "graph cannot take)"
    )


# The categories of msf-export's flags: the sections of its help, in this order (ExportRequest's
# flags before ExportOptions' within each); "" the variant choice after the output file.
GRAPH_FLAGS = "graph"  # how the graph is built and checked
INT8_FLAGS = "int8"  # int8 quantisation: the flag, its calibration stacks, the weights' bit width
STORAGE_FLAGS = "storage"  # weight storage, staged or plain graph, overwriting the output
FLAG_SECTIONS = ("", GRAPH_FLAGS, INT8_FLAGS, STORAGE_FLAGS)


@options_type
@dataclass(frozen=True)
class ExportOptions:
    """Settings shared by all variants. ``tolerance_deg`` None: the variant's own limit.
    ``checks``: (N, H, W) of the rendered checks (default: N = 3, 7, 32 at non-square sizes,
    or the static shape). ``calib_*``: int8 calibration (and verification) tiles.
    ``weight_bits``: int8 weights in 7 or 8 bits (None: 7 where this CPU lacks VNNI, see
    quantize.quantize_model; 7-bit files compute exactly on every CPU, so a model shipped to
    other machines is exported with 7). The flagged fields are msf-export's too."""

    opset: int = flag(
        DEFAULT_OPSET,
        f"ONNX opset, {MIN_OPSET}-{MAX_OPSET} (default {DEFAULT_OPSET}: GELU as Erf, widest "
        f"runtime support; int8 needs {MIN_INT8_OPSET} or higher)",
        type=int_range(MIN_OPSET, MAX_OPSET),
        category=GRAPH_FLAGS,
    )
    train_lights: int = flag(
        TRAIN_LIGHTS,
        "light count the model was trained with; stored in the metadata and used by the "
        f"runtime's sqrt(N / train_lights) scaling (default {TRAIN_LIGHTS})",
        type=positive_int,
        category=GRAPH_FLAGS,
    )
    static: StaticShape | None = flag(
        None,
        "export fixed shapes (batch 1) for NPUs / OpenVINO / OAK compilers; H and W multiples of 4",
        type=static_shape,
        metavar="N,H,W",
        category=GRAPH_FLAGS,
    )
    simplify: bool = flag(
        False,
        "simplify the graph with onnxslim (dynamic axes are kept)",
        action="store_true",
        category=GRAPH_FLAGS,
    )
    tolerance_deg: float | None = flag(
        None,
        f"verification limit in degrees (default: the variant's own, {TOLERANCE_DEG} max vs "
        f"PyTorch for fp32/fp16, {INT8_MEAN_LIMIT_DEG} mean vs the fp32 graph for int8)",
        name="--tolerance",
        type=positive_float,
        metavar="DEG",
        category=GRAPH_FLAGS,
    )
    checks: tuple[tuple[int, int, int], ...] | None = None
    threads: int | None = None
    calib_tile: int = 64
    calib_lights: int = 96
    calib_tiles_per_stack: int = 3
    weight_bits: int | None = flag(
        None,
        "int8 weights in 7 or 8 bits (default: 7 where this CPU lacks VNNI, whose int8 "
        "kernels saturate 8-bit weights; 7-bit files compute exactly on every CPU, so export "
        "with 7 for other machines)",
        type=int,
        choices=(7, 8),
        category=INT8_FLAGS,
    )

    @property
    def reduce_range(self) -> bool | None:
        """quantize_model's name for 7-bit weights (None: decided by this CPU)."""
        return None if self.weight_bits is None else self.weight_bits == 7


@options_type
@dataclass(frozen=True, kw_only=True)
class ExportRequest:
    """One msf-export run: the checkpoint, the file to write, the variant (named, or picked by
    the flags as :func:`variant_for` does), the calibration stacks and the settings
    (``options``); ``pipeline.export_variant`` takes the same parts. No flag here: the
    positional checkpoint, ``-o`` and ``-v`` / ``-q`` (the parser adds them by hand, as every
    command does) and ``options`` (its own flags)."""

    checkpoint: Path | None = None  # None only with list_variants
    output: Path | None = None  # None: the checkpoint's name with .onnx (cli.default_output)
    variant: str | None = flag(
        None,
        "the export variant (default staged, or what the flags below pick); see --list-variants",
        choices=VARIANT_NAMES,
    )
    list_variants: bool = flag(
        False, "print the variants table (passes, verification rule) and exit", action="store_true"
    )
    int8: bool = flag(
        False,
        "write a static int8 QDQ model (transposed convs rewritten as conv + depth-to-space, "
        "per-channel weights), calibrated on --calib stacks",
        action="store_true",
        category=INT8_FLAGS,
    )
    calib: tuple[Path, ...] | None = flag(
        None,
        "real stacks to calibrate --int8 on (e.g. DiLiGenT/ballPNG psmImages/cat)",
        type=path_arg,
        nargs="+",
        metavar="STACK",
        category=INT8_FLAGS,
    )
    fp16_weights: bool = flag(
        False,
        "store weights as float16 (half the file size; computed in float32, verified "
        "against the network with fp16-rounded weights)",
        action="store_true",
        category=STORAGE_FLAGS,
    )
    plain: bool = flag(
        False,
        "write one graph (all lights at once) for runtimes other than msf-run: ONNX "
        "Runtime, OpenVINO, TensorRT; msf-run runs it too, with more memory",
        action="store_true",
        category=STORAGE_FLAGS,
    )
    staged: bool = flag(
        False,
        "the staged graph (the default; kept for older command lines): cut at the three "
        "max-over-lights steps, msf-run feeds a few lights at a time, several times less "
        "memory per pixel at high light counts; same normals",
        action="store_true",
        category=STORAGE_FLAGS,
    )
    overwrite: bool = flag(
        False, "replace an existing output file", action="store_true", category=STORAGE_FLAGS
    )
    options: ExportOptions = field(default_factory=ExportOptions)
    verbose: bool = False  # -v: the export's progress lines
    quiet: bool = False  # -q: errors only


@dataclass(frozen=True)
class VerificationRow:
    """One check of the written file: the angle to the reference over the object pixels."""

    lights: int
    size: tuple[int, int]  # (H, W)
    max_deg: float
    mean_deg: float
    pixels: int
    norm_error: float = 0.0  # max | |n| - 1 | of the file's normals over the same pixels
    source: str = "rendered"

    def line(self) -> str:
        h, w = self.size
        return (
            f"N={self.lights:>3} {w}x{h} ({self.source}): max {self.max_deg:.2e} deg, "
            f"mean {self.mean_deg:.2e} deg over {self.pixels} object px, "
            f"| |n|-1 | <= {self.norm_error:.1e}"
        )


@dataclass(frozen=True)
class ExportResult:
    """What ``export_variant`` wrote and how the written file was verified.

    ``rows``: the final file (loaded from disk by ONNX Runtime) against ``rule``'s reference.
    ``reference_rows``: int8 only, the in-memory fp32 graph against PyTorch before quantising
    (that graph is the int8 reference). ``notes``: e.g. the quantisation summary.
    """

    path: Path
    variant: str
    rule: VerifyRule
    limit_deg: float
    rows: tuple[VerificationRow, ...]
    reference_rows: tuple[VerificationRow, ...] = ()
    size_bytes: int = 0
    notes: dict[str, object] = field(default_factory=dict)

    @property
    def max_deg(self) -> float:
        return max(r.max_deg for r in self.rows)

    @property
    def mean_deg(self) -> float:
        """Pixel-weighted mean angle over all rows."""
        px = sum(r.pixels for r in self.rows)
        return sum(r.mean_deg * r.pixels for r in self.rows) / px if px else math.nan

    def lines(self) -> list[str]:
        out = [
            f"reference (fp32 graph vs PyTorch, in memory before quantising) {r.line()}"
            for r in self.reference_rows
        ]
        q = self.notes.get("quantization")
        if isinstance(q, dict):
            out.append(
                f"int8: {q['deconvs_rewritten']} transposed convs rewritten, calibrated "
                f"on {q['calibration_samples']} tiles of "
                f"{', '.join(q['calibration_stacks'])}"
            )
        out += [f"verified {self.variant} {r.line()}" for r in self.rows]
        stat = self.max_deg if self.rule.statistic == "max" else self.mean_deg
        out.append(
            f"verified {self.variant}: {self.rule.statistic} {stat:.3g} deg; rule "
            f"{self.rule.describe(self.limit_deg)} (the written file, loaded by ONNX "
            "Runtime)"
        )
        out.append(f"wrote {self.path} ({self.variant}, {self.size_bytes / 1e6:.1f} MB)")
        return out


def check_options(variant: Variant, options: ExportOptions, calib: Sequence[object] | None) -> None:
    """Refuse impossible requests before anything slow happens (InputError, one line)."""
    from msfnet.common.errors import InputError

    if not MIN_OPSET <= options.opset <= MAX_OPSET:
        raise InputError(
            f"{opt('opset', options.opset)}: supported opsets are {MIN_OPSET}-{MAX_OPSET}",
            option="opset",
        )
    if variant.needs_calibration and options.opset < MIN_INT8_OPSET:
        raise InputError(
            f"{opt('opset', options.opset)}: int8 needs opset {MIN_INT8_OPSET} or "
            "higher (per-channel quantisation)",
            option="opset",
        )
    if options.train_lights < 1:
        raise InputError(
            f"{opt('train_lights')} must be positive, got {options.train_lights}",
            option="train_lights",
        )
    tol = options.tolerance_deg
    if tol is not None and not (math.isfinite(tol) and tol > 0):
        raise InputError(
            f"{opt('tolerance_deg')} must be a positive number of degrees, got {tol}",
            option="tolerance_deg",
        )
    if variant.graph == "staged" and options.static is not None:
        raise InputError(
            f"{opt('staged')} and {opt('static')} do not combine (the staged graph's entry "
            "points need dynamic shapes)",
            option="staged",
        )
    if variant.needs_shape and options.static is None:
        raise InputError(f"variant {variant.name} needs {opt('static', verbatim('N,H,W'))}")
    if not variant.needs_shape and options.static is not None:
        raise InputError(
            f"{opt('static', verbatim('N,H,W'))} is for the static variants, not {variant.name}",
            option="static",
        )
    if options.weight_bits not in (None, 7, 8):
        raise InputError(
            f"{opt('weight_bits', options.weight_bits)}: expected 7 or 8", option="weight_bits"
        )
    if options.weight_bits is not None and not variant.needs_calibration:
        raise InputError(
            f"{opt('weight_bits')}: only the int8 variants quantise weights, not {variant.name}",
            option="weight_bits",
        )
    if variant.needs_calibration and not calib:
        raise InputError(
            f"{variant.name} needs {opt('calib', verbatim('STACK [STACK ...]'))} "
            "(real stacks to calibrate on)"
        )


__all__ = [
    "DEFAULT_OPSET",
    "FLAG_SECTIONS",
    "FP16_RULE",
    "FP32_RULE",
    "INT8_RULE",
    "MAX_OPSET",
    "MIN_OPSET",
    "TOLERANCE_DEG",
    "VARIANTS",
    "VARIANT_NAMES",
    "ExportOptions",
    "ExportRequest",
    "ExportResult",
    "StaticShape",
    "Variant",
    "VerificationRow",
    "VerifyRule",
    "check_options",
    "get_variant",
    "static_shape",
    "variant_for",
]
