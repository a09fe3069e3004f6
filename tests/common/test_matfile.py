"""MATLAB v5 files read without SciPy: the same arrays as scipy.io.loadmat, or None to fall back
to it; damaged files refused in one line, never a crash or a huge allocation."""

from __future__ import annotations

import struct
import subprocess
import sys
import tracemalloc
import zlib
from pathlib import Path

import numpy as np
import pytest

from msfnet.common.errors import InputError
from msfnet.common.matfile import MAX_VALUES, mat_directory

sio = pytest.importorskip("scipy.io")


def mat_shapes(path: Path) -> dict[str, tuple[int, ...]] | None:
    """Every variable's name and dimensions (None: not a level-5 file)."""
    directory = mat_directory(path)
    return None if directory is None else directory.shapes


def mat_array(path: Path, name: str) -> np.ndarray | None:
    """Variable ``name``'s values as MatDirectory.array reads them (None: not level 5)."""
    directory = mat_directory(path)
    return None if directory is None else directory.array(name)


# Element types and classes of the format, for the hand-built files
MI = {"i1": 1, "u1": 2, "i2": 3, "u2": 4, "i4": 5, "u4": 6, "f4": 7, "f8": 9, "i8": 12, "u8": 13}
CLASS = {"f8": 6, "f4": 7, "i1": 8, "u1": 9, "i2": 10, "u2": 11, "i4": 12, "u4": 13}


def _element(kind: int, payload: bytes, order: str, small: bool = True) -> bytes:
    """A tagged element; payloads of at most 4 bytes in the small format (as MATLAB writes)."""
    if small and len(payload) <= 4:
        return struct.pack(order + "I", len(payload) << 16 | kind) + payload.ljust(4, b"\0")
    return struct.pack(order + "II", kind, len(payload)) + payload + bytes(-len(payload) % 8)


def _matrix(
    name: str,
    values: np.ndarray,
    order: str,
    cls: str | None = None,
    stored: str | None = None,
    flags: int = 0,
    small: bool = True,
) -> bytes:
    """A miMATRIX element: ``values`` of class ``cls`` stored as ``stored`` (default: the
    array's own type), column-major."""
    cls = cls or values.dtype.str[1:]
    stored = stored or cls
    data = np.asarray(values).ravel(order="F").astype(order + stored).tobytes()
    body = (
        _element(6, struct.pack(order + "II", CLASS[cls] | flags, 0), order)
        + _element(5, struct.pack(order + f"{values.ndim}i", *values.shape), order)
        + _element(1, name.encode(), order)
        + _element(MI[stored], data, order, small)
    )
    return struct.pack(order + "II", 14, len(body)) + body


def _compressed(matrix: bytes, order: str) -> bytes:
    packed = zlib.compress(matrix)
    return struct.pack(order + "II", 15, len(packed)) + packed


def _v5_file(path: Path, elements: list[bytes], order: str) -> Path:
    mark = struct.pack(order + "H", ord("M") << 8 | ord("I"))  # reads "IM" in a little-endian file
    header = b"MATLAB 5.0 MAT-file, hand-built by msfnet's tests".ljust(116) + bytes(8)
    path.write_bytes(header + struct.pack(order + "H", 0x0100) + mark + b"".join(elements))
    return path


