"""Inspection maps from estimated normals (torch-free): albedo, height, curvature, mesh, pictures
and a self-contained HTML report.

    from msfnet.runtime.results.maps import MapOptions, compute_maps, write_maps
    maps = compute_maps(images, lights, intensities, mask, normals, MapOptions(method="bini"))
    files = write_maps(outdir, maps, images=images, error_deg=err, profile=profile)

Modules, one job each: ``albedo`` (least-squares RGB albedo), ``integrate`` (normals -> height:
Frankot-Chellappa, masked Poisson, discontinuity-aware BiNI-style), ``curvature`` (mean
curvature, shape index), ``mesh`` (PLY via plyfile), ``pictures`` (matplotlib, lazily),
``report`` (report.html), ``api`` (this entry point). Matplotlib and plyfile are imported only
when writing.
"""

from msfnet.runtime.results.maps.api import (
    MAP_NAMES,
    InspectionMaps,
    MapOptions,
    compute_maps,
    stack_maps,
    write_maps,
)
from msfnet.runtime.results.maps.integrate import METHODS, Intrinsics, integrate_normals

__all__ = [
    "MAP_NAMES",
    "METHODS",
    "InspectionMaps",
    "Intrinsics",
    "MapOptions",
    "compute_maps",
    "integrate_normals",
    "stack_maps",
    "write_maps",
]
