"""Publishing outputs (common/files/atomic.py): umask permissions, all or nothing, concurrent
commits never mix, signals deferred, contents flushed before the rename.
"""

from __future__ import annotations

import json
import os
import signal
from collections.abc import Callable
from pathlib import Path

import pytest
from _runtime_helpers import msfnet_folder as _msfnet_folder
from _runtime_helpers import staging_leftovers as _leftovers

from msfnet.common import files
from msfnet.common.errors import InputError
from msfnet.common.files import (
    MANIFEST,
    STAGING_TAG,
    scratch_folder,
    staged_files,
    staged_folder,
    write_atomic,
    write_text,
    written_outputs,
)

# ---------------------------------------------------------------------------- permissions


def _write_each(kind: str, target: Path) -> list[Path]:
    """Write with one helper; return the paths whose mode to check."""
    if kind == "write_text":
        write_text(target, "x")
        return [target]
    if kind == "write_atomic":
        write_atomic(target, lambda t: t.write_bytes(b"x"))
        return [target]
    if kind == "staged_files":
        with staged_files([target, target.with_name("b.txt")]) as temps:
            for t in temps:
                t.write_text("x")
        return [target, target.with_name("b.txt")]
    with staged_folder(target) as tmp:
        (tmp / "f.txt").write_text("x")
    return [target, target / "f.txt", target / MANIFEST]


@pytest.mark.parametrize("umask", [0o022, 0o077, 0o002])
@pytest.mark.parametrize("kind", ["write_text", "write_atomic", "staged_files", "staged_folder"])
def test_outputs_follow_the_umask(kind: str, umask: int, tmp_path: Path) -> None:
    old = os.umask(umask)
    try:
        paths = _write_each(kind, tmp_path / "out" / "a.txt")
    finally:
        os.umask(old)
    for p in paths:
        want = (0o777 if p.is_dir() else 0o666) & ~umask
        assert p.stat().st_mode & 0o777 == want, (p, oct(p.stat().st_mode))
    assert not _leftovers(tmp_path)


# ---------------------------------------------------------------------------- all or nothing


class Boom(Exception):
    pass


def _fail(_: Path) -> None:
    raise Boom


FAILING_WRITES: dict[str, Callable[[Path], None]] = {
    "write_atomic": lambda p: write_atomic(p / "new" / "deeper" / "a.txt", _fail),
    "staged_folder": lambda p: _staged_folder_failing(p / "new" / "deeper" / "out"),
    "staged_files (second file fails)": lambda p: _staged_files_failing(p / "new" / "d" / "a.txt"),
    "scratch_folder": lambda p: _scratch_failing(p / "new" / "deeper" / "m.onnx"),
}


def _scratch_failing(target: Path) -> None:
    with scratch_folder(target) as scratch:
        (scratch / "fp32.onnx").write_bytes(b"half")
        raise Boom


def _staged_folder_failing(out: Path) -> None:
    with staged_folder(out) as tmp:
        (tmp / "half.npy").write_bytes(b"half")
        raise Boom


def _staged_files_failing(first: Path) -> None:
    with staged_files([first, first.parent / "b.png"]) as temps:
        temps[0].write_text("complete")
        raise Boom


@pytest.mark.parametrize("case", sorted(FAILING_WRITES))
def test_failed_write_leaves_nothing(case: str, tmp_path: Path) -> None:
    """Not the output, not a staging file, not even the folders created for it."""
    with pytest.raises(Boom):
        FAILING_WRITES[case](tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_staged_files_keeps_old_versions_on_failure(tmp_path: Path) -> None:
    a, b = tmp_path / "l.txt", tmp_path / "l_confidence.txt"
    a.write_text("old a")
    b.write_text("old b")
    with pytest.raises(Boom), staged_files([a, b], overwrite=True) as temps:
        temps[0].write_text("new a")
        raise Boom
    assert (a.read_text(), b.read_text()) == ("old a", "old b")
    assert not _leftovers(tmp_path)


def test_staged_files_rolls_back_a_failed_rename(tmp_path: Path, monkeypatch) -> None:
    """The second rename fails (disk trouble): the first target gets its old version back."""
    a, b = tmp_path / "l.txt", tmp_path / "d.png"
    a.write_text("old a")
    real_replace = os.replace
    calls: list[tuple[str, str]] = []

    def replace(src, dst):  # moves: a aside, new a in place, then fail on b's rename
        calls.append((str(src), str(dst)))
        if Path(dst) == b:
            raise OSError(28, "No space left on device", str(b))
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    with pytest.raises(OSError), staged_files([a, b], overwrite=True) as temps:
        temps[0].write_text("new a")
        temps[1].write_text("new b")
    assert a.read_text() == "old a" and not b.exists()
    assert not _leftovers(tmp_path)


def test_staged_files_refuses_existing_and_duplicate_targets(tmp_path: Path) -> None:
    a = tmp_path / "a.txt"
    with pytest.raises(InputError, match="same file"), staged_files([a, tmp_path / "." / "a.txt"]):
        pass
    a.write_text("user data")
    with (
        pytest.raises(InputError, match="appeared while running"),
        staged_files([tmp_path / "b.txt", a]) as temps,
    ):
        for t in temps:
            t.write_text("new")
    assert a.read_text() == "user data" and not (tmp_path / "b.txt").exists()
    assert not _leftovers(tmp_path)


# ---------------------------------------------------------------------------- concurrency


def test_concurrent_folder_writers_never_mix(tmp_path: Path) -> None:
    """Both passed the up-front check, both staged; the first commit wins and the second is
    told, its staging removed: never a folder with files of both."""
    out = tmp_path / "out"
    first = staged_folder(out)
    second = staged_folder(out)
    tmp1, tmp2 = first.__enter__(), second.__enter__()
    (tmp1 / "normals.npy").write_text("run 1")
    (tmp1 / "only_in_1.txt").write_text("run 1")
    (tmp2 / "normals.npy").write_text("run 2")
    first.__exit__(None, None, None)
    with pytest.raises(InputError, match=r"appeared while running.*overwrite=True"):
        second.__exit__(None, None, None)
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST, "normals.npy", "only_in_1.txt"]
    assert (out / "normals.npy").read_text() == "run 1"
    assert not _leftovers(tmp_path)


