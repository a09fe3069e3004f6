"""The one way msfnet writes files: atomically, never over an input, all-or-nothing.

Rules every command follows (issue #13):
- an output never is, contains or lies inside an input (symlinks resolved, checked both ways);
- an existing output is replaced only with ``overwrite``, and a folder only if msfnet wrote it
  (its ``.msfnet-output.json`` manifest lists every file in it): nothing else is ever deleted;
- files are written to a temporary sibling and renamed into place; folders are staged beside
  the target and renamed as a whole; on SIGINT/SIGTERM the staging is removed, and staging left
  by a killed process (``kill -9``) is removed by the next run writing to the same place;
- output locations are checked before any long computation (:func:`check_output`);
- files get the user's normal permissions (umask), like any other tool's output.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import tempfile
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from .errors import InputError

MANIFEST = ".msfnet-output.json"
STAGING_TAG = ".msf-partial-"  # ".<name>.msf-partial-<pid>-<random>" beside the target


class Terminated(BaseException):
    """SIGTERM/SIGHUP arrived: unwinds like Ctrl-C so every ``finally`` cleans up."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def _raise_terminated(signum: int, frame: object) -> None:
    raise Terminated(signum)


def install_signal_handlers() -> None:
    """Turn SIGTERM (and SIGHUP) into an exception, so staged outputs are removed on a kill."""
    for name in ("SIGTERM", "SIGHUP"):
        sig = getattr(signal, name, None)
        if sig is not None:
            # outside the main thread this raises ValueError: keep the default behaviour there
            with contextlib.suppress(ValueError):
                signal.signal(sig, _raise_terminated)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _resolved(path: Path) -> Path:
    return Path(os.path.realpath(path))


def _is_within(inner: Path, outer: Path) -> bool:
    return inner == outer or outer in inner.parents


def check_output(target: str | Path, inputs: Iterable[str | Path | None] = (), *,
                 overwrite: bool = False, folder: bool = False) -> Path:
    """Refuse, before any work, an output that would clash with an input or with existing data.

    ``folder``: the output is a folder of files (replaced only if msfnet wrote it).
    Returns the target as given. Raises InputError naming the path.
    """
    target = Path(target)
    real = _resolved(target)
    for item in inputs:
        if item is None:
            continue
        src = _resolved(Path(item))
        if real == src:
            raise InputError("the output would replace an input; choose another output path",
                             target)
        if _is_within(src, real):
            raise InputError(f"the output {'folder ' if folder else ''}contains the input "
                             f"{item}; choose another output path", target)
        if src.is_dir() and _is_within(real, src):
            raise InputError(f"the output lies inside the input folder {item}; inputs are "
                             "never written to: choose another output path", target)
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
                    raise InputError("output folder exists and is not empty; pass --overwrite "
                                     "to replace it", target)
                foreign = foreign_files(target)
                if foreign:
                    raise InputError(f"--overwrite: the folder holds files msfnet did not write "
                                     f"(e.g. {foreign[0]}); refusing to delete them", target)
        else:
            if target.is_dir():
                raise InputError("output path is a folder", target)
            if not overwrite:
                raise InputError("output exists; pass --overwrite to replace it", target)
        if not os.access(target if folder else real.parent, os.W_OK):
            raise InputError("output is not writable", target)
    elif not os.access(parent, os.W_OK):
        raise InputError(f"cannot write here: {parent} is not writable", target)
    return target


def foreign_files(folder: Path) -> list[str]:
    """Entries of an existing output folder that its msfnet manifest does not list."""
    listed: set[str] = set()
    manifest = folder / MANIFEST
    if manifest.is_file():
        try:
            listed = set(json.loads(manifest.read_text()).get("files", []))
        except (ValueError, AttributeError):
            listed = set()
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
    prefix = f".{target.name}{STAGING_TAG}"
    for entry in parent.iterdir():
        if not entry.name.startswith(prefix):
            continue
        pid_text = entry.name[len(prefix):].split("-", 1)[0]
        if pid_text.isdigit() and not _pid_alive(int(pid_text)):
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)


def _staging_name(target: Path) -> str:
    return f".{target.name}{STAGING_TAG}{os.getpid()}-"


def write_atomic(path: str | Path, write: Callable[[Path], object]) -> Path:
    """Write one file through a temporary sibling and a rename: never a half-written file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_staging(path)
    fd, tmp_name = tempfile.mkstemp(prefix=_staging_name(path), suffix=path.suffix,
                                    dir=path.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes files 0600; outputs follow the umask
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def write_text(path: str | Path, text: str) -> Path:
    return write_atomic(path, lambda t: t.write_text(text))


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


def write_json(path: str | Path, data: object) -> Path:
    return write_text(path, json_text(data))


def vectors_text(rows: np.ndarray | Sequence[Sequence[float]], fmt: str = "{:.8f}") -> str:
    """One row of numbers per line (light directions, intensities)."""
    return "".join(" ".join(fmt.format(float(v)) for v in r) + "\n" for r in rows)


def write_vectors(path: str | Path, rows: np.ndarray | Sequence[Sequence[float]],
                  fmt: str = "{:.8f}") -> Path:
    return write_text(path, vectors_text(rows, fmt))


@contextmanager
def staged_folder(outdir: str | Path, *, overwrite: bool = False) -> Iterator[Path]:
    """Yield an empty staging folder beside ``outdir``; on success it becomes ``outdir``.

    Everything written into it appears at once (one rename) or not at all: an exception, Ctrl-C
    or SIGTERM (with :func:`install_signal_handlers`) removes the staging folder. A manifest of
    the files is added, so a later ``--overwrite`` knows the folder is msfnet's own.
    """
    outdir = Path(outdir)
    outdir.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_staging(outdir)
    tmp = Path(tempfile.mkdtemp(prefix=_staging_name(outdir), dir=outdir.parent))
    tmp.chmod(0o777 & ~_umask())
    try:
        yield tmp
        names = sorted(p.name for p in tmp.iterdir())
        (tmp / MANIFEST).write_text(json.dumps({"files": names}) + "\n")
        (tmp / MANIFEST).chmod(0o666 & ~_umask())
        _commit(tmp, outdir, overwrite)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def _commit(tmp: Path, outdir: Path, overwrite: bool) -> None:
    """Put the finished staging folder in place; an old msfnet folder goes only afterwards."""
    old = None
    if outdir.exists():
        if outdir.is_dir() and any(outdir.iterdir()):
            if not overwrite:
                raise InputError("output folder appeared while running; pass --overwrite",
                                 outdir)
            foreign = foreign_files(outdir)
            if foreign:
                raise InputError(f"--overwrite: the folder holds files msfnet did not write "
                                 f"(e.g. {foreign[0]}); refusing to delete them", outdir)
        old = outdir.with_name(f"{_staging_name(outdir)}old")
        os.replace(outdir, old)
    os.replace(tmp, outdir)
    if old is not None and old.exists():
        shutil.rmtree(old, ignore_errors=True)


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


__all__ = ["MANIFEST", "Terminated", "check_output", "install_signal_handlers", "json_text",
           "numbered_folder", "remove_stale_staging", "staged_folder", "to_jsonable",
           "vectors_text", "write_atomic", "write_json", "write_text", "write_vectors"]
