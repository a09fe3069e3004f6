"""Reading and writing images at full bit depth, in RGB order.

OpenCV keeps 16 bits (Pillow silently drops to 8 for 16-bit RGB PNGs) but returns BGR and cannot
read TGA; Pillow reads TGA. So: OpenCV first, Pillow for what OpenCV cannot decode.

One path-to-bytes rule: a file is opened by Python (which takes any name the OS gives, even one
that is not UTF-8) and its bytes are decoded from memory (``cv2.imdecode``, Pillow on a buffer).
No path is ever handed to a C library: OpenCV's ``imread``/``imwrite`` crash (SIGSEGV) on a
name holding a byte that is not UTF-8, such as a Latin-1 ``\xe9``.

One size check before decoding: :func:`image_header` reads an image's size (and, where the
header tells, its sample depth) without decoding it, and :func:`array_shape` does the same for
``.npy`` and MATLAB ``.mat`` arrays, so a caller can compare every file of a stack with the
memory budget and with each other before a single pixel is inflated.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import struct
import tempfile
import threading
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import cv2
import numpy as np

from msfnet.common.errors import InputError, first_line
from msfnet.common.files import write_atomic
from msfnet.common.matfile import mat_directory

# Refuse images above this many pixels from the header, before decoding (a decompression bomb:
# a few KB of PNG that decodes to tens of GB). 250 MP is ~10x a large industrial sensor.
MAX_PIXELS = 250_000_000

# The largest image file read: the raw size of the largest image allowed (MAX_PIXELS of four
# float32 channels), plus an eighth for headers, offset tables and metadata. Compression only
# makes a file smaller than raw, so a larger file is no image we would decode. Checked before
# the file is read: formats without a header reader here (EXR, float TIFF) have their pixels
# counted only once decoded, after the whole file was in memory.
MAX_IMAGE_BYTES = MAX_PIXELS * 4 * 4 * 9 // 8

# OpenCV logs decoder failures on stderr ("[ERROR:0@0.2] global grfmt_tiff.cpp ..."); msfnet
# reports a bad file itself, in one line.
with contextlib.suppress(AttributeError):  # older OpenCV has no logging module
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)

# What a complete file ends with. An interrupted copy is the commonest broken image; libjpeg
# decodes a cut JPEG into grey rows with a warning on stderr, so catch it before decoding.
_PNG_END = b"IEND\xaeB`\x82"
_JPEG_END = b"\xff\xd9"

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".tga", ".jpg", ".jpeg", ".bmp", ".exr", ".pgm", ".ppm")


def natural_key(name: str) -> list[object]:
    """Sort key putting ``x.2`` before ``x.10``."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def list_images(folder: Path, exclude: Iterable[str] = ("mask", "normal", "albedo")) -> list[Path]:
    """Image files of a folder in natural order, skipping masks, normal maps and the like, and
    hidden files (macOS writes ``._001.png`` companions on foreign file systems)."""
    files = [
        p
        for p in folder.iterdir()
        if p.is_file()
        and not p.name.startswith(".")
        and p.suffix.lower() in IMAGE_SUFFIXES
        and not any(word in p.stem.lower() for word in exclude)
    ]
    return sorted(files, key=lambda p: natural_key(p.name))


@dataclass(frozen=True)
class ImageHeader:
    """What an image file's header says, read without decoding a pixel."""

    width: int
    height: int
    bits: int | None  # bits per sample as decoded (8, 16, 32), None where the header is silent

    @property
    def pixels(self) -> int:
        return self.width * self.height

    @property
    def shape(self) -> tuple[int, int]:
        return self.height, self.width


def _check_file(path: Path) -> None:
    if not path.exists():
        raise InputError("image file not found", path)
    if not path.is_file():
        raise InputError("not a regular file (expected an image)", path)


def _png_header(head: bytes) -> ImageHeader | None:
    """Width, height and bit depth from a PNG's IHDR chunk (always the first)."""
    if len(head) < 26 or head[12:16] != b"IHDR":
        return None
    w, h, depth = struct.unpack(">IIB", head[16:25])
    return ImageHeader(w, h, 16 if depth == 16 else 8)


# Pillow modes whose sample depth is certain (others, e.g. 16-bit RGB TIFF, open as "RGB")
_MODE_BITS = {"I;16": 16, "I;16B": 16, "I;16L": 16, "I;16N": 16, "I": 32, "F": 32}


