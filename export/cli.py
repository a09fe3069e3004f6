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
        results = export_checkpoint(args.checkpoint, output, opset=args.opset,
                                    train_lights=args.train_lights, static=args.static,
                                    do_simplify=args.simplify, tolerance_deg=args.tolerance)
    except InputError as exc:
        print(f"msf-export: error: {exc}", file=sys.stderr)
        return 2
    for r in results:
        print(f"verified N={r['lights']:>3} {r['width']}x{r['height']}: max "
              f"{r['max_deg']:.2e} deg, mean {r['mean_deg']:.2e} deg (ONNX Runtime vs PyTorch)")
    print(f"wrote {output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
