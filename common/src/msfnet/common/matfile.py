"""MATLAB level-5 ``.mat`` files read without SciPy (importing ``scipy.io`` costs ~0.6 s).

Readers that trust no size a file declares:

- :func:`mat_directory`: one parse of every variable's element header (a compressed element is
  inflated only as far as its header), kept as a :class:`MatDirectory` that later reads reuse:
  a ground truth's headers are checked, then its values read, from one parse.
- :attr:`MatDirectory.shapes`: every variable's name and dimensions.
- :meth:`MatDirectory.array`: one variable's values, for the common case only (a full, real,
  numeric array); None for anything else, so that callers fall back to ``scipy.io.loadmat``.
- :func:`normals_variable`: the one rule for which variable holds ground-truth normals.
- :func:`not_v5`: what a file that is not level 5 is (v4, v7.3/HDF5, no .mat), for the
  message that refuses it.

The layout: a 128-byte header (text, version 0x0100, the byte-order mark ``IM`` or ``MI``), then
tagged elements. A variable is a miMATRIX element, or the same zlib-compressed inside a
miCOMPRESSED one; its sub-elements are the array flags (class, complex, logical), the
dimensions, the name, then the real part (and the imaginary part when complex). The values are
stored column-major, and may be stored in a narrower type than their class (MATLAB keeps a double
array of small integers as miUINT8, say).
"""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from msfnet.common.errors import InputError, first_line

# Element (data) types of the format
_MI_INT8, _MI_INT32, _MI_UINT32, _MI_MATRIX, _MI_COMPRESSED = 1, 5, 6, 14, 15
_MAT_MAX_VARIABLES = 4096

# How numbers may be stored, by element type
_STORED = {
    1: "i1",
    2: "u1",
    3: "i2",
    4: "u2",
    5: "i4",
    6: "u4",
    7: "f4",
    9: "f8",
    12: "i8",
    13: "u8",
}
# The numeric classes (the array flags' low byte) and the type each reads as
_CLASSES = {
    6: "f8",  # double
    7: "f4",  # single
    8: "i1",
    9: "u1",
    10: "i2",
    11: "u2",
    12: "i4",
    13: "u4",
    14: "i8",
    15: "u8",
}
_COMPLEX, _LOGICAL = 0x0800, 0x0200

# One variable holds at most this many values: a normal map at imageio.MAX_PIXELS (250 MP) times
# three. A damaged or hostile header can declare 2**31 x 2**31 values; refused before any
# allocation.
MAX_VALUES = 750_000_000

# How much of each variable is read (inflated) to list it: flags, dimensions and a name take a
# few dozen bytes in files MATLAB writes. The variable read in full may have a longer header.
_SCAN_BYTES = 512
_HEAD_BYTES = 4096


def _mat_tag(buf: bytes, pos: int, order: str) -> tuple[int, int, int, int]:
    """(type, size, data start, next element) of the element tag at ``pos``; the small format
    packs size and type into one word and the data into the next four bytes."""
    kind, size = struct.unpack(order + "II", buf[pos : pos + 8])
    if kind >> 16:
        return kind & 0xFFFF, kind >> 16, pos + 4, pos + 8
    return kind, size, pos + 8, pos + 8 + size + (-size % 8)


@dataclass(frozen=True)
class _MatrixHeader:
    """The sub-elements of a miMATRIX element before its values."""

    name: str
    dims: tuple[int, ...]
    flags: int  # class in the low byte, then the complex / global / logical bits
    data: int  # offset of the real part's tag from the start of the miMATRIX tag


def _matrix_header(buf: bytes, order: str) -> _MatrixHeader:
    """Flags, dimensions and name of the miMATRIX element at the start of ``buf``; ValueError
    (or struct.error) where they are damaged or cut off."""
    kind, _size, pos, _next = _mat_tag(buf, 0, order)
    if kind != _MI_MATRIX:
        raise ValueError("not a matrix element")
    kind, size, start, nxt = _mat_tag(buf, pos, order)  # array flags
    if kind != _MI_UINT32 or size < 4:
        raise ValueError("damaged array flags")
    (flags,) = struct.unpack(order + "I", buf[start : start + 4])
    kind, size, start, nxt = _mat_tag(buf, nxt, order)
    if kind != _MI_INT32 or size % 4:
        raise ValueError("damaged dimensions")
    dims = struct.unpack(order + f"{size // 4}i", buf[start : start + size])
    kind, size, start, nxt = _mat_tag(buf, nxt, order)
    name = buf[start : start + size].decode("latin-1") if kind == _MI_INT8 else ""
    return _MatrixHeader(name, tuple(int(d) for d in dims), flags, nxt)


