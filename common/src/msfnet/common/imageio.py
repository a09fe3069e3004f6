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
memory budget and with each other before a single pixel is inflated. PNG, TIFF and EXR headers
are read here, the others through Pillow; an image whose size no header tells is not decoded.

Pixels are read as stored, in every format: a TIFF ``Orientation`` tag is not applied (OpenCV's
TIFF decoder and Pillow would rotate the image, but not the light directions, the mask or the
ground truth, which are all in stored pixels).
"""

from __future__ import annotations

import contextlib
import errno
import io
import os
import re
import stat
import struct
import tempfile
import threading
import zlib
from collections.abc import Callable, Iterable, Iterator
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
# the file is read (the pixel limit, from the header, is checked before it is decoded).
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


def list_images(
    folder: Path, exclude: Iterable[str] = ("mask", "normal", "albedo"), *, strict: bool = True
) -> list[Path]:
    """Image files of a folder in natural order, skipping masks, normal maps and the like, and
    hidden files (macOS writes ``._001.png`` companions on foreign file systems). An entry named
    as an image that is no regular file (a dangling link, a link loop, a folder) is refused,
    naming it: skipped, it left one image fewer than lights, and the light file was blamed.
    ``strict=False`` skips such entries instead: for a look at a folder that is not being read
    as a stack (is it one? how many images?), where a stray broken link stopped a whole batch."""
    files = [
        p
        for p in folder.iterdir()
        if not p.name.startswith(".")
        and p.suffix.lower() in IMAGE_SUFFIXES
        and not any(word in p.stem.lower() for word in exclude)
    ]
    if strict:
        for p in files:
            _check_file(p)
    else:
        files = [p for p in files if p.is_file()]
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
    """InputError unless ``path`` is (or links to) a regular file."""
    try:
        mode = path.stat().st_mode  # through links
    except OSError as exc:
        raise InputError(_missing_file(path, exc), path) from exc
    if stat.S_ISDIR(mode):
        raise InputError("is a folder, not an image file", path)
    if not stat.S_ISREG(mode):
        raise InputError("not a regular file (expected an image)", path)


def _missing_file(path: Path, exc: OSError) -> str:
    """Why ``path`` cannot be opened (``exc``, from stat); a broken link names its target."""
    try:
        target: str | None = os.readlink(path)
    except OSError:  # no link (or gone meanwhile)
        target = None
    if exc.errno == errno.ELOOP and target is not None:
        return f"link loop (to {target})"
    if exc.errno in (errno.ENOENT, errno.ENOTDIR):
        return "image file not found" if target is None else f"dangling link (to {target})"
    return f"cannot read it ({exc.strerror})"


def _png_header(head: bytes) -> ImageHeader | None:
    """Width, height and bit depth from a PNG's IHDR chunk (always the first)."""
    if len(head) < 26 or head[12:16] != b"IHDR":
        return None
    w, h, depth = struct.unpack(">IIB", head[16:25])
    return ImageHeader(w, h, 16 if depth == 16 else 8)


# -- TIFF: the first image directory (IFD), read here. Pillow cannot open many TIFFs OpenCV
# decodes (float RGB, int16, uint32): without this, their size was known only once decoded,
# and a few KB of deflate could declare gigabytes. It is also what lets a truncated TIFF be
# named as one before a decoder fails on it (Pillow's libtiff prints its own line then), and
# an Orientation tag be set aside.

# First four bytes: byte order, and whether it is a BigTIFF (64-bit offsets)
_TIFF_MAGIC = {
    b"II*\x00": ("<", False),
    b"MM\x00*": (">", False),
    b"II+\x00": ("<", True),
    b"MM\x00+": (">", True),
}
# The unsigned integer field types of the tags read: BYTE, SHORT, LONG, IFD, LONG8, IFD8
_TIFF_UINTS = {1: "u1", 3: "u2", 4: "u4", 13: "u4", 16: "u8", 18: "u8"}
_TIFF_MAX_ENTRIES = 65_535  # a classic TIFF's own limit; real files have a few dozen
_WIDTH, _LENGTH, _BITS, _COMPRESSION, _ORIENTATION, _PLANAR = 256, 257, 258, 259, 274, 284
_DATA_TAGS = {"strip": (273, 279), "tile": (324, 325)}  # (offsets, byte counts)
_TIFF_TAGS = {_WIDTH, _LENGTH, _BITS, _COMPRESSION, _ORIENTATION, _PLANAR} | {
    t for p in _DATA_TAGS.values() for t in p
}