def test_concurrent_overwriters_replace_whole_folders(tmp_path: Path) -> None:
    out = _msfnet_folder(tmp_path / "out", ("old.txt",))
    first, second = staged_folder(out, overwrite=True), staged_folder(out, overwrite=True)
    tmp1, tmp2 = first.__enter__(), second.__enter__()
    (tmp1 / "only_in_1.txt").write_text("1")
    (tmp2 / "only_in_2.txt").write_text("2")
    first.__exit__(None, None, None)
    second.__exit__(None, None, None)
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST, "only_in_2.txt"]
    assert json.loads((out / MANIFEST).read_text())["files"] == ["only_in_2.txt"]
    assert not _leftovers(tmp_path)


def test_write_atomic_without_overwrite_refuses_a_file_that_appeared(tmp_path: Path) -> None:
    path = tmp_path / "l.txt"

    def meanwhile(tmp: Path) -> None:
        tmp.write_text("ours")
        path.write_text("another command's")  # appears while we are writing

    with pytest.raises(InputError, match="appeared while running"):
        write_atomic(path, meanwhile, overwrite=False)
    assert path.read_text() == "another command's" and not _leftovers(tmp_path)


def test_signal_during_commit_is_deferred(tmp_path: Path, monkeypatch) -> None:
    """Ctrl-C arriving between moving the old output aside and renaming the new one in used
    to leave no output at all; now the commit completes, then the interrupt is raised."""
    out = _msfnet_folder(tmp_path / "out", ("old.txt",))
    real_replace = os.replace

    def replace(src, dst):
        result = real_replace(src, dst)
        if Path(src) == out:  # the old folder was just moved aside
            os.kill(os.getpid(), signal.SIGINT)
        return result

    monkeypatch.setattr(os, "replace", replace)
    with pytest.raises(KeyboardInterrupt), staged_folder(out, overwrite=True) as tmp:
        (tmp / "new.txt").write_text("complete")
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST, "new.txt"]
    assert not _leftovers(tmp_path)
    assert written_outputs()[-1] == out  # so the CLI can say it was written


def _record_syncs_and_renames(monkeypatch) -> list[tuple[str, str]]:
    """Log of ("fsync", what the descriptor names) and ("rename", target) in call order."""
    log: list[tuple[str, str]] = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd: int) -> None:
        log.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        real_fsync(fd)

    def replace(src, dst) -> None:
        log.append(("rename", str(dst)))
        real_replace(src, dst)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    return log


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="needs /proc to name descriptors")
def test_every_commit_flushes_the_content_before_the_rename(tmp_path: Path, monkeypatch) -> None:
    # A power cut after the rename must not leave an empty file under the output's name.
    log = _record_syncs_and_renames(monkeypatch)
    target = tmp_path / "n.txt"
    write_text(target, "normals")
    renamed = log.index(("rename", str(target)))
    flushed = [i for i, (kind, name) in enumerate(log) if kind == "fsync" and STAGING_TAG in name]
    assert flushed and max(flushed) < renamed  # the temporary sibling, before its rename
    assert ("fsync", str(tmp_path)) in log[renamed:]  # then the folder holding the new name

    log.clear()
    outdir = tmp_path / "maps"
    with staged_folder(outdir) as stage:
        (stage / "sub").mkdir()
        (stage / "sub" / "a.bin").write_bytes(b"a")
        (stage / "b.bin").write_bytes(b"b")
    renamed = log.index(("rename", str(outdir)))
    before = {Path(name).name for kind, name in log[:renamed] if kind == "fsync"}
    assert {"a.bin", "b.bin", MANIFEST, "sub"} <= before  # the subfolder's entries too

    log.clear()
    pair = [tmp_path / "l.txt", tmp_path / "l_confidence.txt"]
    with staged_files(pair) as temps:
        for t in temps:
            t.write_text("x")
    first_rename = min(log.index(("rename", str(p))) for p in pair)
    synced = [name for kind, name in log[:first_rename] if kind == "fsync"]
    assert len([n for n in synced if STAGING_TAG in n]) == 2


