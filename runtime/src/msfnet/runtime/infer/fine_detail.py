"""Fine-detail mode (``msf-run --fine-detail``): relief of a few pixels, kept.

MSF-Net regresses normals at half resolution and upsamples them, so engravings, scratches and
fabric of 1-3 px come out smoothed (the detail check,
:mod:`msfnet.runtime.evaluate.detail_ratio`, measures it). Run on the stack enlarged ``FACTOR``
x, the same relief spans twice the pixels and survives; but the enlarged run sees less of the
object around each pixel and its overall shape is slightly worse. So the result takes both: the
coarse shape of the normal run and the fine detail (the high-pass at the detail check's own
``SIGMA_PX``) of the enlarged run, shrunk back. It costs the enlarged run on top, about 1 +
FACTOR^2 times the inference, and holds the stack and its enlargement (1 + FACTOR^2 times the
stack's memory) within --max-memory, beside the runtime's own base (tiling's BASE_MEMORY_MB,
which the tiles' budget leaves out too)."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from msfnet.common.errors import InputError
from msfnet.common.vocabulary import declare, opt
from msfnet.runtime.engines.method import RunMethod
from msfnet.runtime.evaluate.detail_ratio import SIGMA_PX, masked_smooth
from msfnet.runtime.infer.estimators import Estimate, NetworkEstimator, TilingOptions
from msfnet.runtime.infer.tiling import BASE_MEMORY_MB
from msfnet.runtime.instrument import StageTimer, announce
from msfnet.runtime.stack import Stack
from msfnet.runtime.stack.readers import unit_normals

# ModelOptions.fine_detail, named by its own refusal
declare("fine_detail", "--fine-detail", "store_true")

FACTOR = 2


def enlarge(stack: Stack, factor: int = FACTOR, max_memory_mb: float | None = None) -> Stack:
    """The stack with every image enlarged ``factor`` x (bicubic; mask nearest), in the images'
    own dtype; refused up front if it, the stack itself and the runtime's base would exceed
    ``max_memory_mb`` (the whole process's budget, as the tiles count it)."""
    n, (h, w) = stack.num_lights, stack.shape
    need = BASE_MEMORY_MB + stack.images.nbytes * (1 + factor * factor) / 2**20
    if max_memory_mb is not None and need > max_memory_mb:
        raise InputError(
            f"{opt('fine_detail')} holds the stack and its {factor}x enlargement beside the "
            f"runtime's {BASE_MEMORY_MB} MB: {need:.0f} MB, above "
            f"{opt('max_memory_mb', float(max_memory_mb))} MB (use {opt('roi')}, "
            f"{opt('downscale')}, {opt('max_lights')} or a larger budget)",
            stack.source or stack.name,
            option="fine_detail",
        )
    size = (w * factor, h * factor)
    images = np.empty((n, h * factor, w * factor, 3), stack.images.dtype)
    for i in range(n):  # OpenCV saturates integer types: cubic overshoot never wraps
        images[i] = cv2.resize(stack.images[i], size, interpolation=cv2.INTER_CUBIC)
    if np.issubdtype(images.dtype, np.floating):
        np.maximum(images, 0, out=images)
    mask = cv2.resize(stack.mask.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST)
    return Stack.from_arrays(
        images, stack.lights, mask=mask.astype(bool), intensities=stack.intensities, name=stack.name
    )


def shrink(normals: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """An enlarged run's (H', W', 3) normals averaged back to ``shape`` and made unit again."""
    small = cv2.resize(normals, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)
    return unit_normals(small)


def fuse(
    coarse: np.ndarray, fine: np.ndarray, mask: np.ndarray, sigma: float = SIGMA_PX
) -> np.ndarray:
    """Low-pass of ``coarse`` + high-pass of ``fine``, unit length, zeros outside the mask."""
    fused = masked_smooth(coarse, mask, sigma) + fine - masked_smooth(fine, mask, sigma)
    return unit_normals(fused * mask[..., None])


class FineDetailEstimator:
    """The network at the stack's scale and at ``factor`` x, fused (see the module notes)."""

    method = "msf"

    def __init__(
        self, network: NetworkEstimator, factor: int = FACTOR, sigma: float = SIGMA_PX
    ) -> None:
        if factor < 2:
            raise InputError(f"fine detail needs an enlargement of 2 or more, got {factor}")
        self.network = network
        self.factor = factor
        self.sigma = sigma

    def describe(self) -> RunMethod:
        said = f"x{self.factor}, high-pass sigma {self.sigma:g} px"
        return replace(self.network.describe(), fine_detail=said)

    def estimate(
        self, stack: Stack, tiling: TilingOptions, timer: StageTimer, progress: bool = False
    ) -> Estimate:
        # the enlarged run first: a budget too small for it is refused before any inference,
        # and its tiles are sized for what is left beside the original stack
        with timer("preprocess"):
            big = enlarge(stack, self.factor, tiling.max_memory_mb)
        left = replace(tiling, max_memory_mb=tiling.max_memory_mb - stack.images.nbytes / 2**20)
        h, w = big.shape
        announce(f"fine detail, pass 1 of 2: the network on the stack enlarged to {w}x{h}")
        detail = self.network.estimate(big, left, timer, progress)
        del big
        announce("fine detail, pass 2 of 2: the network on the stack as it is")
        base = self.network.estimate(stack, tiling, timer, progress)
        with timer("postprocess"):
            fine = shrink(detail.normals, stack.shape)
            normals = fuse(base.normals, fine, stack.mask, self.sigma)
        return Estimate(normals, base.plan, base.flops + detail.flops)


__all__ = ["FACTOR", "FineDetailEstimator", "enlarge", "fuse", "shrink"]
