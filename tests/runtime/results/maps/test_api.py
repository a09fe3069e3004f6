"""The entry point: compute_maps / write_maps on a small synthetic stack, bad input, all-or-nothing
writing, the report, and the torch-free promise."""

from __future__ import annotations

import base64
import json
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from _runtime_helpers import MAP_FILES, sphere_stack

from msfnet.common.errors import InputError
from msfnet.runtime.results.maps import (
    InspectionMaps,
    MapOptions,
    compute_maps,
    stack_maps,
    write_maps,
)
from msfnet.runtime.results.maps import api as maps_api
from msfnet.runtime.results.maps.registered import read_tiff

EXPECTED_FILES = MAP_FILES


@pytest.fixture(scope="module")
def stack():
    return sphere_stack(n=8, h=36, w=44)


def test_compute_maps_on_a_rendered_sphere(stack) -> None:
    maps = stack_maps(stack, stack.normals_gt, MapOptions(integration="poisson"))
    m = stack.mask
    # sphere_stack renders albedo 0.8 at a 40000 full scale
    assert np.allclose(maps.albedo[m], 0.8 * 40000, rtol=0.01)
    assert np.isfinite(maps.height[m]).all() and np.isnan(maps.height[~m]).all()
    assert np.nanmedian(maps.curvature) > 0  # a sphere seen from outside is convex
    assert set(maps.timings) == {"albedo", "height (poisson)", "curvature"}
    assert maps.integration is not None and maps.integration.method == "poisson"
    only = compute_maps(None, None, None, m, stack.normals_gt, MapOptions(maps=("curvature",)))
    assert only.albedo is None and only.height is None and only.curvature is not None
    mesh_only = MapOptions(maps=("mesh",))
    assert mesh_only.wants("height")  # the mesh is built from the height


def test_write_maps_files_report_and_json(stack, tmp_path: Path) -> None:
    maps = stack_maps(stack, stack.normals_gt)
    err = np.where(stack.mask, 2.0, 0.0)
    profile = {
        "stages": {
            "load": {"median_s": 0.01, "p90_s": 0.02},
            "inference": {"median_s": 0.5, "p90_s": 0.6},
        }
    }
    files = write_maps(tmp_path, maps, images=stack.images, error_deg=err, profile=profile)
    assert {p.name for p in files} == EXPECTED_FILES
    assert {p.name for p in tmp_path.iterdir()} == EXPECTED_FILES  # no temporaries left
    alb = cv2.imread(str(tmp_path / "albedo.png"), cv2.IMREAD_UNCHANGED)
    assert alb.dtype == np.uint16 and alb.shape == (*stack.shape, 3)
    assert alb[stack.mask].max() == 65535 and not alb[~stack.mask].any()
    height = read_tiff(tmp_path / "height.tif")
    assert height.dtype == np.float32 and np.isnan(height[~stack.mask]).all()
    assert np.array_equal(np.isfinite(read_tiff(tmp_path / "curvature.tif")), stack.mask)
    info = json.loads((tmp_path / "maps.json").read_text())
    assert info["options"]["method"] == "poisson" and info["units"]["height"] == "px"
    assert info["pixels"] == int(stack.mask.sum())
    page = (tmp_path / "report.html").read_text()
    pngs = re.findall(r'src="data:image/png;base64,([^"]+)"', page)
    assert len(pngs) == 7  # inputs, normals, albedo, height, local shape, curvature, error
    for data in pngs:
        assert base64.b64decode(data)[:8] == b"\x89PNG\r\n\x1a\n"
    assert "inference" in page and "maps: curvature" in page  # the latency table
    assert 'src="http' not in page and "<script" not in page  # self-contained


def test_write_failure_leaves_nothing_half_written(stack, tmp_path: Path, monkeypatch) -> None:
    maps = stack_maps(stack, stack.normals_gt, MapOptions(maps=("height", "curvature")))

    def broken(*args, **kwargs):
        raise RuntimeError("drawing failed")

    monkeypatch.setattr("msfnet.runtime.results.maps.pictures.curvature_picture", broken)
    with pytest.raises(RuntimeError):
        write_maps(tmp_path / "out", maps)
    # pictures are drawn before any file is written: nothing appears
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


