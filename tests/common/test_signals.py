"""msf-run killed, interrupted, starved of disk, or racing another msf-run (subprocesses).

A wrapper runs msf-run's own ``main`` with one stage slowed down (or two writers held at a
barrier), so the signal or the race lands at a known point: the tests are deterministic.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from _runtime_helpers import sphere_stack

from msfnet.common.files import MANIFEST, STAGING_TAG
from msfnet.runtime.api import Model
from msfnet.runtime.cli.run import main
from msfnet.runtime.stack import load_stack, save_stack

WRAPPER = """
import sys, time
from pathlib import Path
import msfnet.runtime.infer.estimators as estimators
import msfnet.runtime.results.result as outputs

phase, marker = sys.argv[1], Path(sys.argv[2])
fill = outputs.fill_result_folder

def staged_then_wait(folder, result, **kwargs):
    fill(folder, result, **kwargs)  # every file is staged, not yet renamed into place
    marker.write_text(str(folder))
    if phase == "write":
        time.sleep(120)
    else:  # "barrier": both writers hold here until both have staged
        deadline = time.time() + 60
        while len(list(marker.parent.glob("staged-*"))) < 2 and time.time() < deadline:
            time.sleep(0.01)

def compute_forever(*args, **kwargs):
    marker.write_text("computing")
    time.sleep(120)

if phase == "compute":
    estimators.least_squares_normals = compute_forever
else:
    outputs.fill_result_folder = staged_then_wait
from msfnet.runtime.cli.run import main
sys.exit(main(sys.argv[3:]))
"""


@pytest.fixture
def stack_dir(tmp_path: Path) -> Path:
    return save_stack(sphere_stack(), tmp_path / "in" / "sphere")


def _start(tmp_path: Path, phase: str, marker: Path, argv: list[str], **kwargs) -> subprocess.Popen:
    script = tmp_path / "wrapper.py"
    script.write_text(WRAPPER)
    return subprocess.Popen(
        [sys.executable, str(script), phase, str(marker), *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **kwargs,
    )


def _wait_for(marker: Path, proc: subprocess.Popen, timeout: float = 60) -> None:
    deadline = time.time() + timeout
    while not marker.exists():
        if proc.poll() is not None:
            raise AssertionError(f"msf-run ended early: {proc.communicate()}")
        if time.time() > deadline:
            proc.kill()
            raise AssertionError("msf-run never reached the stage")
        time.sleep(0.01)


def _staging(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if STAGING_TAG in p.name)


# signal -> (exit code, the one stderr line starts with)
SIGNALS = {
    "SIGTERM": (143, "msf-run: terminated (signal 15); nothing was written"),
    "SIGINT": (130, "msf-run: interrupted; nothing was written"),
    "SIGKILL": (-9, None),
}


@pytest.mark.parametrize(
    ("sig", "phase"),
    [
        ("SIGTERM", "write"),
        ("SIGKILL", "write"),
        pytest.param("SIGINT", "write", marks=pytest.mark.slow),
        pytest.param("SIGTERM", "compute", marks=pytest.mark.slow),
        pytest.param("SIGKILL", "compute", marks=pytest.mark.slow),
    ],
)
def test_kill_and_rerun(sig: str, phase: str, stack_dir: Path, tmp_path: Path, capsys) -> None:
    """Killed while computing or with every file staged: no output; a signal that can be
    caught also removes the staging, SIGKILL's is removed by the next run, which succeeds."""
    out = tmp_path / "out" / "result"
    marker = tmp_path / "reached"
    proc = _start(tmp_path, phase, marker, ["--method", "l2", str(stack_dir), "-o", str(out)])
    try:
        _wait_for(marker, proc)
        if phase == "write":
            assert _staging(out.parent), "the staging folder should exist at this point"
        os.kill(proc.pid, getattr(signal, sig))
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    code, line = SIGNALS[sig]
    assert proc.returncode == code, err
    if line is not None:
        assert err.strip().splitlines() == [line], err
        # not even the folder created for the output is left
        assert not out.parent.exists(), list(out.parent.iterdir())
    assert not out.exists()
    # the next run succeeds and leaves nothing but its output
    assert main(["--method", "l2", str(stack_dir), "-o", str(out), "-q"]) == 0
    assert sorted(p.name for p in out.parent.iterdir()) == ["result"]
    assert (out / "normals.npy").is_file() and (out / MANIFEST).is_file()