def _values(dtype: str, shape: tuple[int, ...], seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if dtype.startswith("f"):
        return rng.normal(size=shape).astype(dtype)
    info = np.iinfo(dtype)
    return rng.integers(info.min, info.max, size=shape, endpoint=True, dtype=dtype)


def _same(got: np.ndarray | None, want: np.ndarray) -> None:
    assert got is not None
    assert got.shape == want.shape
    assert got.dtype == want.dtype.newbyteorder("=")
    np.testing.assert_array_equal(got, want)


# ---------------------------------------------------------------- the same arrays as loadmat


@pytest.mark.parametrize("compress", [False, True])
@pytest.mark.parametrize("shape", [(5, 7), (4, 6, 3)])
@pytest.mark.parametrize("dtype", ["f8", "f4", "i2", "u1"])
def test_arrays_written_by_savemat_read_as_loadmat_reads_them(
    tmp_path: Path, dtype: str, shape: tuple[int, ...], compress: bool
) -> None:
    arr = _values(dtype, shape)
    path = tmp_path / "a.mat"
    sio.savemat(path, {"first": np.arange(3.0), "x": arr}, do_compression=compress)
    got = mat_array(path, "x")
    _same(got, sio.loadmat(path)["x"])
    _same(got, arr)  # and the array that was saved, C order as numpy users index it
    assert got is not None and got.flags.writeable


@pytest.mark.parametrize("compress", [False, True])
@pytest.mark.parametrize("order", ["<", ">"])
def test_both_byte_orders_small_elements_and_narrow_storage(
    tmp_path: Path, order: str, compress: bool
) -> None:
    """savemat writes the machine's order only: both are built by hand. MATLAB keeps a double
    array of small integers as miUINT8; it reads as double, as loadmat(mat_dtype=True) gives."""
    wide = _values("f8", (3, 4, 2), seed=1)
    bytes_in_double = np.arange(12, dtype=np.float64).reshape(3, 4) * 20
    pair = np.array([[-3, 7]], dtype=np.int16)  # 4 bytes: a small element
    one = np.array([[200]], dtype=np.uint8)  # 1 byte: a small element
    matrices = [
        _matrix("wide", wide, order),
        _matrix("u8dbl", bytes_in_double, order, cls="f8", stored="u1"),
        _matrix("i16i32", pair.astype(np.int32), order, cls="i4", stored="i2"),
        _matrix("pair", pair, order),
        _matrix("one", one, order),
    ]
    elements = [_compressed(m, order) if compress else m for m in matrices]
    path = _v5_file(tmp_path / f"o{compress}.mat", elements, order)
    typed = sio.loadmat(path, mat_dtype=True)
    plain = sio.loadmat(path)
    for name in ("wide", "u8dbl", "i16i32", "pair", "one"):
        got = mat_array(path, name)
        _same(got, typed[name])
        np.testing.assert_array_equal(got, plain[name])  # values as loadmat's default, too
    _same(mat_array(path, "u8dbl"), bytes_in_double)
    assert mat_shapes(path) == {
        "wide": (3, 4, 2),
        "u8dbl": (3, 4),
        "i16i32": (1, 2),
        "pair": (1, 2),
        "one": (1, 1),
    }


def test_the_named_variable_of_several(tmp_path: Path) -> None:
    a, b = _values("f8", (2, 3), seed=2), _values("f4", (6, 1), seed=3)
    path = tmp_path / "m.mat"
    sio.savemat(path, {"a": a, "Normal_gt": b, "c": np.zeros((0, 3))}, do_compression=True)
    _same(mat_array(path, "Normal_gt"), b)
    _same(mat_array(path, "a"), a)
    _same(mat_array(path, "c"), sio.loadmat(path)["c"])  # empty, of shape (0, 3)
    assert mat_array(path, "absent") is None
    # a name written twice: the last one counts, as in loadmat's dict
    twice = _v5_file(tmp_path / "twice.mat", [_matrix("n", a, "<"), _matrix("n", a * 2, "<")], "<")
    with pytest.warns(UserWarning, match="Duplicate variable name"):
        last = sio.loadmat(twice)["n"]
    _same(mat_array(twice, "n"), last)
    np.testing.assert_array_equal(mat_array(twice, "n"), a * 2)


def test_what_it_does_not_read_is_left_to_loadmat(tmp_path: Path) -> None:
    sparse = pytest.importorskip("scipy.sparse")
    path = tmp_path / "other.mat"
    variables = {
        "sparse": sparse.csc_matrix(np.eye(3)),
        "complex": np.array([[1 + 2j, 3 - 1j]]),
        "cell": np.array([np.zeros(2), "text"], dtype=object),
        "text": "some characters",
        "logical": np.array([[True, False]]),
        "record": {"field": np.arange(2.0)},
        "fine": np.arange(4.0).reshape(2, 2),
    }
    for compress in (False, True):
        sio.savemat(path, variables, do_compression=compress)
        for name in variables:
            if name != "fine":
                assert mat_array(path, name) is None, name
        _same(mat_array(path, "fine"), variables["fine"])
    sio.savemat(path, {"fine": variables["fine"]}, format="4")  # level 4: no v5 header
    assert mat_array(path, "fine") is None
    (tmp_path / "h5.mat").write_bytes(b"MATLAB 7.3 MAT-file".ljust(512, b"\0"))
    assert mat_array(tmp_path / "h5.mat", "fine") is None


# ---------------------------------------------------------------- damaged and hostile files


@pytest.mark.parametrize("compress", [False, True])
def test_a_cut_file_is_refused_in_one_line(tmp_path: Path, compress: bool) -> None:
    arr = _values("f8", (20, 30), seed=4)
    whole = tmp_path / "whole.mat"
    sio.savemat(whole, {"x": arr}, do_compression=compress)
    data = whole.read_bytes()
    cut = tmp_path / "cut.mat"
    refused = 0
    for end in range(128, len(data) - 1, 37):
        cut.write_bytes(data[:end])
        try:
            got = mat_array(cut, "x")
        except InputError as exc:
            assert "cut.mat" in str(exc) and "\n" not in str(exc)
            refused += 1
            continue
        assert got is None, end  # no variable left at all: loadmat's to refuse
    assert refused >= (len(data) - 128 - 40) // 37  # every cut past the first tag


@pytest.mark.parametrize("compress", [False, True])
def test_numbers_stored_as_no_number_type_are_damage_not_loadmats(
    tmp_path: Path, compress: bool
) -> None:
    """A numeric variable whose values' tag names no number type (0, a reserved type, a
    matrix) is a damaged file: handed to loadmat such files crashed the process (SciPy 1.x
    segfaults in read_var_array on several of them, found by flipping bytes), so it is
    refused in one line instead of left to loadmat."""
    arr = _values("u1", (4, 7), seed=3)
    path = tmp_path / "flipped.mat"
    whole = tmp_path / "whole.mat"
    sio.savemat(whole, {"Normal_gt": arr}, do_compression=False)
    data = bytearray(whole.read_bytes())
    at = data.index(b"Normal_gt") + 16  # name padded to 16 bytes, then the values' tag
    assert struct.unpack("<I", data[at : at + 4])[0] == 2  # miUINT8
    for kind in (0, 8, 10, 11, 14, 514):
        data[at : at + 4] = struct.pack("<I", kind)
        element = bytes(data[128:])
        if compress:
            element = _compressed(element, "<")
        path.write_bytes(bytes(data[:128]) + element)
        with pytest.raises(InputError, match=r"damaged \.mat file") as info:
            mat_array(path, "Normal_gt")
        assert "\n" not in str(info.value), kind


def test_damaged_compressed_bytes_are_caught_by_the_checksum(tmp_path: Path) -> None:
    arr = _values("f8", (16, 16), seed=5)
    whole = tmp_path / "whole.mat"
    sio.savemat(whole, {"x": arr}, do_compression=True)
    data = bytearray(whole.read_bytes())
    bad = tmp_path / "bad.mat"
    outcomes = {"refused": 0, "unchanged": 0}
    for pos in range(140, len(data), 23):  # inside the zlib stream
        flipped = data.copy()
        flipped[pos] ^= 0x10
        bad.write_bytes(flipped)
        try:
            got = mat_array(bad, "x")
        except InputError:
            outcomes["refused"] += 1
            continue
        # a flip in bits the decoder never uses changes nothing; a silently wrong array never
        assert got is not None
        np.testing.assert_array_equal(got, arr)
        outcomes["unchanged"] += 1
    assert outcomes["refused"] > outcomes["unchanged"]


def test_sizes_are_never_trusted(tmp_path: Path) -> None:
    small = np.arange(6.0).reshape(2, 3)
    matrix = _matrix("x", small, "<")
    dims_at = matrix.index(struct.pack("<2i", 2, 3))

    # dimensions whose product is far beyond any normal map (and beyond int64)
    huge = matrix[:dims_at] + struct.pack("<2i", 2**31 - 1, 2**31 - 1) + matrix[dims_at + 8 :]
    path = _v5_file(tmp_path / "huge.mat", [_compressed(huge, "<")], "<")
    with pytest.raises(InputError, match=rf"huge\.mat: .*more than {MAX_VALUES:,} values"):
        mat_array(path, "x")

    negative = matrix[:dims_at] + struct.pack("<2i", -2, -3) + matrix[dims_at + 8 :]
    path = _v5_file(tmp_path / "neg.mat", [negative], "<")
    with pytest.raises(InputError, match=r"neg\.mat: damaged \.mat file .*negative dimension"):
        mat_array(path, "x")

    # dimensions that do not match the bytes of values
    wrong = matrix[:dims_at] + struct.pack("<2i", 4, 3) + matrix[dims_at + 8 :]
    for name, element in (("plain", wrong), ("packed", _compressed(wrong, "<"))):
        path = _v5_file(tmp_path / f"{name}.mat", [element], "<")
        with pytest.raises(InputError, match=rf"{name}\.mat: damaged \.mat file .*bytes of values"):
            mat_array(path, "x")

    # a compressed element declaring more bytes than the file has
    packed = bytearray(_compressed(matrix, "<"))
    packed[4:8] = struct.pack("<I", 10**9)
    path = _v5_file(tmp_path / "long.mat", [bytes(packed)], "<")
    with pytest.raises(InputError, match=r"long\.mat: damaged \.mat file .*past the file's end"):
        mat_array(path, "x")


def test_a_decompression_bomb_is_never_inflated(tmp_path: Path) -> None:
    """64 MB of zeros after a 2x3 array, in one compressed element of ~64 KB: the reader
    inflates the header and the values and stops."""
    matrix = _matrix("x", np.arange(6.0).reshape(2, 3), "<")
    deflate = zlib.compressobj()
    packed = deflate.compress(matrix)
    zeros = bytes(2**20)
    packed += b"".join(deflate.compress(zeros) for _ in range(64)) + deflate.flush()
    path = _v5_file(tmp_path / "bomb.mat", [struct.pack("<II", 15, len(packed)) + packed], "<")
    tracemalloc.start()
    try:
        got = mat_array(path, "x")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert got is None  # not a plain numeric array after all: loadmat's to judge
    assert peak < 8 * 2**20, f"{peak / 2**20:.1f} MB"


# ---------------------------------------------------------------- the real ground truth


@pytest.mark.parametrize("name", ["ballPNG", "bearPNG", "harvestPNG"])
def test_diligent_ground_truth_is_what_loadmat_reads(ball_dir: Path, name: str) -> None:
    path = ball_dir.parent / name / "Normal_gt.mat"
    if not path.is_file():
        pytest.skip(f"{path} not found")
    want = sio.loadmat(path)["Normal_gt"]
    got = mat_array(path, "Normal_gt")
    _same(got, want)
    assert got is not None and got.shape == (512, 612, 3)
    from msfnet.runtime.stack.readers import read_normals, unit_normals

    # read_normals gives what it gave when SciPy read every file
    assert np.array_equal(read_normals(path), unit_normals(np.asarray(want, dtype=np.float32)))


def test_read_normals_does_not_import_scipy_io(tmp_path: Path) -> None:
    from msfnet.runtime.stack.readers import read_normals, unit_normals

    normals = _values("f8", (6, 5, 3), seed=6)
    path = tmp_path / "gt.mat"
    sio.savemat(path, {"other": np.ones((2, 2)), "Normal_gt": normals}, do_compression=True)
    code = (
        "import sys; from pathlib import Path; import numpy as np\n"
        "from msfnet.runtime.stack.readers import read_normals\n"
        f"n = read_normals(Path({str(path)!r}))\n"
        "assert 'scipy.io' not in sys.modules, 'scipy.io was imported'\n"
        "sys.stdout.buffer.write(n.tobytes())\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, check=False)
    assert done.returncode == 0, done.stderr.decode()
    got = np.frombuffer(done.stdout, np.float32).reshape(6, 5, 3)
    np.testing.assert_array_equal(got, unit_normals(normals.astype(np.float32)))
    np.testing.assert_array_equal(read_normals(path), got)


def test_read_normals_falls_back_to_loadmat(tmp_path: Path) -> None:
    """A first variable of a class mat_array leaves alone: read by SciPy as before, with the
    same key choice (Normal_gt, else the first variable)."""
    from msfnet.runtime.stack.readers import read_normals, unit_normals

    normals = _values("f8", (4, 3, 3), seed=7)
    logical = tmp_path / "logical.mat"
    sio.savemat(logical, {"mask": normals > 0})  # loadmat: uint8 0/1
    want = unit_normals((normals > 0).astype(np.float32))
    np.testing.assert_array_equal(read_normals(logical), want)


def _v73_head() -> bytes:
    return b"MATLAB 7.3 MAT-file".ljust(124, b" ") + struct.pack("<H", 0x0200) + b"IM"


@pytest.mark.parametrize(
    ("make", "what"),
    [
        ("v4", "a MATLAB v4 file"),
        ("v4 big-endian", "a MATLAB v4 file"),
        ("v4 truncated", "a MATLAB v4 file"),
        ("v7.3", r"a MATLAB v7.3 file \(HDF5\)"),
        ("garbage", "a file of another format"),
        ("empty", "an empty file"),
    ],
)
def test_a_mat_file_that_is_not_level_5_never_reaches_loadmat(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, make: str, what: str
) -> None:
    """Level 4 has no header to check before loadmat parses it (a damaged or hostile v4 file
    is what can make loadmat misbehave) and holds only 2-D matrices, never an H x W x 3 map:
    refused from its first bytes in one line, as v7.3 (HDF5) and anything else is."""
    from msfnet.runtime.stack.readers import read_normals

    path = tmp_path / "Normal_gt.mat"
    sio.savemat(path, {"Normal_gt": _values("f8", (4, 9), seed=7)}, format="4")
    data = path.read_bytes()
    if make == "v4 big-endian":  # MOPT 1000: IEEE big-endian, double, full matrix
        data = struct.pack(">5i", 1000, 4, 9, 0, 10) + b"Normal_gt\0" + b"\0" * 288
    elif make == "v4 truncated":
        data = data[:40]
    elif make == "v7.3":
        data = _v73_head() + b"\x89HDF\r\n\x1a\n" + b"\0" * 64
    elif make == "garbage":
        data = b"\xff" * 300
    elif make == "empty":
        data = b""
    path.write_bytes(data)

    def no_loadmat(*_args: object, **_kwargs: object) -> None:
        raise AssertionError("loadmat was called")

    monkeypatch.setattr(sio, "loadmat", no_loadmat)
    with pytest.raises(InputError, match=f"{what}, not a MATLAB v5 .mat file") as info:
        read_normals(path)
    assert "\n" not in str(info.value) and str(info.value).startswith(str(path))
    # says once what the file is not (a review found "not a MATLAB .mat file, not a MATLAB v5")
    assert str(info.value).count("not a") == 1 and str(info.value).count("MATLAB v5") == 1


def test_not_v5_names_what_a_file_is() -> None:
    from msfnet.common.matfile import not_v5

    assert not_v5(struct.pack("<5i", 0, 2, 3, 0, 2) + b"a\0") == "a MATLAB v4 file"
    assert not_v5(struct.pack("<5i", 51, 1, 3, 0, 2) + b"a\0") == "a MATLAB v4 file"  # text
    assert not_v5(_v73_head()) == "a MATLAB v7.3 file (HDF5)"
    head = _v73_head()[:124] + struct.pack("<H", 0x0300) + b"IM"
    assert not_v5(head) == "a .mat file of unknown version 0x0300"
    assert not_v5(b"\x89PNG\r\n\x1a\n" + b"\0" * 40) == "a file of another format"
    assert not_v5(b"\0" * 10) == "a file of another format"  # too short for a v4 header
    assert not_v5(b"") == "an empty file"


def test_a_variable_that_cannot_be_normals_never_reaches_loadmat(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The fallback is where a hostile file can still crash the process (loadmat segfaults on
    e.g. a complex flag without its imaginary part): a variable whose dimensions (from the
    headers alone) are not H x W x 3 is refused before it, whatever its class."""
    from msfnet.runtime.stack.readers import read_normals

    def no_loadmat(*_args: object, **_kwargs: object) -> None:
        raise AssertionError("loadmat was called")

    monkeypatch.setattr(sio, "loadmat", no_loadmat)
    path = tmp_path / "complex.mat"
    for value in (np.array([[1 + 2j, 3 - 1j]]), "text", np.ones((4, 5, 2), complex)):
        sio.savemat(path, {"Normal_gt": value})
        with pytest.raises(InputError, match=r"must be H x W x 3, got \("):
            read_normals(path)


def test_more_variables_than_it_lists_is_refused(tmp_path: Path) -> None:
    """Variables past the listing's bound were dropped without a word: a Normal_gt after
    them was not found, and read_normals took the first variable instead."""
    from msfnet.runtime.stack.readers import read_normals

    filler = _matrix("x", np.zeros((1, 1)), "<")
    normals = _matrix("Normal_gt", _values("f8", (2, 2, 3), seed=8), "<")
    first = _matrix("first", np.ones((2, 2, 3)), "<")
    path = _v5_file(tmp_path / "many.mat", [first] + [filler] * 4100 + [normals], "<")
    with pytest.raises(InputError, match="more than 4,096 variables"):
        mat_shapes(path)
    with pytest.raises(InputError, match="more than 4,096 variables"):
        read_normals(path)


# ---------------------------------------------------------------- which variable, parsed once


def test_normals_variable_is_normal_gt_else_the_first_real_variable() -> None:
    from msfnet.common.matfile import normals_variable

    assert normals_variable({"a": (1,), "Normal_gt": (2,)}) == "Normal_gt"
    assert normals_variable({"": (1,), "_x": (1,), "b": (2,), "c": (3,)}) == "b"
    assert normals_variable({"__function_workspace__": (1,), "_x": (2,)}) is None
    assert normals_variable({}) is None


@pytest.mark.parametrize("skipped", ["", "_x"])
def test_header_check_and_read_take_the_same_variable(tmp_path: Path, skipped: str) -> None:
    """An unnamed or "_" first element is no variable to the reader (nor to loadmat): the
    header check took its shape all the same (imageio.array_shape used the first element),
    so it refused a good file or passed a wrong one. Both now look at the second element."""
    from msfnet.common.imageio import array_shape
    from msfnet.runtime.stack.load import check_gt_header
    from msfnet.runtime.stack.readers import read_normals, unit_normals

    decoy = _values("f8", (9, 8, 3), seed=9)
    normals = _values("f8", (4, 5, 3), seed=10)
    for compress in (False, True):
        elements = [_matrix(skipped, decoy, "<"), _matrix("n", normals, "<")]
        if compress:
            elements = [_compressed(e, "<") for e in elements]
        path = _v5_file(tmp_path / f"gt{compress}.mat", elements, "<")
        assert array_shape(path) == (4, 5, 3)
        mat = check_gt_header(path, (4, 5))
        assert mat is not None and mat.normals == "n"
        with pytest.raises(InputError, match="ground truth is 5x4 but images are 8x9"):
            check_gt_header(path, (9, 8))
        want = unit_normals(normals.astype(np.float32))
        np.testing.assert_array_equal(read_normals(path, mat), want)
        np.testing.assert_array_equal(read_normals(path), want)
    # only "_" elements: no variable for the header check, and none for the reader either
    path = _v5_file(tmp_path / "none.mat", [_matrix(skipped, decoy, "<")], "<")
    assert array_shape(path) is None
    with pytest.raises(InputError, match="cannot read ground-truth normals"):
        read_normals(path)


def test_read_normals_parses_the_headers_once(tmp_path: Path, mat_parses: list[Path]) -> None:
    from msfnet.common.matfile import mat_directory
    from msfnet.runtime.stack.readers import read_normals, unit_normals

    normals = _values("f8", (6, 5, 3), seed=11)
    path = tmp_path / "gt.mat"
    sio.savemat(path, {"other": np.ones((2, 2)), "Normal_gt": normals}, do_compression=True)
    want = unit_normals(normals.astype(np.float32))
    mat_parses.clear()  # savemat and the expected values did not parse
    parses = mat_parses
    np.testing.assert_array_equal(read_normals(path), want)
    assert parses == [path]  # was three: the shape check, the listing, the read
    mat = mat_directory(path)
    np.testing.assert_array_equal(read_normals(path, mat), want)
    assert parses == [path, path]  # the given parse is reused
    with pytest.raises(ValueError, match="given to read"):
        read_normals(tmp_path / "other.mat", mat)


def test_a_directory_of_a_changed_file_is_not_trusted(tmp_path: Path) -> None:
    """A file replaced after its headers were parsed is refused at the read: the old offsets
    would point into the new file's data, and a parse made then would skip the checks made on
    the first one."""
    import os

    from msfnet.common.matfile import mat_directory

    path = tmp_path / "gt.mat"
    sio.savemat(path, {"Normal_gt": np.zeros((2, 2, 3))})
    mat = mat_directory(path)
    assert mat is not None
    new = _values("f8", (3, 4, 3), seed=12)
    sio.savemat(tmp_path / "new.mat", {"pad": np.ones((7, 7)), "Normal_gt": new})
    os.replace(tmp_path / "new.mat", path)
    with pytest.raises(InputError, match="changed after its headers were read"):
        mat.array("Normal_gt")
    again = mat_directory(path)  # a new parse reads the new file
    assert again is not None
    _same(again.array("Normal_gt"), new)


def test_a_ground_truth_replaced_after_its_header_check_is_refused(tmp_path: Path) -> None:
    """The header check's parse is what the read trusts (image size, H x W x 3, the total a
    loadmat may read): a file replaced in between is refused, not read unchecked."""
    import os

    from msfnet.runtime.stack.load import check_gt_header
    from msfnet.runtime.stack.readers import read_normals

    path = tmp_path / "Normal_gt.mat"
    sio.savemat(path, {"Normal_gt": _values("f8", (4, 5, 3), seed=13)})
    mat = check_gt_header(path, (4, 5))
    assert mat is not None
    # passes none of the checks: another size, and 2 channels
    sio.savemat(tmp_path / "new.mat", {"Normal_gt": np.ones((300, 200, 2))})
    os.replace(tmp_path / "new.mat", path)
    with pytest.raises(InputError, match="changed after its headers were read"):
        read_normals(path, mat)
    with pytest.raises(InputError, match="changed after its headers were read"):
        mat.array("Normal_gt")


def test_the_loadmat_fallback_reads_the_file_that_was_checked(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A variable the fast reader leaves to SciPy (logical here) is read by loadmat from the
    handle whose file was checked: a replacement by name just before loadmat opens it is not
    what gets read."""
    import os

    import scipy.io

    from msfnet.runtime.stack.load import check_gt_header
    from msfnet.runtime.stack.readers import read_normals

    path = tmp_path / "Normal_gt.mat"
    checked = np.zeros((4, 5, 3), bool)
    checked[..., 2] = True
    sio.savemat(path, {"Normal_gt": checked})
    mat = check_gt_header(path, (4, 5))
    assert mat is not None and mat.array("Normal_gt") is None  # left to loadmat
    real = scipy.io.loadmat

    def swapped_first(source: object, *args: object, **kwargs: object) -> object:
        sio.savemat(tmp_path / "new.mat", {"Normal_gt": -np.ones((4, 5, 3))})
        os.replace(tmp_path / "new.mat", path)
        return real(source, *args, **kwargs)

    monkeypatch.setattr(scipy.io, "loadmat", swapped_first)
    np.testing.assert_array_equal(read_normals(path, mat)[..., 2], np.ones((4, 5), np.float32))
