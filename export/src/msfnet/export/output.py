"""Where the exported file is written: checked before the export, moved into place by one rename.

An export writes into a private work folder beside the target (same file system, so the final
``os.replace`` / ``os.link`` is atomic), named with :data:`TEMP_PREFIX` and locked with
``flock`` while the export runs. The folder is removed on success, failure and interruption
(SIGINT / SIGTERM raise, see :func:`signals_raise`); a run killed outright (SIGKILL, power loss)
leaves it, and the next export into that folder removes it: its lock is free then.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from types import FrameType, TracebackType
from typing import Any

from msfnet.runtime.errors import InputError

try:  # POSIX; elsewhere stale folders are recognised by age only
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None  # type: ignore[assignment]

TEMP_PREFIX = ".msf-export-partial-"
LOCK_NAME = "lock"
# A work folder without its lock file may be one another export has just created: leave it
# alone for this long. Without flock (Windows) a folder this old counts as stale.
UNLOCKED_GRACE_S = 60.0
NO_FLOCK_STALE_S = 24 * 3600.0


class Interrupted(KeyboardInterrupt):
    """SIGTERM / SIGHUP turned into an exception so that every ``finally`` runs."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


@contextlib.contextmanager
def signals_raise() -> Iterator[None]:
    """SIGINT raises KeyboardInterrupt, SIGTERM / SIGHUP raise :class:`Interrupted`, for the
    duration (main thread only; signals already ignored stay ignored; previous handlers are
    restored afterwards)."""

    def on_signal(signum: int, _frame: FrameType | None) -> None:
        raise Interrupted(signum)

    wanted: dict[signal.Signals, Callable[[int, FrameType | None], object]] = {
        signal.SIGINT: signal.default_int_handler, signal.SIGTERM: on_signal}
    if hasattr(signal, "SIGHUP"):
        wanted[signal.SIGHUP] = on_signal
    previous: dict[signal.Signals, Any] = {}
    try:
        for sig, handler in wanted.items():
            if signal.getsignal(sig) is signal.SIG_IGN:
                continue  # ignored on purpose (nohup, background jobs): keep it so
            previous[sig] = signal.signal(sig, handler)
    except ValueError:  # not the main thread: leave the process's handlers alone
        pass
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)  # type: ignore[arg-type]


def _same_file(a: Path, b: Path) -> bool:
    if a.resolve() == b.resolve():
        return True
    try:
        return os.path.samefile(a, b)  # hard links
    except OSError:
        return False


def check_target(target: Path, *, overwrite: bool, inputs: Sequence[Path]) -> None:
    """Refuse an output that is, or would replace, an input, and one that cannot be written."""
    for src in inputs:
        if _same_file(target, src):
            raise InputError(f"the output would replace the input {src}; choose another -o",
                             target)
        if src.is_dir() and target.resolve().is_relative_to(src.resolve()):
            raise InputError(f"the output lies inside the input folder {src}; choose another -o",
                             target)
    if target.is_dir():
        raise InputError("is a folder; give the output file's name, e.g. -o model.onnx", target)
    if (target.exists() or target.is_symlink()) and not overwrite:
        raise InputError("output exists; pass --overwrite to replace it", target)
    folder = target.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise InputError(f"cannot create the output folder: {folder} is a file", target)
    if not os.access(folder, os.W_OK | os.X_OK):
        raise InputError(f"cannot write to {folder} (permission denied)", target)


def remove_stale(folder: Path) -> list[Path]:
    """Remove work folders of exports that no longer run (their lock is free); return them."""
    removed: list[Path] = []
    try:
        entries = [p for p in folder.iterdir() if p.name.startswith(TEMP_PREFIX)]
    except OSError:
        return removed
    for entry in entries:
        if entry.is_dir() and not entry.is_symlink() and _is_stale(entry):
            shutil.rmtree(entry, ignore_errors=True)
            removed.append(entry)
    return removed