@dataclass(frozen=True)
class _TiffLayout:
    """What a TIFF's first IFD says, its structure checked against the file's length."""

    header: ImageHeader
    order: str  # "<" or ">"
    big: bool  # BigTIFF
    orientation_at: int | None  # where the Orientation entry starts, unless it says "as stored"
    planar: bool = False  # PlanarConfiguration 2: one plane a colour, not interleaved samples
    compressed: bool = False  # Compression other than 1 (none): data a decoder may find damaged


def _tiff_layout(f: BinaryIO, path: Path) -> _TiffLayout:
    """The first IFD of the TIFF open as ``f``: size, depth, and every strip or tile inside the
    file; InputError naming the damage otherwise. Only the first IFD is read (the image the
    decoders read), so no crafted chain of IFDs is ever followed, and every offset is checked
    against the file's length before it is read."""
    size = f.seek(0, os.SEEK_END)

    def damaged(why: str) -> InputError:
        return InputError(f"damaged or truncated TIFF ({why})", path)

    def read(at: int, n: int, what: str) -> bytes:
        if at + n > size:
            raise damaged(f"{what} at byte {at:,} runs past the end of the {size:,}-byte file")
        f.seek(at)
        data = f.read(n)
        if len(data) != n:  # shortened while read
            raise damaged(f"{what} at byte {at:,} is cut off")
        return data

    order, big = _TIFF_MAGIC[read(0, 4, "header")]
    width = 8 if big else 4  # of an offset, a count and a value field
    first = read(4, 12 if big else 4, "header")
    if big and struct.unpack(order + "HH", first[:4]) != (8, 0):
        raise damaged("a BigTIFF header with an offset size other than 8")
    (ifd,) = struct.unpack(order + ("Q" if big else "I"), first[-width:])
    (n,) = struct.unpack(
        order + ("Q" if big else "H"), read(ifd, width if big else 2, "image directory (IFD)")
    )
    if n == 0 or n > _TIFF_MAX_ENTRIES:
        raise damaged(f"its first IFD declares {n:,} entries")
    start = ifd + (8 if big else 2)
    entry_size = 4 + 2 * width
    block = read(start, n * entry_size, "image directory (IFD)")
    entries: dict[int, tuple[int, int, bytes, int]] = {}  # tag: (type, count, value, position)
    for i in range(n):
        tag, kind, count = struct.unpack_from(
            order + ("HHQ" if big else "HHI"), block, i * entry_size
        )
        if tag in _TIFF_TAGS and tag not in entries:
            value = block[i * entry_size + 4 + width : (i + 1) * entry_size]
            entries[tag] = (kind, count, value, start + i * entry_size)

    def values(tag: int) -> np.ndarray | None:
        if tag not in entries:
            return None
        kind, count, value, _ = entries[tag]
        code = _TIFF_UINTS.get(kind)
        if code is None or count == 0:
            raise damaged(f"tag {tag} holds {count} values of field type {kind}")
        nbytes = count * int(code[1])
        if nbytes > width:  # stored elsewhere; the field holds their offset
            (at,) = struct.unpack(order + ("Q" if big else "I"), value)
            value = read(at, nbytes, f"tag {tag}'s values")
        return np.frombuffer(value[:nbytes], order + code).astype(np.uint64)

    w, h, bits = values(_WIDTH), values(_LENGTH), values(_BITS)
    if w is None or h is None or not w[0] or not h[0]:
        raise damaged("no image width or height, or a zero one")
    header = ImageHeader(int(w[0]), int(h[0]), None if bits is None else int(bits.max()))
    for kind, (offsets_tag, counts_tag) in _DATA_TAGS.items():
        offsets, counts = values(offsets_tag), values(counts_tag)
        if offsets is None or counts is None:
            continue  # no such data (or byte counts for libtiff to work out)
        if len(offsets) != len(counts):
            raise damaged(f"{len(offsets)} {kind} offsets but {len(counts)} byte counts")
        # offsets and counts apart: their sum could wrap around in 64 bits
        past = (offsets > size) | (counts > np.uint64(size) - np.minimum(offsets, size))
        if past.any():
            k = int(np.argmax(past))
            end = int(offsets[k]) + int(counts[k])
            raise damaged(
                f"{kind} {k + 1} of {len(offsets)} ends at byte {end:,}, past the end of the "
                f"{size:,}-byte file"
            )
    if not any(offsets_tag in entries for offsets_tag, _ in _DATA_TAGS.values()):
        raise damaged("no strip or tile offsets: no image data")
    orientation_at = None
    if _ORIENTATION in entries:
        kind, count, value, at = entries[_ORIENTATION]
        if (kind, count, value[:2]) != (3, 1, struct.pack(order + "H", 1)):
            orientation_at = at
    planar, compression = values(_PLANAR), values(_COMPRESSION)
    planar_config = planar is not None and planar[0] == 2
    compressed = compression is not None and compression[0] != 1
    return _TiffLayout(header, order, big, orientation_at, planar_config, compressed)


