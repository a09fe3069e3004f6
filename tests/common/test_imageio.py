"""PNG writing (common/imageio.py): one encoder, RGB in, full bit depth, errors naming the file
the user knows."""

from __future__ import annotations

import io
import struct
import zlib
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import tifffile

from msfnet.common import imageio, matfile
from msfnet.common.errors import InputError
from msfnet.common.imageio import encode_png, read_image, write_png

RNG = np.random.default_rng(5)
IMAGES = {
    "rgb8": RNG.integers(0, 256, (9, 13, 3), np.uint8),
    "rgb16": RNG.integers(0, 65536, (9, 13, 3), np.uint16),
    "grey16": RNG.integers(0, 65536, (9, 13), np.uint16),
    "strided view": RNG.integers(0, 256, (9, 26, 3), np.uint8)[:, ::2],
}


@pytest.mark.parametrize("name", sorted(IMAGES))
def test_encode_png_writes_rgb_at_full_bit_depth(name: str, tmp_path: Path) -> None:
    img = IMAGES[name]
    path = tmp_path / "a.png"
    encode_png(path, img)
    np.testing.assert_array_equal(read_image(path), img)
    stored = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)  # files hold BGR, as PNG readers expect
    np.testing.assert_array_equal(stored[:, :, ::-1] if img.ndim == 3 else stored, img)
    assert stored.dtype == img.dtype


@pytest.mark.parametrize("name", sorted(IMAGES))
def test_write_png_writes_the_encoders_bytes(name: str, tmp_path: Path) -> None:
    encode_png(tmp_path / "a.png", IMAGES[name])
    write_png(tmp_path / "b.png", IMAGES[name])
    assert (tmp_path / "a.png").read_bytes() == (tmp_path / "b.png").read_bytes()


