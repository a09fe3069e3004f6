"""Inspection maps from estimated normals (torch-free): albedo, height, curvature, mesh, pictures
and a self-contained HTML report.

    from msfnet.runtime.results.maps import MapOptions, compute_maps, write_maps
    maps = compute_maps(images, lights, intensities, mask, normals, MapOptions(integration="bini"))
    files = write_maps(outdir, maps, images=images, error_deg=err, profile=profile)

Modules, one job each: ``albedo`` (least-squares RGB albedo), ``integrate`` (normals -> height:
Frankot-Chellappa, masked Poisson, discontinuity-aware BiNI-style), ``curvature`` (mean
curvature, shape index), ``mesh`` (PLY via plyfile), ``pictures`` (numpy, OpenCV, Pillow),
``report`` (report.html), ``api`` (this entry point). The names below are resolved on first
use, and SciPy and plyfile only when a map is computed or written: importing
msfnet (which names MapOptions) stays quick on an edge box that never asks for maps.
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from msfnet.runtime.results.maps.api import (
        MAP_NAMES,
        InspectionMaps,
        MapOptions,
        compute_maps,
        stack_maps,
        write_maps,
    )

__all__ = ["MAP_NAMES", "InspectionMaps", "MapOptions", "compute_maps", "stack_maps", "write_maps"]


def __getattr__(name: str) -> object:
    if name not in __all__:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(import_module(f"{__name__}.api"), name)
    globals()[name] = value  # resolved once
    return value
