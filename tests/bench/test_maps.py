"""python -m msfnet.bench.maps runs end to end (on a small frame; timings are not asserted)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from msfnet.bench.maps import bench_object, main


def test_maps_bench_runs_and_reports(tmp_path: Path, capsys) -> None:
    out = tmp_path / "maps.json"
    assert main(["--size", "48", "60", "--repeat", "1", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "CPU:" in text and "poisson" in text and "bini" in text
    res = json.loads(out.read_text())
    assert res["frame"] == "60x48" and res["mask_pixels"] > 1000
    for method in ("fc", "poisson", "bini"):
        # a coarse sanity bound at this tiny size (accuracy: tests/runtime/maps)
        assert res["methods"][method]["rms_pct_of_range"] < 2.0
    _, mask, _ = bench_object(48, 60)
    assert mask.sum() == res["mask_pixels"]


def _no_timing(*args: object, **kwargs: object) -> dict:
    raise AssertionError("timed before the output was checked")


def test_json_output_follows_the_output_rules(tmp_path: Path, capsys, monkeypatch) -> None:
    """--json is checked before the timing, never silently replaced, and written whole."""
    from msfnet.bench import maps

    out = tmp_path / "maps.json"
    out.write_text("earlier\n")
    monkeypatch.setattr(maps, "run", _no_timing)
    assert main(["--size", "48", "60", "--repeat", "1", "--json", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("python -m msfnet.bench.maps: error: ")
    assert str(out) in err[0] and "--overwrite" in err[0]
    assert out.read_text() == "earlier\n"
    monkeypatch.undo()
    assert (
        main(["--size", "48", "60", "--repeat", "1", "--json", str(out), "--overwrite", "-q"]) == 0
    )
    assert json.loads(out.read_text())["frame"] == "60x48"
    assert capsys.readouterr().out == ""  # -q: errors only
    assert sorted(p.name for p in tmp_path.iterdir()) == ["maps.json"]  # no temporary left


def test_json_output_must_be_a_file_and_options_are_checked(tmp_path: Path, capsys) -> None:
    assert main(["--json", str(tmp_path)]) == 2  # a folder
    assert capsys.readouterr().err.count("\n") == 1
    with pytest.raises(SystemExit) as exc:
        main(["--repeat", "0"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--repeat" in err[0]


def test_cpu_and_cores_come_from_runtime_cpu(monkeypatch) -> None:
    """One place knows the CPU: its model from runtime.cpu.detect_cpu, the cores from
    runtime.cpu.usable_cores (at least 1, also where the affinity query reports none)."""
    from msfnet.bench import maps
    from msfnet.common import cpu
    from msfnet.common.cpu import CpuInfo

    monkeypatch.setattr(cpu, "detect_cpu", lambda: CpuInfo.from_flags([], model="Test CPU 9000"))
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(), raising=False)
    res = maps.run(("fc",), 1, (24, 30))
    assert res["cpu"] == "Test CPU 9000" and res["cores"] == 1