def _as_stored(data: bytes, layout: _TiffLayout) -> bytes:
    """``data`` with the TIFF's Orientation entry rewritten to 1 (top-left: as stored), so that
    neither decoder turns the pixels. OpenCV 5's TIFF decoder applies the tag whatever the
    flags (IMREAD_IGNORE_ORIENTATION too), Pillow on load; the file itself is not touched."""
    if layout.orientation_at is None:
        return data
    at = layout.orientation_at
    entry = struct.pack(
        layout.order + ("HHQH6x" if layout.big else "HHIH2x"), _ORIENTATION, 3, 1, 1
    )
    return data[:at] + entry + data[at + len(entry) :]


# -- OpenEXR: the header's dataWindow (Pillow reads no EXR; OpenCV may decode it)

_EXR_MAGIC = b"\x76\x2f\x31\x01"
_EXR_MAX_ATTRIBUTES = 1_000  # real headers have a dozen or two


def _exr_header(f: BinaryIO, path: Path) -> ImageHeader:
    """Width and height of the first part of an OpenEXR file, from its dataWindow attribute
    (a sequence of name, type name, size, value; every read bounded by the file)."""
    size = f.seek(0, os.SEEK_END)

    def damaged(why: str) -> InputError:
        return InputError(f"damaged or truncated EXR file ({why})", path)

    def text(at: int) -> bytes:
        f.seek(at)
        chunk = f.read(256)  # names and type names are at most 255 bytes
        if b"\0" not in chunk:
            raise damaged(f"no attribute name ends at byte {at:,}")
        return chunk[: chunk.index(b"\0")]

    at = 8  # magic and version
    for _ in range(_EXR_MAX_ATTRIBUTES):
        name = text(at)
        if not name:
            break  # the end of the header
        kind = text(at + len(name) + 1)
        at += len(name) + len(kind) + 2
        f.seek(at)
        field = f.read(4)
        if len(field) < 4:
            raise damaged(f"the header is cut off at byte {at:,}")
        (length,) = struct.unpack("<i", field)
        at += 4
        if length < 0 or at + length > size:
            raise damaged(f"attribute {name.decode('latin-1')!r} runs past the end of the file")
        if (name, kind, length) == (b"dataWindow", b"box2i", 16):
            f.seek(at)
            x0, y0, x1, y1 = struct.unpack("<4i", f.read(16))
            if x1 < x0 or y1 < y0:
                raise damaged(f"an empty dataWindow ({x0}, {y0}) - ({x1}, {y1})")
            return ImageHeader(x1 - x0 + 1, y1 - y0 + 1, 32)  # OpenCV decodes EXR as float32
        at += length
    raise damaged("no dataWindow in its header")


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
            return ImageHeader(int(w), int(h), bits)
    except Exception:  # a format Pillow does not know: no header to read
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
    if head.startswith(b"\x89PNG"):
        header = _png_header(head)
    elif head[:4] in _TIFF_MAGIC:
        header = _tiff_layout(f, path).header
    elif head.startswith(_EXR_MAGIC):
        header = _exr_header(f, path)
    else:
        header = _pillow_header(f)
    f.seek(0)
    _check_pixels(header, path)
    return header


