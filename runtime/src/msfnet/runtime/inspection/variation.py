"""A variation model learnt from good parts: per pixel, the centre and the robust spread of the
local shape (and curvature) over N good parts aligned to the first (docs/run.md, "Inspection
station", Variation model). It is written as a run folder plus ``spread_*.tif`` and
``variation.json``, which :func:`~msfnet.runtime.inspection.defects.read_run` reads as a
reference that carries its spreads.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from msfnet.common.errors import InputError
from msfnet.common.files import json_text, staged_folder
from msfnet.common.vocabulary import opt, verbatim
from msfnet.runtime.inspection.defects import DefectOptions, InspectionInput, align_to, find_defects
from msfnet.runtime.results.maps.registered import write_tiff

MIN_GOOD_PARTS = 3  # a median and a spread of fewer say nothing
MAD_TO_SIGMA = 1.4826  # the median absolute deviation of a normal distribution, in sigmas
VARIATION_FILE = "variation.json"
SUGGEST_FACTOR = 1.25  # the suggested --depth: this times the depth the worst good part needs
SEARCH_STEPS = 24  # bisection steps (log scale) for the depth a good part needs


@dataclass(frozen=True)
class GoodPartsStatistics:
    """``needed``: per good part, the smallest depth threshold at which it passes the rule
    (its min-area, polarity, sigmas and keep-out) against a model of the *other* good parts
    (against all of them when there are only MIN_GOOD_PARTS: ``held_out`` False)."""

    units: str
    needed: tuple[float, ...]
    held_out: bool

    @property
    def suggested_depth(self) -> float:
        """SUGGEST_FACTOR x the largest need, rounded up to 2 significant digits."""
        value = SUGGEST_FACTOR * max(self.needed, default=0.0)
        if not (math.isfinite(value) and value > 0):
            return 0.0
        digits = 1 - math.floor(math.log10(value))
        return math.ceil(value * 10**digits) / 10**digits

    def line(self) -> str:
        how = "left out of the model" if self.held_out else "in the model (3 parts: none held out)"
        least = opt("depth", verbatim(f"{min(self.needed):.2g}"))
        return (
            f"each good part, {how}, passes from {least} to "
            f"{max(self.needed):.2g} {self.units}: suggested "
            f"{opt('depth', self.suggested_depth)} {self.units}"
        )


@dataclass
class VariationModel:
    """``centre``: the reference the parts are aligned to and judged against (its
    ``local_shape_spread`` / ``curvature_spread`` set); ``parts``: the good parts' sources;
    ``shifts``: each one's alignment to the first (x, y px)."""

    centre: InspectionInput
    parts: tuple[str, ...]
    shifts: tuple[tuple[float, float], ...]
    statistics: GoodPartsStatistics | None

    def save(self, folder: Path, *, overwrite: bool = False) -> Path:
        """Write the model as a run folder the inspection reads (see the module notes)."""
        c = self.centre
        maps = {
            "local_shape.tif": c.local_shape,
            "curvature.tif": c.curvature,
            "albedo.tif": c.albedo,
            "spread_local_shape.tif": c.local_shape_spread,
            "spread_curvature.tif": c.curvature_spread,
        }
        info = {
            "registered": {
                "pixel_size_mm": c.pixel_size_mm,
                "local_size_px": c.local_size_px,
                "local_shape": c.units["depth"],
                "curvature": c.units["curvature"],
            },
            "frame": c.frame.as_dict(),
            "options": {"intrinsics": None},
        }
        stats = self.statistics
        record = {
            "kind": "msfnet variation model",
            "version": 1,
            "good_parts": list(self.parts),
            "shifts_px": [list(s) for s in self.shifts],
            "depth_needed_by_good_parts": None if stats is None else list(stats.needed),
            "suggested_depth": None if stats is None else stats.suggested_depth,
        }
        with staged_folder(folder, overwrite=overwrite) as tmp:
            for name, values in maps.items():
                if values is not None:
                    write_tiff(tmp / name, values, f"msfnet variation model: {name}")
            (tmp / "maps.json").write_text(json_text(info), encoding="utf-8")
            (tmp / VARIATION_FILE).write_text(json_text(record), encoding="utf-8")
        return folder


