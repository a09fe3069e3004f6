"""Result files: normals.npy / normals.png, profile.json, metrics.json and error.png.

normals.npy: H x W x 3 float32, camera frame, zeros outside the mask; normals.png: 16-bit RGB,
(n + 1) / 2, zeros outside the mask; with ground truth, metrics.json (NormalMetrics) and
error.png (angular error picture with a colour bar, automatic range, blank where not scored).
Written all together through :func:`msfnet.common.files.staged_folder`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

import numpy as np

from msfnet.common.files import json_text, staged_folder
from msfnet.common.imageio import encode_png
from msfnet.runtime.evaluate.metrics import NormalMetrics
from msfnet.runtime.results.maps import InspectionMaps
from msfnet.runtime.results.provenance import Provenance
from msfnet.runtime.stack import Stack


class Result(Protocol):
    """What the files are written from (``msfnet.Result`` is one): the writer depends on the
    data, not on the Model API that produced it."""

    stack: Stack
    normals: np.ndarray
    metrics: NormalMetrics | None
    error_deg: np.ndarray | None
    maps: InspectionMaps | None

    def profile(self) -> dict[str, object]: ...


def normals_png(normals: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W, 3) unit normals -> 16-bit RGB (n + 1) / 2, zeros outside the mask."""
    # one float32 work array, changed in place (no float64 H x W x 3 temporaries)
    n = np.nan_to_num(np.clip(np.asarray(normals, np.float32), -1, 1), copy=False)
    n += 1.0
    n *= 0.5 * 65535.0
    img = np.rint(n, out=n).astype(np.uint16)
    img[~mask] = 0
    return img


def write_rgb_png(path: Path, rgb: np.ndarray) -> None:
    """Into a staging folder (callers make the folder atomic)."""
    encode_png(path, rgb)


def fill_result_folder(folder: Path, result: Result, report: bool = True) -> None:
    """Write a result's files into an (empty, staging) folder: the normals as data and as a
    picture with a colour-convention sphere, metrics and an error picture with a colour bar
    (automatic range) when there is ground truth, the profile, and the inspection maps with
    report.html when they were computed."""
    from msfnet.runtime.results.maps import pictures, write_maps

    mask = result.stack.mask
    profile = result.profile()
    if "provenance" not in profile:  # where it came from, in profile.json and report.html
        src = result.stack.source or result.stack.name
        profile["provenance"] = Provenance.of(src, profile).as_dict()
    np.save(folder / "normals.npy", np.ascontiguousarray(result.normals, np.float32))
    write_rgb_png(folder / "normals.png", normals_png(result.normals, mask))
    # the figures need Pillow (their text); without it everything else is written
    draw = pictures.can_draw()
    rendered: dict[str, bytes] = {}
    if draw:
        rendered["normals"] = pictures.png_bytes(pictures.normals_picture(result.normals, mask))
        (folder / "normals_view.png").write_bytes(rendered["normals"])
    if result.metrics is not None and result.error_deg is not None:
        metrics: dict[str, object] = dict(result.metrics.as_dict())
        if draw:
            vmax = pictures.error_range(result.error_deg, mask)
            metrics["error_png_max_deg"] = vmax
            rendered["error"] = pictures.png_bytes(
                pictures.error_picture(result.error_deg, mask, vmax=vmax)
            )
            (folder / "error.png").write_bytes(rendered["error"])
        (folder / "metrics.json").write_text(json_text(metrics))
    (folder / "profile.json").write_text(json_text(profile))
    if result.maps is not None:
        images = result.stack.images if result.stack.images.shape[-1] == 3 else None
        # the report shows the same two pictures: drawn once (a map's mask equals the stack's)
        write_maps(
            folder,
            result.maps,
            images=images,
            error_deg=result.error_deg,
            profile=profile,
            report=report,
            title=f"msfnet: {result.stack.name}",
            rendered=rendered,
        )


def write_result(
    result: Result,
    outdir: Path,
    *,
    overwrite: bool = False,
    report: bool = True,
    write_mask: bool = False,
) -> list[Path]:
    """Write every result file (``write_mask``: mask.png too), or none of them. Returns the
    final paths."""
    with staged_folder(outdir, overwrite=overwrite) as tmp:
        fill_result_folder(tmp, result, report=report)
        if write_mask:
            write_rgb_png(tmp / "mask.png", result.stack.mask.astype(np.uint8) * 255)
        names = sorted(p.name for p in tmp.iterdir())
    return [outdir / n for n in names]


__all__ = ["fill_result_folder", "normals_png", "write_result", "write_rgb_png"]
