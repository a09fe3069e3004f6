"""PNG writing (common/imageio.py): one encoder, RGB in, full bit depth, errors naming the file
the user knows."""

from __future__ import annotations

import io
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

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
        assert matfile.mat_shapes(path) == {"other": (2, 2), "Normal_gt": (6, 7, 3)}
        assert imageio.array_shape(path) == (6, 7, 3)  # Normal_gt, wherever it is stored
    damaged = tmp_path / "cut.mat"
    damaged.write_bytes((tmp_path / "nTrue.mat").read_bytes()[:150])
    with pytest.raises(InputError, match=r"damaged \.mat file"):
        matfile.mat_shapes(damaged)
    (tmp_path / "v4.mat").write_bytes(bytes(200))  # not level 5: no header to read
    assert matfile.mat_shapes(tmp_path / "v4.mat") is None


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
