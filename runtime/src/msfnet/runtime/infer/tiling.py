"""Memory-bounded spatial tiling with a halo, so the stitched normals equal the untiled ones.

Why space and not lights: every stage takes the max over *all* lights, so a light chunk would see
a different max. Every stage is local in space, so a tile whose halo covers the receptive field
(19 px before, 18 after, from :func:`msfnet.runtime.infer.flops.receptive_field`) reproduces the
untiled output in its core. Origins are multiples of 4 so the network's stride-2 grids line up,
and windows are clipped to the padded image exactly like the untiled input, so edge tiles see the
same zero padding. Tiles whose core holds no mask pixel are skipped; cores shrink to the mask.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from msfnet.common.errors import InputError
from msfnet.common.vocabulary import opt
from msfnet.runtime.contract import INPUT_MULTIPLE as MULTIPLE
from msfnet.runtime.engines.staged_loop import STORED_BYTES_PER_PIXEL_LIGHT
from msfnet.runtime.infer.flops import receptive_field
from msfnet.runtime.infer.normalise import padded_size

HALO = padded_size(max(receptive_field()), MULTIPLE)  # 20 px: keeps window origins on the grid
# Activations per (network-input pixel x light of one call): the bound for what has not been
# measured (ONNX Runtime fp32, arena off, engines/ort_session.py). ACTIVATION_BYTES: measured
# whole-process peaks on staged graphs with a margin for run-to-run spread, so peak RSS stays
# under --max-memory (OpenVINO int8's arenas per pixel-light grow as its 2-light call shrinks);
# figures in docs/benchmark.md, "Measurements behind the code's rules".
BYTES_PER_PIXEL_LIGHT = 3000
ACTIVATION_BYTES = {
    ("onnxruntime", "fp32"): 3600,
    ("openvino", "fp32"): 3800,
    ("openvino", "int8"): 4800,
}
BASE_MEMORY_MB = 300  # runtime + engine + model, outside the per-tile working set
DEFAULT_MAX_MEMORY_MB = 4096


@dataclass(frozen=True)
class Tile:
    """Rectangles as (y0, y1, x0, x1) in padded-image pixels: core (written) and window (run)."""

    core: tuple[int, int, int, int]
    window: tuple[int, int, int, int]

    @property
    def pixels(self) -> int:
        y0, y1, x0, x1 = self.window
        return (y1 - y0) * (x1 - x0)


@dataclass
class TilePlan:
    tiles: list[Tile]
    skipped: int
    tile_size: int | None  # max window edge; None = untiled
    halo: int

    @property
    def pixels(self) -> int:
        return sum(t.pixels for t in self.tiles)


def _down(v: int) -> int:
    return v // MULTIPLE * MULTIPLE


def activation_bytes(engine: str, precision: str, staged: bool = True) -> int:
    """Activations per (window pixel x light of one call) for ``engine`` at ``precision``: for a
    staged graph the measured figure where there is one, else the BYTES_PER_PIXEL_LIGHT bound.
    Plain graphs stay under the bound, so they keep it (the staged figures would shrink their
    windows for nothing). Names are matched without
    case, and an export's label by its leading precision (a ModelSession reports "int8-qdq" or
    "fp32 (fp16-stored weights)", not "int8" / "fp32")."""
    if not staged:
        return BYTES_PER_PIXEL_LIGHT
    label = precision.strip().lower()
    known = next((p for p in ("fp32", "bf16", "int8") if label.startswith(p)), label)
    return ACTIVATION_BYTES.get((engine.strip().lower(), known), BYTES_PER_PIXEL_LIGHT)


def bytes_per_pixel(
    lights: int, chunk: int | None = None, activation: int = BYTES_PER_PIXEL_LIGHT
) -> float:
    """Working set per window pixel: all lights at once (monolithic graph), or, for a staged
    graph run ``chunk`` lights at a time, the stored stage outputs (with one chunk's spare room,
    staged_loop.run_stages) plus one chunk's activations (``activation`` bytes a pixel-light)."""
    if chunk is None:
        return lights * activation
    per_call = min(chunk, lights)
    return (lights + per_call) * STORED_BYTES_PER_PIXEL_LIGHT + per_call * activation


