"""Zones (inspection.zones, msf-inspect --zones): areas with their own thresholds or left out,
drawn in the camera image's pixels; a file that does not fit is one line, exit 2."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from msfnet.common.errors import InputError
from msfnet.runtime.inspection.defects import DefectOptions, InspectionInput, find_defects
from msfnet.runtime.inspection.zones import read_zones
from msfnet.runtime.results.maps.registered import Frame

H, W = 60, 80


def _part(frame: Frame | None = None) -> InspectionInput:
    local = np.zeros((H, W), np.float32)
    local[10:14, 10:14] = -0.05  # a shallow dent in the "seal" zone
    local[40:44, 60:64] = -0.5  # a deep one under the "logo"
    local[40:44, 20:24] = -0.05  # a shallow one outside every zone
    units = {"depth": "px", "curvature": "1/px"}
    return InspectionInput(local, None, None, units, None, "part", frame=frame or Frame())


def _zones(tmp_path: Path, zones: list[dict], name: str = "zones.json") -> Path:
    path = tmp_path / name
    path.write_text(json.dumps({"zones": zones}))
    return path


SEAL = {"name": "seal", "polygon": [[0, 0], [30, 0], [30, 30], [0, 30]], "depth": 0.02}
LOGO = {"name": "logo", "polygon": [[55, 35], [70, 35], [70, 50], [55, 50]], "ignore": True}


def test_a_zone_has_its_own_threshold_and_an_ignored_one_is_left_out(tmp_path: Path) -> None:
    zones = read_zones(_zones(tmp_path, [SEAL, LOGO]))
    plain, _ = find_defects(_part(), DefectOptions(depth=0.1))
    assert len(plain.regions) == 1  # the deep dent only
    zoned, labels = find_defects(_part(), DefectOptions(depth=0.1), zones=zones)
    assert [r.zone for r in zoned.regions] == ["seal"]  # the logo's dent is not judged
    assert labels[10:14, 10:14].all() and not labels[40:44, 60:64].any()
    assert not labels[40:44, 20:24].any()  # outside every zone: the rule's 0.1


def test_zones_follow_the_maps_crop_and_downscale(tmp_path: Path) -> None:
    """Drawn on the camera frame: a map cut at (100, 50) and downscaled 2x sees the seal zone
    where the camera image's (100..160, 50..110) falls, map (0..30, 0..30)."""
    seal = dict(SEAL, polygon=[[100, 50], [160, 50], [160, 110], [100, 110]])
    zones = read_zones(_zones(tmp_path, [seal]))
    verdict, _ = find_defects(_part(Frame((100, 50), 2)), DefectOptions(depth=0.1), zones=zones)
    assert sorted(r.zone for r in verdict.regions) == ["", "seal"]


@pytest.mark.parametrize(
    ("content", "words"),
    [
        ("not json", "not valid JSON"),
        (json.dumps({"zone": []}), "expected"),
        (json.dumps({"zones": [{"name": "a", "polygon": [[0, 0], [1, 1]]}]}), "3 or more"),
        (json.dumps({"zones": [dict(SEAL, depth=-1)]}), "positive number"),
        (json.dumps({"zones": [dict(SEAL, dpeth=0.1)]}), "unknown key(s) dpeth"),
        (json.dumps({"zones": [dict(SEAL, ignore="yes")]}), "true or false"),
    ],
)
def test_a_bad_zone_file_says_what_is_wrong(tmp_path: Path, content: str, words: str) -> None:
    path = tmp_path / "z.json"
    path.write_text(content)
    with pytest.raises(InputError, match=words.replace("(", r"\(").replace(")", r"\)")):
        read_zones(path)


def test_a_zone_outside_the_maps_is_refused_not_ignored(tmp_path: Path) -> None:
    far = dict(SEAL, polygon=[[900, 900], [990, 900], [990, 990]])
    zones = read_zones(_zones(tmp_path, [far]))
    with pytest.raises(InputError, match="lies outside the 80x60 maps"):
        find_defects(_part(), DefectOptions(depth=0.1), zones=zones)


def test_msf_inspect_takes_zones_and_refuses_a_bad_file_before_any_work(tmp_path, capsys):
    from msfnet.runtime.cli.inspect import main

    bad = tmp_path / "bad.json"
    bad.write_text("{")
    code = main(["nowhere/", "--depth", "0.1", "--zones", str(bad), "-o", str(tmp_path / "v")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "bad.json" in err and "not valid JSON" in err
    assert len(err.splitlines()) == 1 and not (tmp_path / "v").exists()