def test_files_written_into_a_staged_folder_are_flushed_once(tmp_path: Path, monkeypatch) -> None:
    # msf-synth writes thousands of small files through write_atomic inside a staged folder:
    # each is flushed at the folder's commit only, not also on its own.
    log = _record_syncs_and_renames(monkeypatch)
    with staged_folder(tmp_path / "set") as stage:
        for i in range(12):
            write_text(stage / f"{i}.txt", "x")
    synced = [Path(name).name for kind, name in log if kind == "fsync"]
    assert sorted(n for n in synced if n.endswith(".txt")) == sorted(f"{i}.txt" for i in range(12))


def test_a_file_system_that_cannot_flush_folders_still_gets_outputs(
    tmp_path: Path, monkeypatch
) -> None:
    # Network and FUSE file systems answer EINVAL to fsync on a folder: best effort there.
    real_fsync = os.fsync

    def fsync(fd: int) -> None:
        if Path(f"/proc/self/fd/{fd}").resolve().is_dir():
            raise OSError(22, "Invalid argument")
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    with staged_folder(tmp_path / "maps") as stage:
        (stage / "sub").mkdir()
        (stage / "sub" / "a.txt").write_text("a")
    write_text(tmp_path / "n.txt", "n")
    assert (tmp_path / "maps" / "sub" / "a.txt").read_text() == "a"
    assert (tmp_path / "n.txt").read_text() == "n"


def test_a_file_that_may_only_be_written_is_flushed_through_a_write_handle(
    tmp_path: Path, monkeypatch
) -> None:
    # (umask 0477 or a 0200 file: opening it for reading is refused; root cannot show that.)
    real_open = os.open
    modes: list[int] = []

    def open_(path, flags, *args):
        if (
            STAGING_TAG in str(path)
            and not Path(path).is_dir()
            and flags in (os.O_RDONLY, os.O_WRONLY)
        ):  # not mkstemp's creation
            modes.append(flags)
            if flags == os.O_RDONLY:
                raise PermissionError(13, "Permission denied", str(path))
        return real_open(path, flags, *args)

    monkeypatch.setattr(os, "open", open_)
    write_text(tmp_path / "n.txt", "normals")
    assert (tmp_path / "n.txt").read_text() == "normals"
    assert modes == [os.O_RDONLY, os.O_WRONLY]


def test_a_failed_flush_names_the_output_and_leaves_nothing(tmp_path: Path, monkeypatch) -> None:
    def fsync(fd: int) -> None:
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(os, "fsync", fsync)
    target = tmp_path / "out" / "n.txt"
    with pytest.raises(OSError) as exc:
        write_text(target, "normals")
    assert exc.value.filename == str(target) and exc.value.errno == 5
    assert not (tmp_path / "out").exists()
    with pytest.raises(OSError) as exc, staged_folder(tmp_path / "maps") as stage:
        (stage / "a.txt").write_text("a")
    assert exc.value.filename == str(tmp_path / "maps")
    assert not _leftovers(tmp_path) and not (tmp_path / "maps").exists()


def test_an_output_replaced_again_counts_once(tmp_path: Path) -> None:
    # msf-train rewrites last.pth every few minutes: an interrupted run has one output there.
    files.forget_written()
    for text in ("a", "b", "c"):
        write_text(tmp_path / "last.txt", text)
    write_text(tmp_path / "other.txt", "x")
    assert written_outputs() == [tmp_path / "last.txt", tmp_path / "other.txt"]
    files.forget_written()


@pytest.mark.parametrize(
    "writer", ["write_atomic", "staged_files", "staged_folder", "staged_folder_unnamed"]
)
def test_a_full_disk_names_the_output_not_its_temporary(writer: str, tmp_path: Path) -> None:
    """A write failing as a full disk does (OSError without a file name) is reported against
    the output the user named: "error: No space left on device" alone said nothing of where."""
    import errno

    def full(_path: Path) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    target = tmp_path / "out.bin"
    with pytest.raises(OSError) as exc:
        if writer == "write_atomic":
            write_atomic(target, full)
        elif writer == "staged_files":
            with staged_files([target]) as (tmp,):
                full(tmp)  # a writer that names no file: the one output
        elif writer == "staged_folder":
            with staged_folder(target) as tmp:
                (tmp / "a.npy").write_bytes(b"x")
                raise OSError(errno.ENOSPC, "No space left on device", str(tmp / "b.npy"))
        else:  # review-stack23.md 11: "msf-run: error: No space left on device", no file
            with staged_folder(target) as tmp:
                full(tmp / "error.png")
    assert exc.value.errno == errno.ENOSPC
    assert exc.value.filename == str(target)
    assert list(tmp_path.iterdir()) == []


def test_an_error_that_is_no_write_error_is_not_pinned_on_the_output(tmp_path: Path) -> None:
    import errno

    with pytest.raises(OSError) as exc, staged_folder(tmp_path / "out"):
        raise OSError(errno.ECONNREFUSED, "Connection refused")
    assert exc.value.filename is None
