"""Rendered inspection plates: deterministic, known defects, marks that are albedo only."""

from __future__ import annotations

import numpy as np
import pytest

from msfnet.runtime.results.maps.registered import local_shape
from msfnet.synth.plates import PlateOptions, render_plate


@pytest.fixture(scope="module")
def plate():
    return render_plate(PlateOptions(seed=3))


def test_same_seed_same_plate_other_seed_other_plate(plate) -> None:
    again = render_plate(PlateOptions(seed=3))
    assert np.array_equal(again.stack.images, plate.stack.images)
    assert again.defect_list == plate.defect_list
    other = render_plate(PlateOptions(seed=4))
    assert not np.array_equal(other.stack.images, plate.stack.images)


def test_defects_are_what_the_issue_asks_for(plate) -> None:
    o = plate.options
    assert plate.stack.num_lights == o.lights and 12 <= o.lights <= 16
    scratches = [d for d in plate.defect_list if d.kind == "scratch"]
    dents = [d for d in plate.defect_list if d.kind == "dent"]
    assert len(scratches) == 3 and len(dents) == 2
    for d in scratches:
        assert d.width >= 2.0 and 0.2 <= d.depth <= 0.3
    # the height dips by the stated depth below the plate's own (tilted, bowed) surface: its
    # local shape at 12 px, to 25 % (the trend fit takes a little of each defect)
    local = local_shape(plate.height, plate.surface, 12.0)
    for d in plate.defect_list:
        footprint = plate.defects == d.label
        assert footprint.sum() >= 2 * 10  # at least 2 px wide, 10 long
        assert float(np.min(local[footprint])) == pytest.approx(-d.depth, rel=0.25)


def test_marks_change_the_albedo_only(plate) -> None:
    stack, marks = plate.stack, plate.marks
    assert marks.any() and not (marks & (plate.defects > 0)).any()
    # no relief under a mark: the height there is the plate's own smooth surface
    inner = marks & stack.mask
    local = local_shape(plate.height, plate.surface, 12.0)
    assert float(np.abs(local[inner]).max()) < 0.01
    # but the images are much darker there (ink)
    bright = stack.images[:, ~marks & stack.mask].mean()
    assert stack.images[:, inner].mean() < 0.4 * bright


def test_mask_edge_roi_and_background(plate) -> None:
    o = plate.options
    h, w = plate.stack.shape
    assert not plate.stack.mask[:, o.mask_edge :].any()
    assert plate.surface[: h - o.background_rows, o.mask_edge :].all()
    # the background strip is black under every light, the surface past the cut is lit
    assert plate.stack.images[:, ~plate.surface].mean() < 100  # read noise only (of 65535)
    assert plate.stack.images[:, : h - o.background_rows, o.mask_edge :].mean() > 5000
    x, y, rw, rh = plate.roi
    assert x + rw < w and plate.surface[y : y + rh, x + rw].all()  # the ROI cuts the surface
