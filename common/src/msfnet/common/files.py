"""The one way msfnet writes files: atomically, never over an input, all-or-nothing.

Rules every command follows (issue #13):
- an output never is, contains or lies inside an input (symlinks resolved, checked both ways);
- an existing output is replaced only with ``overwrite``, and a folder only if msfnet wrote it
  (its ``.msfnet-output.json`` manifest lists every file in it): nothing else is ever deleted;
  the manifest also names the command that wrote the folder, so a command can refuse to replace
  another's (msf-synth replaces only a benchmark root it rendered);
- files are written to a temporary sibling and renamed into place; folders are staged beside
  the target and renamed as a whole; on SIGINT/SIGTERM the staging is removed, and staging left
  by a killed process (``kill -9``) is removed by the next run writing to the same place;
- several output files of one command appear together or not at all (:func:`staged_files`);
- intermediate files a command needs on disk go to a scratch folder beside the output that is
  always removed (:func:`scratch_folder`), and after a ``kill -9`` by the next run;
- output locations are checked before any long computation (:func:`check_output`);
- commits hold a lock on the output's parent folder and defer Ctrl-C/SIGTERM, so two commands
  writing to the same place never mix their files (the second one is told, or replaces the first
  with ``overwrite``), and a signal never lands between removing an old output and renaming the
  new one into place;
- files get the user's normal permissions (umask), like any other tool's output;
- contents are flushed to disk before the rename that publishes them, and the folder after it
  (:func:`_durable`), so a power cut never leaves an empty or partly written file under an
  output's name (a few ms a file: 2 ms for 1 MB, 41 ms for 10 MB measured; the files of a
  staged folder are flushed once, at its commit, from 8 threads).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path

import numpy as np

from msfnet.common.errors import InputError
from msfnet.common.signals import signals_deferred

MANIFEST = ".msfnet-output.json"
STAGING_TAG = ".msf-partial-"  # ".<name>.msf-partial-<pid>-<random>" beside the target


# The command writing outputs (each CLI sets it around its body with :func:`writing_as`), kept
# in every output folder's manifest; folders written from Python without a command say so.
_command: ContextVar[str | None] = ContextVar("msfnet_command", default=None)
API_WRITER = "msfnet (Python API)"


@contextmanager
def writing_as(command: str) -> Iterator[None]:
    """Record ``command`` as the writer of the output folders made inside the block."""
    token = _command.set(command)
    try:
        yield
    finally:
        _command.reset(token)


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


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


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
        for folder in sorted({_resolved(f) for f in folders}):  # one order: no deadlock
            fd = os.open(folder, os.O_RDONLY)
            fds.append(fd)
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        for fd in fds:
            os.close(fd)  # closing releases the lock


def _make_parents(path: Path) -> list[Path]:
    """Create the missing folders above ``path``; return them, deepest first, so a failed
    command can remove what it created (an error leaves nothing behind, not even folders)."""
    missing = []
    parent = path.parent
    while not parent.exists():
        missing.append(parent)
        parent = parent.parent
    path.parent.mkdir(parents=True, exist_ok=True)
    return missing


def _remove_empty(folders: Iterable[Path]) -> None:
    for folder in folders:
        with contextlib.suppress(OSError):
            folder.rmdir()


def _resolved(path: Path) -> Path:
    return Path(os.path.realpath(path))


def _is_within(inner: Path, outer: Path) -> bool:
    return inner == outer or outer in inner.parents


def check_output(
    target: str | Path,
    inputs: Iterable[str | Path | None] = (),
    *,
    overwrite: bool = False,
    folder: bool = False,
    command: str | None = None,
) -> Path:
    """Refuse, before any work, an output that would clash with an input or with existing data.

    ``folder``: the output is a folder of files (replaced only if msfnet wrote it; with
    ``command``, only if that command wrote it, see :func:`refuse_foreign`).
    Returns the target as given. Raises InputError naming the path.
    """
    target = Path(target)
    real = check_not_input(target, inputs, folder=folder)
    # the nearest existing ancestor must be a writable folder
    parent = real.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise InputError(f"cannot create the output: {parent} is a file, not a folder", target)
    if target.exists() or target.is_symlink():
        if folder:
            if not target.is_dir():
                raise InputError("output path exists and is not a folder", target)
            if any(target.iterdir()):
                if not overwrite:
                    raise InputError(
                        "output folder exists and is not empty; pass --overwrite to replace it",
                        target,
                    )
                refuse_foreign(target, command)
        else:
            if target.is_dir():
                raise InputError("output path is a folder", target)
            if not overwrite:
                raise InputError("output exists; pass --overwrite to replace it", target)
        # replacing means renaming in the parent folder (and, for a folder, reading it)
        if not os.access(real.parent, os.W_OK):
            raise InputError(f"cannot replace the output: {real.parent} is not writable", target)
    elif not os.access(parent, os.W_OK):
        raise InputError(f"cannot write here: {parent} is not writable", target)
    return target


def same_file(a: str | Path, b: str | Path) -> bool:
    """Two names of one file (a hard link, a symlink): replacing one would still be writing
    "over" the other, as a user sees it. False when either does not exist (yet)."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def check_not_input(
    target: str | Path, inputs: Iterable[str | Path | None] = (), *, folder: bool = False
) -> Path:
    """Refuse an output that is, contains or lies inside an input (symlinks resolved).
    Returns the resolved target."""
    target = Path(target)
    real = _resolved(target)
    for item in inputs:
        if item is None:
            continue
        src = _resolved(Path(item))
        if real == src or same_file(real, src):
            raise InputError(
                "the output would replace an input; choose another output path", target
            )
        if _is_within(src, real):
            raise InputError(
                f"the output {'folder ' if folder else ''}contains the input "
                f"{item}; choose another output path",
                target,
            )
        if src.is_dir() and _is_within(real, src):
            raise InputError(
                f"the output lies inside the input folder {item}; inputs are "
                "never written to: choose another output path",
                target,
            )
    return real


