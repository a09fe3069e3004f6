"""A triangle mesh of the height map, written as binary PLY with the ``plyfile`` library.

One vertex per valid pixel (finite height inside the mask). Each 2 x 2 block of pixels gives
two triangles when all four are valid and one when three are, so the mesh follows the mask
border. Orthographic vertices are (col, -row, height) in pixels: x right, y up, z toward the
camera, the same frame as the normals, so ``normals`` can serve as vertex normals unchanged.
With intrinsics and a depth map the vertices are the back-projected points
(d (u - cx)/fx, -d (v - cy)/fy, -d) in that same frame (the camera at the origin looking down
-z). Triangles are wound counter-clockwise seen from the camera, so their face normals agree
with the vertex normals. ``max_jump`` drops triangles spanning a larger height difference (a
depth discontinuity) instead of bridging it with a wall of stretched triangles.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from msfnet.common.errors import InputError
from msfnet.common.files import write_atomic
from msfnet.runtime.results.maps.albedo import display_level
from msfnet.runtime.results.maps.integrate import Intrinsics


@dataclass
class Mesh:
    """vertices: (V, 3) float32; faces: (F, 3) int32 vertex indices; normals: (V, 3) float32 or
    None; colors: (V, 3) uint8 or None."""

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None


def albedo_colors(albedo: np.ndarray, valid: np.ndarray, percentile: float = 99.5) -> np.ndarray:
    """(H, W, 3) albedo -> (H, W, 3) uint8, scaled so the ``percentile`` of the valid pixels'
    largest channel maps to 255 (the absolute scale is in albedo.npy, not in the colours);
    black where the albedo is unknown (NaN)."""
    top = display_level(albedo, valid, percentile)
    scale = 255.0 / top if top > 0 else 0.0
    return np.clip(np.rint(np.nan_to_num(albedo) * scale), 0, 255).astype(np.uint8)


def height_mesh(
    height: np.ndarray,
    mask: np.ndarray,
    *,
    normals: np.ndarray | None = None,
    colors: np.ndarray | None = None,
    intrinsics: Intrinsics | None = None,
    depth: np.ndarray | None = None,
    max_jump: float | None = None,
) -> Mesh:
    """Triangulate an (H, W) height map over an (H, W) bool mask; see the module docstring.

    normals: (H, W, 3) vertex normals; colors: (H, W, 3) uint8 vertex colours; intrinsics with
    depth (H, W): back-project (perspective) instead of the orthographic pixel grid.
    """
    z = np.asarray(height, np.float64)
    m = np.asarray(mask, bool)
    if z.shape != m.shape:
        raise InputError(f"height is {z.shape} but the mask is {m.shape}")
    for name, arr in (("normals", normals), ("colors", colors)):
        if arr is not None and np.shape(arr) != (*m.shape, 3):
            raise InputError(f"{name} must be {(*m.shape, 3)}, got {np.shape(arr)}")
    valid = m & np.isfinite(z)
    h, w = m.shape
    index = np.full((h, w), -1, np.int64)
    index[valid] = np.arange(int(valid.sum()))
    rows, cols = np.nonzero(valid)
    if intrinsics is not None:
        if depth is None or np.shape(depth) != m.shape:
            raise InputError("a perspective mesh needs the depth map beside the intrinsics")
        dist = np.asarray(depth, np.float64)[valid]
        x = dist * (cols - intrinsics.cx) / intrinsics.fx
        y = -dist * (rows - intrinsics.cy) / intrinsics.fy
        verts = np.stack([x, y, -dist], axis=1)
    else:
        verts = np.stack([cols, -rows, z[valid]], axis=1).astype(np.float64)
    # corners of every 2 x 2 block: a top-left, b top-right, c bottom-left, d bottom-right
    a, b = index[:-1, :-1], index[:-1, 1:]
    c, d = index[1:, :-1], index[1:, 1:]
    tris = [
        # all four valid: (a, c, b) and (b, c, d), counter-clockwise seen from +z
        np.stack([a, c, b], -1)[(a >= 0) & (b >= 0) & (c >= 0) & (d >= 0)],
        np.stack([b, c, d], -1)[(a >= 0) & (b >= 0) & (c >= 0) & (d >= 0)],
        # exactly three valid: the one triangle they span
        np.stack([a, c, b], -1)[(a >= 0) & (b >= 0) & (c >= 0) & (d < 0)],
        np.stack([b, c, d], -1)[(a < 0) & (b >= 0) & (c >= 0) & (d >= 0)],
        np.stack([a, c, d], -1)[(a >= 0) & (b < 0) & (c >= 0) & (d >= 0)],
        np.stack([a, d, b], -1)[(a >= 0) & (b >= 0) & (c < 0) & (d >= 0)],
    ]
    faces = np.concatenate(tris, axis=0)
    if max_jump is not None and faces.size:
        zv = z[valid][faces]
        faces = faces[(zv.max(axis=1) - zv.min(axis=1)) <= max_jump]
    vn = None if normals is None else np.asarray(normals, np.float32)[valid]
    vc = None if colors is None else np.asarray(colors, np.uint8)[valid]
    return Mesh(verts.astype(np.float32), faces.astype(np.int32), vn, vc)


def write_ply(path: str | Path, mesh: Mesh) -> Path:
    """Write a binary little-endian PLY, atomically (all or nothing): the header from plyfile,
    the data as whole arrays."""
    from plyfile import PlyData, PlyElement

    groups = [
        (("x", "y", "z"), "<f4", mesh.vertices),
        (("nx", "ny", "nz"), "<f4", mesh.normals),
        (("red", "green", "blue"), "u1", mesh.colors),
    ]
    present = [(names, kind, values) for names, kind, values in groups if values is not None]
    vert = np.empty(len(mesh.vertices), dtype=[(n, k) for names, k, _ in present for n in names])
    for names, _, values in present:
        for i, name in enumerate(names):
            vert[name] = values[:, i]
    # plyfile states the format (the header); the data go out as whole arrays, since plyfile
    # writes list properties one face at a time in Python (docs/benchmark.md). Each face is its
    # count (uchar 3) and three int32; the face element is described from an empty array, with
    # the count given, to copy no face.
    no_faces = np.empty(0, dtype=[("vertex_indices", "<i4", (3,))])
    face = PlyElement("face", PlyElement.describe(no_faces, "face").properties, len(mesh.faces))
    header = PlyData([PlyElement.describe(vert, "vertex"), face], text=False, byte_order="<").header
    packed = np.empty(len(mesh.faces), dtype=[("count", "u1"), ("vertex_indices", "<i4", (3,))])
    packed["count"] = 3
    packed["vertex_indices"] = mesh.faces

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii") + b"\n")
            vert.tofile(f)  # the arrays' own bytes, no copy
            packed.tofile(f)

    path = Path(path)
    write_atomic(path, write)
    return path


__all__ = ["Mesh", "albedo_colors", "height_mesh", "write_ply"]
