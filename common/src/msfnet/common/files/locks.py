"""A lock a long-running writer holds on its folder for as long as it works there.

Commits lock the output's parent folder only for the instant of the renames; a capture session
writes into one folder frame after frame for minutes, and two of them into one folder would
both report success with one's frames gone. :func:`folder_lock` refuses the second.

The lock is ``flock`` on a hidden file in the folder (not on the folder itself: the commits of
the holder's own frames flock that one, and flock locks of one process on two descriptors
conflict). The file is removed when the lock is released; one left by a killed process holds no
lock (the kernel drops it with the process) and is taken over by the next run.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from msfnet.common.errors import InputError
from msfnet.common.files.staging import make_parents, remove_empty

LOCK_NAME = ".msfnet-busy.lock"

# Folders this process holds, so a nested holder (a command, then the library call it makes)
# does not lock itself out.
_held: dict[Path, int] = {}


class FolderBusy(InputError):
    """Another process is working in the folder."""


def _holder_pid(fd: int) -> str:
    with contextlib.suppress(OSError, ValueError):
        return f" (pid {int(os.pread(fd, 32, 0).decode().strip())})"
    return ""


def _open_locked(lock: Path, folder: Path, who: str) -> int:
    import fcntl

    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            pid = _holder_pid(fd)
            os.close(fd)
            raise FolderBusy(
                f"another {who} is working in this folder{pid}; wait for it to finish or "
                "use another folder",
                folder,
            ) from None
        except BaseException:
            os.close(fd)
            raise
        # The previous holder may have removed the file between our open and our lock: then
        # we hold a lock on a name nobody else sees; take the file that is there now instead.
        try:
            same = os.fstat(fd).st_ino == os.stat(lock, follow_symlinks=False).st_ino
        except FileNotFoundError:
            same = False
        if same:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
            return fd
        os.close(fd)


@contextmanager
def folder_lock(folder: str | Path, who: str) -> Iterator[Path]:
    """Hold ``folder`` (created if missing) for the block; a second process asking for it
    gets :class:`FolderBusy` at once, naming ``who`` (e.g. "msf-capture"). A folder created
    here is removed again if it is still empty at the end. Without fcntl (Windows) nothing is
    locked."""
    folder = Path(folder)
    key = Path(os.path.realpath(folder))
    if key in _held:  # this process holds it already
        _held[key] += 1
        try:
            yield folder
        finally:
            _held[key] -= 1
        return
    try:
        import fcntl  # noqa: F401
    except ImportError:
        yield folder
        return
    created = make_parents(folder / LOCK_NAME)
    lock = folder / LOCK_NAME
    try:
        fd = _open_locked(lock, folder, who)
    except BaseException:
        remove_empty(created)
        raise
    _held[key] = 1
    try:
        yield folder
    finally:
        del _held[key]
        # removed while still held, so nobody can lock the old file after we let go
        with contextlib.suppress(OSError):
            lock.unlink()
        os.close(fd)
        remove_empty(created)


__all__ = ["LOCK_NAME", "FolderBusy", "folder_lock"]
