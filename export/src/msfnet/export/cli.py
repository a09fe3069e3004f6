"""msf-export: MSF-Net checkpoint (.pth) -> verified ONNX model with a dynamic light count."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from msfnet.runtime.errors import InputError

from .onnx_export import DEFAULT_OPSET, TOLERANCE_DEG, StaticShape, export_checkpoint


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="msf-export",
        description="Export an MSF-Net PyTorch checkpoint ({'state_dict': ...} or a bare "
        "state_dict, legacy or zip format) to ONNX, then verify ONNX Runtime against PyTorch. "
        "Inputs: images float32 (B,N,3,H,W), lights float32 (B,N,3); output normals float32 "
        "(B,3,H,W). N, H, W are dynamic unless --static; H and W must be multiples of 4.",
    )
    p.add_argument("checkpoint", type=Path, help="PyTorch checkpoint (.pth/.pth.tar)")
    p.add_argument("-o", "--output", type=Path, default=None,
                   help="output .onnx (default: the checkpoint's name with .onnx)")
    p.add_argument("--opset", type=int, default=DEFAULT_OPSET,
                   help=f"ONNX opset (default {DEFAULT_OPSET}: GELU as Erf, widest runtime "
                   "support)")
    p.add_argument("--train-lights", type=int, default=32,
                   help="light count the model was trained with; stored in the metadata and "
                   "used by the runtime's sqrt(N / train_lights) scaling (default 32)")
    p.add_argument("--static", type=StaticShape.parse, default=None, metavar="N,H,W",
                   help="export fixed shapes (batch 1) for NPUs / OpenVINO / OAK compilers")
    p.add_argument("--simplify", action="store_true",
                   help="simplify the graph with onnxslim (dynamic axes are kept)")
    p.add_argument("--tolerance", type=float, default=TOLERANCE_DEG,
                   help=f"max allowed ONNX Runtime vs PyTorch angle in degrees "
                   f"(default {TOLERANCE_DEG})")
    p.add_argument("--int8", action="store_true",
                   help="write a static int8 QDQ model (transposed convs rewritten as conv + "
                   "depth-to-space, per-channel weights), calibrated on --calib stacks")
    p.add_argument("--calib", type=Path, nargs="+", default=None, metavar="STACK",
                   help="real stacks to calibrate --int8 on (e.g. DiLiGenT/ballPNG "
                   "psmImages/cat)")
    p.add_argument("--fp16-weights", action="store_true",
                   help="store weights as float16 (half the file size; computed in float32, "
                   "verified against the network with fp16-rounded weights)")
    p.add_argument("--staged", action="store_true",
                   help="write the staged graph (cut at the three max-over-lights steps) that "
                   "msf-run feeds a few lights at a time: several times less memory per pixel "
                   "at high light counts, so bigger tiles and less halo work; same normals")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    output = args.output or args.checkpoint.with_suffix(".onnx")
    try:
        if output.exists() and not args.overwrite:
            raise InputError("output exists; pass --overwrite to replace it", output)
        if args.train_lights < 1:
            raise InputError(f"--train-lights must be positive, got {args.train_lights}")
        if args.int8 and not args.calib:
            raise InputError("--int8 needs --calib STACK [STACK ...] (real stacks to calibrate on)")
        fp32_out = output.with_name(f".{output.stem}.fp32.onnx") if args.int8 else output
        results = export_checkpoint(args.checkpoint, fp32_out, opset=args.opset,
                                    train_lights=args.train_lights, static=args.static,
                                    do_simplify=args.simplify, tolerance_deg=args.tolerance,
                                    fp16_weights=args.fp16_weights, staged=args.staged)
        if args.int8:  # the verified fp32 graph is the quantiser's input
            from .quantize import load_calibration_stacks, quantize_int8

            try:
                summary = quantize_int8(fp32_out, output, load_calibration_stacks(args.calib))
            finally:
                fp32_out.unlink(missing_ok=True)
            print(f"int8: {summary['deconvs_rewritten']} transposed convs rewritten, calibrated "
                  f"on {summary['calibration_samples']} tiles of "
                  f"{', '.join(summary['calibration_stacks'])}")
    except InputError as exc:
        print(f"msf-export: error: {exc}", file=sys.stderr)
        return 2
    for r in results:
        print(f"verified N={r['lights']:>3} {r['width']}x{r['height']}: max "
              f"{r['max_deg']:.2e} deg, mean {r['mean_deg']:.2e} deg over {r['pixels']} object px "
              "of a rendered stack (ONNX Runtime vs PyTorch)")
    print(f"wrote {output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
