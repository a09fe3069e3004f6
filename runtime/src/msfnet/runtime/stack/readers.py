"""Small stack files: light directions / intensities (txt or json) and ground-truth normals."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np

from msfnet.common.errors import InputError, first_line
from msfnet.common.imageio import MAX_PIXELS, array_shape, check_same_size, npy_layout, read_image
from msfnet.common.matfile import MatDirectory, mat_directory, normals_variable, not_v5

# A light file lists one row per light. Real rigs have tens to a few hundred lights; the bounds
# refuse a wrong file (a point cloud, a log) at once instead of parsing it for minutes.
MAX_LIGHTS = 10_000
MAX_VECTOR_FILE_BYTES = 4 * 2**20  # 10,000 rows of three long numbers, pretty-printed, fit

# The names a JSON light file may give its rows: an object's other keys are refused, never
# guessed at (a "positions_mm" list is no directions).
JSON_KEYS = {
    "light directions": ("light_directions", "directions", "lights"),
    "light intensities": ("light_intensities", "intensities"),
}
_ALL_KEYS = tuple(k for keys in JSON_KEYS.values() for k in keys)

# A number as people write them in text files; float() also takes "0_5" (as 5.0), "1_000" and
# non-ASCII digits, which no light file means.
_NUMBER = re.compile(
    r"[+-]?(?:(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?|nan|inf|infinity)", re.IGNORECASE | re.ASCII
)


def _check_small_file(path: Path, what: str) -> None:
    if not path.exists():
        raise InputError(f"{what} file not found", path)
    if not path.is_file():
        raise InputError(f"{what}: not a regular file", path)
    size = path.stat().st_size
    if size > MAX_VECTOR_FILE_BYTES:
        raise InputError(
            f"{what} file is {size / 2**20:.1f} MB, more than {MAX_LIGHTS:,} lights take "
            f"({MAX_VECTOR_FILE_BYTES / 2**20:.0f} MB at most): not a light file?",
            path,
        )


def _too_many(count: int, what: str, path: Path) -> None:
    if count > MAX_LIGHTS:
        raise InputError(
            f"{what}: {count:,} rows, more than the {MAX_LIGHTS:,} lights msfnet accepts: "
            "not a light file?",
            path,
        )


def _json_rows(data: object, what: str, path: Path) -> list[object]:
    """The rows of a JSON light file: a bare list, or the list under one of this kind's
    names (:data:`JSON_KEYS`) in an object that has no key of another meaning."""
    if isinstance(data, dict):
        unknown = sorted(str(k) for k in data if k not in _ALL_KEYS)
        names = JSON_KEYS.get(what, ())
        if unknown:
            raise InputError(
                f"{what}: unknown key {unknown[0]!r} in the JSON object (a light file names "
                f"its rows {', '.join(repr(k) for k in _ALL_KEYS)})",
                path,
            )
        present = [k for k in names if k in data]
        if not present:
            raise InputError(
                f"{what}: the JSON object has no {' or '.join(repr(k) for k in names)} key "
                f"(it has {', '.join(repr(k) for k in data) or 'none'})",
                path,
            )
        if len(present) > 1:
            raise InputError(
                f"{what}: the JSON object has both {present[0]!r} and {present[1]!r}; give one",
                path,
            )
        data = data[present[0]]
    if not isinstance(data, list):
        raise InputError(
            f"{what}: expected a JSON list of [x, y, z] rows (or an object holding one under "
            f"{' or '.join(repr(k) for k in JSON_KEYS.get(what, ()))})",
            path,
        )
    _too_many(len(data), what, path)
    for i, row in enumerate(data):
        values = row if isinstance(row, list) else [row]
        for v in values:
            # bool is an int to Python; a quoted "0.5" is text: neither is a number here
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise InputError(f"{what}: row {i + 1} holds {v!r}, not a number", path)
    return data


def _text_rows(text: str, what: str, path: Path) -> list[list[float]]:
    rows = [r.replace(",", " ").split() for r in text.splitlines()]
    rows = [r for r in rows if r and not r[0].startswith("#")]
    if rows and len(rows[0]) == 1 and len(rows) > 1 and len(rows[1]) != 1:
        count = rows[0][0]  # a leading count line ("12")
        rows = rows[1:]
        if not count.isdigit():  # "3.7" alone on the first line is no count of rows
            raise InputError(
                f"cannot parse {what}: the first line holds one number, {count[:40]!r}; a "
                "count line must be a whole number, and rows need 3 numbers",
                path,
            )
        if int(count) != len(rows):
            raise InputError(
                f"{what}: the first line says {count} rows but {len(rows)} follow", path
            )
    _too_many(len(rows), what, path)  # before any number is converted
    widths = {len(r) for r in rows}
    if len(widths) > 1:
        raise InputError(
            f"cannot parse {what}: rows have {sorted(widths)} numbers (expected 3 per row)", path
        )
    out = []
    for i, row in enumerate(rows):
        for token in row:
            if not _NUMBER.fullmatch(token):
                raise InputError(
                    f"cannot parse {what}: row {i + 1}: {token[:40]!r}"
                    f"{'...' if len(token) > 40 else ''} is not a number",
                    path,
                )
        out.append([float(v) for v in row])
    return out


def read_vectors(path: Path, what: str) -> np.ndarray:
    """Rows of 3 numbers from txt (optional leading count line) or JSON (a list of rows, or an
    object holding one under a name of :data:`JSON_KEYS`): the one reader of light files.

    ``what``: "light directions" or "light intensities" (the JSON names and the messages)."""
    _check_small_file(path, what)
    # utf-8-sig: Windows editors ("UTF-8" in Notepad) start the file with a byte-order mark
    try:
        text = path.read_text(encoding="utf-8-sig")
        if path.suffix.lower() == ".json":
            arr = np.asarray(_json_rows(json.loads(text), what, path), dtype=np.float64)
        else:
            arr = np.asarray(_text_rows(text, what, path), dtype=np.float64)
    except (ValueError, TypeError, UnicodeDecodeError, RecursionError) as exc:
        # json.JSONDecodeError is a ValueError; RecursionError: absurdly nested JSON
        raise InputError(f"cannot parse {what}: {first_line(exc)}", path) from exc
    if arr.size == 0:
        raise InputError(f"{what} file holds no rows", path)
    if arr.ndim != 2 or arr.shape[1] != 3:
        cols = f"{arr.shape[1]} numbers per row" if arr.ndim == 2 else f"shape {arr.shape}"
        raise InputError(f"{what} must have 3 numbers per row, got {cols}", path)
    if not np.all(np.isfinite(arr)):
        rows_bad = np.flatnonzero(~np.all(np.isfinite(arr), axis=1)) + 1
        raise InputError(
            f"{what} contain NaN or infinite values (row(s) {rows_bad.tolist()[:5]})", path
        )
    if np.any(np.abs(arr) > np.finfo(np.float32).max):
        raise InputError(f"{what}: values beyond the float32 range", path)
    return arr.astype(np.float32)


def companion_intensities(lights: Path) -> Path | None:
    """``lights`` itself when it is a JSON object that also holds the intensities (under a
    name of :data:`JSON_KEYS`), else None: such a file's intensities are used, never dropped.
    Damage is left to :func:`read_vectors` to report."""
    if lights.suffix.lower() != ".json":
        return None
    try:
        _check_small_file(lights, "light directions")
        data = json.loads(lights.read_text(encoding="utf-8-sig"))
    except (InputError, OSError, ValueError, UnicodeDecodeError, RecursionError):
        return None
    named = JSON_KEYS["light intensities"]
    return lights if isinstance(data, dict) and any(k in data for k in named) else None


def unit_normals(n: np.ndarray) -> np.ndarray:
    """Normals scaled to unit length; zero, tiny or non-finite vectors become 0 (not scored)."""
    n = np.asarray(n)
    # a copy, scaled in place (one full-size array): float32 where that holds the input
    # exactly (float32, float16, small ints), float64 otherwise (float64, int32/64, float128)
    wide = np.result_type(n.dtype, np.float32) != np.float32
    out = np.array(n, dtype=np.float64 if wide else np.float32)
    bad = ~np.isfinite(out)
    if bad.any():
        out[bad] = 0.0
    # lengths summed in float64 (no overflow of huge float32 values), one per pixel: no
    # float64 copy of the whole map
    length = np.sqrt(np.einsum("...i,...i->...", out, out, dtype=np.float64))
    scale = np.divide(1.0, length, out=np.zeros_like(length), where=length > 1e-6)
    out *= scale[..., None].astype(out.dtype, copy=False)
    return out.astype(np.float32, copy=False)


def check_gt_header(path: Path, shape: tuple[int, int]) -> MatDirectory | None:
    """Ground truth compared with the stored image size from its header, before it is read
    (a 248 MP normal map or a compressed 10 GB .mat variable is refused unopened). Returns a
    v5 .mat file's parsed headers, for :func:`read_normals` to read from; None otherwise.

    An early refusal only: :func:`read_normals` given the same ``shape`` checks again the file
    it reads (a .npy or image header from its own handle; a .mat file must still be the one
    parsed here)."""
    if path.suffix.lower() == ".mat":  # the variable read_normals reads (normals_variable)
        mat = mat_directory(path)
        if mat is not None:
            _check_mat_header(mat, shape)
        return mat
    found = array_shape(path)
    if found is not None:
        check_same_size(found, shape, "ground truth", path)
    return None


def _check_mat_header(mat: MatDirectory, shape: tuple[int, int]) -> None:
    found = mat.normals_shape
    if found is not None:
        check_same_size(found, shape, "ground truth", mat.path)
    # loadmat (the fallback) reads every variable, not only the normals
    shapes = mat.shapes
    total = sum(int(np.prod(d, dtype=np.int64)) for d in shapes.values())
    h, w = shape
    if total > h * w * 3 + 2**20:
        raise InputError(
            f"holds {total:,} values in {len(shapes)} variable(s), far more than "
            f"the ground truth of {w}x{h} images: refusing to read it",
            mat.path,
        )


def _mat_normals(path: Path, mat: MatDirectory | None) -> np.ndarray:
    """A .mat file's normals variable (:func:`normals_variable`). Read by
    :meth:`MatDirectory.array` (a plain numeric array, the usual case: no SciPy import, ~0.6 s);
    anything else by SciPy, from the handle of the file whose headers were checked. ``mat``:
    the file's headers where already parsed."""
    if mat is None:
        mat = mat_directory(path)
    if mat is None:
        # Level 4 and v7.3 are refused, not handed to loadmat unchecked: DiLiGenT's and
        # msfnet's files are level 5, a v4 file never holds an H x W x 3 map, and v7.3 is
        # HDF5, which loadmat cannot read.
        with open(path, "rb") as f:
            what = not_v5(f.read(128))
        raise InputError(
            f"ground-truth normals: {what}, not a MATLAB v5 .mat file (save it with "
            "MATLAB's -v7 or -v6, or scipy.io.savemat's default)",
            path,
        )
    key = mat.normals
    found = None
    if key is not None:
        dims = mat.shapes[key]
        # refused from its header: what is not H x W x 3 never reaches loadmat, which a damaged
        # file can crash (a segfault, not an exception)
        if len(dims) != 3 or dims[2] != 3:
            raise InputError(f"ground-truth normals must be H x W x 3, got {dims}", path)
        found = mat.array(key)
    if found is not None:
        return found
    import scipy.io

    with mat.reopen() as f:  # the checked file itself: a replacement by name since is refused
        variables = scipy.io.loadmat(f)
    key = normals_variable(variables)
    if key is None:
        raise InputError("cannot read ground-truth normals (the file holds no variable)", path)
    return np.asarray(variables[key])


