"""msf-bench pieces that do not time anything: schedule, ratios, extrapolation, report files."""

from __future__ import annotations

import json

from msfnet.bench.cli import schedule
from msfnet.bench.report import per_light_estimate, write_report
from msfnet.bench.workloads import WORKLOADS


def _row(wl, variant, threads, median, lights, pixels):
    return {
        "workload": wl,
        "label": wl,
        "variant": variant,
        "threads": threads,
        "median_s": median,
        "p90_s": median,
        "peak_rss_mb": 100.0,
        "lights": lights,
        "pixels": pixels,
        "gflop": 1.0,
        "gflops_per_s": 1.0 / median,
        "max_deg": 0.1,
        "mean_deg": 0.01,
    }


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
    rows = [
        _row("b", "torch-fp32", 2, 4.0, 32, 16384),
        _row("b", "ort-fp32", 2, 2.0, 32, 16384),
        _row("b", "ort-int8", 2, 0.5, 32, 16384),
        _row("b", "per-light", 2, 8.0, 32, 16384),
    ]
    result = {
        "date": "d",
        "quick": True,
        "elapsed_s": 1.0,
        "rows": rows,
        "machine": {
            "cpu": "x",
            "cores": 2,
            "isa_flags": [],
            "platform": "p",
            "python": "3",
            "onnxruntime": "1",
        },
        "peaks": [{"dtype": "fp32", "threads": 2, "gflops": 2.0}],
        "models": {"random_weights": True, "checkpoint": "c"},
        "variants": {},
        "e2e": [
            {
                "variant": "default",
                "threads": 2,
                "lights": 32,
                "height": 128,
                "width": 256,
                "median_s": 1.0,
                "peak_rss_mb": 500.0,
                "mean_deg_vs_fp32": 0.2,
                "max_deg_vs_fp32": 1.0,
                "engine": "onnxruntime",
                "precision": "int8",
                "graph": "monolithic",
                "command": "msf-run STACK",
                "choice": "onnxruntime int8: why",
            }
        ],
    }
    files = write_report(result, tmp_path)
    data = json.loads((tmp_path / "report.json").read_text())
    int8 = next(r for r in data["rows"] if r["variant"] == "ort-int8")
    assert int8["x_vs_ort_fp32"] == 4.0 and int8["x_vs_torch"] == 8.0
    assert int8["x_vs_per_light"] == 16.0
    assert data["e2e"][0]["x_vs_per_light"] == 16.0  # 8 s * 2 (pixels) / 1 s
    md = (tmp_path / "REPORT.md").read_text()
    # (d) default: 16x the per-light loop at 500 MiB -> the 60x half fails
    assert "16.0x the per-light loop" in md and "target >= 60x and <= 1536 MiB **not met**" in md
    # the default path (int8 here) on (b): 4x ORT fp32 within 0.5 deg on a non-bf16 CPU
    assert "(ort-int8, what msf-run picks here), 2 threads: 4.00x ORT fp32" in md
    assert "target >= 1.5x within 0.5 deg on a non-bf16 CPU **met**" in md
    assert "msf-run's engine choice: onnxruntime int8: why" in md
    assert "| (b) fp32 ORT" not in files["table"]
    assert "bytecode cache" not in md  # not recorded: nothing said
    result["machine"]["python_bytecode_cache"] = False
    write_report(result, tmp_path / "nocache")
    assert "bytecode cache is off here" in (tmp_path / "nocache" / "REPORT.md").read_text()