def refuse_foreign(folder: Path, command: str | None = None) -> None:
    """--overwrite replaces a folder only if msfnet wrote everything in it, and with
    ``command`` only if that command did (folders from before the manifest named its writer
    stay replaceable)."""
    manifest = _read_manifest(folder)
    if manifest is None and (folder / MANIFEST).exists():
        raise InputError(
            f"--overwrite: the folder's {MANIFEST} is damaged, so msfnet cannot "
            "tell its own files; refusing to delete anything",
            folder,
        )
    foreign = foreign_files(folder)
    if foreign:
        raise InputError(
            f"--overwrite: the folder holds files msfnet did not write (e.g. "
            f"{foreign[0]}); refusing to delete them",
            folder,
        )
    writer = manifest[1] if manifest else None
    if command is not None and writer is not None and writer != command:
        raise InputError(
            f"--overwrite: the folder is {writer}'s output, not {command}'s; "
            "refusing to replace it (choose another folder)",
            folder,
        )


def _read_manifest(folder: Path) -> tuple[list[str], str | None] | None:
    """An output folder's manifest ``{"files": [names], "command": writer}`` as (files,
    writer); None when it is missing or damaged (not JSON, "files" not a list of names)."""
    try:
        data = json.loads((folder / MANIFEST).read_text())
    except (OSError, ValueError, RecursionError):  # missing, unreadable, not UTF-8, not JSON
        return None
    if not isinstance(data, dict):
        return None
    files_ = data.get("files")
    if not isinstance(files_, list) or not all(isinstance(f, str) for f in files_):
        return None
    writer = data.get("command")  # absent in folders written before it was recorded
    return files_, writer if isinstance(writer, str) else None


