"""python -m msfnet.bench.accuracy, the measurement behind runtime/engines/dispatch.py's defaults:
on small random-weight exports, each path is compared with the fp32 reference on the same input."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from _runtime_helpers import png_stack

from msfnet.bench.accuracy import EnginePath, main, measure

STAGED = EnginePath("onnxruntime", "fp32", "fp32_staged")
OTHER = EnginePath("onnxruntime", "fp32", "other")  # other weights: must show as a deviation
INT8 = EnginePath("onnxruntime", "int8", "int8")  # its file is missing: left out


@pytest.fixture(scope="module")
def stack_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return png_stack(tmp_path_factory.mktemp("acc") / "ballPNG", 16, n=8, h=40, w=40)


def test_measure_compares_every_path_with_the_fp32_reference(
    stack_dir: Path, sensitive_onnx: Path, staged_onnx: Path, random_onnx: Path, tmp_path: Path
) -> None:
    """The staged export of the same weights matches the plain reference (fp32: the same
    function in another order); other weights are far off; a missing file is left out."""
    models = {
        "fp32": sensitive_onnx,
        "fp32_staged": staged_onnx,
        "other": random_onnx,
        "int8": tmp_path / "missing.onnx",
    }
    lines: list[str] = []
    rows = measure(
        stack_dir,
        models,
        lights=(4, 8),
        size=32,
        threads=1,
        repeats=1,
        paths=(STAGED, OTHER, INT8),
        log=lines.append,
    )
    assert [(r["lights"], r["path"]) for r in rows] == [
        (n, p) for n in (4, 8) for p in ("onnxruntime fp32", STAGED.label, OTHER.label)
    ]
    for i in (0, 3):  # per light count: the reference, then the paths in order
        ref, staged, other = rows[i : i + 3]
        assert (ref["mean_deg"], ref["max_deg"], ref["x_ort_fp32"]) == (0.0, 0.0, 1.0)
        for r in (ref, staged, other):
            assert r["size"] == 32 and r["median_s"] > 0
        for r in (staged, other):
            assert r["effective_precision"] == "fp32"
            assert r["x_ort_fp32"] == pytest.approx(ref["median_s"] / r["median_s"])
        assert staged["mean_deg"] < 0.01 and staged["max_deg"] < 0.05
        assert 1.0 < other["mean_deg"] <= other["max_deg"]
    assert len(lines) == 4 and all("deg" in line for line in lines)


@pytest.mark.slow
def test_command_measures_the_exports_in_a_models_folder(
    stack_dir: Path, sensitive_onnx: Path, staged_onnx: Path, tmp_path: Path
) -> None:
    root = tmp_path / "data"
    (root / "DiLiGenT").mkdir(parents=True)
    (root / "DiLiGenT" / "ballPNG").symlink_to(stack_dir, target_is_directory=True)
    models = tmp_path / "models"
    models.mkdir()
    (models / "fp32.onnx").symlink_to(sensitive_onnx)
    (models / "fp32_staged.onnx").symlink_to(staged_onnx)
    # in a process of its own: the command also runs OpenVINO, whose threads left in the test
    # process crashed a later test's torch DataLoader workers (SIGSEGV)
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "msfnet.bench.accuracy",
            "--data",
            str(root),
            "--models",
            str(models),
            "--lights",
            "8",
            "--size",
            "32",
            "--threads",
            "1",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr
    assert "| 8 | onnxruntime fp32 staged | 0.00" in done.stdout


@pytest.mark.parametrize(
    "argv, problem",
    [
        ([], "staged model"),  # the bundled model is staged: no plain reference
        (["--models", "nowhere"], "--models: folder not found"),
    ],
)
def test_command_errors_are_one_line(
    argv: list[str],
    problem: str,
    stack_dir: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    root = tmp_path / "data"
    (root / "DiLiGenT").mkdir(parents=True)
    (root / "DiLiGenT" / "ballPNG").symlink_to(stack_dir, target_is_directory=True)
    assert main(["--data", str(root), *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("python -m msfnet.bench.accuracy: error: ")
    assert problem in err[0]


@pytest.mark.parametrize("option", [["--size", "0"], ["--lights", "8,x"], ["--threads", "-1"]])
def test_options_are_checked(option: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(option)
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and option[0] in err[0]