def test_each_variant_is_compared_with_its_own_precisions_peak(tmp_path):
    rows = [
        _row("b", "ort-fp32", 2, 2.0, 32, 16384),
        _row("b", "ort-int8", 2, 1.0, 32, 16384),
        _row("b", "ov-bf16", 2, 0.25, 32, 16384),
        _row("b", "torch-fp32", 2, 4.0, 32, 16384),
    ]
    peaks = [
        {"engine": "torch", "dtype": "fp32", "threads": 2, "gflops": 1.0},
        {"engine": "onnxruntime", "dtype": "fp32", "threads": 2, "gflops": 2.0},
        {"engine": "onnxruntime", "dtype": "int8", "threads": 2, "gflops": 20.0},
        {"engine": "openvino", "dtype": "bf16", "threads": 2, "gflops": 8.0},
    ]
    features = {
        "avx2": True,
        "avx512f": True,
        "avx512_vnni": True,
        "avx_vnni": True,
        "avx512_bf16": True,
        "amx_bf16": True,
        "amx_int8": True,
        "source": "py-cpuinfo",
    }
    result = {
        "date": "d",
        "quick": True,
        "elapsed_s": 1.0,
        "rows": rows,
        "peaks": peaks,
        "machine": {
            "cpu": "Xeon",
            "cores": 2,
            "isa_flags": ["amx_bf16"],
            "cpu_features": features,
            "platform": "p",
            "python": "3",
            "onnxruntime": "1",
            "openvino": "2026.4",
        },
        "models": {"random_weights": True, "checkpoint": "c"},
        "variants": {},
        "dispatch": {"fp32": "openvino bf16: fp32 model; CPU has native bf16 (AMX)"},
    }
    write_report(result, tmp_path)
    data = {r["variant"]: r for r in json.loads((tmp_path / "report.json").read_text())["rows"]}
    # gflops_per_s is 1/median: 0.5, 1, 4, 0.25 GFLOP/s
    assert data["ort-fp32"]["fraction_own_peak"] == 0.25  # 0.5 / ORT fp32 2.0
    assert data["ort-int8"]["fraction_own_peak"] == 0.05  # 1 / ORT int8 20
    assert data["ov-bf16"]["fraction_own_peak"] == 0.5  # 4 / OpenVINO bf16 8
    assert data["torch-fp32"]["fraction_own_peak"] == 0.25  # 0.25 / torch fp32 1
    # '% fp32 peak' is against ORT's own fp32 GEMM, not torch's
    assert data["ov-bf16"]["fraction_fp32_peak"] == 2.0
    md = (tmp_path / "REPORT.md").read_text()
    assert "amx_bf16 yes" in md and "avx512_bf16 yes" in md and "openvino 2026.4" in md
    assert "dispatch on this machine, fp32 model: openvino bf16" in md
    # the fastest (b) variant against its own precision's peak
    assert (
        "fastest variant on (b), ov-bf16: 50 % of the same-run openvino bf16 matmul peak: "
        "target >= 80 % **not met**" in md
    )


def test_openvino_bf16_variants_are_scheduled_on_every_workload():
    variants = ["ort-fp32", "ov-bf16", "ov-bf16-staged", "torch-fp32", "per-light"]
    keys = {(wl.key, v, t) for wl, v, t, _, _ in schedule(False, variants, [2, 1])}
    for wl in WORKLOADS:
        for v in ("ov-bf16", "ov-bf16-staged"):
            assert (wl.key, v, 2) in keys
    assert ("c", "per-light", 2) not in keys  # extrapolated, too slow to run
    assert ("b", "ov-bf16-staged", 1) not in keys  # 1 thread on big inputs: shipped ORT only


def _lights_result(bf16: bool, measured: bool) -> dict:
    """A --lights 8 report: (d) on 8 lights of a 100 x 50 image, default command 0.5 s with a
    0.2 s inference stage; the per-light loop 30 s on that whole image (``measured``), else
    only a (b) crop run to extrapolate from (8 s at 32 lights, 16384 px)."""
    rows = [_row("b", "per-light", 2, 8.0, 32, 16384)]
    if measured:
        rows.append({**_row("d", "per-light", 2, 30.0, 8, 5000), "times_s": [29.0, 31.0]})
    return {
        "date": "d",
        "quick": False,
        "elapsed_s": 1.0,
        "rows": rows,
        "lights": 8,
        "machine": {
            "cpu": "x",
            "cores": 2,
            "isa_flags": [],
            "cpu_features": {"avx2": True, "avx512_bf16": bf16, "amx_bf16": False},
            "platform": "p",
            "python": "3",
            "onnxruntime": "1",
        },
        "peaks": [],
        "models": {"random_weights": True, "checkpoint": "c"},
        "variants": {},
        "e2e": [
            {
                "variant": "default",
                "threads": 2,
                "lights": 8,
                "height": 50,
                "width": 100,
                "walls_s": [0.6, 0.5, 0.4],
                "median_s": 0.5,
                "inference_s": 0.2,
                "peak_rss_mb": 300.0,
                "command": "msf-run STACK --max-lights 8",
            }
        ],
    }


