"""msf-export: MSF-Net checkpoint (.pth) -> verified ONNX model with a dynamic light count.

Options and errors work as in every msfnet command (``common/cli.py``): one line on
stderr, ``msf-export: error: <file or option>: <problem>``, exit 2 for bad arguments or input
(and failed verification), 130 for Ctrl-C, 128 + n for signal n, 1 for an internal error. A
traceback is shown only with ``--debug``. The file is written through ``common/files.py``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from msfnet.common.cli import (
    Command,
    command_main,
    int_range,
    make_parser,
    path_arg,
    positive_float,
    positive_int,
)
from msfnet.common.errors import InputError
from msfnet.export.variants import (
    DEFAULT_OPSET,
    INT8_MEAN_LIMIT_DEG,
    MAX_OPSET,
    MIN_OPSET,
    TOLERANCE_DEG,
    VARIANT_NAMES,
    VARIANTS,
    ExportOptions,
    StaticShape,
    Variant,
    get_variant,
)

PROG = "msf-export"
COMMAND = Command(PROG, extra="export")


def _static(text: str) -> StaticShape:
    try:
        return StaticShape.parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _table() -> str:
    rows = [
        f"  {v.name:<12} {v.summary}\n  {'':<12} passes: {' -> '.join(v.passes)}\n"
        f"  {'':<12} verified: {v.rule.describe()}"
        for v in VARIANTS
    ]
    return "variants:\n" + "\n".join(rows)


EXAMPLES = (
    "msf-export checkp_30.pth.tar -o msfnet.onnx        # staged fp32, verified, for msf-run",
    "msf-export model.pth --plain -o plain.onnx         # one graph, for other runtimes",
    "msf-export model.pth --variant staged-int8 --calib ballPNG cat/ -o int8.onnx",
    "msf-export model.pth --static 32,512,512 -o oak.onnx   # fixed shapes for NPU compilers",
    "msf-export --list-variants                         # fp32, fp16, static, staged, int8...",
)


def build_parser() -> argparse.ArgumentParser:
    p = make_parser(
        PROG,
        "Export an MSF-Net PyTorch checkpoint ({'state_dict': ...} or a bare "
        "state_dict, legacy or zip format) to ONNX, then verify the written file with ONNX "
        "Runtime. Inputs: images float32 (B,N,3,H,W), lights float32 (B,N,3); output normals "
        "float32 (B,3,H,W). N, H, W are dynamic unless --static; H and W must be multiples "
        "of 4. By default the staged graph (cut at the max-over-lights steps), which msf-run "
        "feeds a few lights at a time: far less memory at many lights; --plain writes one "
        "graph for other runtimes. The file appears only after it passed verification.",
        EXAMPLES,
        verbose=True,
    )
    p.epilog = (
        _table() + "\n\nThe flags --static, --plain, --fp16-weights and --int8 pick "
        "the same rows (no flag = staged; e.g. --int8 = staged-int8, --plain --int8 = "
        "int8).\n\n" + (p.epilog or "")
    )
    _add_input_output_arguments(p)
    _add_graph_arguments(p)
    _add_int8_arguments(p)
    _add_storage_arguments(p)
    return p


def _add_input_output_arguments(p: argparse.ArgumentParser) -> None:
    """The checkpoint, the output file and the variant choice (or the table of variants)."""
    p.add_argument(
        "checkpoint", type=path_arg, nargs="?", help="PyTorch checkpoint (.pth/.pth.tar)"
    )
    p.add_argument(
        "-o",
        "--output",
        type=path_arg,
        default=None,
        help="output .onnx (default: the checkpoint's name with .onnx in place of its "
        ".pth / .pth.tar)",
    )
    p.add_argument(
        "--variant",
        choices=VARIANT_NAMES,
        default=None,
        help="the export variant (default staged, or what the flags below pick); "
        "see --list-variants",
    )
    p.add_argument(
        "--list-variants",
        action="store_true",
        help="print the variants table (passes, verification rule) and exit",
    )


def _add_graph_arguments(p: argparse.ArgumentParser) -> None:
    """How the graph is built and checked: opset, training light count, static shapes,
    simplification and the verification tolerance."""
    p.add_argument(
        "--opset",
        type=int_range(MIN_OPSET, MAX_OPSET),
        default=DEFAULT_OPSET,
        help=f"ONNX opset, {MIN_OPSET}-{MAX_OPSET} (default {DEFAULT_OPSET}: GELU as "
        "Erf, widest runtime support; int8 needs 13 or higher)",
    )
    p.add_argument(
        "--train-lights",
        type=positive_int,
        default=32,
        help="light count the model was trained with; stored in the metadata and "
        "used by the runtime's sqrt(N / train_lights) scaling (default 32)",
    )
    p.add_argument(
        "--static",
        type=_static,
        default=None,
        metavar="N,H,W",
        help="export fixed shapes (batch 1) for NPUs / OpenVINO / OAK compilers; "
        "H and W multiples of 4",
    )
    p.add_argument(
        "--simplify",
        action="store_true",
        help="simplify the graph with onnxslim (dynamic axes are kept)",
    )
    p.add_argument(
        "--tolerance",
        type=positive_float,
        default=None,
        metavar="DEG",
        help=f"verification limit in degrees (default: the variant's own, "
        f"{TOLERANCE_DEG} max vs PyTorch for fp32/fp16, {INT8_MEAN_LIMIT_DEG} mean "
        "vs the fp32 graph for int8)",
    )


def _add_int8_arguments(p: argparse.ArgumentParser) -> None:
    """int8 quantisation: the flag, its calibration stacks and the weights' bit width."""
    p.add_argument(
        "--int8",
        action="store_true",
        help="write a static int8 QDQ model (transposed convs rewritten as conv + "
        "depth-to-space, per-channel weights), calibrated on --calib stacks",
    )
    p.add_argument(
        "--calib",
        type=path_arg,
        nargs="+",
        default=None,
        metavar="STACK",
        help="real stacks to calibrate --int8 on (e.g. DiLiGenT/ballPNG psmImages/cat)",
    )
    p.add_argument(
        "--weight-bits",
        type=int,
        choices=(7, 8),
        default=None,
        help="int8 weights in 7 or 8 bits (default: 7 where this CPU lacks VNNI, whose int8 "
        "kernels saturate 8-bit weights; 7-bit files compute exactly on every CPU, so "
        "export with 7 for other machines)",
    )