def tile_size_for_memory(
    max_memory_mb: float,
    lights: int,
    chunk: int | None = None,
    stack_mb: float = 0.0,
    activation: int = BYTES_PER_PIXEL_LIGHT,
) -> int:
    """Largest square window (multiple of 4) whose working set fits in ``max_memory_mb`` (the
    user's budget for the whole run) beside the loaded stack's ``stack_mb``; ``activation``:
    the engine's bytes a pixel-light (:func:`activation_bytes`)."""
    budget = (max_memory_mb - stack_mb - BASE_MEMORY_MB) * 2**20
    per_pixel = bytes_per_pixel(lights, chunk, activation)
    side = _down(int(math.sqrt(max(budget, 0) / per_pixel)))
    smallest = 2 * HALO + MULTIPLE
    if side < smallest:
        need = BASE_MEMORY_MB + stack_mb + smallest**2 * per_pixel / 2**20
        raise InputError(
            f"{opt('max_memory_mb', float(max_memory_mb))} MB is too small for {lights} lights: "
            f"the loaded stack and the smallest tile ({smallest} px) need about "
            f"{need:.0f} MB",
            option="max_memory_mb",
        )
    return side


def _axis_cores(lo: int, hi: int, core_max: int) -> list[tuple[int, int]]:
    """Split [lo, hi) into equal-ish parts of at most core_max, starts on multiples of 4."""
    length = hi - lo
    parts = max(1, -(-length // core_max))
    step = padded_size(-(-length // parts))
    return [(a, min(a + step, hi)) for a in range(lo, hi, step)]


def _window(c0: int, c1: int, size: int, fixed: int | None, halo: int) -> tuple[int, int]:
    """Window around core [c0, c1) on an axis of padded length ``size``."""
    if fixed is None:
        return max(0, c0 - halo), min(size, c1 + halo)
    start = min(max(0, c0 - halo), max(0, size - fixed))  # static models: every window the same
    return start, start + fixed


def plan_tiles(
    mask: np.ndarray, tile: int | None, halo: int = HALO, fixed: tuple[int, int] | None = None
) -> TilePlan:
    """Cover the mask with tiles whose windows are at most ``tile`` px (None: one untiled pass).

    ``fixed`` (H, W): every window has exactly this size (static-shape exports); windows that
    reach past the padded image are zero-filled by the caller.
    """
    h, w = mask.shape
    hp, wp = padded_size(h), padded_size(w)
    if tile is None and fixed is None:
        return TilePlan([Tile((0, hp, 0, wp), (0, hp, 0, wp))], 0, None, 0)
    if fixed is not None:
        core_y, core_x = fixed[0] - 2 * halo, fixed[1] - 2 * halo
        tile = max(fixed)
    else:
        assert tile is not None
        if tile % MULTIPLE or tile < 2 * halo + MULTIPLE:
            raise InputError(
                f"{opt('tile', tile)}: must be a multiple of {MULTIPLE} and at least "
                f"{2 * halo + MULTIPLE} (2 x {halo} px halo + 4)",
                option="tile",
            )
        core_y = core_x = tile - 2 * halo
    if core_y < MULTIPLE or core_x < MULTIPLE:
        raise InputError(f"static model shape {fixed} is too small for the {halo} px halo")
    ys, xs = np.nonzero(mask)
    y0, y1 = _down(int(ys.min())), min(hp, padded_size(int(ys.max()) + 1))
    x0, x1 = _down(int(xs.min())), min(wp, padded_size(int(xs.max()) + 1))
    padded_mask = np.zeros((hp, wp), bool)
    padded_mask[:h, :w] = mask
    tiles: list[Tile] = []
    skipped = 0
    for cy0, cy1 in _axis_cores(y0, y1, core_y):
        for cx0, cx1 in _axis_cores(x0, x1, core_x):
            sub = padded_mask[cy0:cy1, cx0:cx1]
            if not sub.any():
                skipped += 1
                continue
            # shrink the core to the mask inside it: less halo'd area to compute
            sy, sx = np.nonzero(sub)
            ky0, ky1 = cy0 + _down(int(sy.min())), min(cy1, cy0 + padded_size(int(sy.max()) + 1))
            kx0, kx1 = cx0 + _down(int(sx.min())), min(cx1, cx0 + padded_size(int(sx.max()) + 1))
            wy = _window(ky0, ky1, hp, None if fixed is None else fixed[0], halo)
            wx = _window(kx0, kx1, wp, None if fixed is None else fixed[1], halo)
            tiles.append(Tile((ky0, ky1, kx0, kx1), (*wy, *wx)))
    return TilePlan(tiles, skipped, tile, halo)


__all__ = [
    "ACTIVATION_BYTES",
    "BYTES_PER_PIXEL_LIGHT",
    "DEFAULT_MAX_MEMORY_MB",
    "HALO",
    "Tile",
    "TilePlan",
    "activation_bytes",
    "bytes_per_pixel",
    "plan_tiles",
    "tile_size_for_memory",
]
