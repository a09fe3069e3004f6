"""The part of a map that holds the mask: every map computes and draws on this box only, so a
small part in a large frame costs what the part costs."""

from __future__ import annotations

import numpy as np


def mask_box(valid: np.ndarray, margin: int = 0) -> tuple[slice, slice] | None:
    """Row and column slices of ``valid``'s bounding box grown by ``margin`` pixels on each
    side and clipped to the image; None where no pixel is valid."""
    rows = np.flatnonzero(valid.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(valid.any(axis=0))
    h, w = valid.shape
    return (
        slice(max(int(rows[0]) - margin, 0), min(int(rows[-1]) + margin + 1, h)),
        slice(max(int(cols[0]) - margin, 0), min(int(cols[-1]) + margin + 1, w)),
    )
