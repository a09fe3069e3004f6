"""A variation model learnt from good parts: per pixel, the centre and the robust spread of the
local shape (and curvature) over N good parts aligned to the first.

One golden part says where a good part's surface is, not how much good parts differ: a dome's
rim, a highlight the fit bends around, a label's relief all differ a little from part to part,
and an absolute threshold either floods there or misses small defects elsewhere. With N good
parts, a pixel of a new part is a defect where it leaves the centre by more than ``sigmas``
robust standard deviations *and* by at least the depth threshold (the floor: a pixel that never
varied would otherwise flag noise).

The model is written as a run folder (maps.json, local_shape.tif and curvature.tif holding the
centre, albedo.tif the first part's, for alignment) plus ``spread_local_shape.tif`` /
``spread_curvature.tif`` and ``variation.json``: :func:`~msfnet.runtime.inspection.defects.read_run`
reads it as a reference that carries its spreads.
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
from msfnet.runtime.inspection.defects import InspectionInput, align_to
from msfnet.runtime.results.maps.registered import write_tiff

MIN_GOOD_PARTS = 3  # a median and a spread of fewer say nothing
MAD_TO_SIGMA = 1.4826  # the median absolute deviation of a normal distribution, in sigmas
VARIATION_FILE = "variation.json"
SUGGEST_FACTOR = 1.5  # the suggested --depth: this times the good parts' 99.9th percentile


@dataclass(frozen=True)
class GoodPartsStatistics:
    """How far the good parts themselves leave the centre (|local shape - centre|, in the
    depth units) where they agree best (the pixels of the lower half of the spread): there the
    depth floor, not the spread, decides, so the floor is chosen from these."""

    units: str
    p99: float
    p999: float
    max: float

    @property
    def suggested_depth(self) -> float:
        """SUGGEST_FACTOR x the 99.9th percentile, rounded up to 2 significant digits."""
        value = SUGGEST_FACTOR * self.p999
        if not (math.isfinite(value) and value > 0):
            return 0.0
        digits = 1 - math.floor(math.log10(value))
        return math.ceil(value * 10**digits) / 10**digits

    def line(self) -> str:
        return (
            f"where good parts agree best they leave the centre by p99 {self.p99:.3g}, p99.9 "
            f"{self.p999:.3g}, max {self.max:.3g} {self.units}: suggested --depth "
            f"{self.suggested_depth:g} {self.units}"
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
        record = {
            "kind": "msfnet variation model",
            "version": 1,
            "good_parts": list(self.parts),
            "shifts_px": [list(s) for s in self.shifts],
            "statistics": None if self.statistics is None else self.statistics.__dict__,
            "suggested_depth": None if self.statistics is None else self.statistics.suggested_depth,
        }
        with staged_folder(folder, overwrite=overwrite) as tmp:
            for name, values in maps.items():
                if values is not None:
                    write_tiff(tmp / name, values, f"msfnet variation model: {name}")
            (tmp / "maps.json").write_text(json_text(info), encoding="utf-8")
            (tmp / VARIATION_FILE).write_text(json_text(record), encoding="utf-8")
        return folder


def train_variation(parts: Sequence[InspectionInput]) -> VariationModel:
    """The model of ``parts`` (good parts mapped alike; aligned to the first as a reference
    is). InputError for fewer than MIN_GOOD_PARTS or parts that cannot be aligned."""
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
    if centre_l is not None and spread_l is not None:
        stats = _good_statistics(np.stack(local), centre_l, spread_l, first.units["depth"])
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


def _good_statistics(
    local: np.ndarray, centre: np.ndarray, spread: np.ndarray, units: str
) -> GoodPartsStatistics:
    held = np.isfinite(spread)
    if not held.any():
        return GoodPartsStatistics(units, 0.0, 0.0, 0.0)
    quiet = held & (spread <= np.median(spread[held]))
    dev = np.abs(local[:, quiet] - centre[None, quiet])
    values = dev[np.isfinite(dev)]
    if values.size == 0:
        return GoodPartsStatistics(units, 0.0, 0.0, 0.0)
    p99, p999 = (float(v) for v in np.percentile(values, (99, 99.9)))
    return GoodPartsStatistics(units, p99, p999, float(values.max()))


__all__ = [
    "MIN_GOOD_PARTS",
    "VARIATION_FILE",
    "GoodPartsStatistics",
    "VariationModel",
    "train_variation",
]
