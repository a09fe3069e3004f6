"""The one stack writer: the DiLiGenT layout, which every msfnet tool reads.

:func:`save_stack` writes a whole stack. It is made of the per-file writers below, which are
also what ``msf-capture`` (msfnet.calib.capture) writes the stack it builds from its raw frames
with, so both write the same files under the same names, in the same format, atomically
(each file through a temporary sibling and a rename: ``files.write_atomic``).
The names written are the first (canonical) ones of the names the loader accepts.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from msfnet.common.files import vectors_text, write_atomic, write_text
from msfnet.common.imageio import write_png
from msfnet.runtime.stack.load import GT_NAMES, INTENSITY_NAMES, LIGHTS_NAMES, MASK_NAMES
from msfnet.runtime.stack.types import Stack

FILENAMES_FILE = "filenames.txt"
LIGHTS_FILE = LIGHTS_NAMES[0]  # light_directions.txt
INTENSITIES_FILE = INTENSITY_NAMES[0]  # light_intensities.txt
MASK_FILE = MASK_NAMES[0]  # mask.png
NORMALS_FILE = GT_NAMES[0]  # Normal_gt.mat (MATLAB v5, key Normal_gt, float64)


def filenames_text(names: Sequence[str]) -> str:
    """filenames.txt: one image name a line."""
    return "\n".join(names) + "\n"


def write_filenames(folder: str | Path, names: Sequence[str]) -> Path:
    return write_text(Path(folder) / FILENAMES_FILE, filenames_text(names))


def write_lights(folder: str | Path, lights: np.ndarray) -> Path:
    """light_directions.txt: one ``x y z`` row a light (``files.vectors_text``)."""
    return write_text(Path(folder) / LIGHTS_FILE, vectors_text(lights))


def write_intensities(folder: str | Path, intensities: np.ndarray) -> Path:
    """light_intensities.txt: one ``r g b`` row a light."""
    return write_text(Path(folder) / INTENSITIES_FILE, vectors_text(intensities))


def write_mask(folder: str | Path, mask: np.ndarray) -> Path:
    """mask.png: 8-bit grey, 255 inside the object, 0 outside."""
    path = Path(folder) / MASK_FILE
    write_png(path, np.asarray(mask, bool).astype(np.uint8) * 255)
    return path


def write_normals(folder: str | Path, normals: np.ndarray) -> Path:
    """Normal_gt.mat: ground-truth normals (H, W, 3) as float64 under the key Normal_gt."""
    from scipy.io import savemat

    gt = np.asarray(normals, np.float64)
    return write_atomic(Path(folder) / NORMALS_FILE, lambda t: savemat(str(t), {"Normal_gt": gt}))


def write_image(path: str | Path, img: np.ndarray, bit_depth: int = 16) -> Path:
    """One stack image as a PNG of ``bit_depth`` bits: floats are rounded, then clipped, and
    values are never rescaled (an image already of that depth is written as it is)."""
    top = 65535 if bit_depth == 16 else 255
    dtype = np.uint16 if bit_depth == 16 else np.uint8
    if img.dtype != dtype:
        vals = np.rint(img) if img.dtype.kind == "f" else img.astype(np.int64)
        img = np.clip(vals, 0, top).astype(dtype)
    write_png(path, img)
    return Path(path)


def save_stack(stack: Stack, folder: str | Path, bit_depth: int = 16) -> Path:
    """Write a stack in the DiLiGenT layout (16-bit PNGs, text lights, mask, Normal_gt.mat)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    names = stack.filenames or [f"{i + 1:03d}.png" for i in range(stack.num_lights)]
    names = [Path(n).with_suffix(".png").name for n in names]
    for name, img in zip(names, stack.images, strict=True):
        write_image(folder / name, img, bit_depth)
    write_filenames(folder, names)
    write_lights(folder, stack.lights)
    write_intensities(folder, stack.intensities)
    write_mask(folder, stack.mask)
    if stack.normals_gt is not None:
        write_normals(folder, stack.normals_gt)
    return folder


__all__ = [
    "FILENAMES_FILE",
    "INTENSITIES_FILE",
    "LIGHTS_FILE",
    "MASK_FILE",
    "NORMALS_FILE",
    "filenames_text",
    "save_stack",
    "write_filenames",
    "write_image",
    "write_intensities",
    "write_lights",
    "write_mask",
    "write_normals",
]
