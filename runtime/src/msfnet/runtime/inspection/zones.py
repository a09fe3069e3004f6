"""Zones of a part: areas with their own thresholds, or left out, given as polygons in the
camera image's pixels in a small JSON file (format: docs/run.md, "Inspection station", Zones).
Each zone has a ``name``, a ``polygon`` (3+ [x, y] points) and ``ignore: true`` or its own
``depth`` / ``curvature`` (a missing one keeps the rule's); later zones win where they overlap.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from msfnet.common.errors import InputError, first_line
from msfnet.runtime.results.maps.registered import Frame

MAX_ZONES = 255  # one byte of labels; far more than any drawing holds
_KEYS = {"name", "polygon", "depth", "curvature", "ignore"}


@dataclass(frozen=True)
class Zone:
    name: str
    polygon: tuple[tuple[float, float], ...]  # camera image pixels (x, y)
    depth: float | None = None
    curvature: float | None = None
    ignore: bool = False


@dataclass(frozen=True)
class Zones:
    zones: tuple[Zone, ...]
    source: str = "zones"

    def labels(self, shape: tuple[int, int], frame: Frame) -> np.ndarray:
        """(H, W) int16 on the maps' pixels: the index of the zone each pixel is in, -1 for
        none. InputError for a zone that falls wholly outside the maps (a file for another
        camera, ROI or part)."""
        out = np.full(shape, -1, np.int16)
        (x0, y0), k = frame.origin_xy, frame.downscale
        for i, zone in enumerate(self.zones):
            # image pixel centres -> map pixel centres (a map pixel covers k x k image ones)
            pts = [((x - x0 + 0.5) / k - 0.5, (y - y0 + 0.5) / k - 0.5) for x, y in zone.polygon]
            one = np.zeros(shape, np.uint8)
            cv2.fillPoly(one, [np.round(np.array(pts) * 16).astype(np.int32)], 1, shift=4)
            if not one.any():
                raise InputError(
                    f"zone {zone.name!r} lies outside the {shape[1]}x{shape[0]} maps (its "
                    "polygon is in the camera image's pixels): a zone file for another part "
                    "or ROI?",
                    self.source,
                )
            out[one > 0] = i
        return out


def read_zones(path: Path) -> Zones:
    """The zones of a JSON file (see the module notes); InputError naming what is wrong."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as exc:
        raise InputError(f"cannot read the zone file ({first_line(exc)})", path) from exc
    except (ValueError, UnicodeDecodeError) as exc:
        raise InputError(f"not valid JSON ({first_line(exc)})", path) from exc
    items = data.get("zones") if isinstance(data, dict) else None
    if not isinstance(items, list) or not items:
        raise InputError('expected {"zones": [{"name": ..., "polygon": [[x, y], ...]}, ...]}', path)
    if len(items) > MAX_ZONES:
        raise InputError(f"{len(items)} zones: at most {MAX_ZONES}", path)
    return Zones(tuple(_zone(item, n, path) for n, item in enumerate(items, 1)), str(path))


def _zone(item: object, n: int, path: Path) -> Zone:
    if not isinstance(item, dict):
        raise InputError(f"zone {n}: expected an object with a name and a polygon", path)
    unknown = set(item) - _KEYS
    if unknown:
        raise InputError(
            f"zone {n}: unknown key(s) {', '.join(sorted(unknown))} (known: "
            f"{', '.join(sorted(_KEYS))})",
            path,
        )
    name = item.get("name", f"zone {n}")
    polygon = item.get("polygon")
    try:
        points = tuple((float(x), float(y)) for x, y in polygon)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        points = ()
    if len(points) < 3 or not all(math.isfinite(v) for p in points for v in p):
        raise InputError(f"zone {name!r}: the polygon needs 3 or more [x, y] points", path)
    ignore = item.get("ignore", False)
    if not isinstance(ignore, bool):
        raise InputError(f"zone {name!r}: ignore must be true or false", path)
    limits = {}
    for key in ("depth", "curvature"):
        value = item.get(key)
        ok = value is None or (
            isinstance(value, (int, float))
            and not isinstance(value, bool)
            and math.isfinite(value)
            and value > 0
        )
        if not ok:
            raise InputError(f"zone {name!r}: {key} must be a positive number, got {value!r}", path)
        limits[key] = None if value is None else float(value)
    return Zone(str(name), points, limits["depth"], limits["curvature"], ignore)


__all__ = ["Zone", "Zones", "read_zones"]
