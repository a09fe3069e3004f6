"""Text forms of what commands write: JSON without bare NaN, rows of numbers."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np


def to_jsonable(value: object) -> object:
    """Replace non-finite floats by None (bare NaN is not JSON) and numpy scalars by Python's."""
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    return value


def json_text(data: object) -> str:
    return json.dumps(to_jsonable(data), indent=2, allow_nan=False) + "\n"


def vectors_text(rows: np.ndarray | Sequence[Sequence[float]], fmt: str = "{:.8f}") -> str:
    """One row of numbers per line (light directions, intensities)."""
    return "".join(" ".join(fmt.format(float(v)) for v in r) + "\n" for r in rows)


__all__ = ["json_text", "to_jsonable", "vectors_text"]