def _is_stale(workdir: Path) -> bool:
    try:
        age = time.time() - workdir.stat().st_mtime
    except OSError:
        return False
    if fcntl is None:
        return age > NO_FLOCK_STALE_S
    try:
        fd = os.open(workdir / LOCK_NAME, os.O_RDWR)
    except FileNotFoundError:
        return age > UNLOCKED_GRACE_S
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return False  # held: that export is running
    finally:
        os.close(fd)  # also drops the lock we may have taken
    return True


class OutputSlot:
    """The target's private work folder for the duration of one export.

    ``with OutputSlot(target, overwrite=..., inputs=[...]) as slot``: checks the target and
    creates the work folder before any slow work (so an unwritable target fails at once);
    ``slot.write(data)`` writes the one candidate file, ``slot.commit(path)`` moves it into
    place atomically, ``slot.scratch`` is a folder for tools that need files. Leaving the block
    removes the work folder in every case, and folders it created for a target it never wrote.
    """

    def __init__(self, target: str | Path, *, overwrite: bool = False,
                 inputs: Sequence[str | Path] = ()) -> None:
        self.target = Path(target)
        self.overwrite = overwrite
        self.inputs = [Path(p) for p in inputs]
        self.workdir: Path | None = None
        self._lock_fd: int | None = None
        self._created: list[Path] = []
        self.committed = False

    def __enter__(self) -> OutputSlot:
        check_target(self.target, overwrite=self.overwrite, inputs=self.inputs)
        try:
            self._make_parents()
            remove_stale(self.target.parent)
            self.workdir = Path(tempfile.mkdtemp(prefix=TEMP_PREFIX, dir=self.target.parent))
            self._lock_fd = os.open(self.workdir / LOCK_NAME, os.O_CREAT | os.O_RDWR, 0o600)
            if fcntl is not None:
                fcntl.flock(self._lock_fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            self._cleanup()
            raise InputError(f"cannot write here ({exc.strerror or exc})", self.target) from exc
        except BaseException:
            self._cleanup()
            raise
        return self

    def _make_parents(self) -> None:
        missing = []
        folder = self.target.parent
        while not folder.exists() and folder != folder.parent:
            missing.append(folder)
            folder = folder.parent
        for folder in reversed(missing):
            folder.mkdir()
            self._created.append(folder)

    @property
    def scratch(self) -> Path:
        assert self.workdir is not None, "use OutputSlot as a context manager"
        path = self.workdir / "scratch"
        path.mkdir(exist_ok=True)
        return path

    def write(self, data: bytes) -> Path:
        """The candidate file (in the work folder), flushed to disk."""
        assert self.workdir is not None, "use OutputSlot as a context manager"
        path = self.workdir / self.target.name
        try:
            with open(path, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
        except OSError as exc:
            raise InputError(f"cannot write the output ({exc.strerror or exc})",
                             self.target) from exc
        return path

    def commit(self, path: Path) -> Path:
        """Move the verified candidate into place: one rename, never a partial file."""
        try:
            if self.overwrite:
                os.replace(path, self.target)
            else:
                try:  # link refuses to clobber a file created since the check
                    os.link(path, self.target)
                except FileExistsError:
                    raise InputError("output appeared during the export; pass --overwrite "
                                     "to replace it", self.target) from None
                except OSError:  # no hard links on this file system
                    if self.target.exists():
                        raise InputError("output exists; pass --overwrite to replace it",
                                         self.target) from None
                    os.replace(path, self.target)
        except InputError:
            raise
        except OSError as exc:
            raise InputError(f"cannot move the output into place ({exc.strerror or exc})",
                             self.target) from exc
        self.committed = True
        _fsync_folder(self.target.parent)
        return self.target

    def _cleanup(self) -> None:
        if self.workdir is not None:
            shutil.rmtree(self.workdir, ignore_errors=True)
            self.workdir = None
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None
        if not self.committed:
            for folder in reversed(self._created):  # innermost first; only if still empty
                with contextlib.suppress(OSError):
                    folder.rmdir()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self._cleanup()


def _fsync_folder(folder: Path) -> None:
    """Make the rename itself durable (POSIX); best effort."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


__all__ = ["TEMP_PREFIX", "Interrupted", "OutputSlot", "check_target", "remove_stale",
           "signals_raise"]
