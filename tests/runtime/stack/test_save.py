"""save_stack writes an integer stack as the float32 copy of it would be written."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _runtime_helpers import as_float32, png_stack

from msfnet.runtime.imageio import read_image
from msfnet.runtime.stack import load_stack, save_stack


@pytest.mark.parametrize(("stored", "written"), [(16, 16), (16, 8), (8, 16), (8, 8)])
def test_integer_stack_saves_like_its_float32_copy(tmp_path: Path, stored: int,
                                                   written: int) -> None:
    stack = load_stack(png_stack(tmp_path / "in", stored, n=4))
    a = save_stack(stack, tmp_path / "int", bit_depth=written)
    b = save_stack(as_float32(stack), tmp_path / "float", bit_depth=written)
    for name in stack.filenames:
        img = read_image(a / name)
        assert img.dtype == (np.uint16 if written == 16 else np.uint8)
        np.testing.assert_array_equal(img, read_image(b / name))
    if stored == 16 and written == 8:
        assert read_image(a / stack.filenames[0]).max() == 255  # clipped, not rescaled