def test_lights_runs_compare_with_the_per_light_loop_measured_on_the_same_input(tmp_path):
    write_report(_lights_result(bf16=True, measured=True), tmp_path)
    run = json.loads((tmp_path / "report.json").read_text())["e2e"][0]
    # the whole-image row, not the (b) crop scaled (8 s * 8/32 * 5000/16384 = 0.61 s)
    assert run["per_light_measured"] and run["per_light_estimate_s"] == 30.0
    assert run["x_vs_per_light"] == 60.0  # 30 s / 0.5 s end to end
    assert abs(run["x_vs_per_light_inference"] - 150.0) < 1e-9  # 30 s / 0.2 s inference
    md = (tmp_path / "REPORT.md").read_text()
    assert (
        "60.0x the per-light loop (30.0 s, measured on the same whole 8-light image); "
        "msf-run's inference stage alone 0.20 s, 150.0x; peak RSS 300 MiB: target >= 60x "
        "on a CPU with native bf16 **met**" in md
    )
    assert "(median of 29.0, 31.0)" in md and "the per-light loop on (d)'s input" in md


def test_lights_target_depends_on_native_bf16_and_marks_extrapolation(tmp_path):
    write_report(_lights_result(bf16=False, measured=False), tmp_path)
    run = json.loads((tmp_path / "report.json").read_text())["e2e"][0]
    assert not run["per_light_measured"]
    assert abs(run["per_light_estimate_s"] - 8.0 * 8 / 32 * 5000 / 16384) < 1e-9
    md = (tmp_path / "REPORT.md").read_text()
    assert "extrapolated from (b) to the whole 8-light image" in md
    assert "target >= 30x on a CPU without native bf16 **not met**" in md
    assert "| ~1.2 | 0.20 | ~3.1 |" in md  # x per-light, inference s, inference only


def test_a_default_path_without_a_b_variant_is_said_not_measured(tmp_path):
    """Where msf-run's default (e.g. OpenVINO fp32 staged) has no (a)-(c) variant, the (b)
    target line says so instead of vanishing; a path with a variant is judged as before."""
    result = _lights_result(bf16=True, measured=True)
    result["e2e"][0].update(engine="openvino", precision="fp32", graph="staged")
    write_report(result, tmp_path)
    md = (tmp_path / "REPORT.md").read_text()
    assert (
        "the default path on (b) (openvino fp32 staged, what msf-run picks here): not "
        "measured, no (a)-(c) variant runs it" in md
    )
    result["e2e"][0].update(precision="bf16")  # a path with a variant, not run at 2 threads
    result["rows"].append({**_row("b", "ov-bf16-staged", 1, 1.0, 32, 16384), "mean_deg": 0.1})
    write_report(result, tmp_path / "one-thread")
    md = (tmp_path / "one-thread" / "REPORT.md").read_text()
    assert (
        "(openvino bf16 staged, what msf-run picks here): not measured, no ov-bf16-staged "
        "row at 2 threads in this run" in md
    )
    result["rows"].append({**_row("b", "ov-bf16-staged", 2, 1.0, 32, 16384), "mean_deg": 0.1})
    write_report(result, tmp_path / "again")
    md = (tmp_path / "again" / "REPORT.md").read_text()
    assert "not measured, no (a)-(c)" not in md and "the default path on (b) (ov-bf16-staged" in md


def test_the_whole_image_row_is_never_scaled_to_other_sizes():
    rows = [_row("d", "per-light", 2, 30.0, 8, 5000)]
    assert per_light_estimate(rows, 8, 5000, 2) == (30.0, True)
    assert per_light_estimate(rows, 32, 16384, 2) is None  # crops: no (a)-(c) run to scale


def test_the_int8_default_path_has_its_own_variant() -> None:
    """msf-run's default where the int8 twin is (OpenVINO int8, staged) is timed on (a)-(c)
    as ov-int8-staged, on the staged int8 export (which needs the calibration stacks)."""
    from msfnet.bench.cli import INT8_MODEL_VARIANTS
    from msfnet.bench.report import PATH_VARIANT
    from msfnet.bench.workloads import VARIANTS

    assert PATH_VARIANT[("openvino", "int8", "staged")] == "ov-int8-staged"
    assert VARIANTS["ov-int8-staged"].model == "int8_staged"
    assert set(INT8_MODEL_VARIANTS) == {"ort-int8", "ov-int8-staged"}
