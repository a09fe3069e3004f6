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
