"""The pinhole camera model shared by light calibration and normal integration."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from msfnet.common.errors import InputError

# Focal lengths a camera can have, per pixel of the image's longer side: 0.01 is a ~179 degree
# field of view; well above 10,000 the sphere fit's rays are parallel to float64 precision
# (docs/benchmark.md, "Measurements behind the code's rules").
FOCAL_PER_SIDE = (0.01, 1e4)
PRINCIPAL_REACH = 10  # image sides the principal point may lie outside the image (shift lenses)


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels (row/column coordinates of the stored image); where an
    option is None instead, the camera is orthographic."""

    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        values = (self.fx, self.fy, self.cx, self.cy)
        # zero or non-finite focal lengths would make every ray degenerate (and loops spin)
        if not (all(np.isfinite(values)) and self.fx > 0 and self.fy > 0):
            raise InputError(
                f"intrinsics need finite values and positive focal lengths, got "
                f"fx={self.fx:g} fy={self.fy:g} cx={self.cx:g} cy={self.cy:g}"
            )

    @classmethod
    def coerce(cls, value: Intrinsics | Sequence[float] | None) -> Intrinsics | None:
        """None, an Intrinsics or a (fx, fy, cx, cy) sequence -> Intrinsics or None."""
        if value is None or isinstance(value, Intrinsics):
            return value
        vals = [float(v) for v in value]
        if len(vals) != 4:
            raise InputError(f"intrinsics must be (fx, fy, cx, cy), got {len(vals)} values")
        return cls(*vals)

    def check_for(self, shape: tuple[int, int], option: str = "intrinsics") -> None:
        """Refuse intrinsics that are finite yet absurd for images of ``shape`` (H, W): the
        rays through the image must come out finite and unit, and the focal lengths must give
        a field of view between ~179 and ~0.006 degrees (beyond that, perspective cannot be
        told from orthographic in float64, and the sphere fit returns one direction for every
        light). ``option`` names what the user gave (``--focal``, ``--intrinsics``)."""
        h, w = int(shape[0]), int(shape[1])
        side = max(h, w, 1)
        lo, hi = side * FOCAL_PER_SIDE[0], side * FOCAL_PER_SIDE[1]
        for label, f in (("FX", self.fx), ("FY", self.fy)):
            if not lo <= f <= hi:
                what = "the focal length" if self.fx == self.fy else f"{label}"
                raise InputError(
                    f"{option}: {what} {f:g} px is outside {lo:g}..{hi:g} px for {w}x{h} "
                    "images (a field of view between ~0.006 and ~179 degrees); give it in "
                    "pixels, or leave it out for an orthographic camera"
                )
        reach = PRINCIPAL_REACH * side
        if not (-reach <= self.cx <= w + reach and -reach <= self.cy <= h + reach):
            raise InputError(
                f"{option}: the principal point ({self.cx:g}, {self.cy:g}) lies more than "
                f"{PRINCIPAL_REACH} image sides outside the {w}x{h} image"
            )
        xs = np.array([0.0, w - 1.0, 0.0, w - 1.0, (w - 1) / 2])
        ys = np.array([0.0, 0.0, h - 1.0, h - 1.0, (h - 1) / 2])
        with np.errstate(all="ignore"):
            rays = self.rays(xs, ys)
            norms = np.linalg.norm(rays, axis=-1)
            unit = np.all(np.isfinite(rays)) and np.allclose(norms, 1.0, atol=1e-9)
        if not unit:
            raise InputError(f"{option}: the view rays through the image are not finite")

    def rays(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Unit rays from the camera through pixels (camera looks down -z)."""
        d = np.stack([(x - self.cx) / self.fx, -(y - self.cy) / self.fy, -np.ones_like(x)], -1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)


__all__ = ["Intrinsics"]