def _two_writers(
    tmp_path: Path, stack_dir: Path, out: Path, extra: list[list[str]]
) -> list[tuple[int, str]]:
    procs = [
        _start(
            tmp_path,
            "barrier",
            tmp_path / f"staged-{i}",
            ["--method", "l2", str(stack_dir), "-o", str(out), "-q", *extra[i]],
        )
        for i in range(2)
    ]
    try:
        results = []
        for proc in procs:
            _, err = proc.communicate(timeout=120)
            results.append((proc.returncode, err))
        return results
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()


def test_two_writers_to_the_same_output(stack_dir: Path, tmp_path: Path) -> None:
    """Both checked -o before either wrote, both staged: one wins, the other says so in one
    line, and the folder is the winner's, complete."""
    out = tmp_path / "out"
    results = _two_writers(tmp_path, stack_dir, out, [[], []])
    codes = sorted(code for code, _ in results)
    assert codes == [0, 2], results
    loser = next(err for code, err in results if code == 2).strip().splitlines()
    assert len(loser) == 1 and "appeared while running" in loser[0], loser
    assert "--overwrite" in loser[0]
    names = sorted(p.name for p in out.iterdir())
    # one complete result folder (every file of one run), never a mix
    assert {
        MANIFEST,
        "error.png",
        "metrics.json",
        "normals.npy",
        "normals_view.png",
        "profile.json",
        "height.tif",
        "report.html",
    } <= set(names)
    assert json.loads((out / MANIFEST).read_text())["files"] == sorted(set(names) - {MANIFEST})
    assert not _staging(tmp_path)


@pytest.mark.slow
def test_two_overwriters_leave_one_complete_result(stack_dir: Path, tmp_path: Path) -> None:
    """With --overwrite both succeed; the folder is entirely one run's (7 or 6 lights)."""
    out = tmp_path / "out"
    selects = [["--select", "1-7", "--overwrite"], ["--select", "2-7", "--overwrite"]]
    results = _two_writers(tmp_path, stack_dir, out, selects)
    assert [code for code, _ in results] == [0, 0], results
    lights = json.loads((out / "profile.json").read_text())["lights"]
    spec = {7: "1-7", 6: "2-7"}[lights]
    expected = Model.least_squares()(load_stack(stack_dir, select=spec)).normals
    np.testing.assert_array_equal(np.load(out / "normals.npy"), expected)
    assert json.loads((out / "metrics.json").read_text())["pixels"] > 0
    assert not _staging(tmp_path)


def _limit_file_size() -> None:
    import resource

    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG instead of a kill
    resource.setrlimit(resource.RLIMIT_FSIZE, (8000, 8000))


@pytest.mark.skipif(not hasattr(signal, "SIGXFSZ"), reason="needs RLIMIT_FSIZE (POSIX)")
def test_output_disk_full(stack_dir: Path, tmp_path: Path) -> None:
    """The output device fills up while the results are written (files over 8 KB fail)."""
    out = tmp_path / "out"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "msfnet.runtime.cli.run",
            "--method",
            "l2",
            str(stack_dir),
            "-o",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=120,
        preexec_fn=_limit_file_size,
    )
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("msf-run: error: "), proc.stderr
    assert "File too large" in lines[0] or "disk full" in lines[0], lines
    assert not out.exists() and not _staging(tmp_path)


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders anyway")
def test_read_only_output_is_refused_before_any_work(
    stack_dir: Path, tmp_path: Path, capfd
) -> None:
    parent = tmp_path / "ro"
    parent.mkdir()
    parent.chmod(0o555)
    try:
        assert main(["--method", "l2", str(stack_dir), "-o", str(parent / "out")]) == 2
        lines = capfd.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and "not writable" in lines[0], lines
        assert list(parent.iterdir()) == []
    finally:
        parent.chmod(0o755)


# ---------------------------------------------------------------------------- Ctrl-C, one line

STARTUP = """
import os, signal, sys
sys.argv[0] = "/usr/local/bin/msf-calib"  # what a console script's argv[0] looks like
import msfnet  # the first msfnet import: Ctrl-C becomes one line from here on
assert "multiprocessing" not in sys.modules  # the guard comes first: it costs no import
os.kill(os.getpid(), getattr(signal, sys.argv[1]))  # Ctrl-C or a kill while it still imports
import msfnet.calib.cli
print("not reached")
"""

