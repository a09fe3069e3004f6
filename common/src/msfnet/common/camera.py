"""The pinhole camera model shared by light calibration and normal integration."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from msfnet.common.errors import InputError


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

    def rays(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Unit rays from the camera through pixels (camera looks down -z)."""
        d = np.stack([(x - self.cx) / self.fx, -(y - self.cy) / self.fy, -np.ones_like(x)], -1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)


__all__ = ["Intrinsics"]
