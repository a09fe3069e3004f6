"""msf-export under bad arguments, clashing outputs, interruption and degenerate checkpoints.

Every failure is one line ``msf-export: error: ...`` (exit 2), Ctrl-C one line (exit 130), and
the target folder holds neither a partial nor an unverified file afterwards. msf-export writes
through ``common/files.py`` (its rules are tested case by case in tests/runtime/test_files.py);
these tests hold the command to them where an export can break them: the candidate file lives
under a staging name while it is verified, the int8 quantiser's scratch folder beside it.
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

from msfnet.common.files import STAGING_TAG  # noqa: E402
from msfnet.export.cli import main as export_main  # noqa: E402
from msfnet.export.passes import PASSES  # noqa: E402


def _one_line_error(capsys, *parts: str, start: str = "msf-export: error: ") -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith(start), err
    for part in parts:
        assert part in err, err
    return err


def _staging(folder: Path) -> list[Path]:
    """files.py's temporary files and folders (``.<target>.msf-partial-<pid>-...``)."""
    if not folder.is_dir():  # the folder made for a new output comes with the write
        return []
    return [p for p in folder.iterdir() if STAGING_TAG in p.name]


# option, value, what the message must say: rejected by argparse before anything is read
BAD_OPTIONS = [
    ("--opset", "99", "--opset: must lie in 9..20, got '99'"),
    ("--opset", "5", "--opset: must lie in 9..20"),
    ("--opset", "x", "--opset: 'x' is not an integer"),
    ("--static", "foo", "--static: 'foo': expected N,H,W"),
    ("--static", "8,30,32", "--static: '8,30,32': need N >= 1 and H, W positive multiples of 4"),
    ("--static", "0,32,32", "multiples of 4"),
    ("--tolerance", "nan", "--tolerance: 'nan' is not a finite number"),
    ("--tolerance", "-1", "--tolerance: must be a positive number, got '-1'"),
    ("--tolerance", "0", "--tolerance: must be a positive number"),
    ("--tolerance", "inf", "--tolerance: 'inf' is not a finite number"),
    ("--train-lights", "0", "--train-lights: must be a positive integer, got '0'"),
    ("--train-lights", "2.5", "--train-lights: '2.5' is not an integer"),
    ("--variant", "fp64", "--variant: invalid choice: 'fp64'"),
    ("--weight-bits", "6", "--weight-bits: invalid choice: 6"),
    ("--weight-bits", "x", "--weight-bits: invalid int value: 'x'"),
]


@pytest.mark.parametrize(
    ("option", "value", "message"), BAD_OPTIONS, ids=[f"{o}={v}" for o, v, _ in BAD_OPTIONS]
)
def test_bad_option_values_give_one_line_and_exit_2(
    option: str, value: str, message: str, tmp_path: Path, capsys
) -> None:
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
    (["--weight-bits", "7"], "--weight-bits: only the int8 variants quantise weights"),
]


@pytest.mark.parametrize(
    ("args", "message"), BAD_REQUESTS, ids=[" ".join(a) for a, _ in BAD_REQUESTS]
)
def test_impossible_requests_fail_before_reading_anything(
    args: list[str], message: str, tmp_path: Path, capsys
) -> None:
    assert export_main([str(tmp_path / "absent.pth"), "-o", str(tmp_path / "m.onnx"), *args]) == 2
    _one_line_error(capsys, message)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("how", ["same path", "dotted path", "symlink", "hard link"])
def test_output_may_never_replace_the_checkpoint(
    how: str, he_ckpt: Path, tmp_path: Path, capsys
) -> None:
    ckpt = tmp_path / "x.pth"
    ckpt.write_bytes(he_ckpt.read_bytes())
    out = {
        "same path": ckpt,
        "dotted path": tmp_path / "sub" / ".." / "x.pth",
        "symlink": tmp_path / "link.onnx",
        "hard link": tmp_path / "hard.onnx",
    }[how]
    if how == "symlink":
        out.symlink_to(ckpt)
    elif how == "hard link":
        os.link(ckpt, out)
    (tmp_path / "sub").mkdir(exist_ok=True)
    before = ckpt.read_bytes()
    assert export_main([str(ckpt), "-o", str(out), "--overwrite"]) == 2
    _one_line_error(capsys, "the output would replace an input")
    assert ckpt.read_bytes() == before
    assert not _staging(tmp_path)