def _npy_normals(path: Path, shape: tuple[int, int] | None) -> np.ndarray:
    """A .npy file's array, its header checked and its values read through one handle (a file
    replaced by name in between is not read), never unpickled."""
    with open(path, "rb") as f:
        try:
            dims, fortran, dtype = npy_layout(f)  # the header's declared length checked first
        except ValueError as exc:
            raise InputError(f"damaged .npy header ({first_line(exc)})", path) from exc
        if dtype.hasobject or dtype.kind not in "biuf":  # objects would need unpickling
            raise InputError(
                f"ground-truth normals must be numbers, got a .npy array of dtype {dtype}", path
            )
        if len(dims) != 3 or dims[2] != 3:
            raise InputError(f"ground-truth normals must be H x W x 3, got {dims}", path)
        if shape is not None:
            check_same_size(dims, shape, "ground truth", path)
        if dims[0] * dims[1] > MAX_PIXELS:
            raise InputError(
                f"ground truth is {dims[1]}x{dims[0]}, above the {MAX_PIXELS / 1e6:.0f} MP "
                "limit: refusing to read it",
                path,
            )
        count = dims[0] * dims[1] * 3
        want = count * dtype.itemsize
        left = os.fstat(f.fileno()).st_size - f.tell()
        if left < want:  # known before reading (or allocating): no partial array
            raise InputError(
                f"truncated .npy file ({left:,} of the {want:,} bytes its header declares)", path
            )
        values = np.empty(count, dtype)
        got = f.readinto(values.view(np.uint8).data)
        if got != want:  # shrunk while read
            raise InputError(f"truncated .npy file ({got:,} of {want:,} bytes read)", path)
    return values.reshape(dims, order="F" if fortran else "C")


