"""save_stack writes an integer stack as the float32 copy of it would be written; it is made of
the per-file writers msf-capture uses too."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _runtime_helpers import as_float32, png_stack

from msfnet.common.imageio import read_image
from msfnet.runtime.stack import (
    FILENAMES_FILE,
    INTENSITIES_FILE,
    LIGHTS_FILE,
    MASK_FILE,
    NORMALS_FILE,
    load_stack,
    read_normals,
    save_stack,
    write_filenames,
    write_image,
    write_intensities,
    write_lights,
    write_mask,
    write_normals,
)


@pytest.mark.parametrize(("stored", "written"), [(16, 16), (16, 8), (8, 16), (8, 8)])
def test_integer_stack_saves_like_its_float32_copy(
    tmp_path: Path, stored: int, written: int
) -> None:
    stack = load_stack(png_stack(tmp_path / "in", stored, n=4))
    a = save_stack(stack, tmp_path / "int", bit_depth=written)
    b = save_stack(as_float32(stack), tmp_path / "float", bit_depth=written)
    for name in stack.filenames:
        img = read_image(a / name)
        assert img.dtype == (np.uint16 if written == 16 else np.uint8)
        np.testing.assert_array_equal(img, read_image(b / name))
    if stored == 16 and written == 8:
        assert read_image(a / stack.filenames[0]).max() == 255  # clipped, not rescaled


def test_per_file_writers_are_what_save_stack_writes(tmp_path: Path) -> None:
    stack = load_stack(png_stack(tmp_path / "in", 16, n=4))
    assert stack.normals_gt is not None
    whole = save_stack(stack, tmp_path / "whole")
    parts = tmp_path / "parts"
    for name, img in zip(stack.filenames, stack.images, strict=True):
        write_image(parts / name, img)
    write_filenames(parts, stack.filenames)
    write_lights(parts, stack.lights)
    write_intensities(parts, stack.intensities)
    write_mask(parts, stack.mask)
    write_normals(parts, stack.normals_gt)
    files = sorted(p.name for p in whole.iterdir())
    assert files == sorted(p.name for p in parts.iterdir())
    assert {FILENAMES_FILE, LIGHTS_FILE, INTENSITIES_FILE, MASK_FILE, NORMALS_FILE} <= set(files)
    for name in files:
        if name != NORMALS_FILE:  # a .mat file records when it was written
            assert (whole / name).read_bytes() == (parts / name).read_bytes(), name
    np.testing.assert_array_equal(
        read_normals(parts / NORMALS_FILE), read_normals(whole / NORMALS_FILE)
    )
    a, b = load_stack(whole), load_stack(parts)
    for field in ("images", "lights", "intensities", "mask", "normals_gt"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert not list(parts.glob(".*"))  # every file went through a temporary and a rename