@pytest.mark.parametrize("where", ["under a file", "a folder", "read-only folder"])
def test_unwritable_output_fails_before_the_export(
    where: str, he_ckpt: Path, tmp_path: Path, capsys, monkeypatch
) -> None:
    if where == "read-only folder" and os.geteuid() == 0:
        pytest.skip("root writes into read-only folders")
    blocker = tmp_path / "file.txt"
    blocker.write_text("x")
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    out = {
        "under a file": blocker / "sub" / "m.onnx",
        "a folder": tmp_path,
        "read-only folder": ro / "m.onnx",
    }[where]

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


def test_output_inside_a_calibration_folder_is_refused(
    he_ckpt: Path, tmp_path: Path, capsys
) -> None:
    stack = tmp_path / "stack"
    stack.mkdir()
    assert (
        export_main([str(he_ckpt), "-o", str(stack / "q.onnx"), "--int8", "--calib", str(stack)])
        == 2
    )
    _one_line_error(capsys, "inside the input folder")
    assert list(stack.iterdir()) == []


@pytest.mark.slow
def test_zero_weight_checkpoint_fails_verification(zero_ckpt: Path, tmp_path: Path, capsys) -> None:
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


def test_ctrl_c_before_the_write_is_one_line_and_leaves_nothing(
    he_ckpt: Path, tmp_path: Path, capsys, monkeypatch
) -> None:
    from dataclasses import replace

    def interrupted(*_a: object) -> None:
        assert not (tmp_path / "new").exists()  # checked, but nothing made before the write
        raise KeyboardInterrupt

    for name in ("torch-export", "torch-export-staged"):  # whichever graph the default is
        monkeypatch.setitem(PASSES, name, replace(PASSES[name], run=interrupted))
    out = tmp_path / "new" / "m.onnx"
    assert export_main([str(he_ckpt), "-o", str(out)]) == 130
    err = capsys.readouterr().err.strip()
    assert err == "msf-export: interrupted; nothing was written"
    assert list(tmp_path.iterdir()) == []


def test_ctrl_c_while_verifying_removes_the_candidate(
    he_ckpt: Path, tmp_path: Path, capsys, monkeypatch
) -> None:
    """The written, not yet verified file exists only under its staging name; Ctrl-C during
    its verification removes it and the folder made for it."""
    import msfnet.export.pipeline as pipeline

    seen: list[Path] = []

    def interrupted(path: Path, *_a: object) -> None:
        seen.append(path)
        assert path.is_file() and path.parent == out.parent and STAGING_TAG in path.name
        assert not out.exists()
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "file_runner", interrupted)
    out = tmp_path / "new" / "m.onnx"
    assert export_main([str(he_ckpt), "-o", str(out)]) == 130
    assert capsys.readouterr().err.strip() == "msf-export: interrupted; nothing was written"
    assert len(seen) == 1 and not seen[0].exists()
    assert list(tmp_path.iterdir()) == []


def test_ctrl_c_while_quantising_removes_the_scratch_folder(
    he_ckpt: Path, calib_npz: Path, tmp_path: Path, capsys, monkeypatch
) -> None:
    """int8's quantiser needs files: they go to a scratch folder beside the target (removed
    after a kill -9 by the next export there, see test_killed_export_...)."""
    import msfnet.export.quantize as quantize

    seen: list[Path] = []

    def interrupted(_model: object, _stacks: object, scratch: Path, **_kw: object) -> None:
        seen.append(scratch)
        assert scratch.is_dir() and scratch.parent == out.parent
        assert scratch.name.startswith(f".{out.name}{STAGING_TAG}")
        (scratch / "fp32.onnx").write_bytes(b"half")
        raise KeyboardInterrupt

    monkeypatch.setattr(quantize, "quantize_model", interrupted)
    out = tmp_path / "new" / "q.onnx"
    assert export_main([str(he_ckpt), "-o", str(out), "--int8", "--calib", str(calib_npz)]) == 130
    assert capsys.readouterr().err.strip() == "msf-export: interrupted; nothing was written"
    assert len(seen) == 1 and not seen[0].exists()
    assert list(tmp_path.iterdir()) == []


def test_internal_errors_are_one_line_unless_debug(
    he_ckpt: Path, tmp_path: Path, capsys, monkeypatch
) -> None:
    from dataclasses import replace

    def broken(*_a: object) -> None:
        raise ZeroDivisionError("boom")

    for name in ("torch-export", "torch-export-staged"):
        monkeypatch.setitem(PASSES, name, replace(PASSES[name], run=broken))
    args = [str(he_ckpt), "-o", str(tmp_path / "m.onnx")]
    assert export_main(args) == 1
    _one_line_error(
        capsys, "ZeroDivisionError: boom", "--debug", start="msf-export: internal error: "
    )
    with pytest.raises(ZeroDivisionError):
        export_main([*args, "--debug"])
    assert list(tmp_path.iterdir()) == []


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