def _pillow_header(f: BinaryIO) -> ImageHeader | None:
    from PIL import Image

    Image.MAX_IMAGE_PIXELS = None  # our own limit applies, with our own message
    try:
        with Image.open(f) as im:
            w, h = im.size
            bits = _MODE_BITS.get(im.mode)
            if bits is None and im.format in ("JPEG", "BMP", "TGA"):
                bits = 8
            elif bits is None and im.format == "TIFF":
                per_sample = im.tag_v2.get(258)  # BitsPerSample
                if isinstance(per_sample, tuple) and per_sample:
                    bits = int(max(per_sample))
                elif isinstance(per_sample, int):
                    bits = per_sample
            return ImageHeader(int(w), int(h), bits)
    except Exception:  # a format Pillow does not know (EXR, float TIFF): no header to read
        return None


def image_header(path: str | Path) -> ImageHeader | None:
    """The size of an image from its header (no decoding), None where no header reader knows
    the format; InputError for a missing file or a size above MAX_PIXELS (a decompression
    bomb: a few KB of PNG can decode to tens of GB)."""
    path = Path(path)
    _check_file(path)
    with open(path, "rb") as f:  # Python opens any name (see the module notes)
        return _header(f, path)


def _header(f: BinaryIO, path: Path) -> ImageHeader | None:
    """:func:`image_header` of the file open as ``f`` (read from its start, left there)."""
    head = f.read(32)
    f.seek(0)
    header = _png_header(head) if head.startswith(b"\x89PNG") else _pillow_header(f)
    f.seek(0)
    if header is not None and header.pixels > MAX_PIXELS:
        w, h = header.width, header.height
        raise InputError(
            f"image is {w}x{h} ({w * h / 1e6:.0f} MP), above the "
            f"{MAX_PIXELS / 1e6:.0f} MP limit: refusing to decode it",
            path,
        )
    return header


def read_image(
    path: str | Path, shape: tuple[int, int] | None = None, what: str = "image"
) -> np.ndarray:
    """Read an image as H x W x 3 (RGB) or H x W, in its stored dtype (uint8/uint16/float32).
    ``shape``: the (H, W) it must have, compared from its header before it is decoded (a
    mask or ground truth against the stack; ``what`` names it in the message)."""
    path = Path(path)
    _check_file(path)
    # One handle for the header check and the bytes decoded: a file replaced by name between
    # the two would reach the decoder unchecked (a bomb past the pixel limit, say)
    with open(path, "rb") as f:
        header = _header(f, path)  # size refused before the file is read or decoded
        if shape is not None:
            check_same_size(header.shape if header else None, shape, what, path)
        size = os.fstat(f.fileno()).st_size  # the file open, not the name: it may change
        if size > MAX_IMAGE_BYTES:
            raise InputError(
                f"file is {size / 1e9:.2f} GB, above the {MAX_IMAGE_BYTES / 1e9:.2f} GB read "
                f"limit (a {MAX_PIXELS / 1e6:.0f} MP image of four float32 channels, "
                "uncompressed, with headers); save float64 images as float32",
                path,
            )
        data = _checked_bytes(f.read(), path)
    img = None if path.suffix.lower() == ".tga" else _decode_with_opencv(data, path)
    if img is None:
        img = _decode_with_pillow(data, path)
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[:, :, :3]
    if img.ndim not in (2, 3) or img.size == 0 or (img.ndim == 3 and img.shape[2] != 3):
        raise InputError(f"unsupported image shape {img.shape}", path)
    if shape is not None:  # formats without a header reader: compared once decoded
        check_same_size(img.shape, shape, what, path)
    return np.ascontiguousarray(img)


def _checked_bytes(data: bytes, path: Path) -> bytes:
    """A file's bytes (read once, by Python), checked. PNG and JPEG files that stop before
    their end marker (truncated copies) and PNG files whose chunks fail their CRC (damaged
    bytes) are refused: libpng would print its own line on stderr before failing, or decode
    damaged rows."""
    if not data:  # what a failed capture leaves (disk full, camera timeout)
        raise InputError("empty file (0 bytes)", path)
    head, tail = data[:8], data[-64:]
    if head.startswith(b"\x89PNG") and _PNG_END not in tail:
        raise InputError("truncated PNG (the file stops before its end marker)", path)
    if head.startswith(b"\xff\xd8") and _JPEG_END not in tail:
        raise InputError("truncated JPEG (the file stops before its end marker)", path)
    if head.startswith(b"\x89PNG"):
        _check_png_chunks(data, path)
    return data


