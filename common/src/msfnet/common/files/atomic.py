"""Publishing outputs: a file through a temporary sibling and a rename, a folder staged and
renamed as a whole, several files together or not at all.

Every commit holds an advisory lock on the output's parent folder and defers Ctrl-C/SIGTERM,
re-checks what lies at the output's name (:func:`check_replaceable`: something may have been
put there since the up-front check), and flushes contents to disk before the rename that
publishes them and the folder after it, so a power cut never leaves an empty or partly written
file under an output's name (a few ms a file, docs/benchmark.md; the files of a staged folder
are flushed once, at its commit, from 8 threads).
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from msfnet.common.errors import InputError
from msfnet.common.files.locations import check_replaceable, resolved
from msfnet.common.files.manifest import (
    MANIFEST,
    current_writer,
    manifest_text,
    refuse_foreign,
    tree_names,
)
from msfnet.common.files.staging import (
    STAGING_TAG,
    make_parents,
    new_staging,
    remove_empty,
    remove_stale_staging,
    staging_name,
    umask,
)
from msfnet.common.files.text import json_text, vectors_text
from msfnet.common.signals import signals_deferred
from msfnet.common.vocabulary import opt

# Outputs this process has put in place, so an interrupted command can say truthfully what it
# left behind (a multi-stack msf-run interrupted on its second stack has written the first).
_written: list[Path] = []


def written_outputs() -> list[Path]:
    """Outputs committed by this process since the last :func:`forget_written`."""
    return list(_written)


def forget_written() -> None:
    _written.clear()


def _flush_and_close(fd: int) -> None:
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync(path: Path) -> None:
    """Flush one file's data to disk. A file this process may only write (umask 0477, mode
    0200) is opened for writing instead; one it cannot open at all is left to the page cache
    (best effort: the write itself already succeeded). Errors of the flush itself (EIO, ENOSPC)
    propagate: the data may not be on disk."""
    modes = (os.O_WRONLY, os.O_RDONLY) if os.name == "nt" else (os.O_RDONLY, os.O_WRONLY)
    for mode in modes:
        try:
            fd = os.open(path, mode)
        except PermissionError:
            continue
        _flush_and_close(fd)
        return


def _fsync_folder(folder: Path) -> None:
    """Flush a folder's entries (renames, new names), best effort: Windows cannot open a
    folder, and some file systems (network, FUSE) refuse to flush one."""
    if os.name != "nt":
        with contextlib.suppress(OSError):
            _flush_and_close(os.open(folder, os.O_RDONLY))


def _durable(paths: Sequence[Path], target: Path) -> None:
    """Flush these files (or every file and folder in these folders) to disk before the rename
    that publishes them, so the published name never points at data still only in memory.
    Many files are flushed from a few threads (fsync releases the GIL; the file system then
    commits them together). An error names ``target``, not the temporary file."""
    files_: list[Path] = []
    folders: list[Path] = []
    for path in paths:
        if path.is_dir() and not path.is_symlink():
            for item in path.rglob("*"):
                if item.is_symlink():
                    continue
                (folders if item.is_dir() else files_).append(item)
            folders.append(path)
        else:
            files_.append(path)
    try:
        if len(files_) > 8:
            with ThreadPoolExecutor(max_workers=8) as pool:
                list(pool.map(_fsync, files_))
        else:
            for item in files_:
                _fsync(item)
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror or str(exc), str(target)) from exc
    for folder in folders:
        _fsync_folder(folder)


def _sync_folders(folders: Iterable[Path]) -> None:
    """Flush the renames in these folders (best effort, see :func:`_fsync_folder`)."""
    for folder in {Path(f) for f in folders}:
        _fsync_folder(folder)


@contextmanager
def _commit_lock(folders: Iterable[Path]) -> Iterator[None]:
    """Exclusive advisory locks on the given folders (the outputs' parents) while committing.

    flock on the folder itself, so no lock file is ever left behind; without fcntl (Windows)
    commits are not serialised.
    """
    try:
        import fcntl
    except ImportError:
        yield
        return
    fds: list[int] = []
    try:
        for folder in sorted({resolved(f) for f in folders}):  # one order: no deadlock
            fd = os.open(folder, os.O_RDONLY)
            fds.append(fd)
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        for fd in fds:
            os.close(fd)  # closing releases the lock


def _appeared(path: Path) -> InputError:
    return InputError(
        f"output appeared while running (another command wrote it?); pass {opt('overwrite')} "
        "to replace it",
        path,
    )


_WRITE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO, errno.EROFS}


@contextmanager
def _errors_name(targets: Sequence[tuple[Path, Path]], default: Path | None) -> Iterator[None]:
    """An OSError while filling a temporary (a full disk) names the output the user gave, not
    the hidden temporary beside it: ``targets`` pairs each temporary with its output; an
    error naming no file names ``default``."""
    try:
        yield
    except OSError as exc:
        where = None if exc.filename is None else str(exc.filename)
        if where is None:
            # only an error of writing is the output's (a full disk, a quota: numpy's and
            # Python's writes report no file name); any other is left as it came
            target = default if exc.errno in _WRITE_ERRNOS else None
        else:
            inside = [t for tmp, t in targets if where == str(tmp) or where.startswith(f"{tmp}/")]
            target = inside[0] if inside else None
        if target is None or exc.errno is None:
            raise
        raise OSError(exc.errno, exc.strerror or str(exc), str(target)) from exc


def write_atomic(
    path: str | Path,
    write: Callable[[Path], object],
    *,
    overwrite: bool = True,
    output: bool = True,
) -> Path:
    """Write one file through a temporary sibling and a rename: never a half-written file.

    ``overwrite=False``: refuse (InputError) if the file exists when it is about to be put in
    place, e.g. written meanwhile by another command (commands check before any work with
    :func:`check_output`; this closes the window between that check and the end). Whatever
    ``overwrite`` says, only a regular file is ever replaced (:func:`check_replaceable`).
    ``output=False``: a file that is no result of the command (a cache), so it is not listed
    among the outputs an interrupted command reports as kept.
    """
    path = Path(path)
    created = make_parents(path)
    remove_stale_staging(path)
    tmp = new_staging(path, folder=False)
    done = False
    try:
        with _errors_name([(tmp, path)], path):
            write(tmp)
        os.chmod(tmp, 0o666 & ~umask())  # mkstemp makes files 0600; outputs follow the umask
        # A file inside a staging folder is flushed with the whole folder when that commits.
        staged = any(STAGING_TAG in part for part in path.parts)
        if not staged:
            _durable([tmp], path)
        with signals_deferred(), _commit_lock([path.parent]):
            check_replaceable(path)
            if not overwrite and os.path.lexists(path):
                raise _appeared(path)
            os.replace(tmp, path)
            # A file inside a staging folder is not an output yet; one replaced again (msf-train's
            # last.pth every few minutes) is still one output.
            if output and not staged and path not in _written:
                _written.append(path)
        done = True
        if not staged:
            _sync_folders([path.parent])
    finally:
        tmp.unlink(missing_ok=True)
        if not done:
            remove_empty(created)
    return path


def write_text(path: str | Path, text: str, *, overwrite: bool = True, output: bool = True) -> Path:
    return write_atomic(path, lambda t: t.write_text(text), overwrite=overwrite, output=output)


def write_json(
    path: str | Path, data: object, *, overwrite: bool = True, output: bool = True
) -> Path:
    return write_text(path, json_text(data), overwrite=overwrite, output=output)


def write_vectors(
    path: str | Path,
    rows: np.ndarray | Sequence[Sequence[float]],
    fmt: str = "{:.8f}",
    *,
    overwrite: bool = True,
) -> Path:
    return write_text(path, vectors_text(rows, fmt), overwrite=overwrite)


@contextmanager
def staged_folder(
    outdir: str | Path, *, overwrite: bool = False, command: str | None = None
) -> Iterator[Path]:
    """Yield an empty staging folder beside ``outdir``; on success it becomes ``outdir``.

    Everything written into it appears at once (one rename) or not at all: an exception, Ctrl-C
    or SIGTERM (with :func:`install_signal_handlers`) removes the staging folder. A manifest of
    the files and of the command writing them (``command``, else the one of
    :func:`writing_as`) is added, so a later ``--overwrite`` knows the folder is msfnet's own.
    ``command`` also limits ``overwrite`` to that command's folders (see :func:`refuse_foreign`).
    """
    outdir = Path(outdir)
    created = make_parents(outdir)
    remove_stale_staging(outdir)
    tmp = new_staging(outdir, folder=True)
    done = False
    try:
        tmp.chmod(0o777 & ~umask())
        with _errors_name([(tmp, outdir)], outdir):
            yield tmp
            (tmp / MANIFEST).write_text(manifest_text(tree_names(tmp), current_writer(command)))
            (tmp / MANIFEST).chmod(0o666 & ~umask())
            _durable([tmp], outdir)
        with signals_deferred(), _commit_lock([outdir.parent]):
            _commit(tmp, outdir, overwrite, command)
            _written.append(outdir)
        done = True
        _sync_folders([outdir.parent])
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
        if not done:
            remove_empty(created)


def _commit(tmp: Path, outdir: Path, overwrite: bool, command: str | None = None) -> None:
    """Put the finished staging folder in place; an old msfnet folder goes only afterwards.

    Runs under the parent folder's lock: whatever is at ``outdir`` now is what gets checked.
    """
    old = None
    if os.path.lexists(outdir):
        try:
            check_replaceable(outdir, folder=True)
        except InputError as exc:
            raise InputError(f"appeared while running: {exc.message}", outdir) from exc
        if any(outdir.iterdir()):
            if not overwrite:
                raise InputError(
                    "output folder appeared while running (another command wrote "
                    f"it?); pass {opt('overwrite')} to replace it",
                    outdir,
                )
            refuse_foreign(outdir, current_writer(command))
        old = new_staging(outdir, folder=True)
        os.replace(outdir, old / "old")
    try:
        os.replace(tmp, outdir)
    except BaseException:
        if old is not None:  # put the previous output back
            os.replace(old / "old", outdir)
        raise
    finally:
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)


@contextmanager
def staged_files(targets: Sequence[str | Path], *, overwrite: bool = False) -> Iterator[list[Path]]:
    """Several output files that appear together or not at all (msf-calib's lights file, its
    confidence file and diagnostic images).

    Yields one temporary path per target (a sibling, same suffix); fill them all. On success
    they are renamed into place under the parents' locks with signals deferred; if one rename
    fails the ones already done are rolled back (earlier versions restored). On any failure no
    target is touched and the temporaries and any folders created for them are removed.
    ``overwrite=False`` refuses targets that appeared meanwhile.
    """
    paths = [Path(t) for t in targets]
    if len({resolved(p) for p in paths}) != len(paths):
        raise InputError(
            f"two outputs of this command are the same file: {', '.join(str(p) for p in paths)}"
        )
    created: list[Path] = []
    temps: list[Path] = []
    done = False
    try:
        for path in paths:
            created += make_parents(path)
            remove_stale_staging(path)
            temps.append(new_staging(path, folder=False))
        # an error naming no file: the one output, or the folder the outputs share
        where = paths[0] if len(paths) == 1 else Path(os.path.commonpath(paths))
        with _errors_name(list(zip(temps, paths, strict=True)), where):
            yield list(temps)
        for tmp in temps:
            os.chmod(tmp, 0o666 & ~umask())
        for tmp, path in zip(temps, paths, strict=True):
            _durable([tmp], path)
        with signals_deferred(), _commit_lock([p.parent for p in paths]):
            _commit_files(list(zip(temps, paths, strict=True)), overwrite)
            _written.extend(paths)
        done = True
        _sync_folders(p.parent for p in paths)
    finally:
        for tmp in temps:
            tmp.unlink(missing_ok=True)
        if not done:
            remove_empty(created)


def _commit_files(pairs: list[tuple[Path, Path]], overwrite: bool) -> None:
    for _, path in pairs:
        check_replaceable(path)
        if not overwrite and os.path.lexists(path):
            raise _appeared(path)
    backups: list[tuple[Path, Path | None]] = []  # (target, its previous version moved aside)
    try:
        for tmp, path in pairs:
            backup = None
            if os.path.lexists(path):
                backup = path.with_name(f"{staging_name(path)}old{path.suffix}")
                os.replace(path, backup)
            backups.append((path, backup))
            os.replace(tmp, path)
    except BaseException:
        for path, backup in reversed(backups):
            if backup is not None:
                os.replace(backup, path)
            else:
                path.unlink(missing_ok=True)
        raise
    for _, backup in backups:
        if backup is not None:
            backup.unlink(missing_ok=True)


__all__ = [
    "forget_written",
    "staged_files",
    "staged_folder",
    "write_atomic",
    "write_json",
    "write_text",
    "write_vectors",
    "written_outputs",
]