def read_normals(
    path: Path, mat: MatDirectory | None = None, *, shape: tuple[int, int] | None = None
) -> np.ndarray:
    """Ground-truth normals (H, W, 3) from .mat (key Normal_gt; MATLAB v5 only), .npy or an
    8/16-bit PNG. ``mat``: a .mat file's headers where a header check parsed them already
    (:func:`check_gt_header`), so that they are not parsed again. ``shape``: the (H, W) they
    must have, checked from the header of the file read, before its values are.

    A file's header is checked and its values read through one handle (a .mat file from a
    given parse: refused where it is no longer the file parsed)."""
    if mat is not None and mat.path != path:
        raise ValueError(f"headers of {mat.path} given to read {path}")
    suffix = path.suffix.lower()
    try:
        if suffix == ".mat":
            if mat is None:
                mat = mat_directory(path)
            if mat is not None and shape is not None:
                _check_mat_header(mat, shape)
            n = np.asarray(_mat_normals(path, mat), dtype=np.float32)
        elif suffix == ".npy":
            n = _npy_normals(path, shape).astype(np.float32)
        else:
            img = read_image(path, shape, "ground truth")
            scale = 65535.0 if img.dtype == np.uint16 else 255.0
            n = img.astype(np.float32) / scale * 2.0 - 1.0
            n[np.all(img == 0, axis=-1)] = 0.0
    except InputError:
        raise
    except Exception as exc:
        raise InputError(f"cannot read ground-truth normals ({first_line(exc)})", path) from exc
    if n.ndim != 3 or n.shape[2] != 3:
        raise InputError(f"ground-truth normals must be H x W x 3, got {n.shape}", path)
    if shape is not None:
        check_same_size(n.shape, shape, "ground truth", path)
    return unit_normals(n)