def _check_pixels(header: ImageHeader | None, path: Path) -> None:
    if header is not None and header.pixels > MAX_PIXELS:
        w, h = header.width, header.height
        raise InputError(
            f"image is {w}x{h} ({w * h / 1e6:.0f} MP), above the "
            f"{MAX_PIXELS / 1e6:.0f} MP limit: refusing to decode it",
            path,
        )


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
    if header is None:  # no header tells its size: refused rather than decoded blind
        raise InputError("cannot decode image: not a format this tool reads", path)
    tiff = data[:4] in _TIFF_MAGIC
    listen = False  # hear the decoder's complaints: only compressed data can be found damaged
    if tiff:
        # the bytes decoded, read again (the header came from the file before they were read)
        layout = _tiff_layout(io.BytesIO(data), path)
        listen = layout.compressed
        _check_pixels(layout.header, path)
        if layout.planar and (layout.header.bits or 8) > 8:
            # OpenCV 5.1 reads its planes as if interleaved (R00 R01 R02 for R G B), Pillow
            # has no 16-bit colour: 72 deg of garbage normals, without a word
            raise InputError(
                f"{layout.header.bits}-bit TIFF with separate colour planes "
                "(PlanarConfiguration 2), which no decoder here reads right; save it with "
                "interleaved samples (the default of most writers)",
                path,
            )
        data = _as_stored(data, layout)
    opencv = path.suffix.lower() != ".tga" or tiff  # OpenCV cannot read TGA
    img = _decode_with_opencv(data, path, listen) if opencv else None
    if img is None and tiff:
        # OpenCV 5.1 fails on some sound TIFFs from memory (8-bit or 1-bit with 16 x 16 or
        # 48 x 48 tiles, as tifffile writes them): Pillow reads those; a structure checked
        # sound that both fail on holds damaged data. libtiff behind Pillow prints its
        # complaint on stderr before failing: kept for the one error line, the rest (another
        # thread's output) passed on as it came
        with _captured_stderr() as said:
            try:
                img = _decode_with_pillow(data, path)
            except InputError as exc:
                failure: InputError | None = exc
            else:
                failure = None
        libtiff = _decoder_lines(said[0], lambda line: _LIBTIFF_LINE.match(line.strip()))
        if failure is not None:
            cause = failure.__cause__
            why = libtiff[0] if libtiff else first_line(cause) if cause else failure.message
            raise InputError(
                "cannot decode TIFF (damaged image data, or a kind of TIFF neither OpenCV nor "
                f"Pillow reads: {why})",
                path,
            ) from failure
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


@contextlib.contextmanager
def _opencv_log(level: int) -> Iterator[None]:
    """OpenCV's log at ``level`` for the block (under _STDERR_LOCK, by the caller's capture)."""
    try:
        before = cv2.utils.logging.getLogLevel()
        cv2.utils.logging.setLogLevel(level)
    except AttributeError:  # older OpenCV has no logging module
        yield
        return
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(before)


_OPENCV_LOG = re.compile(r"\[\s*(ERROR|WARN|INFO)[^\]]*\] ")
# libtiff's messages are "<module>: <text>" (TIFFFillStrip: ..., ZIPDecode: ..., LZWDecode: ...)
_LIBTIFF_LINE = re.compile(r"(TIFF\w*|\w+Decode\w*|\w+PreDecode|\w+SetupDecode): ")


