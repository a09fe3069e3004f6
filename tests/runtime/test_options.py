"""ModelOptions: every setting checked when a Model is made, before any work."""

from __future__ import annotations

import numpy as np
import pytest
from _runtime_helpers import sphere_stack

from msfnet import MapOptions, Model
from msfnet.common.errors import InputError
from msfnet.runtime.options import ModelOptions


@pytest.mark.parametrize(
    ("given", "names"),
    [
        ("height,curvature", ("height", "curvature")),  # msf-run's --maps
        (" height , curvature ", ("height", "curvature")),
        (["height"], ("height",)),
        (("albedo", "mesh"), ("albedo", "mesh")),
        ({"curvature", "height"}, ("height", "curvature")),  # a set: the usual order
        ("inspect", ("albedo", "height", "curvature")),  # a preset: no mesh
        ("all", ("albedo", "height", "curvature", "mesh")),
    ],
)
def test_maps_as_names_are_map_options(given: object, names: tuple[str, ...]) -> None:
    """``maps="height,curvature"`` was taken, and failed with an AttributeError after the
    first stack's inference; names now mean MapOptions with those maps."""
    model = Model.least_squares(maps=given)  # type: ignore[arg-type]
    assert model.maps == MapOptions(maps=names)
    assert Model(method="l2", maps=given).maps == MapOptions(maps=names)
    result = model(sphere_stack(n=5, h=20, w=24))
    assert result.maps is not None and result.maps.height is not None


def test_the_preset_none_is_normals_only() -> None:
    assert Model.least_squares(maps="none").maps is None
    assert ModelOptions(method="l2", maps="none").maps is None


@pytest.mark.parametrize(
    ("given", "words"),
    [
        (True, "maps=True: expected map names"),
        (1, "maps=1: expected map names"),
        ({"height": 1}, "expected map names"),
        ([MapOptions()], "expected map names"),
        ("", "names no map; maps=None computes none"),
        ("height,heigth", "unknown map(s) 'heigth'"),
    ],
)
def test_other_maps_are_refused_when_the_model_is_made(given: object, words: str) -> None:
    with pytest.raises(InputError) as caught:
        Model(method="l2", maps=given)
    assert words in str(caught.value) and "--" not in str(caught.value)
    with pytest.raises(InputError, match=r"expected map names|no map|unknown map"):
        ModelOptions(method="l2", maps=given)  # type: ignore[arg-type]


def test_map_options_and_none_pass_unchanged() -> None:
    chosen = MapOptions(maps=("albedo",), integration="fc")
    assert Model(method="l2", maps=chosen).maps is chosen
    assert Model(method="l2", maps=None).maps is None


@pytest.mark.parametrize("tile", [5, 40, 46, -4, 64.0, "64", True])
def test_a_bad_tile_is_refused_when_the_model_is_made(tile: object) -> None:
    """``Model(tile=5)`` was accepted and refused only at the first call."""
    with pytest.raises(InputError, match=r"tile=.*expected 0 \(no tiling\) or .* at least 44") as e:
        Model(method="l2", tile=tile)
    assert "--tile" not in str(e.value)


@pytest.mark.parametrize("tile", [None, 0, 44, 64, np.int64(96)])
def test_good_tiles_are_kept(tile: object) -> None:
    opts = Model(method="l2", tile=tile).options
    assert opts.tile == tile and (tile is None or type(opts.tile) is int)


def test_a_refusal_names_the_setting_it_refuses(tmp_path) -> None:
    """InputError.option: the keyword a caller can react to, not only prose."""
    from _runtime_helpers import png_stack

    from msfnet import load_stack

    with pytest.raises(InputError) as bad_tile:
        Model(method="l2", tile=5)
    assert bad_tile.value.option == "tile"
    folder = png_stack(tmp_path / "s", 8)
    with pytest.raises(InputError) as backwards:
        load_stack(folder, select="5-2")
    assert backwards.value.option == "select" and str(backwards.value).startswith("select='5-2'")
    assert InputError("plain words").option is None