def _check_png_chunks(data: bytes, path: Path) -> None:
    """Every chunk's CRC-32 verified (zlib's, at memory speed: a few ms for a 16-bit frame)."""
    pos = 8
    while pos + 12 <= len(data):
        length, kind = struct.unpack(">I4s", data[pos : pos + 8])
        end = pos + 8 + length
        if end + 4 > len(data):
            raise InputError(f"corrupt PNG (chunk at byte {pos} runs past the end)", path)
        (crc,) = struct.unpack(">I", data[end : end + 4])
        if zlib.crc32(data[pos + 4 : end]) != crc:
            name = kind.decode("latin-1")
            raise InputError(f"corrupt PNG (chunk {name!r} at byte {pos} fails its checksum)", path)
        if kind == b"IEND":
            return
        pos = end + 4
    raise InputError("corrupt PNG (no IEND chunk where the chunks end)", path)


# libjpeg decodes damaged data with a warning on stderr ("Corrupt JPEG data: ...") and no error:
# JPEG decoding runs with stderr captured, one file at a time (stderr is process-wide), and the
# damage libjpeg notices is refused. JPEG has no checksum: a few changed bytes inside the image
# data can still decode unnoticed (PNG's CRCs catch those; prefer PNG or TIFF for stacks).
_STDERR_LOCK = threading.Lock()
_JPEG_DAMAGE = ("Corrupt JPEG data", "Premature end of JPEG", "Invalid JPEG", "Bogus")


def _benign_padding(line: str) -> bool:
    """A few bytes of padding before the end marker (common in webcam MJPEG frames): libjpeg
    calls it corrupt data, but every pixel decodes. Thousands of them mean lost data."""
    found = re.match(r"Corrupt JPEG data: (\d+) extraneous bytes before marker 0xd9", line)
    return found is not None and int(found.group(1)) <= 64


@contextlib.contextmanager
def _captured_stderr() -> Iterator[list[str]]:
    """What C libraries write on file descriptor 2 meanwhile (the text, once the block ends)."""
    text: list[str] = []
    with _STDERR_LOCK, tempfile.TemporaryFile() as sink:
        saved = os.dup(2)
        try:
            os.dup2(sink.fileno(), 2)
            yield text
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            text.append(sink.read().decode("utf-8", "replace"))


def _decode_with_opencv(data: bytes, path: Path) -> np.ndarray | None:
    try:
        return _opencv_decode(data, path)
    except cv2.error as exc:  # OpenCV asserts on some inputs rather than returning None
        raise InputError(f"cannot decode image (OpenCV: {first_line(exc)})", path) from exc


def _opencv_decode(data: bytes, path: Path) -> np.ndarray | None:
    buf = np.frombuffer(data, np.uint8)
    if data.startswith(b"\xff\xd8"):
        with _captured_stderr() as said:
            img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
        damage: list[str] = []
        other: list[str] = []
        for line in said[0].splitlines():
            if _benign_padding(line):
                continue
            (damage if line.startswith(_JPEG_DAMAGE) else other).append(line)
        if other:  # not the decoder's: another thread's output, passed on as it was
            os.write(2, ("\n".join(other) + "\n").encode())
        if damage:
            raise InputError(f"corrupt JPEG ({damage[0].strip()})", path)
    else:
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    if img is not None and img.ndim == 3:
        img = img[:, :, 2::-1] if img.shape[2] >= 3 else img  # BGR(A) -> RGB
    return img


def _decode_with_pillow(data: bytes, path: Path) -> np.ndarray:
    try:
        from PIL import Image

        with Image.open(io.BytesIO(data)) as im:
            im.load()
            if im.mode in ("P", "PA", "LA", "RGBA", "CMYK", "YCbCr"):
                im = im.convert("RGB")
            return np.asarray(im)
    except Exception as exc:  # Pillow raises many types for corrupt files
        if type(exc).__name__ == "UnidentifiedImageError":  # its text names a BytesIO object
            raise InputError("cannot decode image: not a format this tool reads", path) from exc
        raise InputError(
            f"cannot decode image ({type(exc).__name__}: {first_line(exc)})", path
        ) from exc


def check_same_size(
    found: tuple[int, ...] | None, shape: tuple[int, int], what: str, path: Path
) -> None:
    """InputError unless ``found`` (an array's or a header's (height, width, ...)) starts with
    the stack's ``shape``: the one wording of every mask, ground-truth and image size check."""
    if found is None or tuple(found[:2]) == tuple(shape):
        return
    size = f"{found[1]}x{found[0]}" if len(found) >= 2 else f"of shape {tuple(found)}"
    raise InputError(f"{what} is {size} but images are {shape[1]}x{shape[0]}", path)