@pytest.mark.slow
def test_existing_output_and_staging_of_other_runs(he_ckpt: Path, tmp_path: Path, capsys) -> None:
    """Staging a killed export left (a file and an int8 scratch folder) goes with the next
    export to that target; a running export's (a live pid) and other targets' stay. An existing
    output is replaced only with --overwrite."""
    out = tmp_path / "m.onnx"
    dead = _dead_pid()
    stale_file = tmp_path / f".m.onnx{STAGING_TAG}{dead}-a1b2.onnx"
    stale_file.write_bytes(b"half")
    stale_scratch = tmp_path / f".m.onnx{STAGING_TAG}{dead}-c3d4"
    stale_scratch.mkdir()
    (stale_scratch / "fp32.onnx").write_bytes(b"half")
    live = tmp_path / f".m.onnx{STAGING_TAG}{os.getppid()}-e5f6.onnx"
    live.write_bytes(b"being written")
    other = tmp_path / f".other.onnx{STAGING_TAG}{dead}-g7h8.onnx"
    other.write_bytes(b"not ours")
    args = [str(he_ckpt), "-o", str(out), "--plain"]
    assert export_main(args) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([out.name, live.name, other.name])
    capsys.readouterr()
    out.write_bytes(b"keep me")
    assert export_main(args) == 2
    _one_line_error(capsys, str(out), "output exists; pass --overwrite to replace it")
    assert out.read_bytes() == b"keep me"
    assert export_main([*args, "--overwrite"]) == 0
    assert out.read_bytes() != b"keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([out.name, live.name, other.name])


# A child that runs the real msf-export, only with a pause before the written file is verified:
# the candidate then exists (under its staging name) for long enough to be signalled or killed
# there, on any machine (an AMX CPU finishes the whole export within a second).
_SLOW_VERIFY = """
import sys, time
import msfnet.export.pipeline as pipeline
real = pipeline.file_runner
def slow(*args, **kwargs):
    time.sleep(120)
    return real(*args, **kwargs)
pipeline.file_runner = slow
from msfnet.export.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _cli(*args: str, slow_verify: bool = False) -> subprocess.Popen:
    """msf-export in a child process with default signal handling (a background pytest may
    have SIGINT ignored, which the child would inherit)."""
    head = ["-c", _SLOW_VERIFY] if slow_verify else ["-m", "msfnet.export.cli"]
    return subprocess.Popen(
        [sys.executable, *head, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )


def _wait_for_candidate(proc: subprocess.Popen, folder: Path) -> Path:
    """The written, unverified model under its staging name, once it is complete."""
    deadline = time.monotonic() + 240
    while True:
        found = [p for p in _staging(folder) if p.suffix == ".onnx" and p.stat().st_size]
        if found:
            break
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "the export never wrote its file"
        time.sleep(0.05)
    time.sleep(0.5)  # written: the child sleeps before verifying
    return found[0]


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_signalled_export_leaves_nothing(
    sig: signal.Signals, he_ckpt: Path, tmp_path: Path
) -> None:
    out = tmp_path / "new" / "m.onnx"
    proc = _cli(str(he_ckpt), "-o", str(out), slow_verify=True)
    _wait_for_candidate(proc, out.parent)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == (130 if sig == signal.SIGINT else 128 + sig), err
    word = "interrupted" if sig == signal.SIGINT else "terminated"
    assert err.strip().count("\n") == 0 and word in err and "nothing was written" in err, err
    assert list(tmp_path.iterdir()) == []  # also the folder made for the output


@pytest.mark.slow
def test_killed_export_leaves_no_file_and_the_next_run_cleans_up(
    he_ckpt: Path, tmp_path: Path
) -> None:
    out = tmp_path / "m.onnx"
    proc = _cli(str(he_ckpt), "-o", str(out), slow_verify=True)
    candidate = _wait_for_candidate(proc, tmp_path)
    proc.kill()  # SIGKILL: no handler runs
    proc.communicate(timeout=60)
    assert not out.exists()
    assert _staging(tmp_path) == [candidate]  # only a recognisable staging file
    again = _cli(str(he_ckpt), "-o", str(out))
    stdout, err = again.communicate(timeout=300)
    assert again.returncode == 0, err
    assert f"wrote {out}" in stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.onnx"]
