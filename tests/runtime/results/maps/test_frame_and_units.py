"""What the written maps claim about themselves holds: NaN / 0 outside the mask as maps.json and
the docs say, an unknown albedo as NaN, the pixel size under --downscale, where the maps sit in
the stored image (maps.json "frame", TIFF tags), the local size bound, the TIFFs listed, and the
report's height range with its unit."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import tifffile
from _runtime_helpers import sphere_stack

from msfnet.common.errors import InputError
from msfnet.runtime.results.maps import MapOptions, compute_maps, stack_maps, write_maps
from msfnet.runtime.results.maps.api import OUTSIDE_MASK, height_range_text
from msfnet.runtime.results.maps.registered import (
    Frame,
    check_local_size,
    local_shape,
    read_tiff,
    tiff_placement,
)


def _tags(path: Path) -> dict[str, Any]:
    with tifffile.TiffFile(path) as tif:
        return {t.name: t.value for t in tif.pages[0].tags.values()}


def _saturated_sphere():
    """sphere_stack as 16-bit images with its top-left quarter at full scale in every image:
    no observation is kept there, so its albedo is unknown."""
    stack = sphere_stack(n=8, h=36, w=44)
    images = np.minimum(stack.images, 60000.0).astype(np.uint16)
    images[:, :18, :22] = 65535
    return replace(stack, images=images)


def test_registered_tiffs_hold_what_maps_json_says_outside_the_mask(tmp_path: Path) -> None:
    """Every TIFF maps.json lists is NaN outside the mask; albedo.tif is NaN where no
    observation was kept (was: 0, a black surface), and albedo.png is black there."""
    stack = _saturated_sphere()
    maps = stack_maps(stack, stack.normals_gt, MapOptions(maps=("albedo", "height", "curvature")))
    write_maps(tmp_path, maps, report=False)
    info = json.loads((tmp_path / "maps.json").read_text())
    assert info["registered"]["outside_mask"] == OUTSIDE_MASK
    files = info["registered"]["files"]
    assert sorted(files) == sorted(p.name for p in tmp_path.glob("*.tif"))
    out = ~maps.mask
    for name in files:
        assert np.isnan(read_tiff(tmp_path / name)[out]).all(), name
    unknown = maps.mask.copy()
    unknown[18:, :] = False
    unknown[:, 22:] = False  # the saturated quarter inside the mask
    known = maps.mask & ~unknown
    assert unknown.sum() > 20 and known.sum() > 200
    for albedo in (read_tiff(tmp_path / "albedo.tif"),):
        assert np.isnan(albedo[unknown]).all() and np.isnan(albedo[out]).all()
        # sphere_stack renders albedo 0.8 at a 40000 full scale (below 60000: not clipped)
        np.testing.assert_allclose(albedo[known], 0.8 * 40000, rtol=0.01)
    png = cv2.imread(str(tmp_path / "albedo.png"), cv2.IMREAD_UNCHANGED)
    assert np.all(png[unknown] == 0) and np.all(png[out] == 0)
    assert png[known].min() > 30000  # scaled on the known pixels, not blacked out by a NaN


def test_pixel_size_is_the_stored_images_and_scales_with_downscale(tmp_path: Path) -> None:
    """image_pixel_size_mm is a stored-image pixel; with downscale K every mm map uses K x it,
    and maps.json records both sizes."""
    stack = sphere_stack(n=8, h=36, w=44)
    opts = MapOptions(
        maps=("height", "curvature"), image_pixel_size_mm=0.05, frame=Frame((0, 0), 3)
    )
    assert opts.pixel_size_mm == pytest.approx(0.15, rel=1e-12)
    maps = stack_maps(stack, stack.normals_gt, opts)
    write_maps(tmp_path, maps, report=False)
    m = maps.mask
    assert maps.height is not None and maps.curvature is not None
    np.testing.assert_allclose(read_tiff(tmp_path / "height.tif")[m], maps.height[m] * 0.15, 1e-6)
    np.testing.assert_allclose(
        read_tiff(tmp_path / "curvature.tif")[m], maps.curvature[m] / 0.15, 1e-5
    )
    reg = json.loads((tmp_path / "maps.json").read_text())["registered"]
    assert reg["image_pixel_size_mm"] == 0.05  # as given, not 0.15 / 3 rounded
    assert reg["pixel_size_mm"] == pytest.approx(0.15, rel=1e-12)
    # only the map pixel given (the API): the stored image's follows from the frame
    assert MapOptions(pixel_size_mm=0.1, frame=Frame((0, 0), 2)).image_pixel_size_mm == 0.05
    with pytest.raises(InputError, match="image pixel size"):
        MapOptions(pixel_size_mm=0.05, image_pixel_size_mm=0.05, frame=Frame((0, 0), 2))
    with pytest.raises(InputError, match="positive"):
        MapOptions(image_pixel_size_mm=float("nan"))


def test_frame_in_maps_json_and_tiff_tags(tmp_path: Path) -> None:
    """maps.json's "frame" and the TIFFs' XPosition / YPosition and resolution tags."""
    stack = sphere_stack(n=8, h=36, w=44)
    frame = Frame((64, 10), 2)
    opts = MapOptions(maps=("height",), image_pixel_size_mm=0.05, frame=frame)
    write_maps(tmp_path / "mm", stack_maps(stack, stack.normals_gt, opts), report=False)
    info = json.loads((tmp_path / "mm" / "maps.json").read_text())
    assert info["frame"] == {"origin_xy": [64, 10], "downscale": 2}
    tags = _tags(tmp_path / "mm" / "height.tif")
    assert int(tags["ResolutionUnit"]) == 3  # centimetre
    for key in ("XResolution", "YResolution"):  # a map pixel is 0.1 mm: 100 per cm
        num, den = tags[key]
        assert num / den == pytest.approx(100.0, rel=1e-9)
    x_num, x_den = tags["XPosition"]
    y_num, y_den = tags["YPosition"]
    assert x_num / x_den == pytest.approx(64 * 0.005, rel=1e-9)  # cm
    assert y_num / y_den == pytest.approx(10 * 0.005, rel=1e-9)
    # without a pixel size: one stored-image pixel is the unit
    opts = MapOptions(maps=("height",), frame=frame)
    write_maps(tmp_path / "px", stack_maps(stack, stack.normals_gt, opts), report=False)
    tags = _tags(tmp_path / "px" / "height.tif")
    assert int(tags["ResolutionUnit"]) == 1
    assert tags["XResolution"] == (1, 2) and tags["XPosition"] == (64, 1)
    assert tags["YPosition"] == (10, 1)
    # a plain run: the identity frame, and the tags as before (resolution 1, no unit)
    plain = json.loads(
        json.dumps(stack_maps(stack, stack.normals_gt, MapOptions(maps=("height",))).summary())
    )
    assert plain["frame"] == {"origin_xy": [0, 0], "downscale": 1}
    assert tiff_placement(Frame(), None)["resolution"] == (1.0, 1.0)


def test_frame_maps_a_map_pixel_to_its_image_pixel() -> None:
    assert Frame((64, 10), 2).image_xy(0, 0) == (64.5, 10.5)  # the 2 x 2 block's centre
    assert Frame((64, 10), 1).image_xy(3, 4) == (67.0, 14.0)
    assert Frame((0, 0), 3).image_xy(1, 2) == (4.0, 7.0)
    for bad in (((-1, 0), 1), ((0, 0), 0), ((0.5, 0), 1)):
        with pytest.raises(InputError):
            Frame(*bad)  # type: ignore[arg-type]


def test_a_local_size_above_the_maps_longer_side_is_refused_at_once() -> None:
    """1e5 px on a 36 x 44 stack took about a minute of Gaussian sums (1e9: out of memory);
    now refused before any map is made, with what the bound is."""
    stack = sphere_stack(n=8, h=36, w=44)
    check_local_size(44, (36, 44))  # the longer side itself is fine
    for size in (45.0, 1e5, 1e9):
        opts = MapOptions(maps=("height",), local_size_px=size)
        with pytest.raises(InputError, match=r"longer side \(44 px"):
            compute_maps(None, None, None, stack.mask, stack.normals_gt, opts)
    # the default size on a part smaller than it (a 9 x 8 thumbnail) stays accepted
    tiny = sphere_stack(n=4, h=8, w=9)
    check_local_size(12.0, (8, 9))
    with pytest.raises(InputError, match="at most 12"):
        check_local_size(13.0, (8, 9))
    maps = compute_maps(None, None, None, tiny.mask, tiny.normals_gt, MapOptions(maps=("height",)))
    assert maps.local_shape is not None
    with pytest.raises(InputError, match="at most 44"):
        local_shape(np.zeros((36, 44)), stack.mask, 1e7)
    # a perspective run has no local shape: the size is not used, nor refused
    persp = MapOptions(maps=("height",), local_size_px=1e5, intrinsics=(60.0, 60.0, 22.0, 18.0))
    assert compute_maps(None, None, None, stack.mask, stack.normals_gt, persp).local_shape is None


@pytest.mark.parametrize("tiff", [True, False])
def test_maps_json_lists_only_the_tiffs_written(tmp_path: Path, tiff: bool) -> None:
    """A perspective run writes no height.tif / local_shape.tif: maps.json names neither
    (was: both under "registered"); --no-tiff: none at all."""
    stack = sphere_stack(n=8, h=36, w=44)
    opts = MapOptions(intrinsics=(60.0, 60.0, 22.0, 18.0), tiff=tiff)
    write_maps(tmp_path, stack_maps(stack, stack.normals_gt, opts), report=False)
    reg = json.loads((tmp_path / "maps.json").read_text())["registered"]
    on_disk = sorted(p.name for p in tmp_path.glob("*.tif"))
    assert sorted(reg["files"]) == on_disk
    assert "height" not in reg and "local_shape" not in reg
    if tiff:
        assert {"gradient_p.tif", "curvature.tif", "albedo.tif"} <= set(on_disk)
        assert reg["curvature"] == "1/px" and "height.tif" not in on_disk
    else:
        assert on_disk == [] and "curvature" not in reg and "normals" not in reg


def test_report_height_range_has_its_unit(tmp_path: Path) -> None:
    stack = sphere_stack(n=8, h=36, w=44)
    assert height_range_text(13.5, MapOptions()) == "13.5 px"
    assert height_range_text(13.5, MapOptions(pixel_size_mm=0.05)) == "13.5 px (0.675 mm)"
    persp = MapOptions(intrinsics=(60.0, 60.0, 22.0, 18.0))
    assert height_range_text(2.0, persp) == "2 depth_ref units"
    opts = MapOptions(maps=("height",), image_pixel_size_mm=0.05, frame=Frame((0, 0), 2))
    maps = stack_maps(stack, stack.normals_gt, opts)
    write_maps(tmp_path, maps, report=True)
    text = (tmp_path / "report.html").read_text()
    assert maps.height is not None
    rng = float(np.nanmax(maps.height) - np.nanmin(maps.height))
    assert f"height range: {rng:.4g} px ({rng * 0.1:.4g} mm)" in text


def test_an_unknown_albedo_does_not_blank_the_colours() -> None:
    """One NaN albedo (no observation kept) made the percentile NaN: mesh colours all black and
    the report's picture scaled to 1. The known pixels keep their scale; the unknown is black."""
    from msfnet.runtime.results.maps import pictures
    from msfnet.runtime.results.maps.mesh import albedo_colors

    albedo = np.full((6, 7, 3), 0.5, np.float32)
    albedo[2, 3] = np.nan
    mask = np.ones((6, 7), bool)
    colors = albedo_colors(albedo, mask)
    assert colors[0, 0].tolist() == [255, 255, 255] and colors[2, 3].tolist() == [0, 0, 0]
    if pictures.can_draw():  # graded values: the picture as without the NaN, but for it
        graded = np.linspace(20.0, 50.0, 6 * 7 * 3, dtype=np.float32).reshape(6, 7, 3)
        with_nan = graded.copy()
        with_nan[2, 3] = np.nan
        want = pictures.albedo_picture(graded, mask)
        got = pictures.albedo_picture(with_nan, mask)
        assert got.shape == want.shape
        assert np.mean(np.any(got != want, axis=-1)) < 0.05
