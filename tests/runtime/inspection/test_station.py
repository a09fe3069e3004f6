"""The warm station (inspection.station): one verdict per part with only the rule's maps, the
same verdict msf-inspect gives, a reference mapped once."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from msfnet.common.errors import InputError
from msfnet.runtime.api import Model
from msfnet.runtime.inspection.defects import DefectOptions, find_defects, from_maps
from msfnet.runtime.inspection.station import Station, rule_maps
from msfnet.runtime.options import ModelOptions
from msfnet.runtime.results.maps import MapOptions
from msfnet.runtime.stack import save_stack
from msfnet.synth.plates import PlateOptions, render_plate

RULE = DefectOptions(depth=0.1)
L2 = ModelOptions(method="l2")


@pytest.fixture(scope="module")
def plates():
    bad = render_plate(PlateOptions(seed=1, mask_edge=None))
    good = render_plate(PlateOptions(seed=1, mask_edge=None, relief=False))
    return bad, good


def test_the_rule_decides_the_maps() -> None:
    assert rule_maps(DefectOptions(depth=0.1), False) == ("height",)
    assert rule_maps(DefectOptions(curvature=0.01), False) == ("curvature",)
    assert rule_maps(DefectOptions(depth=0.1, curvature=0.01), True) == (
        "height",
        "curvature",
        "albedo",
    )


def test_a_station_finds_each_defect_and_computes_only_what_the_rule_reads(plates) -> None:
    bad, good = plates
    station = Station(RULE, L2, reference=good.stack)
    fail = station.inspect(bad.stack, "bad")
    ok = station.inspect(good.stack, "good")
    assert not fail.passed and ok.passed
    hit = {int(bad.defects[fail.labels == k].max()) for k in range(1, fail.labels.max() + 1)}
    assert hit == set(range(1, len(bad.defect_list) + 1))  # each defect, nothing else
    # the albedo (what the reference is aligned on), the height; no curvature
    assert fail.part.albedo is not None and fail.part.curvature is None
    alone = Station(RULE, L2).inspect(bad.stack)  # no reference: the height only
    assert alone.part.albedo is None and alone.part.curvature is None
    assert fail.times.decode == 0.0 and fail.times.normals > 0 and fail.times.maps > 0
    assert "FAIL" in repr(fail) and "PASS" in repr(ok)


def test_the_station_judges_as_a_whole_run_does(plates) -> None:
    """The same regions as msf-inspect's path (every map computed, then judged)."""
    bad, good = plates
    model = Model(options=L2.replace(maps=MapOptions(maps=("albedo", "height", "curvature"))))
    ref = from_maps(model(good.stack).maps, "good")  # type: ignore[arg-type]
    whole, labels = find_defects(from_maps(model(bad.stack).maps, "bad"), RULE, ref)  # type: ignore[arg-type]
    station = Station(RULE, L2, reference=good.stack).inspect(bad.stack)
    assert np.array_equal(labels, station.labels)
    assert [r.depth for r in whole.regions] == pytest.approx(
        [r.depth for r in station.verdict.regions], abs=1e-6
    )


def test_a_part_folder_is_decoded_with_its_time(plates, tmp_path: Path) -> None:
    bad, good = plates
    save_stack(bad.stack, tmp_path / "p1")
    save_stack(good.stack, tmp_path / "golden")
    station = Station(RULE, L2, reference=tmp_path / "golden")
    found = station.inspect(tmp_path / "p1")
    assert found.name == "p1" and not found.passed and found.times.decode > 0
    assert set(found.times.milliseconds()) == {"decode", "normals", "maps", "judge", "total"}


def test_a_missing_reference_is_refused_at_once(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no such file"):
        Station(RULE, L2, reference=tmp_path / "nowhere")


def test_a_curvature_rule_alone_still_tells_dents_and_scratches(plates) -> None:
    """No local shape computed: the kind's sign comes from the curvature (review 5)."""
    bad, _ = plates
    found = Station(DefectOptions(curvature=0.02), L2).inspect(bad.stack)
    kinds = {r.kind for r in found.verdict.regions}
    assert found.part.local_shape is None and kinds and "bump" not in kinds


def test_a_reference_without_the_rules_map_is_refused_at_start(plates, tmp_path: Path) -> None:
    _, good = plates
    Model(options=L2.replace(maps=MapOptions(maps=("height",))))(good.stack).save(tmp_path / "ref")
    with pytest.raises(InputError, match="no curvature map"):
        Station(DefectOptions(curvature=0.02), L2, reference=tmp_path / "ref")
