"""Light and intensity files as editors write them."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from msfnet.common.errors import InputError
from msfnet.runtime.stack.readers import MAX_LIGHTS, MAX_VECTOR_FILE_BYTES, read_vectors

ROWS = [[-0.0629, 0.1, 0.99], [0.2, -0.3, 0.93], [0.0, 0.5, 0.86]]


@pytest.mark.parametrize("suffix", [".txt", ".json"])
def test_a_utf8_byte_order_mark_is_read(tmp_path: Path, suffix: str) -> None:
    """Windows Notepad's "UTF-8" starts the file with a BOM; it was refused as
    "could not convert string to float: '\\ufeff-0.0629'"."""
    text = (
        "\n".join(" ".join(map(str, r)) for r in ROWS) + "\r\n" if suffix == ".txt" else str(ROWS)
    )
    path = tmp_path / f"light_directions{suffix}"
    path.write_bytes(b"\xef\xbb\xbf" + text.encode())
    np.testing.assert_allclose(read_vectors(path, "light directions"), ROWS, rtol=1e-6)


# ---------------------------------------------------------------------------- JSON names


@pytest.mark.parametrize("key", ["light_directions", "directions", "lights"])
def test_a_json_object_names_its_rows(tmp_path: Path, key: str) -> None:
    path = tmp_path / "l.json"
    path.write_text(json.dumps({key: ROWS}))
    np.testing.assert_allclose(read_vectors(path, "light directions"), ROWS, rtol=1e-6)


def test_a_json_file_with_both_kinds_gives_each_its_own(tmp_path: Path) -> None:
    path = tmp_path / "rig.json"
    ints = [[1.0, 0.9, 0.8], [1.1, 1.0, 0.9], [0.9, 1.0, 1.2]]
    path.write_text(json.dumps({"light_intensities": ints, "light_directions": ROWS}))
    np.testing.assert_allclose(read_vectors(path, "light directions"), ROWS, rtol=1e-6)
    np.testing.assert_allclose(read_vectors(path, "light intensities"), ints, rtol=1e-6)


@pytest.mark.parametrize(
    ("content", "words"),
    [
        # the first list was read whatever its key: positions in mm taken for directions
        ({"positions_mm": [[10, 20, 300]] * 3, "light_directions": ROWS}, "'positions_mm'"),
        ({"positions_mm": [[10, 20, 300]] * 3}, "'positions_mm'"),
        ({"light_intensities": ROWS}, "no 'light_directions'"),
        ({"lights": ROWS, "directions": ROWS}, "both"),
        ([["0.5", "0", "1"]] * 3, "not a number"),  # text, not numbers
        ([[True, 0, 1]] * 3, "not a number"),
        ({"lights": "0 0 1"}, "expected a JSON list"),
    ],
)
def test_json_light_files_are_read_by_name_only(
    tmp_path: Path, content: object, words: str
) -> None:
    path = tmp_path / "l.json"
    path.write_text(json.dumps(content))
    with pytest.raises(InputError, match=re.escape(words)):
        read_vectors(path, "light directions")


# ---------------------------------------------------------------------------- numbers, size


@pytest.mark.parametrize("token", ["0_5", "1_000", "٣", "0x1p3", "1.5.2", "--1"])
def test_only_plain_numbers_are_numbers(tmp_path: Path, token: str) -> None:
    """float() reads "0_5" as 5.0 and Arabic-Indic digits as digits: a light file means
    neither."""
    path = tmp_path / "l.txt"
    path.write_text(f"0 0 1\n{token} 0 1\n0.1 0.2 0.9\n", encoding="utf-8")
    with pytest.raises(InputError, match=f"'{token}' is not a number"):
        read_vectors(path, "light directions")


@pytest.mark.parametrize("token", ["1", "-0.5", "+.5", "5.", "1e-3", "-2.5E+02"])
def test_plain_numbers_are_read(tmp_path: Path, token: str) -> None:
    path = tmp_path / "l.txt"
    path.write_text(f"{token} 0 1\n0 {token} 1\n")
    assert read_vectors(path, "light directions")[1, 1] == pytest.approx(float(token))


@pytest.mark.parametrize("suffix", [".txt", ".json"])
def test_more_lights_than_any_rig_are_refused_before_parsing(tmp_path: Path, suffix: str) -> None:
    rows = [[0.0, 0.0, 1.0]] * (MAX_LIGHTS + 1)
    path = tmp_path / f"l{suffix}"
    path.write_text(json.dumps(rows) if suffix == ".json" else "0 0 1\n" * len(rows))
    with pytest.raises(InputError, match=f"{MAX_LIGHTS + 1:,} rows"):
        read_vectors(path, "light directions")
    path.write_text(json.dumps(rows[:MAX_LIGHTS]) if suffix == ".json" else "0 0 1\n" * MAX_LIGHTS)
    assert read_vectors(path, "light directions").shape == (MAX_LIGHTS, 3)


def test_a_huge_file_is_refused_by_its_size(tmp_path: Path) -> None:
    """A 57 MB, 1.7-million-row file was parsed for minutes: its size alone refuses it."""
    path = tmp_path / "l.txt"
    with open(path, "wb") as f:
        f.truncate(MAX_VECTOR_FILE_BYTES + 1)  # sparse: no time spent writing it
    with pytest.raises(InputError, match="MB"):
        read_vectors(path, "light directions")
