"""Benchmark roots (evaluate/datasets.py): the objects and their selections."""

from __future__ import annotations

from pathlib import Path

import pytest
from _runtime_helpers import png_stack

from msfnet.common.errors import InputError
from msfnet.runtime.evaluate.datasets import find_objects


def test_an_objects_txt_selection_that_does_not_fit_names_the_listing(tmp_path: Path) -> None:
    """It failed as "--select '1-20': index 20 is outside 1..8", a flag never given, and
    msf-run found it only mid-batch."""
    png_stack(tmp_path / "a", 16)
    png_stack(tmp_path / "b", 16)
    (tmp_path / "objects.txt").write_text("a\nb 1-20\n")
    with pytest.raises(InputError) as e:
        find_objects(tmp_path)
    text = str(e.value)
    assert "objects.txt" in text and "object b" in text and "1..8" in text
    assert "--select" not in text
    (tmp_path / "objects.txt").write_text("a\nb 2-7\n")
    assert [o.select for o in find_objects(tmp_path)] == [None, "2-7"]


def test_the_users_selection_overrides_a_listed_one_unchecked(tmp_path: Path) -> None:
    """The up-front check refused a listing that --select overrides (a regression)."""
    from msfnet.runtime.cli.run import main as run_main

    root = tmp_path / "bench"
    png_stack(root / "a", 16)
    (root / "objects.txt").write_text("a 7-9\n")
    assert [o.select for o in find_objects(root, select_given=True)] == ["7-9"]
    out = tmp_path / "out"
    argv = [str(root), "--select", "1-6", "--method", "l2", "--no-maps", "-q", "-o", str(out)]
    assert run_main(argv) == 0


def test_two_different_objects_of_one_name_are_told_apart_from_a_repeat(tmp_path: Path) -> None:
    from msfnet.runtime.evaluate.datasets import BenchObject, check_unique

    a, b = tmp_path / "x" / "obj", tmp_path / "y" / "obj"
    with pytest.raises(InputError, match=r"two objects are named 'obj'.*separate runs"):
        check_unique([BenchObject(a, None), BenchObject(b, None)])
    with pytest.raises(InputError, match="listed twice"):
        check_unique([BenchObject(a, None), BenchObject(a, None)])


def test_objects_are_named_and_known_through_dot_and_links(tmp_path: Path, monkeypatch) -> None:
    from msfnet.runtime.evaluate.datasets import BenchObject, folder_name, known_object

    real = tmp_path / "harvestPNG"
    real.mkdir()
    (tmp_path / "h").symlink_to(real)
    monkeypatch.chdir(real)
    assert folder_name(Path(".")) == "harvestPNG"
    assert folder_name(Path("sub/..")) == "harvestPNG"
    assert known_object(tmp_path / "h") == "harvestPNG"
    assert BenchObject(tmp_path / "h", None).name == "h"
