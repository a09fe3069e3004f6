"""msf-run tells a person at a terminal what it is doing (a status line per long step on
stderr, the two passes of --fine-detail, erased at the end) and its outputs say where they came
from (profile.json, report.html)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest
from _runtime_helpers import sphere_stack

from msfnet.runtime.cli import run as run_cli
from msfnet.runtime.cli.run import main as run_main
from msfnet.runtime.stack import save_stack


@pytest.fixture
def stack_dir(tmp_path: Path) -> Path:
    return save_stack(sphere_stack(n=8, h=40, w=48), tmp_path / "sphere")


@pytest.fixture
def terminal(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(run_cli, "_terminal", lambda: True)


def _steps(err: str) -> list[str]:
    """The steps the status line showed (tqdm redraws it in place with carriage returns)."""
    shown = [part.strip() for part in err.replace("\x1b[A", "").split("\r")]
    steps = [p.split(": ", 2)[2].split(" ... ")[0] for p in shown if " ... (" in p]
    return [s for i, s in enumerate(steps) if i == 0 or s != steps[i - 1]]


def test_each_long_step_is_announced(
    random_onnx: Path, stack_dir: Path, tmp_path: Path, capsys, terminal: None
) -> None:
    out = tmp_path / "out"
    argv = [str(stack_dir), "--onnx", str(random_onnx), "--tile", "0", "-o", str(out)]
    assert run_main(argv) == 0
    err = capsys.readouterr().err
    assert _steps(err) == [
        "reading the stack",
        "estimating the normals",
        "inspection maps (albedo, height, curvature)",
        "writing the outputs and report.html",
    ], err
    assert "msf-run: sphere: reading the stack ... (0.0 s)" in err
    # where it came from: profile.json and the report's header
    prov = json.loads((out / "profile.json").read_text())["provenance"]
    sha = hashlib.sha256(random_onnx.read_bytes()).hexdigest()[:12]
    assert prov["model"] == str(random_onnx) and prov["model_sha256"] == sha
    assert prov["input"] == str(stack_dir) and prov["command"].startswith("msf-run ")
    assert prov["date"].endswith("Z") and prov["version"]
    html = (out / "report.html").read_text()
    for fact in (
        f"model: {random_onnx.name} (sha256 {sha})",
        f"engine: {prov['engine']} {prov['precision']}",
        f"input: {stack_dir}",
        "msfnet: ",
        "date: ",
        "command: msf-run ",
        "height integration: poisson",
    ):
        assert fact in html, fact
    assert "method: poisson" not in html


def test_quiet_or_no_terminal_shows_no_status(
    random_onnx: Path, stack_dir: Path, tmp_path: Path, capsys, monkeypatch: pytest.MonkeyPatch
) -> None:
    """-q says nothing; in a pipe or a log (no terminal) stderr keeps only warnings and the
    one error line a failure gives."""
    argv = [str(stack_dir), "--onnx", str(random_onnx), "--tile", "0", "-o", str(tmp_path / "q")]
    assert run_main(argv) == 0
    assert capsys.readouterr().err == ""
    monkeypatch.setattr(run_cli, "_terminal", lambda: True)
    assert run_main([*argv, "-q", "--overwrite"]) == 0
    seen = capsys.readouterr()
    assert seen.err == "" and seen.out == ""


def test_fine_detail_says_it_runs_twice(
    random_onnx: Path, stack_dir: Path, tmp_path: Path, capsys, terminal: None
) -> None:
    out = tmp_path / "fd"
    argv = [str(stack_dir), "--onnx", str(random_onnx), "--tile", "0", "--no-maps", "-o", str(out)]
    assert run_main([*argv, "--fine-detail"]) == 0
    steps = _steps(capsys.readouterr().err)
    assert steps[0] == "reading the stack" and steps[-1] == "writing the outputs"
    passes = [s for s in steps if s.startswith("fine detail")]
    assert passes == [
        "fine detail, pass 1 of 2: the network on the stack enlarged to 96x80",
        "fine detail, pass 2 of 2: the network on the stack as it is",
    ]


def test_the_status_line_ticks_while_a_step_runs(capsys) -> None:
    """It showed the time a step started and never moved (issue #49)."""
    import time

    with run_cli.stage_status("part", True) as step:
        step("estimating the normals")
        time.sleep(1.3)  # one tick of the status line
    shown = capsys.readouterr().err
    assert "estimating the normals ... (0.0 s)" in shown
    assert "estimating the normals ... (1." in shown, shown


def test_in_a_pipe_each_step_is_a_line_on_stdout(
    random_onnx: Path, stack_dir: Path, tmp_path: Path, capsys
) -> None:
    """A run in a pipe said nothing for minutes (issue #49); its steps are lines beside the
    result lines on stdout, stderr keeps warnings and the one error line."""
    argv = [str(stack_dir), "--onnx", str(random_onnx), "--tile", "0", "-o", str(tmp_path / "p")]
    assert run_main(argv) == 0
    seen = capsys.readouterr()
    assert seen.err == ""
    lines = seen.out.splitlines()
    assert lines[:2] == [
        "msf-run: sphere: reading the stack ...",
        "msf-run: sphere: estimating the normals ...",
    ], lines
    assert run_main([*argv, "-q", "--overwrite"]) == 0
    assert capsys.readouterr().out == ""


def test_the_engine_choice_is_one_short_line_and_whole_in_the_profile(
    stack_dir: Path, tmp_path: Path, capsys
) -> None:
    """The ~400-character reason filled a station's log line (issue #49)."""
    out = tmp_path / "e"
    assert run_main([str(stack_dir), "--no-maps", "-o", str(out)]) == 0
    choice = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("engine choice")]
    reason = json.loads((out / "profile.json").read_text())["choice"]
    assert len(choice) == 1 and len(choice[0]) <= 170, choice
    shown = choice[0].removeprefix("engine choice: ").split(" (every reason")[0]
    assert reason.startswith(shown.removesuffix("..."))