def test_a_failed_encode_names_the_final_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Staging names mean nothing to the user: the error names ``name``, and write_png (atomic)
    leaves nothing behind."""
    monkeypatch.setattr(imageio.cv2, "imencode", lambda *a, **k: (False, None))
    with pytest.raises(InputError, match="cannot write image") as exc:
        encode_png(tmp_path / "staging.png", IMAGES["rgb8"], name=tmp_path / "final.png")
    assert exc.value.path == tmp_path / "final.png"
    with pytest.raises(InputError) as exc:
        write_png(tmp_path / "out.png", IMAGES["rgb8"])
    assert exc.value.path == tmp_path / "out.png"
    assert not list(tmp_path.iterdir())


# -- damaged input files: one error naming the file, nothing from the decoders on stderr


def test_a_png_with_damaged_bytes_is_refused_before_decoding(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "005.png"
    write_png(path, RNG.integers(0, 65536, (40, 50, 3), np.uint16))
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one flipped byte inside the image data
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"005\.png: corrupt PNG \(chunk 'IDAT'"):
        read_image(path)
    assert capfd.readouterr().err == ""


def test_a_jpeg_with_damaged_data_is_refused(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    ok, jpeg = cv2.imencode(".jpg", RNG.integers(0, 256, (32, 32, 3), np.uint8))
    assert ok
    data = jpeg.tobytes()
    path = tmp_path / "005.jpg"
    path.write_bytes(data[: len(data) // 2] + b"\xff\xd9")  # half the image data lost
    with pytest.raises(InputError, match=r"005\.jpg: corrupt JPEG \(Corrupt JPEG data"):
        read_image(path)
    assert capfd.readouterr().err == ""
    path.write_bytes(data)  # the intact file reads, and stderr works again afterwards
    assert read_image(path).shape == (32, 32, 3)


def test_padding_before_a_jpeg_end_marker_is_no_damage(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """Webcam frames often carry a few bytes before the end marker: every pixel decodes."""
    img = RNG.integers(0, 256, (32, 32, 3), np.uint8)
    ok, jpeg = cv2.imencode(".jpg", img)
    assert ok
    data = jpeg.tobytes()
    (tmp_path / "a.jpg").write_bytes(data)
    (tmp_path / "b.jpg").write_bytes(data[:-2] + b"\x00" * 4 + data[-2:])
    np.testing.assert_array_equal(read_image(tmp_path / "b.jpg"), read_image(tmp_path / "a.jpg"))
    assert capfd.readouterr().err == ""


def test_other_output_written_while_a_jpeg_decodes_is_not_lost(
    tmp_path: Path, capfd: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """stderr is captured process-wide while libjpeg runs: what is not the decoder's goes
    back out, also when the file is then refused."""
    import os

    ok, jpeg = cv2.imencode(".jpg", RNG.integers(0, 256, (32, 32, 3), np.uint8))
    assert ok
    data = jpeg.tobytes()
    path = tmp_path / "bad.jpg"
    path.write_bytes(data[: len(data) // 2] + b"\xff\xd9")
    decode = cv2.imdecode

    def decode_while_someone_writes(*args: object) -> object:
        os.write(2, b"a line from another thread\n")
        return decode(*args)  # type: ignore[arg-type]

    monkeypatch.setattr(imageio.cv2, "imdecode", decode_while_someone_writes)
    with pytest.raises(InputError, match="corrupt JPEG"):
        read_image(path)
    assert capfd.readouterr().err == "a line from another thread\n"


def test_hidden_companion_files_are_not_images(tmp_path: Path) -> None:
    for name in ("001.png", "002.png", "._001.png", ".hidden.png"):
        (tmp_path / name).write_bytes(b"x")
    assert [p.name for p in imageio.list_images(tmp_path)] == ["001.png", "002.png"]


# -- sizes from headers, before any decoding (issue #27: memory bombs)


@pytest.mark.parametrize(
    ("suffix", "img", "bits"),
    [
        (".png", IMAGES["rgb16"], 16),
        (".png", IMAGES["rgb8"], 8),
        (".tif", IMAGES["rgb16"], 16),
        (".tif", IMAGES["grey16"], 16),
        (".jpg", IMAGES["rgb8"], 8),
        (".bmp", IMAGES["rgb8"], 8),
        # TIFFs Pillow cannot open (their size was known only once decoded): read from the IFD
        (".tif", IMAGES["rgb16"].astype(np.float32), 32),
        (".tif", IMAGES["rgb16"].astype(np.float64), 64),
        (".tif", IMAGES["grey16"].astype(np.int16), 16),
        (".tif", IMAGES["grey16"].astype(np.uint32), 32),
    ],
)
def test_image_header_reads_the_size_without_decoding(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, suffix: str, img: np.ndarray, bits: int
) -> None:
    path = tmp_path / f"a{suffix}"
    encode_png(path, img)
    monkeypatch.setattr(imageio.cv2, "imdecode", lambda *a, **k: pytest.fail("decoded"))
    header = imageio.image_header(path)
    assert header is not None and (header.height, header.width, header.bits) == (9, 13, bits)


def test_image_header_refuses_a_bomb_from_its_ihdr(tmp_path: Path) -> None:
    import struct
    import zlib

    ihdr = struct.pack(">IIBBBBB", 20_000, 20_000, 8, 0, 0, 0, 0)
    chunk = struct.pack(">I", 13) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    path = tmp_path / "bomb.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk)  # no image data needed: never decoded
    with pytest.raises(InputError, match=r"20000x20000 .* above the 250 MP limit"):
        imageio.image_header(path)
    with pytest.raises(InputError, match="above the 250 MP limit"):
        read_image(path)


def test_a_file_larger_than_the_largest_raw_image_is_refused_before_it_is_read(
    tmp_path: Path,
) -> None:
    # EXR and float TIFF have no header reader here: only the file's size can refuse them
    # before all of it is in memory. A sparse file: 4.5 GB long, nothing stored.
    assert imageio.MAX_IMAGE_BYTES > imageio.MAX_PIXELS * 4 * 4  # 4 float32 channels fit
    path = tmp_path / "huge.exr"
    with open(path, "wb") as f:
        f.truncate(imageio.MAX_IMAGE_BYTES + 1)
    with pytest.raises(
        InputError, match=r"file is 4\.50 GB, above the 4\.50 GB read limit .*250 MP"
    ) as info:
        read_image(path)
    assert "\n" not in str(info.value) and str(info.value).startswith(str(path))


def test_the_byte_limit_is_checked_on_the_file_read(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "a.png"
    encode_png(path, IMAGES["rgb8"])
    size = path.stat().st_size
    monkeypatch.setattr(imageio, "MAX_IMAGE_BYTES", size)  # at the limit: read
    np.testing.assert_array_equal(read_image(path), IMAGES["rgb8"])
    monkeypatch.setattr(imageio, "MAX_IMAGE_BYTES", size - 1)  # one byte over: refused
    with pytest.raises(InputError, match="GB read limit"):
        read_image(path)


def test_mask_of_another_size_is_refused_from_its_header(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "mask.png"
    write_png(path, np.full((30, 40), 255, np.uint8))
    monkeypatch.setattr(imageio.cv2, "imdecode", lambda *a, **k: pytest.fail("decoded"))
    with pytest.raises(InputError, match="mask is 40x30 but images are 44x36"):
        imageio.read_mask(path, (36, 44))


def test_array_shapes_of_npy_and_mat_files(tmp_path: Path) -> None:
    scipy_io = pytest.importorskip("scipy.io")
    np.save(tmp_path / "n.npy", np.zeros((4, 5, 3), np.float32))
    assert imageio.array_shape(tmp_path / "n.npy") == (4, 5, 3)
    for compress in (False, True):
        path = tmp_path / f"n{compress}.mat"
        scipy_io.savemat(
            str(path),
            {"other": np.ones((2, 2)), "Normal_gt": np.zeros((6, 7, 3))},
            do_compression=compress,
        )
        assert matfile.mat_directory(path).shapes == {"other": (2, 2), "Normal_gt": (6, 7, 3)}
        assert imageio.array_shape(path) == (6, 7, 3)  # Normal_gt, wherever it is stored
    damaged = tmp_path / "cut.mat"
    damaged.write_bytes((tmp_path / "nTrue.mat").read_bytes()[:150])
    with pytest.raises(InputError, match=r"damaged \.mat file"):
        matfile.mat_directory(damaged)
    (tmp_path / "v4.mat").write_bytes(bytes(200))  # not level 5: no header to read
    assert matfile.mat_directory(tmp_path / "v4.mat") is None


# ------------------------------------------------- .npy headers: the declared length first


def _npy_prefix(version: tuple[int, int], length: int) -> bytes:
    width = "<H" if version == (1, 0) else "<I"
    return b"\x93NUMPY" + bytes(version) + struct.pack(width, length)


@pytest.mark.parametrize("version", [(1, 0), (2, 0), (3, 0)])
def test_npy_layout_reads_every_version_and_stops_at_the_data(version: tuple[int, int]) -> None:
    buf = io.BytesIO()
    array = np.asfortranarray(np.arange(24, dtype=">f8").reshape(2, 3, 4))
    np.lib.format.write_array(buf, array, version=version)
    buf.seek(0)
    shape, fortran, dtype = imageio.npy_layout(buf)
    assert (shape, fortran, dtype) == ((2, 3, 4), True, np.dtype(">f8"))
    assert len(buf.getvalue()) - buf.tell() == array.nbytes  # left where the values start


@pytest.mark.parametrize(
    ("data", "rest", "message"),
    [
        # numpy reads as many bytes as the field declares (4 GB at most) before refusing
        (_npy_prefix((2, 0), 2**32 - 1), 20_000, r"a header of 4,294,967,295 bytes declared"),
        (_npy_prefix((1, 0), 10_001), 20_000, r"a header of 10,001 bytes declared, above 10,000"),
        (_npy_prefix((9, 0), 10), 20_000, r"unknown \.npy format version 9\.0"),
        (b"\x93NUMPY\x01", 0, "no .npy magic string"),
        (_npy_prefix((1, 0), 64) + b"{'descr'", 0, r"cut off in its header \(8 of 64 bytes\)"),
    ],
)
def test_npy_layout_refuses_a_bad_header_before_reading_it(
    data: bytes, rest: int, message: str
) -> None:
    buf = io.BytesIO(data + b" " * rest)  # rest: more than any header limit, were it read
    with pytest.raises(ValueError, match=message):
        imageio.npy_layout(buf)
    assert buf.tell() <= len(data)  # nothing past the length field read (or the short header)


def test_npy_layout_refuses_negative_dimensions() -> None:
    header = b"{'descr': '<f4', 'fortran_order': False, 'shape': (-1, -1, 3), }".ljust(117)
    data = _npy_prefix((1, 0), len(header) + 1) + header + b"\n" + bytes(12)
    with pytest.raises(ValueError, match=r"negative dimension in \(-1, -1, 3\)"):
        imageio.npy_layout(io.BytesIO(data))


def test_array_shape_refuses_a_huge_npy_header_from_its_length(tmp_path: Path) -> None:
    """A sparse 200 MB file whose length field declares a 190 MB header: refused in one line
    from the field (the numpy readers would read the 190 MB first)."""
    path = tmp_path / "n.npy"
    with open(path, "wb") as f:
        f.write(_npy_prefix((2, 0), 190_000_000))
        f.truncate(200_000_000)
    with pytest.raises(InputError, match=r"damaged \.npy header \(a header of 190,000,000") as e:
        imageio.array_shape(path)
    assert "\n" not in str(e.value) and str(e.value).startswith(str(path))


@pytest.mark.parametrize("name", ["003.png", "003.tif", "003.jpg", "003.tga"])
def test_an_empty_image_file_is_bad_input_not_an_internal_error(tmp_path: Path, name: str) -> None:
    """What a failed capture leaves: OpenCV 5 asserted on the empty buffer (cv2.error, exit 1
    as an internal error)."""
    path = tmp_path / name
    path.write_bytes(b"")
    with pytest.raises(InputError, match=r"empty file \(0 bytes\)"):
        read_image(path)


def test_an_unreadable_format_says_so_without_a_python_object(tmp_path: Path) -> None:
    path = tmp_path / "x.tga"
    path.write_bytes(b"not an image at all" * 5)
    with pytest.raises(InputError) as caught:
        read_image(path)
    assert "BytesIO" not in str(caught.value) and "0x" not in str(caught.value)


# -- TIFF structure, read from the first IFD (review-stack23 findings 3, 7 and 12)


def _tiff(
    tags: dict[int, tuple[int, list[int]]],
    data: bytes = b"",
    *,
    big: bool = False,
    order: str = "<",
    ifd_at: int | None = None,
) -> bytes:
    """A TIFF by hand: ``data`` at byte 16 (TIFF_DATA), then the values too long for their
    field, then one IFD of ``tags`` ({tag: (field type, values)}) whose next-IFD pointer
    points back at itself (a loop no reader may follow). ``ifd_at``: the first-IFD offset the
    header gives, if not the real one."""
    codes = {3: "H", 4: "I", 16: "Q"}
    width = 8 if big else 4
    out = bytearray(TIFF_DATA) + data
    fields = []
    for tag, (kind, values) in sorted(tags.items()):
        raw = struct.pack(f"{order}{len(values)}{codes[kind]}", *values)
        if len(raw) > width:
            raw, out = struct.pack(order + ("Q" if big else "I"), len(out)), out + raw
        head = struct.pack(order + ("HHQ" if big else "HHI"), tag, kind, len(values))
        fields.append(head + raw.ljust(width, b"\0"))
    ifd = len(out)
    out += struct.pack(order + ("Q" if big else "H"), len(fields)) + b"".join(fields)
    out += struct.pack(order + ("Q" if big else "I"), ifd)
    first = ifd if ifd_at is None else ifd_at
    magic = b"II" if order == "<" else b"MM"
    if big:
        out[:16] = magic + struct.pack(order + "HHHQ", 43, 8, 0, first)
    else:
        out[:8] = magic + struct.pack(order + "HI", 42, first)
    return bytes(out)


TIFF_DATA = 16  # where _tiff puts the image data


def _grey_tiff(
    img: np.ndarray, tags: dict[int, tuple[int, list[int]]] | None = None, **form: Any
) -> bytes:
    """An uncompressed 8-bit grey TIFF of ``img`` in one strip, made by _tiff (``tags`` added
    or replaced; ``form``: _tiff's keywords)."""
    h, w = img.shape
    base = {
        256: (4, [w]),
        257: (4, [h]),
        258: (3, [8]),
        259: (3, [1]),
        262: (3, [1]),
        273: (4, [TIFF_DATA]),
        277: (3, [1]),
        278: (4, [h]),
        279: (4, [img.size]),
    }
    return _tiff(base | (tags or {}), img.tobytes(), **form)


TIFF_FORMS = [
    pytest.param({}, id="classic little-endian"),
    pytest.param({"order": ">"}, id="classic big-endian"),
    pytest.param({"big": True}, id="BigTIFF little-endian"),
    pytest.param({"big": True, "order": ">"}, id="BigTIFF big-endian"),
]


@pytest.mark.parametrize("form", TIFF_FORMS)
@pytest.mark.parametrize("orientation", [1, 6, 8, 3])
def test_a_tiff_is_read_as_stored_whatever_its_orientation_tag(
    tmp_path: Path, form: dict[str, Any], orientation: int
) -> None:
    """OpenCV 5's TIFF decoder applies an Orientation tag (IMREAD_IGNORE_ORIENTATION or not):
    a tagged stack was read turned, while the lights, mask and ground truth were not (MAE 3.6
    -> 51 deg, exit 0). Every form of TIFF header is read as OpenCV reads it."""
    img = RNG.integers(0, 256, (9, 13), np.uint8)
    path = tmp_path / "a.tif"
    data = _grey_tiff(img, {274: (3, [orientation])}, **form)
    path.write_bytes(data)
    np.testing.assert_array_equal(read_image(path), img)
    header = imageio.image_header(path)
    assert header is not None and (header.shape, header.bits) == ((9, 13), 8)
    assert path.read_bytes() == data  # the file itself is not touched


@pytest.mark.parametrize("orientation", [6, 7])
def test_a_tiff_written_with_an_orientation_tag_reads_like_the_untagged_file(
    tmp_path: Path, orientation: int
) -> None:
    """The reviewer's case: tifffile's RGB 16-bit TIFF with Orientation=6, image and mask."""
    img = IMAGES["rgb16"]
    for tag in (1, orientation):
        extra = [(274, "H", 1, tag, True)]
        tifffile.imwrite(tmp_path / f"{tag}.tif", img, photometric="rgb", extratags=extra)
    tagged, plain = tmp_path / f"{orientation}.tif", tmp_path / "1.tif"
    np.testing.assert_array_equal(read_image(tagged), read_image(plain))
    np.testing.assert_array_equal(read_image(tagged), img)
    mask = tmp_path / "mask.tif"
    extra = [(274, "H", 1, orientation, True)]
    tifffile.imwrite(mask, (img[:, :, 0] > 30000).astype(np.uint8) * 255, extratags=extra)
    np.testing.assert_array_equal(imageio.read_mask(mask, (9, 13)), img[:, :, 0] > 30000)


def _float_rgb_bomb(width: int, height: int, **form: Any) -> bytes:
    """A few KB of deflate declaring a float32 RGB image, every strip the same zlib stream
    (the reviewer's 11 KB file of 269 MP): Pillow cannot open it, OpenCV would decode it."""
    rows = 16
    strip = zlib.compress(bytes(width * 3 * 4 * rows), 9)
    n = -(-height // rows)
    tags = {
        256: (4, [width]),
        257: (4, [height]),
        258: (3, [32, 32, 32]),
        259: (3, [8]),
        262: (3, [2]),
        273: (4, [TIFF_DATA] * n),
        277: (3, [3]),
        278: (4, [rows]),
        279: (4, [len(strip)] * n),
        339: (3, [3, 3, 3]),
    }
    return _tiff(tags, strip, **form)


@pytest.mark.parametrize("form", TIFF_FORMS)
def test_a_float_rgb_tiff_bomb_is_refused_before_decoding(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, form: dict[str, Any]
) -> None:
    """Pillow cannot open float RGB TIFFs: no header, and OpenCV was handed 16400 x 16400 x 3
    float32 (3.2 GB resident from an 11 KB file)."""
    path = tmp_path / "001.tif"
    path.write_bytes(_float_rgb_bomb(16_400, 16_400, **form))
    assert path.stat().st_size < 20_000
    monkeypatch.setattr(imageio.cv2, "imdecode", lambda *a, **k: pytest.fail("decoded"))
    for read in (imageio.image_header, read_image):
        with pytest.raises(InputError, match=r"16400x16400 \(269 MP\), above the 250 MP limit"):
            read(path)


def test_the_float_rgb_tiff_layout_under_the_limit_decodes(tmp_path: Path) -> None:
    """The bomb's layout is a real TIFF: a small one decodes, and its header is read."""
    path = tmp_path / "001.tif"
    path.write_bytes(_float_rgb_bomb(20, 40))
    header = imageio.image_header(path)
    assert header is not None and (header.width, header.height, header.bits) == (20, 40, 32)
    img = read_image(path)
    assert img.shape == (40, 20, 3) and img.dtype == np.float32 and not img.any()


def _hostile(kind: str) -> bytes:
    img = np.zeros((9, 13), np.uint8)
    if kind == "IFD past the end":
        return _grey_tiff(img, ifd_at=10**6)
    if kind == "IFD offset wraps":
        return _grey_tiff(img, big=True, ifd_at=2**64 - 4)
    if kind == "2**40 entries":
        data = bytearray(_grey_tiff(img, big=True))
        (ifd,) = struct.unpack("<Q", data[8:16])
        data[ifd : ifd + 8] = struct.pack("<Q", 2**40)
        return bytes(data)
    if kind == "offsets array of 2**32 - 1":
        data = bytearray(_grey_tiff(img))
        (ifd,) = struct.unpack("<I", data[4:8])
        entry = next(
            ifd + 2 + 12 * i
            for i in range(9)
            if data[ifd + 2 + 12 * i : ifd + 4 + 12 * i] == b"\x11\x01"
        )  # StripOffsets (273)
        data[entry + 4 : entry + 8] = struct.pack("<I", 2**32 - 1)
        return bytes(data)
    if kind == "strip end wraps":
        return _grey_tiff(img, {273: (16, [2**64 - 8]), 279: (16, [117])}, big=True)
    if kind == "no width":
        return _grey_tiff(img, {256: (4, [0])})
    raise AssertionError(kind)


@pytest.mark.parametrize(
    ("kind", "message"),
    [
        ("IFD past the end", r"image directory \(IFD\) at byte 1,000,000 runs past the end"),
        ("IFD offset wraps", r"image directory \(IFD\) at byte 18,446,744,073,709,551,612 runs"),
        ("2**40 entries", "its first IFD declares 1,099,511,627,776 entries"),
        ("offsets array of 2**32 - 1", "tag 273's values at byte .* runs past the end"),
        ("strip end wraps", "strip 1 of 1 ends at byte 18,446,744,073,709,551,725, past the end"),
        ("no width", "no image width or height, or a zero one"),
    ],
)
def test_a_hostile_tiff_structure_is_refused_as_damaged_without_decoding(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, kind: str, message: str
) -> None:
    path = tmp_path / "003.tif"
    path.write_bytes(_hostile(kind))
    monkeypatch.setattr(imageio.cv2, "imdecode", lambda *a, **k: pytest.fail("decoded"))
    with pytest.raises(InputError, match=rf"003\.tif: damaged or truncated TIFF \({message}"):
        read_image(path)


def test_a_truncated_tiff_is_named_as_one_in_one_line(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """Cut in half, OpenCV's TIFF (IFD at the end) was "not a format this tool reads", and a
    zlib TIFF cut at 60 % added a line of libtiff's (from Pillow's decoder) on stderr."""
    img = RNG.integers(0, 65536, (64, 64, 3), np.uint16)
    ok, buf = cv2.imencode(".tif", img)
    assert ok
    path = tmp_path / "003.tif"
    path.write_bytes(buf.tobytes()[: len(buf) // 2])
    with pytest.raises(InputError, match=r"003\.tif: damaged or truncated TIFF \(image directory"):
        read_image(path)
    tifffile.imwrite(path, img, photometric="rgb", compression="zlib", rowsperstrip=8)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 6 // 10])
    with pytest.raises(InputError, match=r"damaged or truncated TIFF \(strip \d of 8 ends at"):
        read_image(path)
    assert capfd.readouterr().err == ""


def test_damaged_data_inside_a_sound_tiff_is_one_line(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """Damage inside a compressed strip: OpenCV fails quietly, Pillow's libtiff complains on
    stderr: its complaint goes into the one error line, not beside it."""
    path = tmp_path / "003.tif"
    tifffile.imwrite(path, IMAGES["rgb16"], photometric="rgb", compression="zlib")
    with tifffile.TiffFile(path) as tif:
        start, length = tif.pages[0].dataoffsets[0], tif.pages[0].databytecounts[0]
    data = bytearray(path.read_bytes())
    for i in range(start + 4, start + length - 4):
        data[i] ^= 0x5A
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"003\.tif: cannot decode TIFF \(damaged image data"):
        read_image(path)
    assert capfd.readouterr().err == ""


# -- other formats no header reader knew: EXR read here, the rest refused before decoding


def _exr(x1: int, y1: int) -> bytes:
    def attribute(name: bytes, kind: bytes, value: bytes) -> bytes:
        return name + b"\0" + kind + b"\0" + struct.pack("<i", len(value)) + value

    return (
        b"\x76\x2f\x31\x01"
        + struct.pack("<I", 2)
        + attribute(b"channels", b"chlist", b"R\0" + bytes(17) + b"\0")
        + attribute(b"compression", b"compression", b"\0")
        + attribute(b"dataWindow", b"box2i", struct.pack("<4i", 0, 0, x1, y1))
        + b"\0"
    )


def test_an_exr_header_gives_the_size_before_decoding(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(imageio.cv2, "imdecode", lambda *a, **k: pytest.fail("decoded"))
    path = tmp_path / "a.exr"
    path.write_bytes(_exr(12, 8))
    header = imageio.image_header(path)
    assert header is not None and (header.width, header.height) == (13, 9)
    path.write_bytes(_exr(19_999, 19_999))
    with pytest.raises(InputError, match=r"20000x20000 .* above the 250 MP limit"):
        read_image(path)
    path.write_bytes(_exr(12, 8)[:40])
    with pytest.raises(InputError, match=r"a\.exr: damaged or truncated EXR file"):
        imageio.image_header(path)


def test_an_image_whose_size_no_header_tells_is_not_decoded(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """OpenCV decodes PAM (and PFM, Radiance HDR) by their bytes, whatever the file's name;
    Pillow reads none of their headers: a 20000 x 20000 PAM of a few bytes was handed to
    OpenCV."""
    path = tmp_path / "001.ppm"
    pam = b"P7\nWIDTH 20000\nHEIGHT 20000\nDEPTH 3\nMAXVAL 255\nTUPLTYPE RGB\nENDHDR\n"
    path.write_bytes(pam + bytes(64))
    monkeypatch.setattr(imageio.cv2, "imdecode", lambda *a, **k: pytest.fail("decoded"))
    with pytest.raises(InputError, match=r"001\.ppm: cannot decode image: not a format"):
        read_image(path)


# -- folders listed without filenames.txt (finding 10)


@pytest.mark.parametrize(
    ("kind", "message"),
    [
        ("dangling link", r"003\.png: dangling link \(to /nonexistent/003\.png\)"),
        ("link loop", r"003\.png: link loop \(to 003\.png\)"),
        ("folder", r"003\.png: is a folder, not an image file"),
    ],
)
def test_an_image_name_that_is_no_file_is_refused_naming_it(
    tmp_path: Path, kind: str, message: str
) -> None:
    """Skipped by is_file(), it left 7 images for 8 lights and the light file was blamed."""
    for name in ("001.png", "002.png"):
        write_png(tmp_path / name, IMAGES["rgb8"])
    entry = tmp_path / "003.png"
    if kind == "dangling link":
        entry.symlink_to("/nonexistent/003.png")
    elif kind == "link loop":
        entry.symlink_to("003.png")
    else:
        entry.mkdir()
    with pytest.raises(InputError, match=message):
        imageio.list_images(tmp_path)


def test_entries_not_taken_as_images_may_be_anything(tmp_path: Path) -> None:
    """Hidden names and masks are never images: a broken one is not the images' business
    (the loader checks a mask it uses); a folder with another name neither."""
    write_png(tmp_path / "001.png", IMAGES["rgb8"])
    (tmp_path / ".002.png").symlink_to("/nonexistent")
    (tmp_path / "mask.png").symlink_to("/nonexistent")
    (tmp_path / "sub").mkdir()
    assert [p.name for p in imageio.list_images(tmp_path)] == ["001.png"]


# -- masks (finding 13a)


@pytest.mark.parametrize(
    ("img", "words"),
    [
        (np.full((9, 13), 255, np.uint16), "32639 of 65535, the 16-bit threshold"),
        (np.full((9, 13), 127, np.uint8), "127"),
        (np.full((9, 13, 3), 0.5, np.float32), "0.5, the threshold of a floating-point mask"),
    ],
)
def test_an_empty_mask_can_be_refused_with_the_threshold_used(
    tmp_path: Path, img: np.ndarray, words: str
) -> None:
    """A 16-bit mask whose object is 255 was "empty (no pixel above 127)": the threshold
    stated is the one read_mask applied."""
    path = tmp_path / ("mask.tif" if img.dtype == np.float32 else "mask.png")
    encode_png(path, img)
    assert not imageio.read_mask(path).any()
    assert imageio.mask_threshold(path) == words


@pytest.mark.parametrize("tile", [(16, 16), (48, 48)])
def test_a_sound_tiff_opencv_cannot_decode_from_memory_is_read_by_pillow(
    tmp_path: Path, tile: tuple[int, int]
) -> None:
    """review-today23.md 1: 8-bit TIFFs with small tiles (tifffile's) were refused as
    damaged once OpenCV failed on them; Pillow reads them, as before."""
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (96, 96, 3), dtype=np.uint8)
    tifffile.imwrite(tmp_path / "t.tif", rgb, tile=tile, photometric="rgb")
    np.testing.assert_array_equal(read_image(tmp_path / "t.tif"), rgb)


def test_a_damaged_strip_opencv_decodes_as_zeros_is_refused(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """review-links23.md 2: OpenCV gave a damaged 8-bit deflate strip back as zeros, its
    libtiff complaint silenced: a stack 4.8 -> 14.5 deg, exit 0."""
    rng = np.random.default_rng(0)
    grey = rng.integers(0, 256, (64, 64), dtype=np.uint8)
    path = tmp_path / "003.tif"
    tifffile.imwrite(path, grey, compression="zlib", rowsperstrip=16)
    np.testing.assert_array_equal(read_image(path), grey)  # sound: read as it is
    with tifffile.TiffFile(path) as tif:
        start = tif.pages[0].dataoffsets[1]
    data = bytearray(path.read_bytes())
    for i in range(start + 2, start + 6):
        data[i] ^= 0xA5
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"003\.tif: damaged TIFF \(ZIPDecode"):
        read_image(path)
    assert capfd.readouterr().err == ""


def test_a_16_bit_tiff_with_separate_colour_planes_is_refused(tmp_path: Path) -> None:
    """review-links23.md 3: OpenCV read its planes as interleaved samples (72 deg, exit 0)."""
    rgb = np.random.default_rng(0).integers(0, 65536, (3, 32, 40), dtype=np.uint16)
    tifffile.imwrite(tmp_path / "p.tif", rgb, planarconfig="separate", photometric="rgb")
    with pytest.raises(InputError, match="separate colour planes"):
        read_image(tmp_path / "p.tif")
    tifffile.imwrite(tmp_path / "c.tif", np.moveaxis(rgb, 0, -1), photometric="rgb")
    np.testing.assert_array_equal(read_image(tmp_path / "c.tif"), np.moveaxis(rgb, 0, -1))


def test_libtiff_lines_are_told_from_other_output(capfd: pytest.CaptureFixture[str]) -> None:
    """What another thread printed while Pillow decoded is passed on, not dropped (review 6)."""
    from msfnet.common.imageio import _LIBTIFF_LINE, _decoder_lines

    text = "progress 3/8\nZIPDecode: Decoding error at scanline 0\nTIFFFillStrip: Read error\n"
    ours = _decoder_lines(text, lambda line: _LIBTIFF_LINE.match(line.strip()))
    assert ours == ["ZIPDecode: Decoding error at scanline 0", "TIFFFillStrip: Read error"]
    assert capfd.readouterr().err == "progress 3/8\n"
