"""mesh.ply: read back with plyfile; vertex count, faces, winding, normals and colours."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData

from msfnet.common.errors import InputError
from msfnet.runtime.results.maps.integrate import Intrinsics
from msfnet.runtime.results.maps.mesh import albedo_colors, height_mesh, write_ply


def test_mesh_roundtrip_counts_winding_and_attributes(surfaces, tmp_path: Path) -> None:
    z, mask, n = surfaces["sphere_cap"](h=24, w=26, radius=14.0, cap=10.0)
    albedo = np.zeros((*mask.shape, 3))
    albedo[mask] = (0.2, 0.4, 0.8)
    mesh = height_mesh(z, mask, normals=n, colors=albedo_colors(albedo, mask))
    path = write_ply(tmp_path / "mesh.ply", mesh)
    ply = PlyData.read(str(path))
    v, f = ply["vertex"], ply["face"]
    assert v.count == mask.sum()
    # every interior 2 x 2 block gives 2 triangles, blocks with 3 valid pixels give 1
    blocks = mask[:-1, :-1].astype(int) + mask[:-1, 1:] + mask[1:, :-1] + mask[1:, 1:]
    assert f.count == 2 * np.sum(blocks == 4) + np.sum(blocks == 3)
    xyz = np.stack([v["x"], v["y"], v["z"]], axis=1)
    rows, cols = np.nonzero(mask)
    assert np.allclose(xyz[:, 0], cols) and np.allclose(xyz[:, 1], -rows)
    assert np.allclose(xyz[:, 2], z[mask], atol=1e-4)
    faces = np.stack(f["vertex_indices"])
    a, b, c = xyz[faces[:, 0]], xyz[faces[:, 1]], xyz[faces[:, 2]]
    face_n = np.cross(b - a, c - a)
    assert np.all(face_n[:, 2] > 0), "triangles must face the camera (+z)"
    vn = np.stack([v["nx"], v["ny"], v["nz"]], axis=1)
    assert np.allclose(vn, n[mask], atol=1e-6)
    # face normals agree with the vertex normals they were built from
    face_n /= np.linalg.norm(face_n, axis=1, keepdims=True)
    mean_vn = vn[faces].mean(axis=1)
    mean_vn /= np.linalg.norm(mean_vn, axis=1, keepdims=True)
    assert np.median(np.sum(face_n * mean_vn, axis=1)) > 0.99
    colours = np.stack([v["red"], v["green"], v["blue"]], axis=1)
    assert colours[:, 2].min() == 255 and colours[:, 0].max() < 80


def test_mesh_perspective_and_jumps(tmp_path: Path) -> None:
    mask = np.ones((6, 8), bool)
    height = np.zeros((6, 8))
    height[:, 4:] = 10.0  # a 10 px step between columns 3 and 4
    full = height_mesh(height, mask)
    cut = height_mesh(height, mask, max_jump=2.0)
    assert len(cut.faces) == len(full.faces) - 2 * 5  # the 5 blocks across the step go
    depth = np.full((6, 8), 100.0)
    intr = Intrinsics(50.0, 50.0, 4.0, 3.0)
    persp = height_mesh(height, mask, intrinsics=intr, depth=depth)
    assert np.allclose(persp.vertices[:, 2], -100.0)
    # pixel (row 3, col 4) sits on the optical axis: x = y = 0
    k = 3 * 8 + 4
    assert np.allclose(persp.vertices[k, :2], 0.0)
    with pytest.raises(InputError, match="depth"):
        height_mesh(height, mask, intrinsics=intr)


def test_mesh_degenerate_masks(tmp_path: Path) -> None:
    empty = height_mesh(np.full((4, 4), np.nan), np.zeros((4, 4), bool))
    assert empty.vertices.shape == (0, 3) and empty.faces.shape == (0, 3)
    ply = PlyData.read(str(write_ply(tmp_path / "empty.ply", empty)))
    assert ply["vertex"].count == 0 and ply["face"].count == 0
    one = np.zeros((4, 4), bool)
    one[1, 2] = True
    single = height_mesh(np.where(one, 0.0, np.nan), one)
    assert single.vertices.shape == (1, 3) and single.faces.shape == (0, 3)
    with pytest.raises(InputError, match="mask"):
        height_mesh(np.zeros((4, 4)), np.ones((4, 5), bool))
    assert not list(tmp_path.glob(".*")), "no temporary file may be left behind"


@pytest.mark.parametrize("attributes", [True, False])
def test_the_file_is_byte_for_byte_what_plyfile_writes(
    surfaces, tmp_path: Path, attributes: bool
) -> None:
    # write_ply packs the faces itself (plyfile writes lists a face at a time in Python):
    # the bytes must be plyfile's own
    from plyfile import PlyElement

    z, mask, n = surfaces["sphere_cap"](h=20, w=23, radius=12.0, cap=9.0)
    albedo = np.zeros((*mask.shape, 3))
    albedo[mask] = (0.2, 0.4, 0.8)
    mesh = height_mesh(
        z,
        mask,
        normals=n if attributes else None,
        colors=albedo_colors(albedo, mask) if attributes else None,
    )
    ours = write_ply(tmp_path / "ours.ply", mesh).read_bytes()
    fields = [("x", "f4"), ("y", "f4"), ("z", "f4")]
    columns = [mesh.vertices]
    if attributes:
        assert mesh.normals is not None and mesh.colors is not None
        fields += [("nx", "f4"), ("ny", "f4"), ("nz", "f4")]
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        columns += [mesh.normals, mesh.colors]
    vert = np.empty(len(mesh.vertices), dtype=fields)
    names = iter(name for name, _ in fields)
    for block in columns:
        for i in range(block.shape[1]):
            vert[next(names)] = block[:, i]
    face = np.empty(len(mesh.faces), dtype=[("vertex_indices", "i4", (3,))])
    face["vertex_indices"] = mesh.faces
    reference = tmp_path / "plyfile.ply"
    PlyData(
        [PlyElement.describe(vert, "vertex"), PlyElement.describe(face, "face")],
        text=False,
        byte_order="<",
    ).write(str(reference))
    assert len(mesh.faces) > 100
    assert ours == reference.read_bytes()