def _add_storage_arguments(p: argparse.ArgumentParser) -> None:
    """Weight storage, staged or plain graph, and overwriting the output."""
    p.add_argument(
        "--fp16-weights",
        action="store_true",
        help="store weights as float16 (half the file size; computed in float32, "
        "verified against the network with fp16-rounded weights)",
    )
    p.add_argument(
        "--plain",
        action="store_true",
        help="write one graph (all lights at once) for runtimes other than msf-run: "
        "ONNX Runtime, OpenVINO, TensorRT; msf-run runs it too, with more memory",
    )
    p.add_argument(
        "--staged",
        action="store_true",
        help="the staged graph (the default; kept for older command lines): cut at "
        "the three max-over-lights steps, msf-run feeds a few lights at a time, "
        "several times less memory per pixel at high light counts; same normals",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")


def resolve_variant(args: argparse.Namespace) -> Variant:
    """--variant, or the row the flags pick; a flag given with --variant must agree with it
    (--static then only supplies the static rows' shape)."""
    from msfnet.export.variants import variant_for

    if args.variant is None:
        return variant_for(
            static=args.static is not None,
            staged=args.staged,
            plain=args.plain,
            fp16_weights=args.fp16_weights,
            int8=args.int8,
        )
    chosen = get_variant(args.variant)
    for flag, given, fits in (
        ("--staged", args.staged, chosen.graph == "staged"),
        ("--plain", args.plain, chosen.graph != "staged"),
        ("--fp16-weights", args.fp16_weights, chosen.precision == "fp16-weights"),
        ("--int8", args.int8, chosen.precision == "int8"),
    ):
        if given and not fits:
            raise InputError(f"{flag} contradicts --variant {chosen.name}")
    return chosen


def _check_args(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    # the checkpoint is optional only for --list-variants: a parse error like argparse's own
    if not args.list_variants and args.checkpoint is None:
        parser.error("the following arguments are required: checkpoint")


def _body(args: argparse.Namespace) -> int:
    if args.list_variants:
        print(_table())
        return 0
    return _export(args)


def main(argv: list[str] | None = None) -> int:
    return command_main(COMMAND, build_parser(), _body, argv, check=_check_args)


_CHECKPOINT_SUFFIXES = (".pth", ".pt", ".ckpt")


def default_output(checkpoint: Path) -> Path:
    """The output without -o: the checkpoint's name with .onnx in place of its suffix, both of
    a double one (``checkp_30.pth.tar`` -> ``checkp_30.onnx``, ``model.pth`` -> ``model.onnx``)."""
    stem = checkpoint.name
    if stem.lower().endswith(".tar"):
        stem = stem[: -len(".tar")]
    for suffix in _CHECKPOINT_SUFFIXES:
        if stem.lower().endswith(suffix):
            stem = stem[: -len(suffix)]
            break
    if not stem or stem == checkpoint.name:
        return checkpoint.with_suffix(".onnx")
    return checkpoint.with_name(stem + ".onnx")


def _export(args: argparse.Namespace) -> int:
    from msfnet.export.pipeline import export_variant  # torch: only once the flags are good

    variant = resolve_variant(args)
    if args.calib and not variant.needs_calibration:
        raise InputError(
            f"--calib: only the int8 variants are calibrated; {variant.name} "
            "would ignore it (add --int8, or drop --calib)"
        )
    options = ExportOptions(
        opset=args.opset,
        train_lights=args.train_lights,
        static=args.static,
        simplify=args.simplify,
        tolerance_deg=args.tolerance,
        weight_bits=args.weight_bits,
    )
    output = args.output or default_output(args.checkpoint)
    result = export_variant(
        args.checkpoint,
        variant,
        output,
        calib=args.calib,
        options=options,
        overwrite=args.overwrite,
        log=print if args.verbose and not args.quiet else None,
    )
    if not args.quiet:
        for line in result.lines():
            print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
