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
    add_flags,
    command_main,
    flag_names,
    make_parser,
    options_from_args,
    path_arg,
)
from msfnet.common.errors import InputError
from msfnet.export.variants import (
    FLAG_SECTIONS,
    VARIANTS,
    ExportOptions,
    ExportRequest,
    Variant,
    get_variant,
    variant_for,
)

PROG = "msf-export"
COMMAND = Command(PROG, extra="export")


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
    # the flags of ExportRequest and ExportOptions, section by section (variants.FLAG_SECTIONS)
    for section in FLAG_SECTIONS:
        for cls in (ExportRequest, ExportOptions):
            add_flags(p, cls, only=flag_names(cls, section))
    return p


def resolve_variant(request: ExportRequest) -> Variant:
    """--variant, or the row the flags pick; a flag given with --variant must agree with it
    (--static then only supplies the static rows' shape)."""
    if request.variant is None:
        return variant_for(
            static=request.options.static is not None,
            staged=request.staged,
            plain=request.plain,
            fp16_weights=request.fp16_weights,
            int8=request.int8,
        )
    chosen = get_variant(request.variant)
    for flag, given, fits in (
        ("--staged", request.staged, chosen.graph == "staged"),
        ("--plain", request.plain, chosen.graph != "staged"),
        ("--fp16-weights", request.fp16_weights, chosen.precision == "fp16-weights"),
        ("--int8", request.int8, chosen.precision == "int8"),
    ):
        if given and not fits:
            raise InputError(f"{flag} contradicts --variant {chosen.name}")
    return chosen


def _check_args(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    # the checkpoint is optional only for --list-variants: a parse error like argparse's own
    if not args.list_variants and args.checkpoint is None:
        parser.error("the following arguments are required: checkpoint")


def _request(args: argparse.Namespace) -> ExportRequest:
    """The run's request, built once from msf-export's parsed flags (-v and -q among them)."""
    given = {
        "checkpoint": args.checkpoint,
        "output": args.output,
        "options": options_from_args(ExportOptions, args),
        "verbose": args.verbose,
        "quiet": args.quiet,
    }
    return options_from_args(ExportRequest, args, overrides=given)


def _body(args: argparse.Namespace) -> int:
    request = _request(args)
    if request.list_variants:
        print(_table())
        return 0
    return _export(request)


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


def _export(request: ExportRequest) -> int:
    from msfnet.export.pipeline import export_variant  # torch: only once the flags are good

    variant = resolve_variant(request)
    if request.calib and not variant.needs_calibration:
        raise InputError(
            f"--calib: only the int8 variants are calibrated; {variant.name} "
            "would ignore it (add --int8, or drop --calib)"
        )
    checkpoint = request.checkpoint
    assert checkpoint is not None  # _check_args: required unless --list-variants
    result = export_variant(
        checkpoint,
        variant,
        request.output or default_output(checkpoint),
        calib=request.calib,
        options=request.options,
        overwrite=request.overwrite,
        log=print if request.verbose and not request.quiet else None,
    )
    if not request.quiet:
        for line in result.lines():
            print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
