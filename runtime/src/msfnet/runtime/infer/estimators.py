"""Estimators: stack -> normals. One protocol, implemented by the network and least squares.

"Which method" is chosen once, by constructing an estimator; nothing downstream branches on it.
The network estimator runs any :class:`~msfnet.runtime.engines.base.Engine` (ONNX Runtime plain
or staged, OpenVINO, or a torch model from ``msfnet.model.predict``) through the same tiling and
normalisation.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from msfnet.runtime.engines.base import Engine
from msfnet.runtime.engines.method import RunMethod
from msfnet.runtime.infer.flops import inference_flops
from msfnet.runtime.infer.least_squares import least_squares_normals
from msfnet.runtime.infer.tiled import choose_plan, infer_normals
from msfnet.runtime.infer.tiling import DEFAULT_MAX_MEMORY_MB, TilePlan
from msfnet.runtime.instrument import StageTimer
from msfnet.runtime.stack import Stack


@dataclass(frozen=True)
class TilingOptions:
    tile: int | None = None  # window edge in px; 0 = untiled; None = sized from max_memory_mb
    max_memory_mb: float = DEFAULT_MAX_MEMORY_MB  # peak memory target for the whole run


@dataclass
class Estimate:
    normals: np.ndarray  # (H, W, 3) float32 unit normals, zeros outside the mask
    plan: TilePlan | None  # tiles run (network estimators)
    flops: float  # work done by the inference stage (0 when not counted)


class Estimator(Protocol):
    method: str  # "msf" (the network) or "l2" (least squares)

    def describe(self) -> RunMethod:
        """What ran, for the profile and the console (engine, precision, threads, ...)."""
        ...

    def estimate(
        self, stack: Stack, tiling: TilingOptions, timer: StageTimer, progress: bool = False
    ) -> Estimate: ...


class NetworkEstimator:
    method = "msf"

    def __init__(self, engine: Engine, reason: str = "", edge_context: bool = True) -> None:
        self.engine = engine
        self.reason = reason  # why this engine / precision was chosen (dispatch)
        # let the network see lit surface beyond a mask edge (tiled.context_mask); False: the
        # published protocol's zeros beyond the mask everywhere
        self.edge_context = edge_context

    def describe(self) -> RunMethod:
        e = self.engine
        return replace(
            e.describe(),
            method=self.method,
            model=str(e.info.path),
            graph="staged" if e.info.staged else "monolithic",
            choice=self.reason or None,
            edge_context=self.edge_context,
        )

    def estimate(
        self, stack: Stack, tiling: TilingOptions, timer: StageTimer, progress: bool = False
    ) -> Estimate:
        plan = choose_plan(stack, self.engine, tiling.tile, tiling.max_memory_mb)
        normals = infer_normals(
            self.engine, stack, plan, timer, progress=progress, edge_context=self.edge_context
        ).normals
        return Estimate(normals, plan, inference_flops(stack.num_lights, plan.pixels))


class LeastSquaresEstimator:
    """Classical per-pixel least squares (Woodham 1980): no model, same loaders and outputs."""

    method = "l2"

    def describe(self) -> RunMethod:
        return RunMethod(method=self.method, engine="numpy", precision="fp64")

    def estimate(
        self, stack: Stack, tiling: TilingOptions, timer: StageTimer, progress: bool = False
    ) -> Estimate:
        with timer("inference"):
            normals = least_squares_normals(stack, max_memory_mb=tiling.max_memory_mb)
        return Estimate(normals, None, 0.0)


# The network needs this many lights. With three (least squares' minimum) it guessed: on a
# rendered 12-light plate it was 25 deg off where least squares was 0.5 (docs/benchmark.md).
NETWORK_MIN_LIGHTS = 4


def for_light_count(estimator: Estimator, stack: Stack) -> tuple[Estimator, Stack]:
    """The estimator that runs on ``stack``: ``estimator``, or least squares where the stack has
    too few lights for the network, with a copy of the stack (arrays shared) whose warnings say
    so, as msf-run prints them (the caller's own Stack is left as it was)."""
    n = stack.num_lights
    if estimator.method != "msf" or n >= NETWORK_MIN_LIGHTS:
        return estimator, stack
    said = (
        f"{n} lights are too few for the network (it needs {NETWORK_MIN_LIGHTS} or more): "
        "least squares ran instead"
    )
    return LeastSquaresEstimator(), replace(stack, warnings=[*stack.warnings, said])


__all__ = [
    "NETWORK_MIN_LIGHTS",
    "Engine",
    "Estimate",
    "Estimator",
    "LeastSquaresEstimator",
    "NetworkEstimator",
    "TilingOptions",
    "for_light_count",
]
