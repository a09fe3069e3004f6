"""The variation model (inspection.variation, msf-inspect --train-good): per-pixel centre and
spread of good parts, per-pixel thresholds, a part from elsewhere called a mismatch."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from msfnet.common.errors import InputError
from msfnet.runtime.api import Model
from msfnet.runtime.cli.inspect import main as inspect_main
from msfnet.runtime.inspection.defects import (
    EXIT_MISMATCH,
    DefectOptions,
    InspectionInput,
    find_defects,
    from_maps,
    read_run,
)
from msfnet.runtime.inspection.variation import train_variation
from msfnet.runtime.results.maps import MapOptions
from msfnet.synth.plates import PlateOptions, render_plate

H, W = 60, 80
ROWS, COLS = np.mgrid[0:H, 0:W]
ZONE = (COLS < 25) & (ROWS < 30)  # where good parts differ a lot (a rim, a highlight)
DENT = (ROWS - 45) ** 2 + (COLS - 60) ** 2 < 16


def _part(rng: np.random.Generator, zone: float, dent: float = 0.0, name: str = "p"):
    local = rng.normal(0, 0.004, (H, W)).astype(np.float32)
    local[ZONE] += zone  # each part its own offset there
    local[DENT] -= dent
    return InspectionInput(
        local_shape=local,
        curvature=None,
        albedo=None,
        units={"depth": "px", "curvature": "1/px"},
        pixel_size_mm=None,
        source=name,
        local_size_px=12.0,
    )


@pytest.fixture(scope="module")
def goods() -> list[InspectionInput]:
    rng = np.random.default_rng(0)
    offsets = (-0.1, 0.06, -0.03, 0.0, 0.03, -0.06, 0.1)  # median 0, spread 0.09 px
    return [_part(rng, z, name=f"good{i}") for i, z in enumerate(offsets)]


def test_a_pixel_is_judged_against_how_much_good_parts_varied_there(goods) -> None:
    model = train_variation(goods)
    spread = model.centre.local_shape_spread
    assert spread is not None
    assert np.nanmedian(spread[ZONE]) > 5 * np.nanmedian(spread[~ZONE])
    rng = np.random.default_rng(1)
    part = _part(rng, 0.0, dent=0.1)
    part.local_shape[ZONE] += 0.1  # within the good parts' variation there  # type: ignore[index]
    rule = DefectOptions(depth=0.04, sigmas=4.0)
    with_model, labels = find_defects(part, rule, model.centre)
    assert len(with_model.regions) == 1 and labels[DENT].all() and not labels[ZONE].any()
    golden, _ = find_defects(part, rule, goods[0])  # one good part knows no variation
    assert len(golden.regions) == 2
    stats = model.statistics
    assert stats is not None and stats.held_out and len(stats.needed) == len(goods)
    # the suggestion covers the neediest held-out good part, with a margin
    assert max(stats.needed) <= stats.suggested_depth <= 1.3 * max(stats.needed)
    for good in goods:  # and at the suggestion every good part passes the whole model
        verdict, _ = find_defects(good, DefectOptions(depth=stats.suggested_depth), model.centre)
        assert verdict.passed


def test_a_part_unlike_the_reference_is_a_mismatch_not_defects(goods) -> None:
    other = _part(np.random.default_rng(2), 0.0)
    other.local_shape[:] = 0.05 * np.sin(COLS / 3.0)  # type: ignore[index]
    verdict, labels = find_defects(other, DefectOptions(depth=0.03), goods[0])
    assert verdict.mismatch is not None and "off the reference" in verdict.mismatch
    assert not verdict.regions and not labels.any()  # nothing compared
    flat = _part(np.random.default_rng(3), 0.0)
    flat.local_shape[DENT] = 0.0  # type: ignore[index]
    flat.local_shape[:, 8:] += 0.2  # type: ignore[index]
    verdict, _ = find_defects(flat, DefectOptions(depth=0.03), goods[3])
    assert verdict.mismatch is not None and "one region covers 9" in verdict.mismatch
    assert verdict.exit_code == EXIT_MISMATCH and verdict.as_dict()["verdict"] == "mismatch"
    assert len(verdict.regions) == 1 and not verdict.passed


def test_many_real_defects_at_a_low_threshold_are_defects_not_a_mismatch() -> None:
    """A plate's five defects, their halos joined at a threshold 10x below their depth, are
    still a failed part with its regions, not "another part"."""
    model = Model.least_squares(maps=MapOptions(maps=("albedo", "height", "curvature")))
    good = render_plate(PlateOptions(seed=4, relief=False, mask_edge=None))
    bad = render_plate(PlateOptions(seed=4, mask_edge=None))
    ref = from_maps(model(good.stack).maps, "good")  # type: ignore[arg-type]
    part = from_maps(model(bad.stack).maps, "bad")  # type: ignore[arg-type]
    verdict, _ = find_defects(part, DefectOptions(depth=0.02), ref)
    assert verdict.word == "fail" and verdict.regions and verdict.mismatch is None


def test_fewer_than_three_good_parts_are_refused(goods) -> None:
    with pytest.raises(InputError, match="at least 3 good parts"):
        train_variation(goods[:2])


def test_the_model_is_a_run_folder_a_reference_reads(goods, tmp_path: Path) -> None:
    model = train_variation(goods)
    model.save(tmp_path / "model")
    back = read_run(tmp_path / "model")
    assert back.local_shape_spread is not None
    np.testing.assert_array_equal(back.local_shape_spread, model.centre.local_shape_spread)
    np.testing.assert_array_equal(back.local_shape, model.centre.local_shape)
    record = json.loads((tmp_path / "model" / "variation.json").read_text())
    assert record["good_parts"] == [g.source for g in goods] and record["suggested_depth"] > 0


def test_msf_inspect_learns_from_good_runs_and_judges_against_the_model(tmp_path, capsys):
    maps = MapOptions(maps=("albedo", "height", "curvature"))
    model = Model.least_squares(maps=maps)
    for i in range(3):
        good = render_plate(PlateOptions(seed=20 + i, relief=False, mask_edge=None))
        model(good.stack).save(tmp_path / f"good{i}")
    model(render_plate(PlateOptions(seed=30, mask_edge=None)).stack).save(tmp_path / "bad")
    goods = [str(tmp_path / f"good{i}") for i in range(3)]
    assert inspect_main(["--train-good", goods[0], goods[1], "-o", str(tmp_path / "m")]) == 2
    assert "at least 3" in capsys.readouterr().err and not (tmp_path / "m").exists()
    assert inspect_main(["--train-good", *goods, "-o", str(tmp_path / "m")]) == 0
    assert "suggested --depth" in capsys.readouterr().out
    argv = ["--reference", str(tmp_path / "m"), "--depth", "0.08", "-o"]
    assert inspect_main([str(tmp_path / "bad"), *argv, str(tmp_path / "v")]) == 1
    assert inspect_main([goods[0], *argv, str(tmp_path / "v0")]) == 0
