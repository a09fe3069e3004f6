"""Small stack files: light directions / intensities (txt or json) and ground-truth normals."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..imageio import read_image


def read_vectors(path: Path, what: str) -> np.ndarray:
    """Rows of 3 numbers from txt (optional leading count line) or json (list or {key: list})."""
    if not path.is_file():
        raise InputError(f"{what} file not found", path)
    try:
        if path.suffix.lower() == ".json":
            data = json.loads(path.read_text())
            if isinstance(data, dict):
                data = next((v for k, v in data.items() if isinstance(v, list)), None)
            arr = np.asarray(data, dtype=np.float64)
        else:
            rows = [r.replace(",", " ").split() for r in path.read_text().splitlines()]
            rows = [r for r in rows if r and not r[0].startswith("#")]
            if rows and len(rows[0]) == 1 and len(rows) > 1:
                rows = rows[1:]  # a leading count line ("12")
            widths = {len(r) for r in rows}
            if len(widths) > 1:
                raise InputError(f"cannot parse {what}: rows have {sorted(widths)} numbers "
                                 "(expected 3 per row)", path)
            arr = np.asarray([[float(v) for v in r] for r in rows], dtype=np.float64)
    except (ValueError, TypeError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot parse {what}: {exc}", path) from exc
    if arr.ndim != 2 or arr.shape[1] != 3:
        cols = arr.shape[1] if arr.ndim == 2 else "no"
        raise InputError(f"{what} must have 3 numbers per row, got {cols} per row "
                         f"(shape {arr.shape})", path)
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{what} contain NaN or infinite values", path)
    return arr.astype(np.float32)


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
        raise InputError(f"cannot read ground-truth normals ({exc})", path) from exc
    if n.ndim != 3 or n.shape[2] != 3:
        raise InputError(f"ground-truth normals must be H x W x 3, got {n.shape}", path)
    n = np.where(np.isfinite(n), n, 0.0)
    norm = np.linalg.norm(n, axis=2, keepdims=True)
    return np.where(norm > 1e-6, n / np.maximum(norm, 1e-6), 0.0).astype(np.float32)
