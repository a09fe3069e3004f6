"""msf-bench pieces that do not time anything: schedule, ratios, extrapolation, report files."""

from __future__ import annotations

import json

from msfnet.bench.cli import schedule
from msfnet.bench.report import per_light_estimate, write_report
from msfnet.bench.workloads import WORKLOADS


def _row(wl, variant, threads, median, lights, pixels):
    return {"workload": wl, "label": wl, "variant": variant, "threads": threads,
            "median_s": median, "p90_s": median, "peak_rss_mb": 100.0, "lights": lights,
            "pixels": pixels, "gflop": 1.0, "gflops_per_s": 1.0 / median,
            "max_deg": 0.1, "mean_deg": 0.01}


def test_per_light_extrapolation_is_linear():
    rows = [_row("b", "per-light", 2, 10.0, 32, 128 * 128)]
    assert per_light_estimate(rows, 32, 128 * 128, 2) == (10.0, True)
    est, measured = per_light_estimate(rows, 96, 2 * 128 * 128, 2)
    assert not measured and abs(est - 60.0) < 1e-9
    assert per_light_estimate(rows, 32, 16384, 1) is None


def test_full_schedule_has_reference_first_and_required_cells():
    cells = schedule(False, ["ort-fp32", "ort-int8", "torch-fp32", "per-light"], [2, 1])
    keys = {(wl.key, v, t) for wl, v, t, _, _ in cells}
    for wl in WORKLOADS:
        assert (wl.key, "ort-fp32", 2) in keys
        assert ((wl.key, "ort-fp32", 1) in keys) == (wl.key != "c")  # (c): 2 threads only
        assert (wl.key, "torch-fp32", 2) in keys
        first = next(v for w, v, t, _, _ in cells if w.key == wl.key)
        assert first == "torch-fp32"
    assert ("b", "per-light", 2) in keys


def test_report_ratios_and_files(tmp_path):
    rows = [_row("b", "torch-fp32", 2, 4.0, 32, 16384), _row("b", "ort-fp32", 2, 2.0, 32, 16384),
            _row("b", "ort-int8", 2, 0.5, 32, 16384), _row("b", "per-light", 2, 8.0, 32, 16384)]
    result = {"date": "d", "quick": True, "elapsed_s": 1.0, "rows": rows,
              "machine": {"cpu": "x", "cores": 2, "isa_flags": [], "platform": "p",
                          "python": "3", "onnxruntime": "1"},
              "peaks": [{"dtype": "fp32", "threads": 2, "gflops": 2.0}],
              "models": {"random_weights": True, "checkpoint": "c"}, "variants": {},
              "e2e": [{"variant": "ort-int8", "threads": 2, "lights": 32, "height": 128,
                       "width": 256, "median_s": 1.0, "peak_rss_mb": 500.0,
                       "mean_deg_vs_fp32": 0.2, "max_deg_vs_fp32": 1.0}]}
    files = write_report(result, tmp_path)
    data = json.loads((tmp_path / "report.json").read_text())
    int8 = next(r for r in data["rows"] if r["variant"] == "ort-int8")
    assert int8["x_vs_ort_fp32"] == 4.0 and int8["x_vs_torch"] == 8.0
    assert int8["x_vs_per_light"] == 16.0
    assert data["e2e"][0]["x_vs_per_light"] == 16.0  # 8 s * 2 (pixels) / 1 s
    md = (tmp_path / "REPORT.md").read_text()
    assert "4.00x fp32 ORT" in md and "**met**" in md
    assert "| (b) fp32 ORT" not in files["table"]
