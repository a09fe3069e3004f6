"""Least squares on integer stacks: the normals of the float32 copy, bit for bit, within the
memory budget."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from _runtime_helpers import as_float32, png_stack

from msfnet.runtime.infer.least_squares import least_squares_normals
from msfnet.runtime.stack import load_stack


@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize(("trim_shadows", "trim_highlights"), [(0.0, 0.0), (0.25, 0.1)])
def test_integer_stack_gives_the_float32_normals(
    tmp_path: Path, bits: int, trim_shadows: float, trim_highlights: float
) -> None:
    held = load_stack(png_stack(tmp_path / "s", bits, n=12, h=60, w=70))
    assert held.images.dtype == (np.uint8 if bits == 8 else np.uint16)
    got = least_squares_normals(held, trim_shadows, trim_highlights)
    want = least_squares_normals(as_float32(held), trim_shadows, trim_highlights)
    np.testing.assert_array_equal(got, want)
    assert np.all(np.linalg.norm(got[held.mask], axis=1) > 0.999)


def test_banded_integer_stack_gives_the_same_normals(tmp_path: Path) -> None:
    held = load_stack(png_stack(tmp_path / "s", 16, n=12, h=60, w=70))
    free = least_squares_normals(as_float32(held))
    budget = held.images.nbytes / 2**20 + 1.0  # a few bands (the output's 0.05 MB aside)
    np.testing.assert_array_equal(
        least_squares_normals(held, max_memory_mb=budget, in_use_mb=0), free
    )


def test_integer_stack_stays_within_the_budget(tmp_path: Path) -> None:
    """The integer gather is cast inside each band: the working set beside the loaded stack
    stays within --max-memory minus the stack, as for float32 stacks."""
    held = load_stack(png_stack(tmp_path / "s", 16, n=24, h=120, w=160))
    stack_mb = held.images.nbytes / 2**20
    for budget_mb in (2.5, 3.5):
        tracemalloc.start()
        try:
            out = least_squares_normals(held, max_memory_mb=stack_mb + budget_mb, in_use_mb=0)
            peak = tracemalloc.get_traced_memory()[1] / 2**20
        finally:
            tracemalloc.stop()
        assert peak <= budget_mb + out.nbytes / 2**20, (peak, budget_mb)


def test_ball_crop_16bit_equals_float32(ball_dir: Path) -> None:
    """DiLiGenT ballPNG (16-bit PNG), a crop around the ball, all 96 lights."""
    held = load_stack(ball_dir, roi=(220, 176, 176, 176))  # the whole ball (mask bbox 142 px)
    assert held.images.dtype == np.uint16 and held.num_lights == 96
    np.testing.assert_array_equal(
        least_squares_normals(held), least_squares_normals(as_float32(held))
    )