def _inflate_head(f: BinaryIO, size: int, want: int) -> bytes:
    """The first ``want`` bytes of a zlib stream of ``size`` bytes at ``f``'s position (the
    decompressor is told the most it may return: a bomb stays a few hundred bytes here)."""
    inflater = zlib.decompressobj()
    out = b""
    left = size
    while len(out) < want and left > 0:
        chunk = f.read(min(left, 4096))
        if not chunk:
            break
        left -= len(chunk)
        try:
            out += inflater.decompress(chunk, want - len(out))
        except zlib.error as exc:
            raise ValueError(f"damaged compressed element ({exc})") from exc
    return out


@dataclass(frozen=True)
class _Variable:
    """Where one variable's element lies in the file, and its header."""

    kind: int  # _MI_MATRIX or _MI_COMPRESSED
    tag: int  # file offset of the element's tag
    size: int  # the bytes its tag declares
    header: _MatrixHeader


def _byte_order(f: BinaryIO) -> str | None:
    """``<`` or ``>`` for a level-5 file (``f`` left after its 128-byte header), else None."""
    head = f.read(128)
    if len(head) < 128 or head[126:128] not in (b"IM", b"MI"):
        return None
    order = "<" if head[126:128] == b"IM" else ">"
    (version,) = struct.unpack(order + "H", head[124:126])
    return order if version == 0x0100 else None


def _variables(f: BinaryIO, order: str, path: Path) -> Iterator[_Variable]:
    """Every variable's element, in file order, read as far as its header."""
    pos = 128
    size_total = os.fstat(f.fileno()).st_size
    count = 0
    while pos + 8 <= size_total:
        f.seek(pos)
        tag = f.read(8)
        kind, size, start, nxt = _mat_tag(tag + b"\0" * 8, 0, order)
        start, nxt = pos + start, pos + nxt
        if kind not in (_MI_COMPRESSED, _MI_MATRIX):
            pos = nxt
            continue
        if count == _MAT_MAX_VARIABLES:  # stopping short would hide the later ones
            raise InputError(f"more than {_MAT_MAX_VARIABLES:,} variables: refusing it", path)
        try:
            if kind == _MI_COMPRESSED:
                nxt = start + size  # compressed elements are not padded
                body = _inflate_head(f, size, _SCAN_BYTES)
            else:
                body = tag + f.read(min(size, _SCAN_BYTES))
            header = _matrix_header(body, order)
        except (ValueError, struct.error) as exc:
            raise InputError(f"damaged .mat file ({first_line(exc)})", path) from exc
        yield _Variable(kind, pos, size, header)
        count += 1
        pos = nxt


# The variable DiLiGenT (and msfnet's own writers) keep ground-truth normals in
NORMALS_VARIABLE = "Normal_gt"


def normals_variable(shapes: Mapping[str, object]) -> str | None:
    """The variable of a .mat file that holds ground-truth normals: ``Normal_gt``, else the
    first variable in file order; None where there is none. Names that are empty or start with
    "_" are skipped: they are not variables to loadmat (an unnamed element, such as MATLAB's
    subsystem data, becomes ``__function_workspace__``), so a file whose first element is one
    of them has its second element's shape checked and its second element read.

    ``shapes`` is keyed by name in file order (:attr:`MatDirectory.shapes`, or what
    ``scipy.io.loadmat`` returns)."""
    names = [k for k in shapes if k and not k.startswith("_")]
    if not names:
        return None
    return NORMALS_VARIABLE if NORMALS_VARIABLE in names else names[0]


def _stamp(f: BinaryIO) -> tuple[int, int, int, int]:
    st = os.fstat(f.fileno())
    return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns


@dataclass(frozen=True)
class MatDirectory:
    """A level-5 .mat file's variables as one parse of their element headers found them.

    Passed from a header check to the read that follows, so that the file is parsed once. The
    file is not held open: :meth:`reopen` opens it again and refuses it where it is no longer
    the file that was parsed (another inode, size or modification time: an atomic writer's
    replacement or an edit in place). Refused, not parsed again: what a caller checked
    (sizes, shapes) was this parse, and a new one would reach the read unchecked."""

    path: Path
    order: str  # "<" or ">"
    variables: tuple[_Variable, ...]
    stamp: tuple[int, int, int, int]  # (device, inode, size, mtime ns) before the parse

    @property
    def shapes(self) -> dict[str, tuple[int, ...]]:
        """Every variable's name and dimensions, in file order (a name that occurs twice: its
        first place, its last dimensions, as loadmat keeps it)."""
        return {v.header.name: v.header.dims for v in self.variables}

    @property
    def normals(self) -> str | None:
        """The variable that holds ground-truth normals (:func:`normals_variable`)."""
        return normals_variable(self.shapes)

    @property
    def normals_shape(self) -> tuple[int, ...] | None:
        """The dimensions of :attr:`normals`; None where the file has no variable."""
        key = self.normals
        return None if key is None else self.shapes[key]

    @contextmanager
    def reopen(self) -> Iterator[BinaryIO]:
        """The parsed file, open for reading (binary); InputError where the path now names
        another file or the file changed. Read through this handle (``scipy.io.loadmat``
        takes it too), not by name: the name may be replaced again after the check."""
        with open(self.path, "rb") as f:
            if _stamp(f) != self.stamp:
                raise InputError(
                    "the file changed after its headers were read (replaced or written to "
                    "meanwhile): run again once it is complete",
                    self.path,
                )
            yield f

    def array(self, name: str) -> np.ndarray | None:
        """Variable ``name``, with the shape and values ``scipy.io.loadmat(path)[name]`` gives,
        in the dtype of its MATLAB class (a double array stored as miUINT8 comes back float64,
        as ``loadmat(..., mat_dtype=True)`` returns it) and native byte order; read from this
        parse (InputError where the file changed since: :meth:`reopen`).

        Only full, real, numeric arrays (double, single, int8 ... uint64) are read; None for
        anything else (sparse, complex, logical, char, cell, struct, a name the file lacks),
        for callers to fall back to ``scipy.io.loadmat``. Where a name occurs twice the last
        one counts, as in loadmat. InputError for a damaged file: a size beyond the file or
        the data, values of no number type (loadmat can crash on those), or more than
        :data:`MAX_VALUES` values."""
        with self.reopen() as f:
            found = None
            for variable in self.variables:
                if variable.header.name == name:
                    found = variable  # the last one counts, as in loadmat
            if found is None:
                return None
            try:
                return _read_values(f, found, self.order, self.path)
            except (ValueError, struct.error) as exc:
                raise InputError(f"damaged .mat file ({first_line(exc)})", self.path) from exc


def mat_directory(path: str | Path) -> MatDirectory | None:
    """Every variable's element header of a MATLAB v5 .mat file, parsed once: a compressed
    element is inflated only as far as its header (a few hundred bytes), never its data. None
    for files that are not v5 (v7.3 is HDF5, which loaders refuse); InputError for a damaged
    one or one of more than 4,096 variables."""
    path = Path(path)
    with open(path, "rb") as f:
        stamp = _stamp(f)  # before the parse: a change during it shows at the next read
        order = _byte_order(f)
        if order is None:
            return None
        return MatDirectory(path, order, tuple(_variables(f, order, path)), stamp)


