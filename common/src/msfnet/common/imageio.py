"""Reading and writing images at full bit depth, in RGB order.

OpenCV keeps 16 bits (Pillow silently drops to 8 for 16-bit RGB PNGs) but returns BGR and cannot
read TGA; Pillow reads TGA. So: OpenCV first, Pillow for what OpenCV cannot decode.
"""

from __future__ import annotations

import contextlib
import os
import re
import struct
import tempfile
import threading
import zlib
from collections.abc import Iterable, Iterator
from pathlib import Path

import cv2
import numpy as np

from msfnet.common.errors import InputError, first_line
from msfnet.common.files import write_atomic

# Refuse images above this many pixels from the header, before decoding (a decompression bomb:
# a few KB of PNG that decodes to tens of GB). 250 MP is ~10x a large industrial sensor.
MAX_PIXELS = 250_000_000

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


def read_image(path: str | Path) -> np.ndarray:
    """Read an image as H x W x 3 (RGB) or H x W, in its stored dtype (uint8/uint16/float32)."""
    path = Path(path)
    if not path.exists():
        raise InputError("image file not found", path)
    if not path.is_file():
        raise InputError("not a regular file (expected an image)", path)
    png = _check_header(path)
    img = None if path.suffix.lower() == ".tga" else _read_with_opencv(path, png)
    if img is None:
        img = _read_with_pillow(path)
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[:, :, :3]
    if img.ndim not in (2, 3) or img.size == 0 or (img.ndim == 3 and img.shape[2] != 3):
        raise InputError(f"unsupported image shape {img.shape}", path)
    return np.ascontiguousarray(img)


def _check_complete(path: Path) -> bytes | None:
    """Refuse PNG and JPEG files that stop before their end marker (truncated copies) and PNG
    files whose chunks fail their CRC (damaged bytes): libpng would print its own line on
    stderr before failing, or decode damaged rows. Returns a PNG's bytes (read once: checked
    here, decoded from memory)."""
    with open(path, "rb") as f:
        head = f.read(8)
        f.seek(0, 2)
        size = f.tell()
        f.seek(max(0, size - 64))
        tail = f.read()
    if head.startswith(b"\x89PNG") and _PNG_END not in tail:
        raise InputError("truncated PNG (the file stops before its end marker)", path)
    if head.startswith(b"\xff\xd8") and _JPEG_END not in tail:
        raise InputError("truncated JPEG (the file stops before its end marker)", path)
    return _checked_png(path) if head.startswith(b"\x89PNG") else None


def _checked_png(path: Path) -> bytes:
    """The file's bytes, every chunk's CRC-32 verified (zlib's, at memory speed: a few ms for
    a 16-bit frame)."""
    data = path.read_bytes()
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
            return data
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


def _check_header(path: Path) -> bytes | None:
    """Read the size from the header (no decoding) and refuse absurd ones; a PNG's bytes
    come back (see :func:`_check_complete`)."""
    png = _check_complete(path)
    try:
        from PIL import Image

        Image.MAX_IMAGE_PIXELS = None  # we apply our own limit below, with a clear message
        with Image.open(path) as im:
            w, h = im.size
    except Exception:
        return png  # not a format Pillow knows: OpenCV will decode it (or report the problem)
    if w * h > MAX_PIXELS:
        raise InputError(
            f"image is {w}x{h} ({w * h / 1e6:.0f} MP), above the "
            f"{MAX_PIXELS / 1e6:.0f} MP limit: refusing to decode it",
            path,
        )
    return png


def _read_with_opencv(path: Path, png: bytes | None = None) -> np.ndarray | None:
    if png is not None:  # already read and checked
        img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    elif path.suffix.lower() in (".jpg", ".jpeg"):
        with _captured_stderr() as said:
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
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
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is not None and img.ndim == 3:
        img = img[:, :, 2::-1] if img.shape[2] >= 3 else img  # BGR(A) -> RGB
    return img


def _read_with_pillow(path: Path) -> np.ndarray:
    try:
        from PIL import Image

        with Image.open(path) as im:
            im.load()
            if im.mode in ("P", "PA", "LA", "RGBA", "CMYK", "YCbCr"):
                im = im.convert("RGB")
            return np.asarray(im)
    except Exception as exc:  # Pillow raises many types for corrupt files
        raise InputError(
            f"cannot decode image ({type(exc).__name__}: {first_line(exc)})", path
        ) from exc


def read_mask(path: str | Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """A boolean mask from a grey or RGB image; anti-aliased edges resolved as > 127 of 255."""
    img = read_image(path)
    if img.ndim == 3:
        img = img.max(axis=2)
    if img.dtype == np.uint16:
        mask = img > 127 * 257
    elif np.issubdtype(img.dtype, np.floating):
        mask = img > 0.5
    else:
        mask = img > 127
    if shape is not None and mask.shape != tuple(shape):
        raise InputError(
            f"mask is {mask.shape[1]}x{mask.shape[0]} but images are {shape[1]}x{shape[0]}", path
        )
    return mask


def encode_png(path: str | Path, img: np.ndarray, name: str | Path | None = None) -> None:
    """Encode an RGB (or grey) uint8/uint16 image at ``path``: the one encoder of every PNG
    writer, meant for a staging path (callers make the write atomic). ``name``: the file the
    error names (the final one, not the staging path); default ``path``. OpenCV picks the
    format from ``path``'s suffix, so a staging name keeps the target's (``.png``; msf-calib's
    diagnostic may also be ``.tif``, ``.bmp`` or ``.jpg``)."""
    arr = np.asarray(img)
    if arr.ndim == 3:
        arr = arr[:, :, ::-1]  # OpenCV writes BGR
    if not cv2.imwrite(str(path), np.ascontiguousarray(arr)):
        raise InputError("cannot write image", path if name is None else name)


def write_png(path: str | Path, img: np.ndarray) -> None:
    """Write an RGB (or grey) uint8/uint16 image as PNG, atomically."""
    path = Path(path)
    write_atomic(path, lambda tmp: encode_png(tmp, img, name=path))
