"""msf-export under bad arguments, clashing outputs, interruption and degenerate checkpoints.

Every failure is one line ``msf-export: error: ...`` (exit 2), Ctrl-C one line (exit 130), and
the target folder holds neither a partial nor an unverified file afterwards.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from msfnet.export.cli import main as export_main  # noqa: E402
from msfnet.export.output import TEMP_PREFIX, OutputSlot, remove_stale  # noqa: E402
from msfnet.export.passes import PASSES  # noqa: E402
from msfnet.runtime.errors import InputError  # noqa: E402


def _one_line_error(capsys, *parts: str) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("msf-export: error: "), err
    for part in parts:
        assert part in err, err
    return err


# option, value, what the message must say: rejected by argparse before anything is read
BAD_OPTIONS = [
    ("--opset", "99", "--opset: 99 is outside the supported opsets 9-20"),
    ("--opset", "5", "--opset: 5 is outside"),
    ("--opset", "x", "--opset: 'x' is not an integer"),
    ("--static", "foo", "--static: 'foo': expected N,H,W"),
    ("--static", "8,30,32", "--static: '8,30,32': need N >= 1 and H, W positive multiples of 4"),
    ("--static", "0,32,32", "multiples of 4"),
    ("--tolerance", "nan", "--tolerance: must be a positive number"),
    ("--tolerance", "-1", "--tolerance: must be a positive number"),
    ("--tolerance", "inf", "--tolerance: must be a positive number"),
    ("--train-lights", "0", "--train-lights: must be positive, got 0"),
    ("--train-lights", "2.5", "--train-lights: '2.5' is not an integer"),
    ("--variant", "fp64", "--variant: invalid choice: 'fp64'"),
]


@pytest.mark.parametrize(("option", "value", "message"), BAD_OPTIONS,
                         ids=[f"{o}={v}" for o, v, _ in BAD_OPTIONS])
def test_bad_option_values_give_one_line_and_exit_2(option: str, value: str, message: str,
                                                    tmp_path: Path, capsys) -> None:
    with pytest.raises(SystemExit) as info:
        export_main([str(tmp_path / "m.pth"), "-o", str(tmp_path / "m.onnx"), option, value])
    assert info.value.code == 2
    _one_line_error(capsys, message)
    assert list(tmp_path.iterdir()) == []


# arguments that parse but cannot work: refused before the checkpoint (absent here) is read
BAD_REQUESTS = [
    (["--staged", "--static", "4,8,8"], "--staged and --static do not combine"),
    (["--int8"], "int8 needs --calib"),
    (["--int8", "--fp16-weights", "--calib", "x.npz"], "--int8 and --fp16-weights"),
    (["--int8", "--static", "4,8,8", "--calib", "x.npz"], "static int8"),
    (["--int8", "--opset", "11", "--calib", "x.npz"], "int8 needs opset 13"),
    (["--variant", "static"], "variant static needs --static N,H,W"),
    (["--variant", "fp32", "--static", "4,8,8"], "--static N,H,W is for the static variants"),
    (["--variant", "fp32", "--staged"], "--staged contradicts --variant fp32"),
]


@pytest.mark.parametrize(("args", "message"), BAD_REQUESTS,
                         ids=[" ".join(a) for a, _ in BAD_REQUESTS])
def test_impossible_requests_fail_before_reading_anything(args: list[str], message: str,
                                                          tmp_path: Path, capsys) -> None:
    assert export_main([str(tmp_path / "absent.pth"), "-o", str(tmp_path / "m.onnx"),
                        *args]) == 2
    _one_line_error(capsys, message)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("how", ["same path", "dotted path", "symlink", "hard link"])
def test_output_may_never_replace_the_checkpoint(how: str, he_ckpt: Path, tmp_path: Path,
                                                 capsys) -> None:
    ckpt = tmp_path / "x.pth"
    ckpt.write_bytes(he_ckpt.read_bytes())
    out = {"same path": ckpt, "dotted path": tmp_path / "sub" / ".." / "x.pth",
           "symlink": tmp_path / "link.onnx", "hard link": tmp_path / "hard.onnx"}[how]
    if how == "symlink":
        out.symlink_to(ckpt)
    elif how == "hard link":
        os.link(ckpt, out)
    (tmp_path / "sub").mkdir(exist_ok=True)
    before = ckpt.read_bytes()
    assert export_main([str(ckpt), "-o", str(out), "--overwrite"]) == 2
    _one_line_error(capsys, "the output would replace the input")
    assert ckpt.read_bytes() == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(TEMP_PREFIX)]


@pytest.mark.parametrize("where", ["under a file", "a folder", "read-only folder"])
def test_unwritable_output_fails_before_the_export(where: str, he_ckpt: Path, tmp_path: Path,
                                                   capsys, monkeypatch) -> None:
    if where == "read-only folder" and os.geteuid() == 0:
        pytest.skip("root writes into read-only folders")
    blocker = tmp_path / "file.txt"
    blocker.write_text("x")
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    out = {"under a file": blocker / "sub" / "m.onnx", "a folder": tmp_path,
           "read-only folder": ro / "m.onnx"}[where]

    def no_export(*_a: object) -> None:
        raise AssertionError("the export started before the output was checked")

    monkeypatch.setattr("msfnet.export.pipeline.load_network", no_export)
    try:
        assert export_main([str(he_ckpt), "-o", str(out)]) == 2
    finally:
        ro.chmod(0o755)
    _one_line_error(capsys, str(out))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file.txt", "ro"]
    assert list(ro.iterdir()) == []


def test_output_inside_a_calibration_folder_is_refused(he_ckpt: Path, tmp_path: Path,
                                                       capsys) -> None:
    stack = tmp_path / "stack"
    stack.mkdir()
    assert export_main([str(he_ckpt), "-o", str(stack / "q.onnx"), "--int8", "--calib",
                        str(stack)]) == 2
    _one_line_error(capsys, "inside the input folder")
    assert list(stack.iterdir()) == []


def test_zero_weight_checkpoint_fails_verification(zero_ckpt: Path, tmp_path: Path,
                                                   capsys) -> None:
    """All-zero weights give (0, 0, 0) normals in PyTorch and ONNX alike: the angle check
    alone passes (atan2(0, 0) = 0), the unit-normal check must not."""
    out = tmp_path / "zero.onnx"
    assert export_main([str(zero_ckpt), "-o", str(out)]) == 2
    _one_line_error(capsys, str(zero_ckpt), "verification failed", "no unit normals")
    assert list(tmp_path.iterdir()) == []


def test_random_bytes_are_not_a_checkpoint(tmp_path: Path, capsys) -> None:
    bad = tmp_path / "noise.pth"
    # not starting like a pickle (0x80, protocol 2-5) or a zip ('PK')
    bad.write_bytes(b"\x00" + np.random.default_rng(0).bytes(4999))
    assert export_main([str(bad), "-o", str(tmp_path / "m.onnx")]) == 2
    err = _one_line_error(capsys, "noise.pth", "not a PyTorch checkpoint")
    assert "pickled" not in err


def test_ctrl_c_during_the_export_is_one_line_and_leaves_nothing(he_ckpt: Path, tmp_path: Path,
                                                                 capsys, monkeypatch) -> None:
    from dataclasses import replace

    def interrupted(*_a: object) -> None:
        assert [p for p in (tmp_path / "new").iterdir() if p.name.startswith(TEMP_PREFIX)]
        raise KeyboardInterrupt

    for name in ("torch-export", "torch-export-staged"):  # whichever graph the default is
        monkeypatch.setitem(PASSES, name, replace(PASSES[name], run=interrupted))
    out = tmp_path / "new" / "m.onnx"
    assert export_main([str(he_ckpt), "-o", str(out)]) == 130
    err = capsys.readouterr().err.strip()
    assert err == "msf-export: interrupted; nothing written"
    assert list(tmp_path.iterdir()) == []  # also the folder it created for the output


def test_internal_errors_are_one_line_unless_debug(he_ckpt: Path, tmp_path: Path, capsys,
                                                   monkeypatch) -> None:
    from dataclasses import replace

    def broken(*_a: object) -> None:
        raise ZeroDivisionError("boom")

    for name in ("torch-export", "torch-export-staged"):
        monkeypatch.setitem(PASSES, name, replace(PASSES[name], run=broken))
    args = [str(he_ckpt), "-o", str(tmp_path / "m.onnx")]
    assert export_main(args) == 1
    _one_line_error(capsys, "internal error: ZeroDivisionError: boom", "--debug")
    with pytest.raises(ZeroDivisionError):
        export_main([*args, "--debug"])
    assert list(tmp_path.iterdir()) == []


def test_stale_work_folders_go_running_ones_stay(tmp_path: Path) -> None:
    stale = tmp_path / f"{TEMP_PREFIX}dead"
    stale.mkdir()
    (stale / "lock").touch()  # lock file nobody holds: its export was killed
    (stale / "m.onnx").write_bytes(b"half")
    with OutputSlot(tmp_path / "m.onnx") as running:
        assert not stale.exists()
        assert running.workdir is not None and running.workdir.exists()
        assert remove_stale(tmp_path) == []  # held by a live export
        running.commit(running.write(b"data"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.onnx"]
    with pytest.raises(InputError, match="output exists"):
        OutputSlot(tmp_path / "m.onnx").__enter__()


def _cli(*args: str) -> subprocess.Popen:
    """msf-export in a child process with default signal handling (a background pytest may
    have SIGINT ignored, which the child would inherit)."""
    return subprocess.Popen([sys.executable, "-m", "msfnet.export.cli", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def _wait_for_work_folder(proc: subprocess.Popen, folder: Path) -> None:
    deadline = time.monotonic() + 120
    while not [p for p in folder.iterdir() if p.name.startswith(TEMP_PREFIX)]:
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "export never started"
        time.sleep(0.05)
    time.sleep(0.05)  # handlers are in place before the work folder appears; a fast export
    # (an AMX CPU) can finish within a second, so signal early


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_signalled_export_leaves_nothing(sig: signal.Signals, he_ckpt: Path,
                                         tmp_path: Path) -> None:
    out = tmp_path / "m.onnx"
    proc = _cli(str(he_ckpt), "-o", str(out))
    _wait_for_work_folder(proc, tmp_path)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == (130 if sig == signal.SIGINT else 128 + sig), err
    assert err.strip().count("\n") == 0 and "interrupted" in err, err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_killed_export_leaves_no_file_and_the_next_run_cleans_up(he_ckpt: Path,
                                                                  tmp_path: Path) -> None:
    out = tmp_path / "m.onnx"
    proc = _cli(str(he_ckpt), "-o", str(out))
    _wait_for_work_folder(proc, tmp_path)
    proc.kill()  # SIGKILL: no handler runs
    proc.communicate(timeout=60)
    assert not out.exists()
    left = [p for p in tmp_path.iterdir() if p.name.startswith(TEMP_PREFIX)]
    assert left  # only a recognisable work folder, never the target
    again = _cli(str(he_ckpt), "-o", str(out))
    stdout, err = again.communicate(timeout=300)
    assert again.returncode == 0, err
    assert f"wrote {out}" in stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.onnx"]