def train_variation(
    parts: Sequence[InspectionInput], rule: DefectOptions | None = None
) -> VariationModel:
    """The model of ``parts`` (good parts mapped alike; aligned to the first as a reference
    is), and the depth threshold each needs to pass ``rule`` (its depth is searched; the rest
    of it, min-area, polarity, sigmas and keep-out, as the parts will be judged).
    InputError for fewer than MIN_GOOD_PARTS or parts that cannot be aligned."""
    if len(parts) < MIN_GOOD_PARTS:
        raise InputError(
            f"a variation model needs at least {MIN_GOOD_PARTS} good parts (5 or more "
            f"recommended), got {len(parts)}"
        )
    first = parts[0]
    local: list[np.ndarray] = []
    curv: list[np.ndarray] = []
    shifts: list[tuple[float, float]] = []
    for part in parts:
        aligned = align_to(first, part) if part is not first else None
        shifts.append((0.0, 0.0) if aligned is None else aligned.shift)
        if first.local_shape is not None:
            moved = part.local_shape if aligned is None else aligned.local_shape
            if moved is None:
                raise InputError("this good part has no local shape map", part.source)
            local.append(moved)
        if first.curvature is not None:
            moved = part.curvature if aligned is None else aligned.curvature
            if moved is not None:
                curv.append(moved)
    centre_l, spread_l = _centre_spread(local)
    centre_c, spread_c = _centre_spread(curv) if len(curv) == len(parts) else (None, None)
    centre = replace(
        first,
        local_shape=centre_l if centre_l is not None else first.local_shape,
        curvature=centre_c if centre_c is not None else first.curvature,
        local_shape_spread=spread_l,
        curvature_spread=spread_c,
        source="variation model",
    )
    stats = None
    if centre_l is not None:
        stats = _needed_depths(first, local, rule or DefectOptions(depth=1.0))
    return VariationModel(centre, tuple(p.source for p in parts), tuple(shifts), stats)


def _centre_spread(maps: list[np.ndarray]) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Per pixel: the median and MAD_TO_SIGMA x the median absolute deviation, over the maps
    that hold the pixel (NaN where fewer than MIN_GOOD_PARTS do)."""
    if not maps:
        return None, None
    stack = np.stack(maps).astype(np.float64)
    held = np.isfinite(stack).sum(axis=0) >= MIN_GOOD_PARTS
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN pixels: outside every part
        centre = np.nanmedian(stack, axis=0)
        spread = MAD_TO_SIGMA * np.nanmedian(np.abs(stack - centre), axis=0)
    centre[~held] = np.nan
    spread[~held] = np.nan
    return centre.astype(np.float32), spread.astype(np.float32)


def _needed_depths(
    first: InspectionInput, local: list[np.ndarray], rule: DefectOptions
) -> GoodPartsStatistics:
    """Per good part (aligned local shape in ``local``), the smallest --depth at which the
    rule passes it against the model of the others: the rule itself decides (hysteresis,
    min-area and all), searched by bisection on a log scale."""
    held_out = len(local) > MIN_GOOD_PARTS
    needed = []
    for i, own in enumerate(local):
        others = [m for k, m in enumerate(local) if k != i] if held_out else local
        centre, spread = _centre_spread(others)
        model = replace(
            first, local_shape=centre, curvature=None, albedo=None, local_shape_spread=spread
        )
        part = replace(first, local_shape=own, curvature=None, albedo=None, source=f"good {i}")
        deviation = np.abs(own - centre)
        hi = 2.0 * float(np.nanmax(deviation)) + 1e-12 if np.isfinite(deviation).any() else 1.0
        lo = hi * 1e-6
        for _ in range(SEARCH_STEPS):
            mid = math.sqrt(lo * hi)
            verdict, _ = find_defects(part, replace(rule, depth=mid, curvature=None), model)
            lo, hi = (lo, mid) if verdict.passed else (mid, hi)
        needed.append(hi)
    return GoodPartsStatistics(first.units["depth"], tuple(needed), held_out)


__all__ = [
    "MIN_GOOD_PARTS",
    "VARIATION_FILE",
    "GoodPartsStatistics",
    "VariationModel",
    "train_variation",
]
