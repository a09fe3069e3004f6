"""Light and intensity files as editors write them."""

from __future__ import annotations

import json
import os
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


# ---------------------------------------------------------------- ground truth: check, then read


def _normals(h: int, w: int, seed: int) -> np.ndarray:
    n = np.random.default_rng(seed).normal(size=(h, w, 3))
    n[..., 2] = np.abs(n[..., 2]) + 0.1
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _one_line(info: pytest.ExceptionInfo[InputError], path: Path) -> str:
    text = str(info.value)
    assert "\n" not in text and text.startswith(f"{path}: ")
    return text


def _write_normal_png(path: Path, n: np.ndarray) -> None:
    from msfnet.common.imageio import write_png

    write_png(path, np.round((n + 1) / 2 * 65535).astype(np.uint16))


def test_an_npy_replaced_after_its_header_check_is_refused_from_the_read(tmp_path: Path) -> None:
    """check_gt_header looked at one file; read_normals opens the name again. Given the
    shape, the read checks the header of what it reads: a replacement of another size (here
    far bigger) is refused before its values are read."""
    from msfnet.runtime.stack.readers import check_gt_header, read_normals

    path = tmp_path / "Normal_gt.npy"
    np.save(path, _normals(4, 5, seed=1))
    assert check_gt_header(path, (4, 5)) is None
    np.save(tmp_path / "new.npy", np.zeros((400, 500, 3)))
    os.replace(tmp_path / "new.npy", path)
    with pytest.raises(InputError, match="ground truth is 500x400 but images are 5x4") as info:
        read_normals(path, shape=(4, 5))
    _one_line(info, path)