def foreign_files(folder: Path) -> list[str]:
    """Entries of an existing output folder that its msfnet manifest does not list (all of
    them when the manifest is missing or damaged)."""
    manifest = _read_manifest(folder)
    listed = set(manifest[0]) if manifest else set()
    return sorted(p.name for p in folder.iterdir() if p.name != MANIFEST and p.name not in listed)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_staging(target: Path) -> None:
    """Remove staging left beside ``target`` by processes that no longer run (kill -9)."""
    parent = target.parent
    if not parent.is_dir():
        return
    prefix = _staging_prefix(target)
    for entry in parent.iterdir():
        if not entry.name.startswith(prefix):
            continue
        pid_text = entry.name[len(prefix) :].split("-", 1)[0]
        if pid_text.isdigit() and not _pid_alive(int(pid_text)):
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)


def _short(name: str, limit: int = 150) -> str:
    """``name`` cut to ``limit`` bytes: a staging name adds ~30 characters and a suffix, and a
    legal 250-byte output name must not fail as "File name too long"."""
    raw = os.fsencode(name)
    if len(raw) <= limit:
        return name
    for end in range(limit, limit - 4, -1):  # not inside a multi-byte character
        try:
            return raw[:end].decode("utf-8")
        except UnicodeDecodeError:
            continue
    return os.fsdecode(raw[:limit])


def _staging_prefix(target: Path) -> str:
    """What every staging name beside ``target`` starts with; the writer's pid follows."""
    return f".{_short(target.name)}{STAGING_TAG}"


def _staging_name(target: Path) -> str:
    return f"{_staging_prefix(target)}{os.getpid()}-"


def _new_staging(target: Path, *, folder: bool) -> Path:
    """A fresh staging folder, or empty file (0600), beside ``target``; a failure (a read-only
    or pseudo file system) names the target the user gave, not the temporary name."""
    try:
        if folder:
            return Path(tempfile.mkdtemp(prefix=_staging_name(target), dir=target.parent))
        # the suffix stays (writers such as OpenCV pick the format by it), unless absurd
        suffix = target.suffix if len(os.fsencode(target.suffix)) <= 32 else ""
        fd, name = tempfile.mkstemp(prefix=_staging_name(target), suffix=suffix, dir=target.parent)
        os.close(fd)
        return Path(name)
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror, str(target)) from exc


@contextmanager
def scratch_folder(target: str | Path) -> Iterator[Path]:
    """A private empty folder beside ``target`` for intermediate files of the command writing
    it (for tools that only work on files, such as onnxruntime's quantiser).

    Always removed on leaving the block, also on errors and signals (with
    :func:`install_signal_handlers`); named like ``target``'s staging, so a folder left by a
    killed process (``kill -9``) is removed by the next run writing ``target``. Beside the
    target, not in /tmp: same file system and disk space as the output. Folders created for it
    are removed again unless something (the output itself) has been put in them meanwhile.
    """
    target = Path(target)
    created = _make_parents(target)
    remove_stale_staging(target)
    tmp = _new_staging(target, folder=True)
    try:
        yield tmp
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        _remove_empty(created)


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
    :func:`check_output`; this closes the window between that check and the end).
    ``output=False``: a file that is no result of the command (a cache), so it is not listed
    among the outputs an interrupted command reports as kept.
    """
    path = Path(path)
    created = _make_parents(path)
    remove_stale_staging(path)
    tmp = _new_staging(path, folder=False)
    done = False
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes files 0600; outputs follow the umask
        # A file inside a staging folder is flushed with the whole folder when that commits.
        staged = any(STAGING_TAG in part for part in path.parts)
        if not staged:
            _durable([tmp], path)
        with signals_deferred(), _commit_lock([path.parent]):
            if not overwrite and (path.exists() or path.is_symlink()):
                raise InputError(
                    "output appeared while running (another command wrote it?); "
                    "pass --overwrite to replace it",
                    path,
                )
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
            _remove_empty(created)
    return path


def write_text(path: str | Path, text: str, *, overwrite: bool = True, output: bool = True) -> Path:
    return write_atomic(path, lambda t: t.write_text(text), overwrite=overwrite, output=output)


def to_jsonable(value: object) -> object:
    """Replace non-finite floats by None (bare NaN is not JSON) and numpy scalars by Python's."""
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    return value


