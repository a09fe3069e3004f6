"""The normals as files: normals.png is 16-bit RGB, (n + 1) / 2, zeros outside the mask (a
result's whole folder: :mod:`msfnet.runtime.results.result`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from msfnet.common.imageio import encode_png


def normals_png(normals: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W, 3) unit normals -> 16-bit RGB (n + 1) / 2, zeros outside the mask."""
    # one float32 work array, changed in place (no float64 H x W x 3 temporaries)
    n = np.nan_to_num(np.clip(np.asarray(normals, np.float32), -1, 1), copy=False)
    n += 1.0
    n *= 0.5 * 65535.0
    img = np.rint(n, out=n).astype(np.uint16)
    img[~mask] = 0
    return img


def write_rgb_png(path: Path, rgb: np.ndarray) -> None:
    """Into a staging folder (callers make the folder atomic)."""
    encode_png(path, rgb)


__all__ = ["normals_png", "write_rgb_png"]
