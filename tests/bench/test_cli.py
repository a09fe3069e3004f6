"""msf-bench's report folder follows the output rules of every msfnet command: inputs and the
folder are checked before any work, the report is built in a staging folder and appears whole
or not at all (also on Ctrl-C and kill), and an earlier report is replaced only with
--overwrite. The benchmark itself is replaced by a stand-in here, except in the slow test."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from _runtime_helpers import png_stack

pytest.importorskip("torch")

from msfnet.bench import cli
from msfnet.common.files import MANIFEST
from msfnet.common.signals import Terminated


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """16 lights, 72 x 72 px: enough for the --quick workloads (16 lights, 64 x 64 crops)."""
    return png_stack(tmp_path_factory.mktemp("bench") / "ball", 16, n=16, h=72, w=72)


def _argv(stack: Path, out: Path, *extra: str) -> list[str]:
    return [
        "--stack",
        str(stack),
        "--calib",
        str(stack),
        "-o",
        str(out),
        "--quick",
        "--variants",
        "ort-fp32",
        "--threads",
        "1",
        "--no-e2e",
        "--random-weights",
        *extra,
    ]


def _tree(folder: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()
    }


def _unreached(*args: object) -> dict:
    raise AssertionError("the benchmark ran before the checks")


def _fake_bench(tag: str, fail: type[BaseException] | None = None):
    """A stand-in for cli.bench: writes a model into the staging folder as the real one does
    (``fail``: then stops there, as Ctrl-C or a kill would) and returns a small result."""

    def bench(args, plan, data, work: Path, scratch: Path) -> dict:
        assert set(data.feeds) == {"a", "b"} and plan.variants == ["ort-fp32"]
        (work / "models").mkdir()
        model = work / "models" / "msfnet_fp32.onnx"
        model.write_text(tag)
        (scratch / "input_a.npz").write_text("scratch")
        if fail is not None:
            raise fail(15) if fail is Terminated else fail()
        return {
            "date": "d",
            "quick": True,
            "elapsed_s": 1.0,
            "rows": [],
            "notes": [],
            "machine": {
                "cpu": "x",
                "cores": 1,
                "isa_flags": [],
                "platform": "p",
                "python": "3",
                "onnxruntime": "1",
            },
            "peaks": [],
            "variants": {},
            "dispatch": {},
            "models": {
                "random_weights": True,
                "checkpoint": str(work / "models" / "r.pth"),
                "fp32": str(model),
            },
        }

    return bench


def _one_error(capfd: pytest.CaptureFixture[str]) -> str:
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("msf-bench: "), err
    return err[0]


@pytest.mark.parametrize("where", ["stack", "inside stack", "holds checkpoint"])
def test_a_report_folder_that_is_or_holds_an_input_is_refused(
    where: str,
    stack: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capfd: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.setattr(cli, "bench", _unreached)
    before = _tree(stack)
    if where == "holds checkpoint":
        ckpt = tmp_path / "out" / "weights.pth"
        ckpt.parent.mkdir()
        ckpt.write_bytes(b"w")
        argv = [a for a in _argv(stack, tmp_path / "out") if a != "--random-weights"]
        argv += ["--checkpoint", str(ckpt)]
        expected = "contains the input"
    else:
        out = stack if where == "stack" else stack / "report"
        argv = _argv(stack, out)
        expected = "replace an input" if where == "stack" else "inside the input folder"
    assert cli.main(argv) == 2
    assert expected in _one_error(capfd)
    assert _tree(stack) == before and not (stack / "models").exists()


def test_a_missing_checkpoint_is_one_line_and_writes_nothing(
    stack: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(cli, "bench", _unreached)
    argv = [a for a in _argv(stack, tmp_path / "bench" / "bad") if a != "--random-weights"]
    assert cli.main([*argv, "--checkpoint", str(tmp_path / "BAD.pth")]) == 2
    line = _one_error(capfd)
    assert "checkpoint not found" in line and "BAD.pth" in line
    assert list(tmp_path.iterdir()) == []  # not even bench/ or bench/bad/models


def test_the_report_appears_whole_and_is_replaced_only_with_overwrite(
    stack: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "report"
    monkeypatch.setattr(cli, "bench", _fake_bench("first"))
    assert cli.main(_argv(stack, out)) == 0
    capfd.readouterr()
    files = _tree(out)
    assert {"REPORT.md", "report.json", MANIFEST, "models/msfnet_fp32.onnx"} <= set(files)
    assert files["models/msfnet_fp32.onnx"] == b"first"
    assert list(tmp_path.iterdir()) == [out]  # no staging or scratch left beside it
    # the report names the published files, not the staging folder they were written in
    data = json.loads((out / "report.json").read_text())
    assert data["models"]["fp32"] == str(out / "models" / "msfnet_fp32.onnx")
    assert ".msf-partial" not in (out / "report.json").read_text()

    monkeypatch.setattr(cli, "bench", _unreached)
    assert cli.main(_argv(stack, out)) == 2
    assert "--overwrite" in _one_error(capfd)
    assert _tree(out) == files

    monkeypatch.setattr(cli, "bench", _fake_bench("second"))
    assert cli.main(_argv(stack, out, "--overwrite")) == 0
    assert (out / "models" / "msfnet_fp32.onnx").read_text() == "second"
    assert list(tmp_path.iterdir()) == [out]


def test_overwrite_never_deletes_files_msfnet_did_not_write(
    stack: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "bench"
    (out / "src").mkdir(parents=True)
    (out / "REPORT.md").write_text("an old report beside source code\n")
    monkeypatch.setattr(cli, "bench", _unreached)
    assert cli.main(_argv(stack, out, "--overwrite")) == 2
    assert "did not write" in _one_error(capfd)
    assert (out / "REPORT.md").read_text() == "an old report beside source code\n"


@pytest.mark.parametrize(("signal_", "code"), [(KeyboardInterrupt, 130), (Terminated, 143)])
@pytest.mark.parametrize("earlier", [False, True])
def test_an_interrupted_run_leaves_no_partial_report(
    signal_: type[BaseException],
    code: int,
    earlier: bool,
    stack: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capfd: pytest.CaptureFixture[str],
) -> None:
    """Ctrl-C or SIGTERM after the models are exported: no OUT/models/*.onnx left, and an
    earlier report stays as it was."""
    out = tmp_path / "report"
    if earlier:
        monkeypatch.setattr(cli, "bench", _fake_bench("earlier"))
        assert cli.main(_argv(stack, out)) == 0
    before = _tree(out) if earlier else None
    capfd.readouterr()
    monkeypatch.setattr(cli, "bench", _fake_bench("new", fail=signal_))
    assert cli.main(_argv(stack, out, "--overwrite")) == code
    assert "nothing was written" in _one_error(capfd)
    if earlier:
        assert _tree(out) == before
        assert list(tmp_path.iterdir()) == [out]
    else:
        assert list(tmp_path.iterdir()) == []


def test_published_names_the_final_folder(tmp_path: Path) -> None:
    work = tmp_path / ".report.msf-partial-1-x"
    result = {
        "models": {"fp32": str(work / "models" / "a.onnx")},
        "e2e": [{"command": f"msf-run S -o {work}/e2e/default", "median_s": 1.0}],
        "data": {"stack": "/data/ball"},
    }
    got = cli.published(result, work, tmp_path / "report")
    assert got["models"]["fp32"] == str(tmp_path / "report" / "models" / "a.onnx")
    assert got["e2e"][0]["command"] == f"msf-run S -o {tmp_path / 'report'}/e2e/default"
    assert got["e2e"][0]["median_s"] == 1.0 and got["data"] == result["data"]


@pytest.mark.slow
def test_a_quick_run_writes_one_complete_report(
    stack: Path, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """The real benchmark (ort-fp32 and the torch reference, one thread, workload (d) included)
    on a small stack: everything it writes lies in the report folder, which names itself."""
    out = tmp_path / "report"
    before = _tree(stack)
    argv = [a for a in _argv(stack, out) if a != "--no-e2e"]
    assert cli.main(argv) == 0, capfd.readouterr().err
    files = set(_tree(out))
    assert {
        "REPORT.md",
        "report.json",
        MANIFEST,
        "models/msfnet_fp32.onnx",
        "models/msfnet_fp32_staged.onnx",
        "models/random_seed0.pth",
    } <= files
    assert any(f.startswith("e2e/default/") for f in files)
    text = (out / "report.json").read_text()
    assert ".msf-partial" not in text and str(out / "models" / "msfnet_fp32.onnx") in text
    data = json.loads(text)
    fp32 = [r for r in data["rows"] if r["variant"] == "ort-fp32"]
    assert fp32 and all(r["mean_deg"] < 0.01 for r in fp32)  # vs the PyTorch reference
    assert list(tmp_path.iterdir()) == [out] and _tree(stack) == before
    capfd.readouterr()
    assert cli.main(argv) == 2  # an earlier report: --overwrite needed
    assert "--overwrite" in _one_error(capfd)


def test_lights_times_msf_run_and_the_per_light_loop_on_the_same_whole_image(
    stack: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    """--quick --lights 4 on the 16-light 72 x 72 stack: (d) runs msf-run --max-lights 4 and
    the published per-light forward on the whole 4-light image (really, with random weights).
    Stand-ins for what other tests cover: the exports, the matmul peaks, the (a)-(c) cells and
    msf-run itself (a fake that records its light count); cells run in this process."""
    import numpy as np
    import torch

    from msfnet.bench import workloads
    from msfnet.model.checkpoint import save_checkpoint
    from msfnet.model.network import MSFNet
    from msfnet.runtime.stack import load_stack

    def models(plan, workdir: Path, calib) -> dict:
        workdir.mkdir()
        torch.manual_seed(0)
        save_checkpoint(MSFNet().eval(), workdir / "r.pth")
        return {
            "checkpoint": str(workdir / "r.pth"),
            "random_weights": True,
            "fp32": "f",
            "fp32_staged": "s",
        }

    gt = load_stack(stack).normals_gt
    max_lights: list[int | None] = []

    def msf_run(stack_dir, onnx, outdir: Path, threads, budget, lights, extra) -> dict:
        max_lights.append(lights)
        outdir.mkdir(parents=True, exist_ok=True)
        np.save(outdir / "normals.npy", gt)
        prof = {"engine": "openvino", "stages": {"inference": {"median_s": 0.01}}}
        return {"wall_s": 0.05, "peak_rss_mb": 100.0, "profile": prof, "command": "msf-run S"}

    def in_process(spec: dict, tmp: Path) -> dict:
        return workloads.run_cell(spec)

    monkeypatch.setattr(cli, "prepare_models", models)
    monkeypatch.setattr(cli, "engine_peaks", lambda threads, engines: [])
    monkeypatch.setattr(cli, "merge_peaks", lambda a, b: [])
    monkeypatch.setattr(cli, "schedule", lambda quick, variants, threads: [])
    monkeypatch.setattr(cli, "time_msf_run", msf_run)
    monkeypatch.setattr(cli, "run_cell_subprocess", in_process)
    out = tmp_path / "report"
    argv = [a for a in _argv(stack, out, "--lights", "4") if a != "--no-e2e"]
    assert cli.main(argv) == 0, capfd.readouterr().err
    assert max_lights and set(max_lights) == {4}  # every (d) row: msf-run --max-lights 4
    data = json.loads((out / "report.json").read_text())
    (row,) = [r for r in data["rows"] if r["workload"] == "d"]
    assert (row["variant"], row["lights"], row["pixels"], row["threads"]) == (
        "per-light",
        4,
        72 * 72,
        1,
    )
    assert len(row["times_s"]) == 1 and row["median_s"] > 0  # --quick: one timed run
    default = next(r for r in data["e2e"] if r["variant"] == "default")
    assert default["per_light_measured"] and default["lights"] == 4
    assert abs(default["x_vs_per_light"] - row["median_s"] / 0.05) < 1e-9
    assert abs(default["x_vs_per_light_inference"] - row["median_s"] / 0.01) < 1e-9
    assert "the default command on 4 lights" in (out / "REPORT.md").read_text()


def test_lights_needs_workload_d_and_enough_lights(
    stack: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(cli, "bench", _unreached)
    assert cli.main(_argv(stack, tmp_path / "r", "--lights", "8")) == 2  # with --no-e2e
    assert "drop --no-e2e" in _one_error(capfd)
    with pytest.raises(SystemExit) as exc:
        cli.main(_argv(stack, tmp_path / "r", "--lights", "2"))
    assert exc.value.code == 2 and "--lights" in capfd.readouterr().err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_warm_model_times_the_default_path_per_stack(stack: Path) -> None:
    """The (d) table's `default-warm` row: the bundled model opened once in its own process,
    a warm-up call, then timed calls on the stack path (no files)."""
    from msfnet.bench.workloads import time_warm_model

    before = _tree(stack)
    warm = time_warm_model(stack, 1, None, max_lights=4, repeats=2)
    assert len(warm["walls_s"]) == 2 and all(w > 0 for w in warm["walls_s"])
    assert warm["profile"]["lights"] == 4 and warm["profile"]["engine"]
    assert warm["peak_rss_mb"] > 50
    assert warm["mae"] is not None and 0 <= warm["mae"] < 90  # the sphere's ground truth
    assert _tree(stack) == before  # nothing written beside the inputs


def test_the_bytecode_cache_is_known_on_or_off(tmp_path: Path, monkeypatch) -> None:
    """The report's bytecode note: on where Python may write the cache, or where every msfnet
    runtime module already has an up-to-date one; off where neither (a module without one)."""
    import py_compile
    import types

    source = tmp_path / "uncached.py"
    source.write_text("x = 1\n")
    module = types.ModuleType("msfnet.runtime.uncached_for_test")
    module.__file__ = str(source)
    modules = {module.__name__: module, "json": json}  # not msfnet's: not looked at
    monkeypatch.delenv("PYTHONDONTWRITEBYTECODE", raising=False)
    assert cli.bytecode_cached(modules)
    monkeypatch.setenv("PYTHONDONTWRITEBYTECODE", "1")
    assert not cli.bytecode_cached(modules)
    py_compile.compile(str(source))  # the cache a default Python would have written
    assert cli.bytecode_cached(modules)


def test_a_budget_msf_run_cannot_meet_is_refused_before_any_work(
    stack: Path, tmp_path: Path, capfd: pytest.CaptureFixture[str], monkeypatch
) -> None:
    """--max-memory 100 ran the whole benchmark, then failed at workload (d) as an internal
    error."""
    monkeypatch.setattr(cli, "bench", _unreached)
    argv = [a for a in _argv(stack, tmp_path / "r") if a != "--no-e2e"]  # (d) runs
    assert cli.main([*argv, "--max-memory", "100"]) == 2
    err = _one_error(capfd)
    assert "--max-memory 100 MB is too small for workload (d)" in err and "need about" in err
    assert not (tmp_path / "r").exists()


def test_msf_run_refusing_workload_d_is_an_input_error_in_its_words(
    tmp_path: Path, monkeypatch
) -> None:
    import subprocess

    from msfnet.bench import workloads
    from msfnet.common.errors import InputError

    class Refused:
        pid = 0
        stderr = None

    monkeypatch.setattr(subprocess, "Popen", lambda *a, **k: Refused())
    monkeypatch.setattr(workloads.os, "wait4", lambda pid, opt: (pid, 2 << 8, None))
    with pytest.raises(InputError, match=r"^workload \(d\): "):
        workloads.time_msf_run(tmp_path / "stack", None, tmp_path / "out", 1, None)