def json_text(data: object) -> str:
    return json.dumps(to_jsonable(data), indent=2, allow_nan=False) + "\n"


def write_json(
    path: str | Path, data: object, *, overwrite: bool = True, output: bool = True
) -> Path:
    return write_text(path, json_text(data), overwrite=overwrite, output=output)


def vectors_text(rows: np.ndarray | Sequence[Sequence[float]], fmt: str = "{:.8f}") -> str:
    """One row of numbers per line (light directions, intensities)."""
    return "".join(" ".join(fmt.format(float(v)) for v in r) + "\n" for r in rows)


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
    created = _make_parents(outdir)
    remove_stale_staging(outdir)
    tmp = _new_staging(outdir, folder=True)
    done = False
    try:
        tmp.chmod(0o777 & ~_umask())
        yield tmp
        names = sorted(p.name for p in tmp.iterdir())
        writer = command or _command.get() or API_WRITER
        (tmp / MANIFEST).write_text(json.dumps({"files": names, "command": writer}) + "\n")
        (tmp / MANIFEST).chmod(0o666 & ~_umask())
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
            _remove_empty(created)


def _commit(tmp: Path, outdir: Path, overwrite: bool, command: str | None = None) -> None:
    """Put the finished staging folder in place; an old msfnet folder goes only afterwards.

    Runs under the parent folder's lock: whatever is at ``outdir`` now is what gets checked.
    """
    old = None
    if outdir.exists() or outdir.is_symlink():
        if not outdir.is_dir():
            raise InputError("output appeared while running and is not a folder", outdir)
        if any(outdir.iterdir()):
            if not overwrite:
                raise InputError(
                    "output folder appeared while running (another command wrote "
                    "it?); pass --overwrite to replace it",
                    outdir,
                )
            refuse_foreign(outdir, command)
        old = _new_staging(outdir, folder=True)
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
    if len({_resolved(p) for p in paths}) != len(paths):
        raise InputError(
            f"two outputs of this command are the same file: {', '.join(str(p) for p in paths)}"
        )
    created: list[Path] = []
    temps: list[Path] = []
    done = False
    try:
        for path in paths:
            created += _make_parents(path)
            remove_stale_staging(path)
            temps.append(_new_staging(path, folder=False))
        yield list(temps)
        for tmp in temps:
            os.chmod(tmp, 0o666 & ~_umask())
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
            _remove_empty(created)


def _commit_files(pairs: list[tuple[Path, Path]], overwrite: bool) -> None:
    for _, path in pairs:
        if path.is_dir():
            raise InputError("output path is a folder", path)
        if not overwrite and (path.exists() or path.is_symlink()):
            raise InputError(
                "output appeared while running (another command wrote it?); "
                "pass --overwrite to replace it",
                path,
            )
    backups: list[tuple[Path, Path | None]] = []  # (target, its previous version moved aside)
    try:
        for tmp, path in pairs:
            backup = None
            if path.exists() or path.is_symlink():
                backup = path.with_name(f"{_staging_name(path)}old{path.suffix}")
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


def numbered_folder(base: str | Path) -> Path:
    """``base``, or ``base-2``, ``base-3``, ...: the first that does not exist yet (re-running a
    command never needs --overwrite and never touches earlier results)."""
    base = Path(base)
    if not base.exists():
        return base
    i = 2
    while base.with_name(f"{base.name}-{i}").exists():
        i += 1
    return base.with_name(f"{base.name}-{i}")


__all__ = [
    "API_WRITER",
    "MANIFEST",
    "check_not_input",
    "check_output",
    "forget_written",
    "json_text",
    "numbered_folder",
    "remove_stale_staging",
    "same_file",
    "scratch_folder",
    "staged_files",
    "staged_folder",
    "to_jsonable",
    "vectors_text",
    "write_atomic",
    "write_json",
    "write_text",
    "write_vectors",
    "writing_as",
    "written_outputs",
]