@pytest.mark.parametrize("method", ("fc", "poisson", "bini"))
def test_degenerate_masks_give_documented_results(stack, tmp_path: Path, method: str) -> None:
    opts = MapOptions(integration=method)
    empty = np.zeros(stack.shape, bool)
    maps = compute_maps(
        stack.images, stack.lights, stack.intensities, empty, stack.normals_gt, opts
    )
    assert np.isnan(maps.albedo).all() and np.isnan(maps.height).all()
    assert np.isnan(maps.curvature).all()
    if method == "poisson":  # the pictures do not depend on the method: draw them once
        files = write_maps(tmp_path / "empty", maps)
        assert {p.name for p in files} == EXPECTED_FILES
    one = np.zeros(stack.shape, bool)
    one[18, 22] = True
    single = compute_maps(
        stack.images, stack.lights, stack.intensities, one, stack.normals_gt, opts
    )
    assert single.height[18, 22] == 0.0 and single.curvature[18, 22] == 0.0
    assert single.albedo[18, 22] == pytest.approx(0.8 * 40000, rel=0.01)
    if method == "poisson":
        write_maps(tmp_path / "one", single, images=stack.images)


def test_bad_input_and_options(stack) -> None:
    bad = stack.normals_gt.copy()
    bad[18, 22] = np.nan
    with pytest.raises(InputError, match="NaN"):
        stack_maps(stack, bad)
    with pytest.raises(InputError, match="albedo needs"):
        compute_maps(None, None, None, stack.mask, stack.normals_gt)
    with pytest.raises(InputError, match="unknown map"):
        MapOptions(maps=("albedo", "depthmap"))
    with pytest.raises(InputError, match="method"):
        MapOptions(integration="sfs")
    with pytest.raises(InputError, match="intrinsics"):
        MapOptions(intrinsics=(100.0, -1.0, 0.0, 0.0))
    assert MapOptions(intrinsics=(100, 100, 20, 18)).intrinsics.fx == 100.0


def test_perspective_options_write_depth(stack, tmp_path: Path) -> None:
    opts = MapOptions(maps=("height", "mesh"), intrinsics=(60.0, 60.0, 22.0, 18.0))
    maps = stack_maps(stack, stack.normals_gt, opts)
    assert isinstance(maps, InspectionMaps) and maps.depth is not None
    assert np.nanmedian(maps.depth) == pytest.approx(60.0, rel=1e-4)  # depth_ref = fx
    names = {p.name for p in write_maps(tmp_path, maps, report=False)}
    # a perspective height is no px / mm height: no height.tif, so its data is height.npy
    assert {"depth.npy", "mesh.ply", "height.npy"} <= names and "report.html" not in names
    assert json.loads((tmp_path / "maps.json").read_text())["units"]["height"] == "depth_ref units"


def test_albedo_png_scale() -> None:
    mask = np.array([[True, False]])
    img = maps_api.albedo_png(np.array([[[1.0, 2.0, 4.0], [9.0, 9.0, 9.0]]]), mask)
    assert img.tolist() == [[[16384, 32768, 65535], [0, 0, 0]]]


TORCH_FREE = r"""
import importlib.abc, sys
class BlockTorch(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "torch" or name.startswith("torch."):
            raise ImportError(f"blocked for this test: {name}")
sys.meta_path.insert(0, BlockTorch())
import numpy as np
from msfnet.runtime.results.maps import MapOptions, compute_maps
from msfnet.runtime.results.maps.mesh import height_mesh, write_ply
m = np.zeros((12, 14), bool); m[3:9, 3:11] = True
n = np.zeros((12, 14, 3)); n[m] = (0.1, 0.2, 0.97)
imgs = np.ones((3, 12, 14, 3), np.float32)
maps = compute_maps(imgs, np.eye(3), np.ones((3, 3)), m, n, MapOptions(integration="bini"))
write_ply(sys.argv[1] + "/mesh.ply", height_mesh(maps.height, m, normals=maps.normals))
import msfnet.runtime.results.maps.pictures  # drawing stays torch-free too
import msfnet.runtime.results.maps.report
assert not any(k == "torch" or k.startswith("torch.") for k in sys.modules)
print("MAPS TORCH-FREE OK")
"""


def test_maps_run_without_torch(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-c", TORCH_FREE, str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "MAPS TORCH-FREE OK" in proc.stdout and (tmp_path / "mesh.ply").is_file()