def not_v5(head: bytes) -> str:
    """What a file that :func:`mat_directory` does not take (not level 5) is, from its first
    128 bytes: a phrase for the message that refuses it ("a MATLAB v4 file", ...)."""
    if len(head) >= 128 and head[126:128] in (b"IM", b"MI"):
        order = "<" if head[126:128] == b"IM" else ">"
        (version,) = struct.unpack(order + "H", head[124:126])
        if version == 0x0200:
            return "a MATLAB v7.3 file (HDF5)"
        return f"a .mat file of unknown version {version:#06x}"
    if len(head) >= 20:
        # A level-4 file starts straight with a variable's header of five int32 words, the
        # first the type code MOPT (machine 0-4, O always 0, precision 0-5, matrix type 0-2)
        # in either byte order: what loadmat looks at to tell v4 from v5.
        for order in "<>":
            (mopt,) = struct.unpack(order + "i", head[:4])
            digits = (mopt // 100 % 10, mopt // 10 % 10, mopt % 10)  # O, P, T
            if 0 <= mopt < 5000 and digits[0] == 0 and digits[1] <= 5 and digits[2] <= 2:
                return "a MATLAB v4 file"
    # a noun phrase like the others: the caller adds "not a MATLAB v5 .mat file" itself
    return "a file of another format" if head else "an empty file"


def _read_values(f: BinaryIO, variable: _Variable, order: str, path: Path) -> np.ndarray | None:
    header = variable.header
    flags = header.flags
    if flags & (_COMPLEX | _LOGICAL) or flags & 0xFF not in _CLASSES:
        return None
    if header.data + 8 > _HEAD_BYTES:  # thousands of dimensions or a long name: not ours
        return None
    if any(d < 0 for d in header.dims):
        raise ValueError(f"negative dimension in {header.dims}")
    count = 1
    for d in header.dims:  # Python ints: no overflow, checked as they grow
        count *= d
        if count > MAX_VALUES:
            raise InputError(
                f"variable {header.name!r} is {'x'.join(map(str, header.dims))}, more than "
                f"{MAX_VALUES:,} values: refusing to read it",
                path,
            )
    start = variable.tag + 8
    if start + variable.size > os.fstat(f.fileno()).st_size:
        raise ValueError(
            f"variable {header.name!r} declares {variable.size:,} bytes, past the file's end"
        )
    if variable.kind == _MI_COMPRESSED:
        f.seek(start)
        stream: _Stream = _Inflated(f.read(variable.size))
    else:  # the plain element, from its tag (the offsets in the header count from there)
        f.seek(variable.tag)
        stream = _Plain(f, variable.size + 8)
    head = stream.read(header.data + 8)
    if len(head) < header.data + 8:
        raise ValueError(f"variable {header.name!r} ends before its values")
    _kind, matrix_size, _start, _next = _mat_tag(head, 0, order)
    kind, size, data, nxt = _mat_tag(head, header.data, order)
    stored = _STORED.get(kind)
    if stored is None:  # a numeric class holds numbers: damage, and loadmat can crash on it
        raise ValueError(f"variable {header.name!r}: values of element type {kind}, no number")
    small = nxt - data == 4  # the small format: the values sit in the tag's second word
    itemsize = int(stored[1])
    if size != count * itemsize or (small and size > 4) or data + size > 8 + matrix_size:
        raise ValueError(
            f"variable {header.name!r}: {size:,} bytes of values for "
            f"{'x'.join(map(str, header.dims))} numbers of {itemsize} bytes"
        )
    if small:
        raw = head[-4:][:size]
    else:
        raw = stream.read(size)
        if len(raw) != size:
            raise ValueError(
                f"variable {header.name!r} is cut off ({len(raw):,} of {size:,} bytes)"
            )
    if not stream.finish():
        return None
    values = np.frombuffer(raw, np.dtype(order + stored))
    # astype copies (the result is writable) and turns the stored type into the class's, in
    # native byte order; MATLAB's column-major order is a Fortran-order reshape (no copy)
    wanted = np.dtype(_CLASSES[flags & 0xFF])
    return values.astype(wanted).reshape(header.dims, order="F")


class _Stream:
    """The bytes of one miMATRIX element, from its tag on."""

    def read(self, n: int) -> bytes:
        raise NotImplementedError

    def finish(self) -> bool:
        """Whether the element ends as a numeric array does after its values (a plain one:
        nothing to check)."""
        return True


class _Plain(_Stream):
    def __init__(self, f: BinaryIO, size: int) -> None:
        self._f, self._left = f, size

    def read(self, n: int) -> bytes:
        data = self._f.read(min(n, self._left))
        self._left -= len(data)
        return data


class _Inflated(_Stream):
    """A miCOMPRESSED element's zlib stream, inflated on demand: no call returns more than it
    was asked for (``max_length``), so a bomb costs no memory."""

    def __init__(self, compressed: bytes) -> None:
        self._z = zlib.decompressobj()
        self._tail = compressed

    def read(self, n: int) -> bytes:
        parts: list[bytes] = []
        got = 0
        while got < n and not self._z.eof:
            part = self._inflate(n - got)
            if not part:  # the input is spent (a cut-off stream)
                break
            parts.append(part)
            got += len(part)
        return parts[0] if len(parts) == 1 else b"".join(parts)

    def finish(self) -> bool:
        # Inflate the little that follows the values (padding) to the stream's end, where zlib
        # checks its Adler-32 sum: damaged bytes that still inflate are caught (as loadmat's
        # verify_compressed_data_integrity does). More than padding: not a plain numeric
        # array after all, left to loadmat.
        extra = 0
        while not self._z.eof:
            part = self._inflate(64)
            if not part:
                raise ValueError("compressed variable is cut off")
            extra += len(part)
            if extra >= 64:
                return False
        return True

    def _inflate(self, most: int) -> bytes:
        try:
            part = self._z.decompress(self._tail, most)
        except zlib.error as exc:
            raise ValueError(f"damaged compressed variable ({exc})") from exc
        self._tail = self._z.unconsumed_tail
        return part
