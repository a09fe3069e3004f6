"""Tiled ONNX inference: per tile normalise -> pad -> run -> crop -> stitch.

Normalisation is per pixel (see normalise.py), so normalising a window of the raw images equals
cropping the normalised image; only the tile's pixels are ever expanded to float network input,
which is what bounds memory.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import cv2
import numpy as np

from msfnet.common.errors import InputError, MsfError, first_line
from msfnet.common.vocabulary import opt
from msfnet.runtime.infer.normalise import network_input
from msfnet.runtime.infer.tiling import (
    DEFAULT_MAX_MEMORY_MB,
    HALO,
    TilePlan,
    activation_bytes,
    plan_tiles,
    tile_size_for_memory,
)
from msfnet.runtime.instrument import StageTimer
from msfnet.runtime.stack import Stack

if TYPE_CHECKING:
    from msfnet.runtime.engines.base import Engine


# An outside pixel counts as surface when its brightness under most lights (the 75th percentile
# over the stack) is at least this fraction of the mask's median one: real backgrounds sit
# well below it, a plate's continuing surface near 1.
CONTEXT_LIT = 0.3
CONTEXT_MIN_WIDTH = 5  # px: thinner lit slivers along a silhouette are anti-aliasing, not surface
CONTEXT_SAMPLE = 20000  # mask pixels sampled for the object's brightness level


def context_mask(stack: Stack, halo: int = HALO) -> np.ndarray:
    """(H, W) bool: the mask plus the pixels within ``halo`` px outside it that are lit surface
    (see the module notes). Equals ``stack.mask`` for a silhouette on a dark background."""
    mask = stack.mask
    if mask.all() or not mask.any():
        return mask
    u8 = mask.astype(np.uint8)
    size = 2 * halo + 1
    near = cv2.dilate(u8, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))).astype(bool)
    ring = near & ~mask
    if not ring.any():
        return mask
    # the object's level from a sample of its pixels (a median needs no more), so the working
    # set is the ring and CONTEXT_SAMPLE pixels per light, never the whole mask
    ys, xs = np.nonzero(mask)
    step = max(1, ys.size // CONTEXT_SAMPLE)
    ys, xs = ys[::step], xs[::step]
    ry, rx = np.nonzero(ring)
    grey = np.empty((stack.num_lights, ry.size), np.float32)
    inside = np.empty((stack.num_lights, ys.size), np.float32)
    for i in range(stack.num_lights):  # one light at a time: never the whole stack as float
        # only the ring's and the sample's pixels are converted (a tenth of a DiLiGenT image)
        scale = 1.0 / stack.intensities[i].astype(np.float32)
        grey[i] = (stack.images[i, ry, rx].astype(np.float32) * scale).mean(axis=1)
        inside[i] = (stack.images[i, ys, xs].astype(np.float32) * scale).mean(axis=1)
    level = float(np.median(np.percentile(inside, 75, axis=0)))
    if level <= 0:
        return mask
    lit = np.zeros(mask.shape, np.uint8)
    lit[ring] = np.percentile(grey, 75, axis=0) >= CONTEXT_LIT * level
    k = cv2.getStructuringElement(cv2.MORPH_RECT, (CONTEXT_MIN_WIDTH, CONTEXT_MIN_WIDTH))
    # the band rule: a lit sliver along a silhouette vanishes, a surface continuing past a cut
    # (lit up to the halo) stays
    opened = cv2.morphologyEx(lit, cv2.MORPH_OPEN, k).astype(bool)
    if not opened.any():
        return mask
    # keep only lit regions that touch the mask
    _, labels = cv2.connectedComponents((opened | mask).astype(np.uint8), connectivity=8)
    touching = np.unique(labels[mask])
    return mask | (opened & np.isin(labels, touching[touching > 0]))


@dataclass
class InferenceResult:
    normals: np.ndarray  # (H, W, 3) float32, zeros outside the mask
    plan: TilePlan


def choose_plan(
    stack: Stack, model: Engine, tile: int | None = None, max_memory_mb: float | None = None
) -> TilePlan:
    """``tile``: window edge in px (0 = untiled); otherwise sized from ``max_memory_mb`` and N."""
    static = model.info.static_shape
    if static is not None:
        n, h, w = static
        if n != stack.num_lights:
            raise InputError(
                f"this model was exported for exactly {n} lights (static shape) but "
                f"the stack has {stack.num_lights}; use {opt('select')}/{opt('max_lights')} or a "
                "dynamic export",
                model.info.path,
            )
        return plan_tiles(stack.mask, None, fixed=(h, w))
    if tile == 0:
        return plan_tiles(stack.mask, None)
    if tile is None:
        # the budget is for the whole process: the loaded stack already occupies part of it
        # (its bytes as held: 2 a value for a 16-bit stack, 4 for float32)
        tile = tile_size_for_memory(
            max_memory_mb or DEFAULT_MAX_MEMORY_MB,
            stack.num_lights,
            model.chunk,
            stack_mb=stack.images.nbytes / 2**20,
            activation=activation_bytes(model.name, model.precision, model.chunk is not None),
        )
    return plan_tiles(stack.mask, tile)


def infer_normals(
    model: Engine,
    stack: Stack,
    plan: TilePlan,
    timer: StageTimer | None = None,
    progress: bool = False,
    edge_context: bool = True,
) -> InferenceResult:
    """Run the plan's tiles through the model and stitch the cores into an (H, W, 3) map.
    ``edge_context``: let the network see lit surface beyond the mask (:func:`context_mask`);
    False: zeros beyond the mask everywhere (the published protocol)."""
    timer = timer or StageTimer()
    seen = stack
    if edge_context:
        with timer("preprocess"):
            context = context_mask(stack)
        if context is not stack.mask:
            seen = replace(stack, mask=context)
    h, w = stack.shape
    n = stack.num_lights
    hp = max(max(t.window[1] for t in plan.tiles), h)
    wp = max(max(t.window[3] for t in plan.tiles), w)
    out = np.zeros((hp, wp, 3), np.float32)
    train_lights = model.info.train_lights
    bar = None
    if progress and len(plan.tiles) > 1:
        from tqdm import tqdm

        bar = tqdm(
            total=len(plan.tiles), unit="tile", desc="inference", file=sys.stderr, leave=False
        )
    for t in plan.tiles:
        wy0, wy1, wx0, wx1 = t.window
        with timer("preprocess"):
            # only the part of the window inside the image holds data; the rest is zero padding
            x, lights = network_input(
                seen,
                slice(wy0, min(wy1, h)),
                slice(wx0, min(wx1, w)),
                train_lights=train_lights,
                shape=(wy1 - wy0, wx1 - wx0),
            )
        with timer("inference"):
            try:
                y = model.run(x, lights)
            except (MemoryError, InputError, MsfError):  # they say what went wrong already
                raise
            except (TypeError, AttributeError, IndexError, KeyError, NameError):
                raise  # a bug of ours, not the engine's: an internal error, not bad input
            except Exception as exc:  # engines' own error types (e.g. allocation failure)
                raise MsfError(
                    f"{model.info.path}: {model.name} failed on a "
                    f"{wx1 - wx0}x{wy1 - wy0} tile with {n} lights "
                    f"({type(exc).__name__}: {_cause(model.name, exc)}); try a smaller "
                    f"{opt('tile')} or {opt('max_memory_mb')}"
                ) from exc
        with timer("postprocess"):
            cy0, cy1, cx0, cx1 = t.core
            out[cy0:cy1, cx0:cx1] = y[0, :, cy0 - wy0 : cy1 - wy0, cx0 - wx0 : cx1 - wx0].transpose(
                1, 2, 0
            )
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    with timer("postprocess"):
        normals = out[:h, :w] * stack.mask[:, :, None]
    return InferenceResult(np.ascontiguousarray(normals, np.float32), plan)


def _cause(engine: str, exc: BaseException) -> str:
    """An engine failure's cause in one line: OpenVINO's text starts with lines naming where in
    its sources it was raised, which say nothing to a user."""
    if engine == "openvino":
        from msfnet.runtime.engines.openvino import openvino_cause

        return openvino_cause(exc) or type(exc).__name__
    return first_line(exc)


__all__ = [
    "CONTEXT_LIT",
    "CONTEXT_MIN_WIDTH",
    "InferenceResult",
    "choose_plan",
    "context_mask",
    "infer_normals",
]
