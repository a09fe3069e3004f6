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


def test_save_takes_the_files_the_load_options_named_as_inputs(tmp_path: Path) -> None:
    """review-links23.md 4: ``m(stack, LoadOptions(mask="out/mask.png")).save("out",
    overwrite=True)`` deleted the mask it had read (msf-run refused the same)."""
    from msfnet.common.errors import InputError

    m = Model.least_squares(maps=None)
    first = m(save_stack(sphere_stack(), tmp_path / "a"), LoadOptions(auto_mask=True))
    first.save(tmp_path / "out")
    assert (tmp_path / "out" / "mask.png").is_file()
    bare = save_stack(sphere_stack(seed=1), tmp_path / "b")
    (bare / "mask.png").unlink()
    again = m(bare, LoadOptions(mask=tmp_path / "out" / "mask.png"))
    with pytest.raises(InputError, match=r"contains the input .*out/mask\.png"):
        again.save(tmp_path / "out", overwrite=True)
    assert (tmp_path / "out" / "mask.png").is_file()
