"""--max-memory on every path: least squares works in row bands within it (it used to ignore
it), loaders refuse a stack that alone exceeds it before decoding, messages quote the user's
value."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from _runtime_helpers import sphere_stack, write_npz_bomb

from msfnet.common.errors import InputError
from msfnet.common.vocabulary import speaking_as
from msfnet.runtime.infer.least_squares import least_squares_normals, rows_for_memory
from msfnet.runtime.stack import LoadOptions, load_stack, save_stack


def _peak_mb(fn) -> tuple[np.ndarray, float]:
    tracemalloc.start()
    try:
        result = fn()
        return result, tracemalloc.get_traced_memory()[1] / 2**20
    finally:
        tracemalloc.stop()


@pytest.mark.parametrize("budget_mb", [2.5, 3.5, 4.5])
def test_least_squares_stays_within_the_budget(budget_mb: float) -> None:
    """Peak memory beside the loaded stack stays within --max-memory minus the stack (numpy
    reports its buffers to tracemalloc; nothing else held: in_use_mb=0), and the normals equal
    the unbanded ones. The whole process is measured in tests/hostile/test_memory.py."""
    stack = sphere_stack(n=24, h=120, w=160)
    stack_mb = stack.images.nbytes / 2**20  # 5.3 MB
    free, unbounded_peak = _peak_mb(lambda: least_squares_normals(stack))
    banded, peak = _peak_mb(
        lambda: least_squares_normals(stack, max_memory_mb=stack_mb + budget_mb, in_use_mb=0)
    )
    out_mb = banded.nbytes / 2**20
    assert peak <= budget_mb + out_mb, (peak, budget_mb)
    assert unbounded_peak > budget_mb + out_mb  # without a budget it would not fit: can fail
    np.testing.assert_allclose(banded, free, atol=1e-6)


@pytest.mark.parametrize("value", [0.001, 1.0, 5.0])
def test_least_squares_refuses_a_budget_below_the_stack(value: float) -> None:
    stack = sphere_stack(n=24, h=120, w=160)
    with (
        speaking_as("msf-run"),
        pytest.raises(
            InputError, match=rf"^--max-memory {value:g} MB is too small for least squares"
        ),
    ):
        rows_for_memory(value, stack, in_use_mb=0)
    with pytest.raises(InputError, match=rf"^max_memory_mb={value:g} MB is too small"):
        rows_for_memory(value, stack, in_use_mb=0)  # from Python: the keyword


@pytest.mark.parametrize("value", [float("nan"), float("inf"), 0.0, -1.0])
def test_least_squares_refuses_nonsense_budgets(value: float) -> None:
    with pytest.raises(InputError, match=r"^max_memory_mb must be a positive number of MB"):
        least_squares_normals(sphere_stack(), max_memory_mb=value)


def test_folder_loader_refuses_before_decoding(tmp_path: Path, monkeypatch) -> None:
    folder = save_stack(sphere_stack(n=8, h=120, w=160), tmp_path / "s")  # 0.88 MB as uint16
    import msfnet.runtime.stack.load as load

    decoded: list[Path] = []
    real = load.read_image
    monkeypatch.setattr(load, "read_image", lambda p, *a: decoded.append(p) or real(p, *a))
    with pytest.raises(InputError, match=r"8 images of 160x120 take 0.88 MB.*max_memory_mb=0.5 MB"):
        load_stack(folder, LoadOptions(max_memory_mb=0.5))
    assert decoded == []  # refused from the headers alone
    assert load_stack(folder, LoadOptions(max_memory_mb=0.5, select="1-3")).num_lights == 3


def test_npz_bomb_is_refused_from_the_header(tmp_path: Path) -> None:
    """A few KB of zip that would inflate to 2 GB is refused without inflating it."""
    # the header claims 1.5 GB; only 4 MB of zeros follow
    path = write_npz_bomb(tmp_path / "bomb.npz", "<f4", (32, 2048, 2048, 3), zeros_mb=4)
    assert path.stat().st_size < 200_000
    with pytest.raises(InputError, match="take 1536 MB loaded"):
        load_stack(path, LoadOptions(max_memory_mb=1024))


def test_msf_run_passes_its_budget_to_the_loader(tmp_path: Path, monkeypatch, capfd) -> None:
    from msfnet.runtime.cli.run import main

    folder = save_stack(sphere_stack(n=8, h=120, w=160), tmp_path / "s")
    import msfnet.runtime.stack.load as load

    decoded: list[Path] = []
    real = load.read_image
    monkeypatch.setattr(load, "read_image", lambda p, *a: decoded.append(p) or real(p, *a))
    assert (
        main(["--method", "l2", str(folder), "-o", str(tmp_path / "o"), "--max-memory", "0.5"]) == 2
    )  # the 16-bit stack takes 0.88 MB
    assert decoded == [], "an image was decoded before the budget was checked"
