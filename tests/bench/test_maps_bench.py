"""python -m msfnet.bench.maps runs end to end (on a small frame; timings are not asserted)."""

from __future__ import annotations

import json
from pathlib import Path

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
