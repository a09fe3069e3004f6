"""``msf-average``: one checkpoint holding the mean of several checkpoints' weights.

Snapshots of one training run lie in one basin of the loss; their mean is often better on real
objects than any one of them (stochastic weight averaging). Means of unrelated models (two runs
from different starts) are usually worse than either: average snapshots of one run, or of a
fine-tune and the weights it started from.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import torch

from msfnet.runtime.cliutil import make_parser, run_command
from msfnet.runtime.errors import InputError
from msfnet.runtime.files import check_output

from .checkpoint import check_state_dict, read_state_dict, save_checkpoint
from .network import MSFNet

PROG = "msf-average"


def average_state_dicts(paths: Sequence[str | Path]) -> dict[str, torch.Tensor]:
    """The element-wise mean of the checkpoints' floating-point tensors (accumulated in float64,
    stored in float32; batch-norm running statistics are averaged like the weights); integer
    tensors (batch-norm step counters) are taken from the first. Every checkpoint is checked
    against the network first: CheckpointError names the one that does not fit."""
    if len(paths) < 2:
        raise ValueError("averaging needs at least two checkpoints")
    reference = MSFNet().state_dict()
    total: dict[str, torch.Tensor] = {}
    for path in paths:
        state = read_state_dict(path)
        check_state_dict(MSFNet(), state, path)
        for key, value in state.items():
            if not reference[key].is_floating_point():
                total.setdefault(key, value.clone())
            elif key in total:
                total[key] += value.double()
            else:
                total[key] = value.double()
    return {k: (v / len(paths)).float() if reference[k].is_floating_point() else v
            for k, v in total.items()}


def build_parser() -> argparse.ArgumentParser:
    p = make_parser(
        PROG,
        "Write one MSF-Net checkpoint whose weights are the mean of the given checkpoints' "
        "(published {'state_dict': ...} format, for msf-export). Average snapshots of one run "
        "(msf-train --snapshot-every) and score the result on real objects before using it.",
        ("msf-average runs/a/snap_0003500.pth runs/a/snap_0004500.pth -o runs/a/avg.pth",
         "msf-average runs/a/snap_*.pth -o avg.pth --fp16 && msf-export avg.pth -o avg.onnx"))
    p.add_argument("checkpoints", nargs="+", type=Path, metavar="CKPT",
                   help="two or more checkpoints of the network (.pth)")
    p.add_argument("-o", "--output", type=Path, required=True, help="checkpoint to write")
    p.add_argument("--fp16", action="store_true",
                   help="store the weights in half precision (half the size; loading casts "
                        "them back to float32)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing OUTPUT")
    return p


def _run(args: argparse.Namespace) -> int:
    if len(args.checkpoints) < 2:
        raise InputError("averaging needs at least two checkpoints, got one",
                         args.checkpoints[0])
    check_output(args.output, args.checkpoints, overwrite=args.overwrite)
    state = average_state_dicts(args.checkpoints)
    model = MSFNet()
    model.load_state_dict(state, strict=True)
    save_checkpoint(model, args.output, fp16=args.fp16)
    if not args.quiet:
        print(f"wrote {args.output}: the mean of {len(args.checkpoints)} checkpoints' weights"
              + (" (fp16)" if args.fp16 else ""))
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run_command(PROG, lambda: _run(args), debug=args.debug)


if __name__ == "__main__":
    sys.exit(main())