DOUBLE = """
import os, signal, sys, time
sys.argv[0] = "/usr/local/bin/msf-x"
from msfnet.common.cli import run_command
from msfnet.common.files import staged_folder

def body():
    with staged_folder(sys.argv[1]) as tmp:
        (tmp / "a.txt").write_text("x")
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(30)
        finally:  # pressed again while the first one unwinds (the staging is being removed)
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.2)
    return 0

code = run_command("msf-x", body)
os.kill(os.getpid(), signal.SIGINT)  # and once more while the program exits
time.sleep(0.2)
sys.exit(code)
"""


def _child(code: str, *args: str) -> subprocess.CompletedProcess[str]:
    # started with Ctrl-C at its default: a background pytest job ignores SIGINT, and children
    # would inherit that
    return subprocess.run(
        [sys.executable, "-c", code, *args],
        capture_output=True,
        text=True,
        timeout=120,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )


@pytest.mark.parametrize(
    ("name", "line"),
    [
        ("SIGINT", "msf-calib: interrupted while starting; nothing was written"),
        ("SIGTERM", "msf-calib: terminated (signal 15) while starting; nothing was written"),
    ],
)
def test_a_signal_while_a_command_starts_is_one_line(name: str, line: str) -> None:
    """Ctrl-C printed Python's 22-57 line traceback of the import that was running; SIGTERM
    in msf-calib's or msf-synth's first tenth of a second ended it without a word (the guard
    came after importing multiprocessing, issue #48)."""
    proc = _child(STARTUP, name)
    assert proc.returncode == 128 + getattr(signal, name), proc.stderr
    assert proc.stderr.strip().splitlines() == [line]
    assert "not reached" not in proc.stdout


def test_a_double_ctrl_c_is_one_line_and_the_cleanup_finishes(tmp_path: Path) -> None:
    """A second Ctrl-C while the first unwound printed a 17-line traceback (and could cut the
    removal of the staging short)."""
    proc = _child(DOUBLE, str(tmp_path / "out"))
    assert proc.returncode == 130, proc.stderr
    assert proc.stderr.strip().splitlines() == ["msf-x: interrupted; nothing was written"]
    assert list(tmp_path.iterdir()) == []


def test_a_python_program_importing_msfnet_keeps_its_own_ctrl_c() -> None:
    code = (
        "import signal, sys\n"
        "import msfnet.common.cli\n"
        "sys.exit(0 if signal.getsignal(signal.SIGINT) is signal.default_int_handler else 1)\n"
    )
    assert _child(code).returncode == 0


# a kill that arrives once the command has said its last line (review-inspect.md 13)
KILLED_WHILE_EXITING = """
import os, signal, sys, time
sys.argv[0] = "/usr/local/bin/msf-x"
import msfnet
from msfnet.common.cli import run_command
from msfnet.common.files import staged_folder

def body():
    with staged_folder(sys.argv[1]) as tmp:
        (tmp / "a.txt").write_text("x")
    print("wrote", sys.argv[1])
    return 0

code = run_command("msf-x", body)
os.kill(os.getpid(), signal.SIGTERM)  # the supervisor's kill while the process shuts down
os.kill(os.getpid(), signal.SIGHUP)
time.sleep(0.2)
sys.exit(code)
"""


def test_a_kill_after_the_command_finished_keeps_its_exit_code(tmp_path: Path) -> None:
    """It exited 143 with no word, the output complete: a supervisor read a failed run."""
    proc = _child(KILLED_WHILE_EXITING, str(tmp_path / "out"))
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""
    assert (tmp_path / "out" / "a.txt").read_text() == "x"


def test_an_in_process_command_gives_the_callers_kill_handlers_back() -> None:
    from msfnet.common.cli import run_command

    def mine(signum: int, frame: object) -> None:
        pass

    before = signal.signal(signal.SIGTERM, mine)
    try:
        assert run_command("msf-x", lambda: 0) == 0
        assert signal.getsignal(signal.SIGTERM) is mine
    finally:
        signal.signal(signal.SIGTERM, before)