def read_mask(path: str | Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """A boolean mask from a grey or RGB image; anti-aliased edges resolved as > 127 of 255."""
    img = read_image(path, shape, "mask")
    if img.ndim == 3:
        img = img.max(axis=2)
    if img.dtype == np.uint16:
        mask = img > 127 * 257
    elif np.issubdtype(img.dtype, np.floating):
        mask = img > 0.5
    else:
        mask = img > 127
    return mask


# -- array files: shapes from their headers


# The longest .npy header read (numpy's own max_header_size). numpy refuses longer ones only
# after reading as many bytes as the length field declares, up to 4 GB: a .npy file (or an
# .npz member of a few MB, inflated) could fill the memory before the refusal. So the field is
# checked before any of the header is read.
NPY_MAX_HEADER = 10_000
_NPY_VERSIONS = ((1, 0), (2, 0), (3, 0))


def npy_layout(f: BinaryIO) -> tuple[tuple[int, ...], bool, np.dtype]:
    """Shape, Fortran order and type of the .npy data that ``f`` (positioned at its magic)
    holds, ``f`` left where the data starts; nothing past the header is read. ValueError for
    a damaged header, an unknown format version, a negative dimension, or a header longer than
    NPY_MAX_HEADER bytes."""
    magic = f.read(8)
    if len(magic) < 8 or not magic.startswith(b"\x93NUMPY"):
        raise ValueError("no .npy magic string")
    version = (magic[6], magic[7])
    if version not in _NPY_VERSIONS:
        raise ValueError(f"unknown .npy format version {version[0]}.{version[1]}")
    width = 2 if version == (1, 0) else 4
    field = f.read(width)
    if len(field) < width:
        raise ValueError("cut off in its header length")
    (length,) = struct.unpack("<H" if width == 2 else "<I", field)
    if length > NPY_MAX_HEADER:
        raise ValueError(f"a header of {length:,} bytes declared, above {NPY_MAX_HEADER:,}")
    text = f.read(length)
    if len(text) < length:
        raise ValueError(f"cut off in its header ({len(text):,} of {length:,} bytes)")
    read = (
        np.lib.format.read_array_header_1_0
        if version == (1, 0)
        else np.lib.format.read_array_header_2_0
    )
    shape, fortran, dtype = read(io.BytesIO(field + text))  # parsed from what was read
    dims = tuple(int(d) for d in shape)
    if any(d < 0 for d in dims):
        raise ValueError(f"negative dimension in {dims}")
    return dims, bool(fortran), np.dtype(dtype)


def npy_header(f: BinaryIO) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and type of the .npy data that ``f`` (positioned at its magic) holds, without
    reading the data (:func:`npy_layout`); ValueError for a damaged header."""
    shape, _fortran, dtype = npy_layout(f)
    return shape, dtype


def array_shape(path: str | Path) -> tuple[int, ...] | None:
    """The shape a file's array will have once read, from its header alone: images (H, W, 3),
    ``.npy`` files, and a ``.mat`` file's normals variable (``Normal_gt``, else its first
    variable, skipping unnamed and "_" ones: :func:`msfnet.common.matfile.normals_variable`,
    the variable the reader reads); None where no header says. InputError for a damaged header
    or an image above MAX_PIXELS."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npy":
        try:
            with open(path, "rb") as f:
                return npy_header(f)[0]
        except ValueError as exc:
            raise InputError(f"damaged .npy header ({first_line(exc)})", path) from exc
    if suffix == ".mat":
        directory = mat_directory(path)
        return None if directory is None else directory.normals_shape
    header = image_header(path)
    return None if header is None else (header.height, header.width, 3)


def encode_png(path: str | Path, img: np.ndarray, name: str | Path | None = None) -> None:
    """Encode an RGB (or grey) uint8/uint16 image at ``path``: the one encoder of every PNG
    writer, meant for a staging path (callers make the write atomic). ``name``: the file the
    error names (the final one, not the staging path); default ``path``. The format comes from
    ``path``'s suffix, so a staging name keeps the target's (``.png``; msf-calib's diagnostic
    may also be ``.tif``, ``.bmp`` or ``.jpg``). Encoded in memory, written by Python (see the
    module notes on names)."""
    arr = np.asarray(img)
    if arr.ndim == 3:
        arr = arr[:, :, ::-1]  # OpenCV writes BGR
    suffix = Path(path).suffix.lower() or ".png"
    try:
        ok, buf = cv2.imencode(suffix, np.ascontiguousarray(arr))
    except cv2.error:
        ok = False
    if not ok:
        raise InputError("cannot write image", path if name is None else name)
    with open(path, "wb") as f:
        f.write(buf.tobytes())


def write_png(path: str | Path, img: np.ndarray) -> None:
    """Write an RGB (or grey) uint8/uint16 image as PNG, atomically."""
    path = Path(path)
    write_atomic(path, lambda tmp: encode_png(tmp, img, name=path))
