"""msf-bench's torch-free modes: --onnx (engines and devices table), --ladder, --requirements."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
from _runtime_helpers import tiny_msfnet_onnx

from msfnet.bench import edge, ladder
from msfnet.common import cpu
from msfnet.common.cpu import CpuInfo
from msfnet.common.vocabulary import speaking_as

SHARED = Path(__file__).resolve().parents[2].parent / "shared" / "data"


def test_edge_table_has_the_ultralytics_columns() -> None:
    rows = [
        edge.EdgeRow("OpenVINO bf16", "ok", 4.27, 4.123, 812.4, 567.0),
        edge.EdgeRow("--device cuda", "skipped: ONNX Runtime has no CUDA", 4.27, None, None, None),
    ]
    text = edge.edge_table(rows).splitlines()
    assert text[0].startswith(
        "| format | status | size (MB) | MAE (deg, mean of DiLiGenT ball / bear / harvest 128 px "
        "crops, 12 lights) | ms"
    )
    assert text[2] == "| OpenVINO bf16 | ✅ | 4.3 | 4.12 | 812 | 567 |"
    assert text[3] == "| --device cuda | ❌ skipped: ONNX Runtime has no CUDA | 4.3 | - | - | - |"


def test_requirements_and_ladder_tables() -> None:
    reqs = [
        edge.Requirement(256, 12, "openvino bf16", 1.234, 456.0),
        edge.Requirement(512, 32, "onnxruntime fp32", None, None, "failed: MemoryError"),
    ]
    lines = edge.requirements_table(reqs).splitlines()
    assert lines[2] == "| 256x256 | 12 | openvino bf16 | 1.23 | 456 |"
    assert lines[3] == "| 512x512 | 32 | onnxruntime fp32 | failed: MemoryError | - |"
    maes = {"ballPNG": 4.0, "bearPNG": 6.0, "harvestPNG": 20.0}
    rows = [
        ladder.LadderRow("full", "all", "openvino bf16", 40.0, 2000.0, maes, 0.3),
        ladder.LadderRow(
            "balanced", "half", "openvino bf16", 10.0, 1200.0, {**maes, "bearPNG": 6.6}, 0.2
        ),
    ]
    table = ladder.ladder_table(rows).splitlines()
    assert "| mean MAE | vs full | detail |" in table[0]
    assert table[2].startswith("| full | openvino bf16 | 40.00 | 1.00 | 2000 | 4.00 | 6.00 | 20.00")
    # 4x faster, mean MAE 10.2 vs 10.0
    assert table[3].endswith("| 10.00 | 4.00 | 1200 | 4.00 | 6.60 | 20.00 | 10.20 | +0.20 | 0.20 |")


def test_edge_paths_say_why_a_row_cannot_run(tmp_path: Path, monkeypatch) -> None:
    model = tiny_msfnet_onnx(tmp_path / "tiny.onnx")
    monkeypatch.setattr(cpu, "detect_cpu", lambda: CpuInfo.from_flags(["avx2"], model="AVX2"))
    monkeypatch.setattr(
        "msfnet.runtime.engines.installed_engines", lambda: {"onnxruntime", "openvino"}
    )
    with speaking_as("msf-bench"):  # its rows name devices as the command's flag
        paths, skipped = edge.edge_paths(model)
    assert [p.label for p in paths[:2]] == ["ONNX Runtime fp32", "OpenVINO fp32"]
    bf16 = next(r for r in skipped if r.format == "OpenVINO bf16")
    assert bf16.status == "no native bf16 on this CPU"
    # devices absent here are rows that say so, never errors
    devices = [r for r in skipped if r.format.startswith("--device ")]
    assert devices and all(r.status.startswith("skipped: ") for r in devices)
    assert all("\n" not in r.status for r in devices)
    monkeypatch.setattr("msfnet.runtime.engines.installed_engines", lambda: {"onnxruntime"})
    paths, skipped = edge.edge_paths(model)
    assert [p.label for p in paths if p.device is None] == ["ONNX Runtime fp32"]
    assert any(r.status == "openvino not installed" for r in skipped)


def _torch_blocked_env(tmp_path: Path) -> dict[str, str]:
    """PYTHONPATH with a `torch` package that refuses to import: blocks torch in msf-bench and
    in every worker process it starts (torch is installed here)."""
    import os

    block = tmp_path / "no_torch" / "torch"
    block.mkdir(parents=True)
    (block / "__init__.py").write_text("raise ImportError('torch is blocked: edge install')\n")
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        p for p in (str(block.parent), env.get("PYTHONPATH", "")) if p
    )
    return env


def test_a_foreign_onnx_file_is_one_line(tmp_path: Path) -> None:
    bogus = tmp_path / "x.onnx"
    bogus.write_bytes(b"not onnx")
    done = subprocess.run(
        [sys.executable, "-m", "msfnet.bench.cli", "--onnx", str(bogus), "-o", str(tmp_path / "r")],
        capture_output=True,
        text=True,
        env=_torch_blocked_env(tmp_path),
        timeout=120,
    )
    assert done.returncode == 2
    assert done.stderr.strip().startswith("msf-bench: error: ") and "cannot load" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "r").exists()


@pytest.mark.slow
def test_msf_bench_onnx_runs_without_torch(tmp_path: Path) -> None:
    if not (SHARED / "DiLiGenT" / "harvestPNG").is_dir():
        pytest.skip(f"shared data not found: {SHARED}")
    model = tiny_msfnet_onnx(tmp_path / "tiny.onnx")
    report = tmp_path / "report"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "msfnet.bench.cli",
            "--onnx",
            str(model),
            "--data",
            str(SHARED),
            "--threads",
            "1",
            "-o",
            str(report),
        ],
        capture_output=True,
        text=True,
        env=_torch_blocked_env(tmp_path),
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    text = (report / "REPORT.md").read_text()
    assert "| ONNX Runtime fp32 | ✅ | " in text
    assert "| OpenVINO fp32 | ✅ | " in text
    assert "torch" not in done.stderr


def test_a_path_whose_normals_are_unusable_gets_no_tick(tmp_path: Path, monkeypatch) -> None:
    """A model answering NaN scored 180 deg on every engine, and every row showed a tick."""
    assert edge._answer_status(4.1) is None
    for mae in (180.0, float("nan"), 95.0):
        assert edge._answer_status(mae).startswith("failed: MAE")
    model = tmp_path / "m.onnx"
    model.write_bytes(b"x" * 1000)
    monkeypatch.setattr(
        edge,
        "edge_paths",
        lambda m, info=None: (
            [edge.EdgePath("ONNX Runtime fp32", "onnxruntime", "fp32", None)],
            [],
        ),
    )
    from msfnet.runtime import engines

    monkeypatch.setattr(engines, "read_model_file", lambda path: SimpleNamespace(train_lights=32))
    monkeypatch.setattr(edge, "validation_crops", lambda data, tl: [])
    monkeypatch.setattr(
        edge,
        "run_worker",
        lambda kind, spec, scratch: {"mae_deg": 180.0, "ms": 5.0, "peak_mb": 300.0},
    )
    rows = edge.onnx_rows(model, tmp_path, 1, tmp_path)
    assert rows[0].status.startswith("failed: MAE 180 deg")
    assert "| ONNX Runtime fp32 | ❌ failed: MAE 180 deg" in edge.edge_table(rows)


def test_device_rows_report_their_parity_with_cpu_fp32() -> None:
    assert edge._parity_status(None) == "ok"
    good = edge._parity_status((0.012, 0.31))
    assert good == "ok: parity 0.012 / 0.31 deg vs CPU fp32"
    assert edge._parity_status((0.8, 4.0)).startswith("failed: parity 0.800")
    row = edge.EdgeRow("--device cuda", good, 4.27, 4.1, 12.0, 900.0)
    assert "| --device cuda | ✅: parity 0.012 / 0.31 deg vs CPU fp32 |" in edge.edge_table([row])


@pytest.mark.slow
def test_msf_bench_ladder_and_requirements_run_without_torch(tmp_path: Path) -> None:
    if not (SHARED / "DiLiGenT" / "harvestPNG").is_dir():
        pytest.skip(f"shared data not found: {SHARED}")
    import json
    from statistics import median

    model = tiny_msfnet_onnx(tmp_path / "tiny.onnx")
    report = tmp_path / "report"
    args = ["--onnx", str(model), "--data", str(SHARED), "--threads", "1", "-o", str(report)]
    done = subprocess.run(
        [sys.executable, "-m", "msfnet.bench.cli", *args, "--ladder", "--requirements", "--quick"],
        capture_output=True,
        text=True,
        env=_torch_blocked_env(tmp_path),
        timeout=900,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    data = json.loads((report / "report.json").read_text())
    assert [r["rung"] for r in data["ladder"]] == ["full", "balanced", "fast"]
    assert all(set(r["mae_deg"]) == {"ballPNG", "bearPNG", "harvestPNG"} for r in data["ladder"])
    cells = {(r["size"], r["lights"]) for r in data["requirements"]}
    assert cells == {(64, 8), (128, 8)}
    assert all(r["status"] == "ok" and r["peak_mb"] > 0 for r in data["requirements"])
    assert "## Speed ladder (--speed)" in (report / "REPORT.md").read_text()
    # medians of ladder.REPEAT runs, every run kept (one sample each moved 2.3x-3.1x)
    for r in data["requirements"]:
        assert len(r["samples_s"]) == ladder.REPEAT and r["seconds"] == median(r["samples_s"])
    for r in data["ladder"]:
        runs = r["samples_s"]
        assert all(len(v) == ladder.REPEAT for v in runs.values())
        assert r["seconds"] == pytest.approx(sum(median(v) for v in runs.values()), rel=1e-12)


@pytest.mark.parametrize(
    "extra",
    [
        ["--checkpoint", "a.pth"],
        ["--random-weights"],
        ["--no-e2e"],
        ["--lights", "8"],
        # read by --requirements only; one thread count measured
        ["--stack", "s"],
        ["--quick"],
        ["--threads", "1,4"],
    ],
)
def test_torch_benchmark_options_are_refused_in_edge_mode(
    tmp_path: Path, extra: list[str], capsys
) -> None:
    """They were ignored in silence: a report on X that never named the --checkpoint Y."""
    from msfnet.bench.cli import main as bench_main

    out = tmp_path / "r"
    assert bench_main(["--onnx", str(tmp_path / "x.onnx"), "-o", str(out), *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and extra[0] in err[0] and "--onnx" in err[0], err
    assert not out.exists()


@pytest.mark.skipif(not (SHARED / "DiLiGenT").is_dir(), reason="needs ../shared/data/DiLiGenT")
def test_onnx_rows_feed_the_network_the_scaling_its_file_declares(
    tmp_path: Path, monkeypatch
) -> None:
    """msf-bench --onnx scored a model exported with --train-lights 96 as if trained on 32
    lights: its MAE was not what msf-run gets from the same file."""
    import numpy as np

    from msfnet.runtime.contract import TRAIN_LIGHTS

    base = edge.validation_crops(SHARED, TRAIN_LIGHTS)
    wide = edge.validation_crops(SHARED, 96)
    scale = np.sqrt(TRAIN_LIGHTS / 96)  # images are multiplied by sqrt(N / train_lights)
    for a, b in zip(base, wide, strict=True):
        np.testing.assert_allclose(b["images"], a["images"] * scale, rtol=1e-5, atol=1e-7)

    # the row processes get crops cut as the file declares (msfnet.train_lights 96 here)
    model = tiny_msfnet_onnx(tmp_path / "m.onnx", **{"msfnet.train_lights": "96"})
    seen = []
    real = edge.validation_crops
    monkeypatch.setattr(
        edge, "validation_crops", lambda data, tl: seen.append(tl) or real(data, tl)
    )
    monkeypatch.setattr(
        edge, "edge_paths", lambda m, info=None: ([edge.EdgePath("ORT", "onnxruntime", "fp32")], [])
    )
    specs = []
    monkeypatch.setattr(
        edge,
        "run_worker",
        lambda kind, spec, scratch: specs.append(spec) or {"mae_deg": 3.0, "ms": 1.0, "peak_mb": 1},
    )
    edge.onnx_rows(model, SHARED, 1, tmp_path)
    assert seen == [96]
    crops = edge.read_crops(Path(specs[0]["crops"]))
    assert [c["name"] for c in crops] == [c["name"] for c in wide]
    for a, b in zip(crops, wide, strict=True):
        np.testing.assert_array_equal(a["images"], b["images"])

    class Engine:
        info = SimpleNamespace(train_lights=96)

        def run(self, images, lights):  # type: ignore[no-untyped-def]
            up = np.zeros((3, *images.shape[-2:]), np.float32)
            up[2] = 1.0
            return [up]

    monkeypatch.setattr(edge, "_open", lambda spec: Engine())
    row = edge.measure_path({"model": "m.onnx", "crops": specs[0]["crops"], "repeats": 1})
    assert 0 < row["mae_deg"] < 90  # scored against the crops' ground truth


def test_requirements_run_onnx_runtime_in_the_files_own_precision(
    tmp_path: Path, monkeypatch
) -> None:
    """The second engine was ONNX Runtime fp32 whatever the file: an int8 export failed on
    half the grid."""
    from msfnet.runtime import engines

    monkeypatch.setattr(engines, "read_model_file", lambda path: path)
    monkeypatch.setattr(engines, "model_precision", lambda info: "int8")
    seen = []

    def worker(kind, spec, scratch):  # type: ignore[no-untyped-def]
        seen.append((spec["engine"], spec["precision"]))
        return {"seconds": 1.0, "peak_mb": 100.0, "samples_s": [1.0, 1.1, 0.9]}

    monkeypatch.setattr(edge, "run_worker", worker)
    edge.requirement_rows(tmp_path / "m_int8.onnx", tmp_path, 1, tmp_path, quick=True)
    assert set(seen) == {(None, None), ("onnxruntime", "int8")}
    seen.clear()
    edge.requirement_rows(None, tmp_path, 1, tmp_path, quick=True)  # the bundled model
    assert set(seen) == {(None, None), ("onnxruntime", "fp32")}


def test_a_ladder_worker_refusing_its_input_is_an_input_error(tmp_path: Path, monkeypatch) -> None:
    """Any worker failure was 'internal error ... please report it', exit 1."""
    import json

    from msfnet.common.errors import InputError
    from msfnet.common.vocabulary import opt

    def refuse(spec):  # type: ignore[no-untyped-def]  # worded as msf-bench's own line
        raise InputError(f"exported for exactly 8 lights ({opt('speed')})", "m.onnx")

    monkeypatch.setattr(ladder, "measure_rung", refuse)
    spec = tmp_path / "spec.json"
    result = tmp_path / "ladder-full.json"
    spec.write_text(json.dumps({"result": str(result)}))
    assert ladder.main([str(spec)]) == 2
    assert json.loads(result.read_text()) == {
        "input_error": "exported for exactly 8 lights (--speed)",
        "path": "m.onnx",
    }

    class Done:
        returncode = 2
        stderr = ""

    monkeypatch.setattr(ladder, "run_process", lambda argv: Done())
    with pytest.raises(InputError, match=r"^m.onnx: speed rung full: exported for exactly 8"):
        ladder.ladder_rows(None, tmp_path, rungs=("full",), scratch=tmp_path)


def _edge_main(*argv: str) -> int:
    from msfnet.bench import cli

    return cli.main(list(argv))


def test_edge_inputs_are_checked_before_any_cell_runs(
    tmp_path: Path, monkeypatch, capfd: pytest.CaptureFixture[str]
) -> None:
    """Each was found cell by cell: a report of failed rows with exit 0, or an internal
    error after minutes of work."""
    from _runtime_helpers import png_stack

    def unreached(*args, **kwargs):  # type: ignore[no-untyped-def]
        raise AssertionError("a cell ran before the checks")

    monkeypatch.setattr(edge, "onnx_rows", unreached)
    monkeypatch.setattr(edge, "requirement_rows", unreached)
    monkeypatch.setattr(ladder, "ladder_rows", unreached)
    monkeypatch.delenv("MSFNET_DATA", raising=False)
    out = tmp_path / "r"

    def one_error(*parts: str) -> None:
        err = capfd.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("msf-bench: error: "), err
        assert all(p in err[0] for p in parts), err
        assert not out.exists()

    # a static-shape export: --onnx scores 12-light 128 px crops it cannot take
    static = tiny_msfnet_onnx(tmp_path / "s.onnx", **{"msfnet.static_shape": "8,64,64"})
    assert _edge_main("--onnx", str(static), "-o", str(out)) == 2
    one_error("s.onnx", "static shape: 8 lights at 64 x 64 px")
    # validation objects without ground truth
    data = tmp_path / "data"
    for name in ("ballPNG", "bearPNG", "harvestPNG"):
        (data / "DiLiGenT" / name).mkdir(parents=True)
    assert _edge_main("--ladder", "--data", str(data), "-o", str(out)) == 2
    one_error("ballPNG", "no ground-truth normals")
    # the requirements grid: its stack is read first; no data root is needed beside it
    monkeypatch.chdir(tmp_path)
    assert _edge_main("--requirements", "--stack", str(tmp_path / "nowhere"), "-o", str(out)) == 2
    one_error("nowhere")
    stack = png_stack(tmp_path / "stack", 8)
    monkeypatch.setattr(edge, "requirement_rows", lambda *a, **k: [])
    assert _edge_main("--requirements", "--quick", "--stack", str(stack), "-o", str(out)) == 0
    assert (out / "REPORT.md").is_file()
