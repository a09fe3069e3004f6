"""The speed ladder (``--speed``): one option trades time for accuracy in measured rungs.

The network's time scales with pixels x lights (infer/flops.py); a least-squares fit costs
little. The rungs below the default cut the network's pixels and lights and give the
fine detail back from a full-resolution robust least-squares fit where its Lambertian model
holds (infer/detail_fusion.py):

    full      the network on every pixel and light (the default)
    balanced  the network at 2/5 of the resolution (1/6.25 of the pixels), upsampled;
              full-resolution detail from least squares where the fit holds (2/5, not half
              resolution: half fell short of the 3x target)
    fast      the network at a third of the resolution (1/9 of the pixels) on at most
              FAST_LIGHTS evenly spaced lights (least squares still uses them all)

Each rung is an estimator (infer/estimators.py): ``reduced_network`` is the network as a rung
runs it, and Model adds the detail fusion as it does for the full network (its default,
infer/compose.py). Measured time, memory, MAE and detail per rung are in docs/benchmark.md
(``msf-bench --ladder``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from msfnet.common.errors import InputError
from msfnet.common.vocabulary import opt
from msfnet.runtime.engines.method import RunMethod
from msfnet.runtime.infer.estimators import Estimate, NetworkEstimator, TilingOptions
from msfnet.runtime.instrument import StageTimer
from msfnet.runtime.stack import Stack, evenly_spaced
from msfnet.runtime.stack.readers import unit_normals

FAST_LIGHTS = 8
# The network sees at least this many pixels a side at a reduced scale: below it, half
# resolution leaves too little context for its receptive field to be worth the saving.
MIN_REDUCED_PX = 32


@dataclass(frozen=True)
class Rung:
    """One step of the ladder: the network's scale (1 = full resolution) and its light budget
    (None: all lights)."""

    name: str
    scale: float  # the network runs on the stack shrunk by this factor
    max_lights: int | None
    summary: str


RUNGS: dict[str, Rung] = {
    "full": Rung("full", 1, None, "network on every pixel and light"),
    "balanced": Rung(
        "balanced", 2.5, None, "network at 2/5 of the resolution + least-squares detail"
    ),
    "fast": Rung(
        "fast",
        3,
        FAST_LIGHTS,
        f"network at a third of the resolution on <= {FAST_LIGHTS} lights + least-squares detail",
    ),
}
DEFAULT_RUNG = "full"


def rung(name: str) -> Rung:
    """``--speed`` value -> its Rung; InputError naming the rungs otherwise."""
    found = RUNGS.get(name.strip().lower())
    if found is None:
        raise InputError(
            f"{opt('speed', name, quote=True)}: expected one of {', '.join(RUNGS)}", option="speed"
        )
    return found


def shrink_stack(stack: Stack, scale: float) -> Stack:
    """The stack at 1/``scale`` resolution (area average, any size: the last row / column may
    average fewer pixels), in the images' own dtype; a pixel is object where at least half of
    its area is."""
    if scale == 1:
        return stack
    h, w = stack.shape
    size = (max(1, math.ceil(w / scale)), max(1, math.ceil(h / scale)))
    images = np.stack([cv2.resize(im, size, interpolation=cv2.INTER_AREA) for im in stack.images])
    if images.ndim == 3:  # cv2 drops a trailing channel of 1
        images = images[..., None]
    mask = cv2.resize(stack.mask.astype(np.float32), size, interpolation=cv2.INTER_AREA) >= 0.5
    return Stack.from_arrays(
        images, stack.lights, mask=mask, intensities=stack.intensities, name=stack.name
    )


def grow_normals(
    normals: np.ndarray, small_mask: np.ndarray, shape: tuple[int, int], mask: np.ndarray
) -> np.ndarray:
    """Reduced-resolution unit normals (object where ``small_mask``) brought to ``shape``
    (bilinear), unit again, zero outside ``mask``. Before the step up, pixels outside the small
    mask take a masked Gaussian average of their neighbours, so the rim the small mask lost is
    filled from the object, not blended with background zeros."""
    m = small_mask.astype(np.float32)
    n = normals.astype(np.float32) * m[..., None]
    weight = cv2.GaussianBlur(m, (0, 0), 1.0)
    filled = cv2.GaussianBlur(n, (0, 0), 1.0) / np.maximum(weight, 1e-6)[..., None]
    n = np.where(small_mask[..., None], n, filled)
    big = cv2.resize(n, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)
    return unit_normals(big * mask[..., None]).astype(np.float32)


class ReducedNetwork(NetworkEstimator):
    """The network on the stack shrunk and thinned as ``rung`` says, its normals brought back
    to the stack's size: a NetworkEstimator, so the detail fusion takes it as the network."""

    def __init__(self, network: NetworkEstimator, step: Rung) -> None:
        super().__init__(network.engine, network.reason)
        self.network = network  # runs the reduced stack, with its own settings (edge context)
        self.rung = step

    def describe(self) -> RunMethod:
        return replace(self.network.describe(), speed=self.rung.name, speed_rung=self.rung.summary)

    def reduced(self, stack: Stack) -> tuple[Stack, float]:
        """The stack the network sees, and the scale actually used (1 where the stack is too
        small to shrink)."""
        r = self.rung
        small = stack
        if r.max_lights is not None and stack.num_lights > r.max_lights:
            small = small.subset(evenly_spaced(stack.num_lights, r.max_lights))
        scale = r.scale if min(stack.shape) / r.scale >= MIN_REDUCED_PX else 1
        return shrink_stack(small, scale), scale

    def estimate(
        self, stack: Stack, tiling: TilingOptions, timer: StageTimer, progress: bool = False
    ) -> Estimate:
        with timer("preprocess"):
            small, scale = self.reduced(stack)
        base = self.network.estimate(small, tiling, timer, progress)
        if scale == 1:
            return base
        with timer("postprocess"):
            normals = grow_normals(base.normals, small.mask, stack.shape, stack.mask)
        return Estimate(normals, base.plan, base.flops)


def reduced_network(network: NetworkEstimator, speed: str | None) -> NetworkEstimator:
    """The network as ``--speed`` runs it (None or 'full': unchanged). The caller adds the
    detail fusion (Model does, by default), as it does for the full-resolution network."""
    step = rung(speed or DEFAULT_RUNG)
    if step.scale == 1 and step.max_lights is None:
        return network
    return ReducedNetwork(network, step)


__all__ = [
    "DEFAULT_RUNG",
    "FAST_LIGHTS",
    "RUNGS",
    "ReducedNetwork",
    "Rung",
    "grow_normals",
    "reduced_network",
    "rung",
    "shrink_stack",
]
