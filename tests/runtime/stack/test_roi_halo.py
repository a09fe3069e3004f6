"""--roi with a halo: the grown crop and the ROI's box inside it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _runtime_helpers import png_stack, sphere_stack

from msfnet.common.errors import InputError
from msfnet.runtime.contract import INPUT_MULTIPLE
from msfnet.runtime.stack import LoadOptions, Stack, load_stack, prepare_stack
from msfnet.runtime.stack.transforms import area_downscale, crop, halo_roi


def test_grown_inside_the_image_and_clipped_at_its_border() -> None:
    grown, box = halo_roi((50, 40, 100, 80), (300, 400), 20)
    assert grown == (30, 20, 140, 120) and box == (20, 100, 20, 120)
    # at the top-left corner and the right border: clipped, the box follows
    grown, box = halo_roi((5, 0, 100, 80), (300, 400), 20)
    assert grown == (0, 0, 125, 100) and box == (0, 80, 5, 105)
    grown, box = halo_roi((390, 10, 10, 10), (300, 400), 20)
    assert grown[0] + grown[2] == 400 and box[3] - box[2] == 10


def test_the_grown_crop_starts_on_the_network_grid_where_it_can() -> None:
    # 23 - 5 = 18 is off a grid of 4: grown to 16; 17 - 5 = 12 is on it
    grown, box = halo_roi((23, 17, 10, 10), (100, 100), 5, align=4)
    assert grown[:2] == (16, 12) and box == (5, 15, 7, 17)
    # downscaled by 2: the grid is 4 held = 8 stored pixels; 22 - 10 = 12 -> 8
    grown, box = halo_roi((22, 40, 10, 10), (100, 100), 5, 2, align=4)
    assert grown[:2] == (8, 24) and box == (8, 13, 7, 12)
    # an ROI off the block grid keeps its own blocks (no full-image run shares them)
    grown, _ = halo_roi((23, 17, 10, 10), (100, 100), 5, 2, align=4)
    assert grown[:2] == (13, 7)
    # clipped at the image's edge, which is on every grid
    assert halo_roi((3, 2, 10, 10), (100, 100), 5, align=4)[0][:2] == (0, 0)


def test_the_box_of_the_grown_crop_is_the_roi_also_downscaled() -> None:
    rng = np.random.default_rng(0)
    img = rng.random((120, 160)).astype(np.float32)
    roi = (23, 17, 64, 48)
    for k in (1, 2, 4):
        grown, (y0, y1, x0, x1) = halo_roi(roi, img.shape, 8, multiple=k)
        inner = area_downscale(crop(img, grown), k)[y0:y1, x0:x1]
        assert np.array_equal(inner, area_downscale(crop(img, roi), k))


# ---------------------------------------------------------------- loading with the halo

ROI = (13, 9, 20, 18)  # x, y, w, h: through the sphere, away from the border on every side


def _same_stack(a: Stack, b: Stack) -> None:
    assert a.shape == b.shape
    assert np.array_equal(a.images, b.images)
    assert np.array_equal(a.mask, b.mask)
    assert a.normals_gt is not None and b.normals_gt is not None
    assert np.array_equal(a.normals_gt, b.normals_gt)


@pytest.mark.parametrize("k", [1, 2])
def test_a_folder_loads_the_grown_roi_and_its_box_is_the_plain_roi(tmp_path: Path, k: int) -> None:
    folder = png_stack(tmp_path / "s", 16, h=48, w=56)
    plain = load_stack(folder, LoadOptions(roi=ROI, downscale=k))
    grown = load_stack(folder, LoadOptions(roi=ROI, downscale=k, roi_halo=6))
    assert plain.roi_box is None and grown.roi_box is not None
    y0, y1, x0, x1 = grown.roi_box
    assert grown.shape[0] > plain.shape[0] and grown.shape[1] > plain.shape[1]
    assert (y1 - y0, x1 - x0) == plain.shape == (ROI[3] // k, ROI[2] // k)
    # around the box the stack keeps its own mask (the object as a full-image run sees it)
    rect, _ = halo_roi(ROI, (48, 56), 6, k, INPUT_MULTIPLE)
    assert np.array_equal(grown.mask, load_stack(folder, LoadOptions(roi=rect, downscale=k)).mask)
    assert grown.mask.sum() > grown.inner().mask.sum()
    _same_stack(grown.inner(), plain)
    assert grown.inner().roi_box is None


def test_a_stack_in_memory_gets_the_same_grown_roi() -> None:
    stack = sphere_stack(h=48, w=56)
    plain = prepare_stack(stack, LoadOptions(roi=ROI))
    grown = prepare_stack(stack, LoadOptions(roi=ROI, roi_halo=6))
    # 13 - 6 and 9 - 6 are off the network's grid of 4: grown to 4 and 0
    assert grown.roi_box == (9, 9 + ROI[3], 9, 9 + ROI[2])
    _same_stack(grown.inner(), plain)
    # a grown stack prepared again for an ROI starts from its own ROI, not the grown crop
    again = prepare_stack(grown, LoadOptions(roi=(0, 0, 10, 10)))
    assert again.shape == (10, 10) and np.array_equal(again.images, plain.images[:, :10, :10])


def test_the_halo_is_clipped_at_the_image_border_and_refused_when_negative(
    tmp_path: Path,
) -> None:
    stack = sphere_stack(h=48, w=56)
    corner = prepare_stack(stack, LoadOptions(roi=(0, 0, 30, 30), roi_halo=20))
    assert corner.roi_box == (0, 30, 0, 30) and corner.shape == (48, 50)
    with pytest.raises(InputError, match="halo"):
        LoadOptions(roi=ROI, roi_halo=-1)
    # an ROI past the image gets the plain ROI's message, naming the file
    folder = png_stack(tmp_path / "s", 8, h=48, w=56)
    with pytest.raises(InputError, match="reaches past"):
        load_stack(folder, LoadOptions(roi=(40, 0, 30, 10), roi_halo=4))
    # the object in the halo only, none in the ROI: refused as a plain crop is
    with pytest.raises(InputError, match="mask is empty"):
        load_stack(folder, LoadOptions(roi=(0, 0, 4, 4), roi_halo=20))
