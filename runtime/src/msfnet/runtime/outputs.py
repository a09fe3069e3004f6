"""Result files, written all-or-nothing: a hidden temporary folder beside OUTDIR, then a rename.

OUTDIR holds normals.npy (H x W x 3 float32, camera frame, zeros outside the mask), normals.png
(16-bit RGB, (n + 1) / 2, zeros outside the mask), profile.json and, when ground truth exists,
metrics.json and error.png (angular error colour map, 0..ERROR_PNG_MAX_DEG, black outside the mask).
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np

from .errors import InputError

ERROR_PNG_MAX_DEG = 45.0


def default_outdir(stack_name: str) -> Path:
    return Path("msf-out") / stack_name


def fresh_outdir(stack_name: str) -> Path:
    """``msf-out/<name>``, or ``<name>-2``, ``-3``... : the first that does not exist yet (the
    demo can be re-run without --overwrite and without touching earlier results)."""
    base = default_outdir(stack_name)
    candidates = (base.with_name(f"{base.name}-{i}") if i > 1 else base for i in range(1, 10**6))
    return next(p for p in candidates if not p.exists())


def _inside(path: Path, folder: Path) -> bool:
    try:
        path.resolve().relative_to(folder.resolve())
        return True
    except ValueError:
        return False


def check_outdir(outdir: Path, overwrite: bool, inputs: list[Path] | tuple[Path, ...] = ()
                 ) -> None:
    """Refuse (before any work) an existing non-empty OUTDIR without --overwrite, a file in its
    place, or an OUTDIR inside an input folder (inputs are never written to)."""
    for src in inputs:
        folder = src if src.is_dir() else src.parent
        if src.is_dir() and _inside(outdir, folder):
            raise InputError(f"output folder {outdir} is inside the input folder; choose another "
                             "-o OUTDIR (inputs are never written to)", folder)
        if src.is_file() and outdir.resolve() == folder.resolve():
            raise InputError("output folder is the input file's folder; choose another -o "
                             "OUTDIR", outdir)
    if outdir.exists() and not outdir.is_dir():
        raise InputError("output path exists and is not a folder", outdir)
    if outdir.is_dir() and any(outdir.iterdir()) and not overwrite:
        raise InputError("output folder exists and is not empty; pass --overwrite to replace it",
                         outdir)


def normals_png(normals: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W, 3) unit normals -> 16-bit RGB (n + 1) / 2, zeros outside the mask."""
    img = np.rint((np.clip(normals, -1, 1) + 1.0) * 0.5 * 65535.0).astype(np.uint16)
    img[~mask] = 0
    return img


def error_png(err_deg: np.ndarray, mask: np.ndarray, max_deg: float = ERROR_PNG_MAX_DEG
              ) -> np.ndarray:
    """(H, W) angular error -> 8-bit RGB colour map (jet, 0..max_deg), black outside the mask."""
    scaled = np.clip(err_deg / max_deg * 255.0, 0, 255).astype(np.uint8)
    bgr = cv2.applyColorMap(scaled, cv2.COLORMAP_JET)
    bgr[~mask] = 0
    return bgr[:, :, ::-1]


def write_rgb_png(path: Path, rgb: np.ndarray) -> None:
    arr = rgb[:, :, ::-1] if rgb.ndim == 3 else rgb
    if not cv2.imwrite(str(path), np.ascontiguousarray(arr)):
        raise InputError("cannot write image", path)


def write_json(path: Path, data: object) -> None:
    path.write_text(json.dumps(data, indent=2, sort_keys=False) + "\n")


def commit_folder(tmp: Path, outdir: Path, overwrite: bool) -> None:
    """Move a finished temporary folder into place; an old OUTDIR is removed only afterwards."""
    old = None
    if outdir.exists():
        if any(outdir.iterdir()) and not overwrite:
            raise InputError("output folder appeared while running; pass --overwrite", outdir)
        old = outdir.with_name(f".{outdir.name}.old-{tmp.name}")
        outdir.rename(old)
    tmp.rename(outdir)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def staging_folder(outdir: Path) -> Path:
    outdir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{outdir.name}.partial-", dir=outdir.parent))
    tmp.chmod(0o755)  # mkdtemp makes it owner-only; the result folder should look like mkdir's
    return tmp


def write_outputs(outdir: Path, normals: np.ndarray, mask: np.ndarray, *, profile: dict,
                  metrics: dict | None = None, error_deg: np.ndarray | None = None,
                  overwrite: bool = False) -> list[Path]:
    """Write every result file, or none of them. Returns the final paths."""
    outdir = Path(outdir)
    tmp = staging_folder(outdir)
    try:
        np.save(tmp / "normals.npy", np.ascontiguousarray(normals, np.float32))
        write_rgb_png(tmp / "normals.png", normals_png(normals, mask))
        if metrics is not None and error_deg is not None:
            write_json(tmp / "metrics.json", {**metrics, "error_png_max_deg": ERROR_PNG_MAX_DEG})
            write_rgb_png(tmp / "error.png", error_png(error_deg, mask))
        write_json(tmp / "profile.json", profile)
        names = sorted(p.name for p in tmp.iterdir())
        commit_folder(tmp, outdir, overwrite)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return [outdir / n for n in names]


__all__ = [
    "ERROR_PNG_MAX_DEG",
    "check_outdir",
    "commit_folder",
    "default_outdir",
    "error_png",
    "normals_png",
    "staging_folder",
    "write_json",
    "write_outputs",
    "write_rgb_png",
]
