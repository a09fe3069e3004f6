"""Text forms of what commands write: JSON without bare NaN, rows of numbers."""

from __future__ import annotations

import json
import os
from collections.abc import Sequence

import numpy as np


def to_jsonable(value: object) -> object:
    """Replace non-finite floats by None (bare NaN is not JSON), numpy scalars by Python's,
    paths by their text and sets by sorted lists."""
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (set, frozenset)):
        value = sorted(value, key=str)
    if isinstance(value, (list, tuple, np.ndarray)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    return value


def json_text(data: object, indent: int | None = 2) -> str:
    """The one JSON form of everything msfnet writes or prints: strict JSON (no NaN), other
    odd values as their text."""
    return json.dumps(to_jsonable(data), indent=indent, allow_nan=False, default=str) + "\n"


def vectors_text(rows: np.ndarray | Sequence[Sequence[float]], fmt: str = "{:.8f}") -> str:
    """One row of numbers per line (light directions, intensities)."""
    return "".join(" ".join(fmt.format(float(v)) for v in r) + "\n" for r in rows)


__all__ = ["json_text", "to_jsonable", "vectors_text"]
