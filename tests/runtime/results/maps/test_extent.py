"""The mask's box that every map works on."""

from __future__ import annotations

import numpy as np

from msfnet.runtime.results.maps.extent import mask_box


def test_box_is_the_tightest_around_the_mask() -> None:
    valid = np.zeros((20, 30), bool)
    valid[4, 7] = valid[11, 19] = True
    assert mask_box(valid) == (slice(4, 12), slice(7, 20))


def test_margin_grows_the_box_and_stops_at_the_image() -> None:
    valid = np.zeros((20, 30), bool)
    valid[1:3, 25:29] = True
    assert mask_box(valid, margin=3) == (slice(0, 6), slice(22, 30))


def test_empty_mask_has_no_box() -> None:
    assert mask_box(np.zeros((5, 5), bool)) is None
