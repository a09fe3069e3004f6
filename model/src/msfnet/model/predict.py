"""Torch inference on a whole stack (validation during training, quick checks of checkpoints).

The deployment path is the ONNX runtime; this twin runs a torch MSFNet through the *same* tiling,
normalisation and stitching code (msfnet.runtime.infer.tiled) by wrapping it in the interface of an
ONNX session. Usage: ``python -m msfnet.model.predict CHECKPOINT STACK [--max-lights N]``.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from pathlib import Path

import numpy as np
import torch

from msfnet.common.cli import command_main, make_parser, path_arg, positive_int, thread_count
from msfnet.model.network import MSFNet
from msfnet.runtime.contract import INPUT_MULTIPLE, TRAIN_LIGHTS, ModelInfo
from msfnet.runtime.engines.method import RunMethod
from msfnet.runtime.evaluate.metrics import normal_metrics
from msfnet.runtime.infer.tiled import infer_normals
from msfnet.runtime.infer.tiling import plan_tiles
from msfnet.runtime.stack import Stack, load_stack


def autocast(enabled: bool, device_type: str = "cpu"):
    return (
        torch.autocast(device_type, dtype=torch.bfloat16) if enabled else contextlib.nullcontext()
    )


class TorchModel:
    """A torch MSFNet as a :class:`msfnet.runtime.engines.base.Engine`, so the runtime's
    tiling and normalisation run it exactly as they run an ONNX model."""

    name = "torch"
    chunk = None  # the whole light stack in one call

    def __init__(self, model: MSFNet, bf16: bool = False, train_lights: int = TRAIN_LIGHTS) -> None:
        self.model = model.eval()
        self.bf16 = bf16
        self.threads: int | None = torch.get_num_threads()
        self.info = ModelInfo(
            Path("<torch model>"), train_lights, INPUT_MULTIPLE, None, self.precision, {}
        )

    @property
    def precision(self) -> str:
        return "bf16" if self.bf16 else "fp32"

    def describe(self) -> RunMethod:
        return RunMethod.of_engine(self)

    @torch.no_grad()
    def run(self, images: np.ndarray, lights: np.ndarray) -> np.ndarray:
        # Inputs go wherever the model lives (a GPU during GPU training's validation).
        device = next(self.model.parameters()).device
        with autocast(self.bf16, device.type):
            out = self.model(
                torch.from_numpy(images).to(device), torch.from_numpy(lights).to(device)
            )
        return out.float().cpu().numpy()


def predict_normals(
    model: MSFNet, stack: Stack, bf16: bool = False, tile: int | None = 128
) -> np.ndarray:
    """(H, W, 3) unit normals, zeros outside the mask; ``tile`` None = one window."""
    plan = plan_tiles(stack.mask, tile)
    normals = infer_normals(TorchModel(model, bf16), stack, plan).normals
    if bf16:  # bf16 outputs are not exactly unit length
        normals /= np.maximum(np.linalg.norm(normals, axis=2, keepdims=True), 1e-8)
    return normals


PROG = "python -m msfnet.model.predict"


def build_parser() -> argparse.ArgumentParser:
    p = make_parser(
        PROG,
        "Torch inference of a checkpoint on one stack; prints MAE/err15/err30 when ground "
        "truth exists.",
        [f"{PROG} runs/mine/best.pth ../shared/data/DiLiGenT/ballPNG --max-lights 12"],
    )
    p.add_argument("checkpoint", type=path_arg)
    p.add_argument("stack", type=path_arg)
    p.add_argument("--max-lights", type=positive_int, default=None)
    p.add_argument(
        "--fp32",
        action="store_true",
        help="no bf16 autocast (it is only used where the CPU has native bf16)",
    )
    p.add_argument("--threads", type=thread_count, default=2)
    p.add_argument(
        "--tile", type=positive_int, default=128, help="tile side in pixels (default 128)"
    )
    return p


def _run(args: argparse.Namespace) -> int:
    from msfnet.model.checkpoint import load_model

    torch.set_num_threads(args.threads)
    model = load_model(args.checkpoint)
    stack = load_stack(args.stack, max_lights=args.max_lights)
    t0 = time.perf_counter()
    bf16 = not args.fp32 and torch.ops.mkldnn._is_mkldnn_bf16_supported()
    normals = predict_normals(model, stack, bf16=bf16, tile=args.tile)
    took = time.perf_counter() - t0
    if stack.normals_gt is not None:
        m = normal_metrics(normals, stack.normals_gt, stack.mask)
        print(
            f"{stack.name}: {stack.num_lights} lights, MAE {m.mae_deg:.2f} deg, median "
            f"{m.median_deg:.2f}, err15 {m.err15:.3f}, err30 {m.err30:.3f} "
            f"({took:.1f} s)"
        )
    else:
        print(f"{stack.name}: predicted in {took:.1f} s (no ground truth)")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Bad options and input are one line and exit code 2, as in the msf-* commands."""
    return command_main(PROG, build_parser(), _run, argv)


if __name__ == "__main__":
    sys.exit(main())
