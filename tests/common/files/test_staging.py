"""Staging beside outputs (common/files/staging.py): stale staging of killed runs removed,
scratch folders always removed, long legal names still written.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from msfnet.common import files
from msfnet.common.files import (
    STAGING_TAG,
    remove_stale_staging,
    scratch_folder,
    staged_folder,
    write_atomic,
)
from msfnet.common.files.staging import new_staging, pid_space

# ---------------------------------------------------------------------------- stale staging


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_stale_staging_of_killed_runs_is_removed(tmp_path: Path) -> None:
    out = tmp_path / "out"
    dead = _dead_pid()
    stale_dir = tmp_path / f".out{STAGING_TAG}{dead}-abc"
    stale_dir.mkdir()
    (stale_dir / "normals.npy").write_bytes(b"half")
    stale_file = tmp_path / f".out{STAGING_TAG}{dead}-old"
    stale_file.write_text("x")
    live = tmp_path / f".out{STAGING_TAG}{os.getppid()}-xyz"  # a running process's staging
    live.mkdir()
    unrelated = tmp_path / f".other{STAGING_TAG}{dead}-abc"
    unrelated.mkdir()
    with staged_folder(out) as tmp:
        (tmp / "a").write_text("a")
    assert not stale_dir.exists() and not stale_file.exists()
    assert live.exists() and unrelated.exists()  # never someone else's work in progress
    remove_stale_staging(tmp_path / "other")
    assert not unrelated.exists()


# ---------------------------------------------------------------------------- scratch folders


def test_scratch_folder_goes_the_output_stays(tmp_path: Path) -> None:
    """Beside the target (named like its staging), always removed; folders made for it stay
    only if the output was put in them."""
    target = tmp_path / "new" / "m.onnx"
    with scratch_folder(target) as scratch:
        assert scratch.is_dir() and scratch.parent == target.parent
        assert scratch.name.startswith(f".m.onnx{STAGING_TAG}{os.getpid()}@{pid_space()}-")
        (scratch / "sub").mkdir()
        (scratch / "sub" / "big.bin").write_bytes(b"x" * 100)
        write_atomic(target, lambda t: t.write_bytes(b"model"))
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["m.onnx", "new"]
    with scratch_folder(tmp_path / "other" / "x.onnx"):
        pass
    assert not (tmp_path / "other").exists()  # made for a file never written: removed


def test_scratch_folder_removed_on_sigterm(tmp_path: Path) -> None:
    code = (
        "import os, signal, sys\n"
        "from pathlib import Path\n"
        "from msfnet.common.files import scratch_folder\n"
        "from msfnet.common.signals import install_signal_handlers\n"
        "signal.signal(signal.SIGTERM, signal.SIG_DFL)  # pytest's may be ignored\n"
        "install_signal_handlers()\n"
        "with scratch_folder(Path(sys.argv[1])) as s:\n"
        "    (s / 'a.bin').write_bytes(b'half')\n"
        "    os.kill(os.getpid(), signal.SIGTERM)\n"
        "    signal.pause()\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, str(tmp_path / "d" / "m.onnx")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode != 0 and "Terminated" in proc.stderr, proc.stderr
    assert list(tmp_path.iterdir()) == []


def test_scratch_folder_of_a_killed_run_is_removed_by_the_next_write(tmp_path: Path) -> None:
    target = tmp_path / "m.onnx"
    stale = tmp_path / f".m.onnx{STAGING_TAG}{_dead_pid()}-abc"
    (stale / "ort.quant.xyz").mkdir(parents=True)
    (stale / "ort.quant.xyz" / "augmented.onnx").write_bytes(b"half")
    with scratch_folder(target) as mine:
        assert not stale.exists()
        write_atomic(tmp_path / "other.txt", lambda t: t.write_text("x"))
        assert mine.exists()  # a live process's scratch: never someone else's to remove
        write_atomic(target, lambda t: t.write_bytes(b"model"))
        assert mine.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.onnx", "other.txt"]


@pytest.mark.parametrize(
    "kind", ["write_atomic", "staged_folder", "staged_files", "scratch_folder"]
)
def test_a_staging_place_refused_names_the_output(kind: str, tmp_path: Path, monkeypatch) -> None:
    """A folder where no temporary can be made (read-only or pseudo file system, e.g. /proc):
    the error is about the output the user named, not the hidden temporary beside it."""
    import errno
    import tempfile

    from msfnet.common import files

    def refuse(*_a: object, prefix: str = "", dir: str = "", **_k: object) -> object:
        raise OSError(errno.EROFS, "Read-only file system", f"{dir}/{prefix}xyz")

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    monkeypatch.setattr(tempfile, "mkdtemp", refuse)
    target = tmp_path / "out.txt"
    with pytest.raises(OSError) as exc:
        if kind == "write_atomic":
            files.write_atomic(target, lambda p: p.write_text("x"))
        elif kind == "staged_files":
            with files.staged_files([target]):
                pass
        else:
            with getattr(files, kind)(target):
                pass
    assert exc.value.filename == str(target) and exc.value.errno == errno.EROFS
    # the output is not there yet by design: the words say it cannot be written, lest a
    # "No such file or directory" read as a missing input
    assert exc.value.strerror == "cannot write the output here (Read-only file system)"
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("name", ["a" * 246 + ".pth", "é" * 120 + ".npy", "x." + "b" * 250])
def test_a_long_legal_output_name_is_written(name: str, tmp_path: Path) -> None:
    """The staging name adds ~30 bytes; a legal name of up to 255 bytes must still work, and
    a stale staging file of a killed writer of that name is still found."""
    target = tmp_path / name
    stale = new_staging(target, folder=False)
    stale.rename(stale.with_name(stale.name.replace(f"{os.getpid()}@", "999999999@", 1)))
    files.write_atomic(target, lambda p: p.write_text("ok"))
    with files.staged_folder(tmp_path / ("d" * 250)) as folder:
        (folder / "f.txt").write_text("ok")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([name, "d" * 250])
    assert target.read_text() == "ok"


def test_staging_of_another_pid_space_is_never_swept(tmp_path: Path) -> None:
    """A pid means something only in its own namespace: on a shared file system a run swept
    another container's live staging (its pid not running here) and that run failed with
    "No such file or directory". Only this pid space's dead writers' staging goes (and that
    of an earlier boot here, and anyone's untouched for a day); staging named before pid
    spaces counts as this one's."""
    import time

    from msfnet.common.files.staging import STALE_AFTER_S

    target = tmp_path / "out"
    prefix = f".out{STAGING_TAG}"
    space, boot = pid_space().split(".")
    names = {
        "other": f"999999999@00000000.{boot}",  # another container's
        "ours": f"999999999@{pid_space()}",  # this pid space's, its writer dead
        "legacy": "999999999",  # named before pid spaces
        "live": f"{os.getpid()}@{pid_space()}",
        # this host and namespace before a reboot (a power cut): gone, whatever pid
        "rebooted": f"{os.getpid()}@{space}.00000000",
        # another container's, untouched for longer than any write takes
        "old": f"1@11111111.{boot}",
    }
    made = {key: tmp_path / f"{prefix}{name}-abc" for key, name in names.items()}
    for path in made.values():
        path.mkdir()
    then = time.time() - STALE_AFTER_S - 60
    os.utime(made["old"], (then, then))
    other, live = made["other"], made["live"]
    remove_stale_staging(target)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([other.name, live.name])
