"""The one stack writer: the DiLiGenT layout, which every msfnet tool reads."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..files import write_atomic, write_text, write_vectors
from ..imageio import write_png
from .types import Stack


def save_stack(stack: Stack, folder: str | Path, bit_depth: int = 16) -> Path:
    """Write a stack in the DiLiGenT layout (16-bit PNGs, text lights, mask, Normal_gt.mat)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    top = 65535 if bit_depth == 16 else 255
    dtype = np.uint16 if bit_depth == 16 else np.uint8
    names = stack.filenames or [f"{i + 1:03d}.png" for i in range(stack.num_lights)]
    names = [Path(n).with_suffix(".png").name for n in names]
    for name, img in zip(names, stack.images, strict=True):
        if img.dtype != dtype:  # floats rounded, then clipped; values are never rescaled
            vals = np.rint(img) if img.dtype.kind == "f" else img.astype(np.int64)
            img = np.clip(vals, 0, top).astype(dtype)
        write_png(folder / name, img)
    write_text(folder / "filenames.txt", "\n".join(names) + "\n")
    write_vectors(folder / "light_directions.txt", stack.lights)
    write_vectors(folder / "light_intensities.txt", stack.intensities)
    write_png(folder / "mask.png", stack.mask.astype(np.uint8) * 255)
    if stack.normals_gt is not None:
        from scipy.io import savemat

        gt = stack.normals_gt.astype(np.float64)
        write_atomic(folder / "Normal_gt.mat", lambda t: savemat(str(t), {"Normal_gt": gt}))
    return folder