def _decoder_lines(text: str, ours: Callable[[str], object]) -> list[str]:
    """The lines of ``text`` (stderr captured around a decode) that ``ours`` claims for the
    decoder, stripped; every other non-blank line, another thread's output, is passed on to
    stderr as it came."""
    lines = [line for line in text.splitlines() if line.strip()]
    other = [line for line in lines if not ours(line)]
    if other:
        os.write(2, ("\n".join(other) + "\n").encode())
    return [line.strip() for line in lines if ours(line)]


def _decode_with_opencv(data: bytes, path: Path, listen: bool = False) -> np.ndarray | None:
    """``listen``: hear libtiff's complaints (a compressed TIFF; decodes one at a time)."""
    try:
        return _opencv_decode(data, path, listen)
    except cv2.error as exc:  # OpenCV asserts on some inputs rather than returning None
        raise InputError(f"cannot decode image (OpenCV: {first_line(exc)})", path) from exc


def _opencv_decode(data: bytes, path: Path, listen: bool = False) -> np.ndarray | None:
    buf = np.frombuffer(data, np.uint8)
    if data.startswith(b"\xff\xd8"):
        with _captured_stderr() as said:
            img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
        libjpeg = _decoder_lines(
            said[0], lambda line: _benign_padding(line) or line.startswith(_JPEG_DAMAGE)
        )
        damage = [line for line in libjpeg if not _benign_padding(line)]
        if damage:
            raise InputError(f"corrupt JPEG ({damage[0]})", path)
    elif listen:
        # libtiff's complaints go through OpenCV's log, silenced: heard here, or a damaged
        # deflate strip decodes as zeros without a word (a stack 4.8 -> 14.5 deg, exit 0).
        # The capture holds stderr, so compressed TIFFs decode one at a time; uncompressed
        # ones (most cameras') have nothing to complain of and decode in parallel
        with _captured_stderr() as said, _opencv_log(cv2.utils.logging.LOG_LEVEL_ERROR):
            img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
        # OpenCV's log lines ("[ERROR:0@0.1] global grfmt_tiff.cpp:117 TIFF_Error ...")
        logged = _decoder_lines(said[0], _OPENCV_LOG.match)
        told = [line.split("TIFF_Error", 1)[1].strip() for line in logged if "TIFF_Error" in line]
        if told and img is not None:  # (None: Pillow is tried next, and says its own)
            raise InputError(f"damaged TIFF ({told[0]})", path)
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
            if im.mode in ("1", "LA"):  # bilevel (a mask): 0 / 255; grey + alpha: grey,
                im = im.convert("L")  # as OpenCV gives them
            elif im.mode in ("P", "PA", "RGBA", "CMYK", "YCbCr"):
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
    """A boolean mask from a grey or RGB image; anti-aliased edges resolved as > 127 of 255
    (> 32639 of 65535 at 16 bits, > 0.5 in a float image: :func:`mask_threshold`)."""
    img = read_image(path, shape, "mask")
    if img.ndim == 3:
        img = img.max(axis=2)
    return img > _mask_threshold(img.dtype)[0]


def _mask_threshold(dtype: np.dtype) -> tuple[float, str]:
    """The value above which a mask pixel of type ``dtype`` is object, and its wording."""
    if dtype == np.uint16:
        return 127 * 257, "32639 of 65535, the 16-bit threshold"
    if np.issubdtype(dtype, np.floating):
        return 0.5, "0.5, the threshold of a floating-point mask"
    return 127, "127"


def mask_threshold(path: str | Path) -> str:
    """The threshold :func:`read_mask` applies to the mask at ``path``, in words, for the
    message that refuses an empty mask ("no pixel above ..."): a 16-bit mask whose object is
    255 is empty, and "above 127" would not say why. Decodes the file again: for the error
    path only."""
    return _mask_threshold(read_image(path).dtype)[1]


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
