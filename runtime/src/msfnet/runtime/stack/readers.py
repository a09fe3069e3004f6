"""Small stack files: light directions / intensities (txt or json) and ground-truth normals."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from msfnet.common.errors import InputError, first_line
from msfnet.common.imageio import read_image

MAX_VECTOR_FILE_BYTES = 64 * 2**20  # a million lights is a few tens of MB of text


def _check_small_file(path: Path, what: str) -> None:
    if not path.exists():
        raise InputError(f"{what} file not found", path)
    if not path.is_file():
        raise InputError(f"{what}: not a regular file", path)
    if path.stat().st_size > MAX_VECTOR_FILE_BYTES:
        raise InputError(
            f"{what} file is {path.stat().st_size / 2**20:.0f} MB: not a list of numbers", path
        )


def read_vectors(path: Path, what: str) -> np.ndarray:
    """Rows of 3 numbers from txt (optional leading count line) or json (list or {key: list})."""
    _check_small_file(path, what)
    # utf-8-sig: Windows editors ("UTF-8" in Notepad) start the file with a byte-order mark
    try:
        text = path.read_text(encoding="utf-8-sig")
        if path.suffix.lower() == ".json":
            data = json.loads(text)
            if isinstance(data, dict):
                data = next((v for k, v in data.items() if isinstance(v, list)), None)
            if not isinstance(data, list):
                raise InputError(
                    f"{what}: expected a JSON list of [x, y, z] rows (or an object holding one)",
                    path,
                )
            arr = np.asarray(data, dtype=np.float64)
        else:
            rows = [r.replace(",", " ").split() for r in text.splitlines()]
            rows = [r for r in rows if r and not r[0].startswith("#")]
            if rows and len(rows[0]) == 1 and len(rows) > 1 and len(rows[1]) != 1:
                count = rows[0][0]  # a leading count line ("12")
                rows = rows[1:]
                if count.isdigit() and int(count) != len(rows):
                    raise InputError(
                        f"{what}: the first line says {count} rows but {len(rows)} follow", path
                    )
            widths = {len(r) for r in rows}
            if len(widths) > 1:
                raise InputError(
                    f"cannot parse {what}: rows have {sorted(widths)} numbers (expected 3 per row)",
                    path,
                )
            arr = np.asarray([[float(v) for v in r] for r in rows], dtype=np.float64)
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


def unit_normals(n: np.ndarray) -> np.ndarray:
    """Normals scaled to unit length; zero, tiny or non-finite vectors become 0 (not scored)."""
    n = np.where(np.isfinite(n), n, 0.0).astype(np.float64)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    return np.where(norm > 1e-6, n / np.maximum(norm, 1e-6), 0.0).astype(np.float32)


def read_normals(path: Path) -> np.ndarray:
    """Ground-truth normals (H, W, 3) from .mat (key Normal_gt), .npy or an 8/16-bit PNG."""
    suffix = path.suffix.lower()
    try:
        if suffix == ".mat":
            from scipy.io import loadmat

            mat = loadmat(str(path))
            keys = [k for k in mat if not k.startswith("_")]
            key = "Normal_gt" if "Normal_gt" in mat else keys[0]
            n = np.asarray(mat[key], dtype=np.float32)
        elif suffix == ".npy":
            n = np.load(path, allow_pickle=False).astype(np.float32)
        else:
            img = read_image(path)
            scale = 65535.0 if img.dtype == np.uint16 else 255.0
            n = img.astype(np.float32) / scale * 2.0 - 1.0
            n[np.all(img == 0, axis=-1)] = 0.0
    except InputError:
        raise
    except Exception as exc:
        raise InputError(f"cannot read ground-truth normals ({first_line(exc)})", path) from exc
    if n.ndim != 3 or n.shape[2] != 3:
        raise InputError(f"ground-truth normals must be H x W x 3, got {n.shape}", path)
    return unit_normals(n)
