"""The Python API's Model (runtime/api.py): what it records of how a stack was cut."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from _runtime_helpers import sphere_stack

from msfnet import LoadOptions, MapOptions, Model
from msfnet.runtime.results.maps.registered import Frame
from msfnet.runtime.stack import save_stack


def test_the_maps_frame_follows_the_load_options(tmp_path: Path) -> None:
    """msf-run recorded the ROI corner and downscale in maps.json and the API did not, so the
    API's run folders placed an msf-inspect verdict in the wrong image pixels."""
    folder = save_stack(sphere_stack(n=8, h=40, w=48), tmp_path / "s")
    model = Model.least_squares(maps=MapOptions(maps=("height",), pixel_size_mm=0.05))
    result = model(folder, LoadOptions(roi=(4, 6, 40, 30), downscale=2))
    assert result.maps is not None
    opts = result.maps.options
    assert opts.frame == Frame((4, 6), 2)
    # the API's pixel size is a map pixel's: kept, the stored image's derived from it
    assert opts.pixel_size_mm == pytest.approx(0.05) and opts.image_pixel_size_mm == 0.025
    result.save(tmp_path / "out")
    info = json.loads((tmp_path / "out" / "maps.json").read_text())
    assert info["frame"] == {"origin_xy": [4, 6], "downscale": 2}
    # a frame the caller set is kept; no cut, no frame
    mine = MapOptions(maps=("height",), frame=Frame((1, 1), 1))
    kept = Model.least_squares(maps=mine)(folder, LoadOptions(roi=(4, 6, 40, 30)))
    assert kept.maps is not None and kept.maps.options.frame == Frame((1, 1), 1)
    whole = Model.least_squares(maps=MapOptions(maps=("height",)))(folder)
    assert whole.maps is not None and whole.maps.options.frame == Frame()
