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
from typing import TYPE_CHECKING

from msfnet.common.cli import Command, command_main, make_parser, path_arg
from msfnet.common.errors import InputError
from msfnet.common.files import check_output, same_file

if TYPE_CHECKING:
    import torch

PROG = "msf-average"
COMMAND = Command(PROG, extra="train")


def average_state_dicts(paths: Sequence[str | Path]) -> dict[str, torch.Tensor]:
    """The element-wise mean of the checkpoints' floating-point tensors (accumulated in float64,
    stored in float32); integer tensors (batch-norm step counters) are taken from the first.

    Batch-norm running statistics are averaged like the weights, not re-estimated on data (the
    snapshots of one fine-tune differ little). The network variant (the paper's ablations,
    ``msf-train --no-mfe / --no-mff``) is read from the first file; every file must fit it and
    hold finite numbers. Raises CheckpointError naming the file that does not.
    """
    import torch

    from msfnet.model.checkpoint import (
        CheckpointError,
        check_state_dict,
        network_for,
        read_state_dict,
    )

    if len(paths) < 2:
        raise ValueError("averaging needs at least two checkpoints")
    total: dict[str, torch.Tensor] = {}
    first = read_state_dict(paths[0])
    network = network_for(first)
    reference = network.state_dict()
    for i, path in enumerate(paths):
        state = first if i == 0 else read_state_dict(path)
        check_state_dict(network, state, path)
        for key, value in state.items():
            if not reference[key].is_floating_point():
                total.setdefault(key, value.clone())
                continue
            if not bool(torch.isfinite(value).all()):
                raise CheckpointError(f"{key} holds NaN or infinite values", path)
            total[key] = total[key] + value.double() if key in total else value.double()
    return {k: (v / len(paths)).float() if v.is_floating_point() else v for k, v in total.items()}


def build_parser() -> argparse.ArgumentParser:
    p = make_parser(
        PROG,
        "Write one MSF-Net checkpoint whose weights are the mean of the given checkpoints'\n"
        "(the published {'state_dict': ...} format, for msf-export). Average snapshots of one\n"
        "run (msf-train --snapshot-every) and score the result on real objects before using\n"
        "it; batch-norm statistics are averaged, not re-estimated.",
        (
            "msf-average runs/a/snap_0003500.pth runs/a/snap_0004500.pth -o runs/a/avg.pth",
            "msf-average runs/a/snap_*.pth -o avg.pth --fp16 && msf-export avg.pth -o avg.onnx",
        ),
    )
    p.add_argument(
        "checkpoints",
        nargs="+",
        type=path_arg,
        metavar="CKPT",
        help="two or more checkpoints of one network variant (.pth), each once",
    )
    p.add_argument("-o", "--output", type=path_arg, required=True, help="checkpoint to write")
    p.add_argument(
        "--fp16",
        action="store_true",
        help="store the weights in half precision (half the size; loading casts "
        "them back to float32)",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing OUTPUT checkpoint (never another kind of file)",
    )
    return p


def _check_inputs(paths: Sequence[Path]) -> None:
    """Two or more, and no file twice (a glob plus a name would weigh a snapshot double)."""
    if len(paths) < 2:
        raise InputError("averaging needs at least two checkpoints, got one", paths[0])
    for i, path in enumerate(paths):
        for earlier in paths[:i]:
            if same_file(path, earlier):  # a missing file: the reader names it later
                raise InputError(
                    f"the same file as {earlier}, given twice: each checkpoint counts once", path
                )


def _run(args: argparse.Namespace) -> int:
    _check_inputs(args.checkpoints)
    check_output(args.output, args.checkpoints, overwrite=args.overwrite)
    from msfnet.model.checkpoint import (
        CheckpointError,
        network_for,
        read_state_dict,
        save_checkpoint,
    )

    if args.output.is_file() and args.output.stat().st_size:  # empty: nothing to lose
        # --overwrite replaces an earlier checkpoint only: read it as one (weights only, never
        # unpickling), since a .docx or a .pkl also starts as a zip or a pickle
        try:
            read_state_dict(args.output)
        except CheckpointError as exc:
            raise InputError(
                f"{exc.message}; --overwrite replaces only an earlier checkpoint: choose "
                "another path",
                args.output,
            ) from exc

    state = average_state_dicts(args.checkpoints)
    model = network_for(state)
    model.load_state_dict(state, strict=True)
    save_checkpoint(
        model, args.output, fp16=args.fp16, averaged_from=[str(p) for p in args.checkpoints]
    )
    if not args.quiet:
        print(
            f"wrote {args.output}: the mean of {len(args.checkpoints)} checkpoints' weights"
            + (" (fp16)" if args.fp16 else "")
        )
    return 0


def main(argv: list[str] | None = None) -> int:
    return command_main(COMMAND, build_parser(), _run, argv)


if __name__ == "__main__":
    sys.exit(main())