def test_an_npy_is_read_from_the_handle_whose_header_was_checked(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The file replaced by name just after its header was parsed: the values read are the
    checked file's (one handle), not the replacement's."""
    from msfnet.runtime.stack.readers import read_normals, unit_normals

    path = tmp_path / "Normal_gt.npy"
    checked = _normals(4, 5, seed=2)
    np.save(path, checked)
    real = np.lib.format.read_array_header_1_0

    def swap_after(f: object, *args: object, **kwargs: object) -> object:
        header = real(f, *args, **kwargs)  # type: ignore[arg-type]
        np.save(tmp_path / "new.npy", -checked)
        os.replace(tmp_path / "new.npy", path)
        return header

    monkeypatch.setattr(np.lib.format, "read_array_header_1_0", swap_after)
    got = read_normals(path, shape=(4, 5))
    np.testing.assert_allclose(got, unit_normals(checked.astype(np.float32)), atol=1e-6)
    assert np.load(path)[0, 0, 2] < 0  # the swap did happen


@pytest.mark.parametrize(
    ("array", "message"),
    [
        (np.ones((4, 5, 3), complex), r"must be numbers, got a \.npy array of dtype complex128"),
        (np.array([[["a"] * 3] * 5] * 4), r"must be numbers, got a \.npy array of dtype <U1"),
        (np.zeros((4, 5), [("x", "f4"), ("y", "f4")]), "must be numbers"),
        (np.ones((4, 5, 2)), r"must be H x W x 3, got \(4, 5, 2\)"),
        (np.ones((60,)), r"must be H x W x 3, got \(60,\)"),
    ],
)
def test_an_npy_of_the_wrong_kind_is_refused_from_its_header(
    tmp_path: Path, array: np.ndarray, message: str
) -> None:
    from msfnet.runtime.stack.readers import read_normals

    path = tmp_path / "Normal_gt.npy"
    np.save(path, array)
    with pytest.raises(InputError, match=message) as info:
        read_normals(path)
    _one_line(info, path)


def test_an_npy_of_objects_is_never_unpickled(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import pickle

    from msfnet.runtime.stack.readers import read_normals

    path = tmp_path / "Normal_gt.npy"
    np.save(path, np.full((4, 5, 3), 0.5, object), allow_pickle=True)

    def no_unpickling(*_args: object, **_kwargs: object) -> None:
        raise AssertionError("unpickled")

    monkeypatch.setattr(pickle, "load", no_unpickling)
    monkeypatch.setattr(pickle, "loads", no_unpickling)
    with pytest.raises(InputError, match=r"must be numbers, got a \.npy array of dtype object"):
        read_normals(path)


def test_a_truncated_or_damaged_npy_is_refused(tmp_path: Path) -> None:
    from msfnet.runtime.stack.readers import read_normals

    path = tmp_path / "Normal_gt.npy"
    np.save(path, _normals(4, 5, seed=3))
    data = path.read_bytes()
    path.write_bytes(data[:-8])  # one float64 short
    with pytest.raises(InputError, match=r"truncated \.npy file \(472 of the 480 bytes") as info:
        read_normals(path, shape=(4, 5))
    _one_line(info, path)
    path.write_bytes(data[:40])  # cut inside the header
    with pytest.raises(InputError, match=r"damaged \.npy header") as info:
        read_normals(path)
    _one_line(info, path)


@pytest.mark.parametrize("layout", ["big-endian", "fortran", "float16", "int16"])
def test_npy_layouts_read_as_numpy_reads_them(tmp_path: Path, layout: str) -> None:
    from msfnet.runtime.stack.readers import read_normals, unit_normals

    n = _normals(4, 5, seed=4)
    array = {
        "big-endian": n.astype(">f8"),
        "fortran": np.asfortranarray(n),
        "float16": n.astype(np.float16),
        "int16": np.round(n * 1000).astype(np.int16),
    }[layout]
    path = tmp_path / "Normal_gt.npy"
    np.save(path, array)
    want = unit_normals(np.load(path, allow_pickle=False).astype(np.float32))
    np.testing.assert_array_equal(read_normals(path, shape=(4, 5)), want)


def test_a_png_replaced_after_its_header_check_is_refused_before_decoding(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from msfnet.common import imageio
    from msfnet.runtime.stack.readers import check_gt_header, read_normals

    path = tmp_path / "Normal_gt.png"
    _write_normal_png(path, _normals(4, 5, seed=5))
    assert check_gt_header(path, (4, 5)) is None
    _write_normal_png(tmp_path / "new.png", _normals(40, 50, seed=6))
    os.replace(tmp_path / "new.png", path)

    def no_decoding(*_args: object) -> None:
        raise AssertionError("decoded")

    monkeypatch.setattr(imageio, "_decode_with_opencv", no_decoding)
    with pytest.raises(InputError, match="ground truth is 50x40 but images are 5x4") as info:
        read_normals(path, shape=(4, 5))
    _one_line(info, path)


def test_a_png_is_decoded_from_the_handle_whose_header_was_checked(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Replaced by name just after its header was read: what is decoded is the checked file
    (a bomb swapped in there would have skipped the pixel limit)."""
    from msfnet.common import imageio
    from msfnet.runtime.stack.readers import read_normals

    path = tmp_path / "Normal_gt.png"
    checked = _normals(4, 5, seed=7)
    _write_normal_png(path, checked)
    real = imageio._png_header

    def swap_after(head: bytes) -> object:
        header = real(head)
        _write_normal_png(tmp_path / "new.png", _normals(40, 50, seed=8))
        os.replace(tmp_path / "new.png", path)
        return header

    monkeypatch.setattr(imageio, "_png_header", swap_after)
    got = read_normals(path, shape=(4, 5))
    np.testing.assert_allclose(got, checked, atol=1e-4)  # 16-bit quantisation: ~3e-5
    assert imageio.image_header(path) is not None


def test_a_load_whose_ground_truth_changes_after_the_check_fails_in_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Through load_stack: the .npy ground truth swapped between check_gt_header and the read
    for one of another size whose values are still being written (cut short). Refused from
    the header the read parses, before any value is read (reading by name again, as before,
    failed on the short values instead, with numpy's reshape message)."""
    from _runtime_helpers import png_stack

    from msfnet.runtime.stack import load, load_stack

    folder = png_stack(tmp_path / "s", 8, n=4)  # 36 x 44
    (folder / "Normal_gt.mat").unlink()
    gt = folder / "Normal_gt.npy"
    np.save(gt, _normals(36, 44, seed=9))
    real = load.check_gt_header

    def swap_after(path: Path, shape: tuple[int, int]) -> object:
        found = real(path, shape)
        np.save(tmp_path / "new.npy", _normals(72, 88, seed=10))
        partial = (tmp_path / "new.npy").read_bytes()[:4096]
        (tmp_path / "new.npy").write_bytes(partial)
        os.replace(tmp_path / "new.npy", gt)
        return found

    monkeypatch.setattr(load, "check_gt_header", swap_after)
    with pytest.raises(InputError, match="ground truth is 88x72 but images are 44x36") as info:
        load_stack(folder)
    _one_line(info, gt)


def test_an_npy_declaring_a_huge_header_is_refused_from_its_length_field(
    tmp_path: Path,
) -> None:
    """numpy's header reader reads all the bytes the length field declares (up to 4 GB) before
    refusing a header over 10,000 bytes: here a sparse file declaring 190 MB. Refused from the
    field, in one line."""
    import struct

    from msfnet.runtime.stack.readers import read_normals

    path = tmp_path / "Normal_gt.npy"
    with open(path, "wb") as f:
        f.write(b"\x93NUMPY\x02\x00" + struct.pack("<I", 190_000_000))
        f.truncate(200_000_000)
    with pytest.raises(InputError, match=r"damaged \.npy header \(a header of 190,000,000") as e:
        read_normals(path, shape=(4, 5))
    _one_line(e, path)


@pytest.mark.parametrize(
    "dtype",
    [np.float16, np.float32, np.float64, np.longdouble, np.int8, np.int16, np.int32, np.int64],
)
def test_unit_normals_of_any_numeric_input(dtype: type) -> None:
    """Unit length in float32 for every numeric input (an .npz's normals may be float128 or
    ints): non-finite components count as 0, vectors under 1e-6 become 0, all within 1e-7 of
    a float64 reference; the caller's array is left as it was."""
    from msfnet.runtime.stack.readers import unit_normals

    rng = np.random.default_rng(3)
    raw = rng.normal(0.0, 5.0, (6, 7, 3))
    raw[0, 0] = 0.0
    x = raw.astype(dtype)
    if np.issubdtype(dtype, np.floating):
        x[1, 1, 0] = np.nan
        x[1, 2] = [np.inf, 1.0, 0.0]
    before = x.copy()
    got = unit_normals(x)
    assert got.dtype == np.float32 and got.shape == x.shape
    np.testing.assert_array_equal(x, before)
    finite = np.where(np.isfinite(x.astype(np.float64)), x.astype(np.float64), 0.0)
    length = np.linalg.norm(finite, axis=-1, keepdims=True)
    want = np.where(length > 1e-6, finite / np.maximum(length, 1e-6), 0.0)
    np.testing.assert_allclose(got, want, atol=1e-7)
    assert not got[0, 0].any()
    np.testing.assert_allclose(unit_normals([1.0, 2.0, 2.0]), [1 / 3, 2 / 3, 2 / 3], atol=1e-7)


def test_a_first_line_of_one_number_that_is_no_count_is_refused(tmp_path: Path) -> None:
    """ "3.7" above 8 rows was taken for a count line and dropped without a word."""
    path = tmp_path / "l.txt"
    path.write_text("3.7\n" + "0 0 1\n" * 8)
    with pytest.raises(InputError, match="count line must be a whole number"):
        read_vectors(path, "light directions")
    path.write_text("8\n" + "0 0 1\n" * 8)
    assert read_vectors(path, "light directions").shape == (8, 3)
