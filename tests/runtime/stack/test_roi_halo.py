"""--roi with a halo: the grown crop and the ROI's box inside it."""

from __future__ import annotations

import numpy as np

from msfnet.runtime.stack.transforms import area_downscale, crop, halo_roi


def test_grown_inside_the_image_and_clipped_at_its_border() -> None:
    grown, box = halo_roi((50, 40, 100, 80), (300, 400), 20)
    assert grown == (30, 20, 140, 120) and box == (20, 100, 20, 120)
    # at the top-left corner and the right border: clipped, the box follows
    grown, box = halo_roi((5, 0, 100, 80), (300, 400), 20)
    assert grown == (0, 0, 125, 100) and box == (0, 80, 5, 105)
    grown, box = halo_roi((390, 10, 10, 10), (300, 400), 20)
    assert grown[0] + grown[2] == 400 and box[3] - box[2] == 10


def test_the_box_of_the_grown_crop_is_the_roi_also_downscaled() -> None:
    rng = np.random.default_rng(0)
    img = rng.random((120, 160)).astype(np.float32)
    roi = (23, 17, 64, 48)
    for k in (1, 2, 4):
        grown, (y0, y1, x0, x1) = halo_roi(roi, img.shape, 8, multiple=k)
        inner = area_downscale(crop(img, grown), k)[y0:y1, x0:x1]
        assert np.array_equal(inner, area_downscale(crop(img, roi), k))
