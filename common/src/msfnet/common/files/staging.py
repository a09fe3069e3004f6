"""Staging names beside an output, and the sweep of staging a killed process left behind.

An output is written as ``.<name>.msf-partial-<pid>@<host>-<random>`` beside its final place
(same file system, so the publishing rename is atomic); the pid lets the next run writing the
same place tell staging of a dead process (``kill -9``) from a live one's and remove only the
former. A pid means something only where it was taken: ``<host>`` names the machine, boot and
pid namespace, and staging of another (a container, another host on a shared file system) is
never touched: its writer may be alive.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import shutil
import socket
import tempfile
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

STAGING_TAG = ".msf-partial-"  # ".<name>.msf-partial-<pid>-<random>" beside the target


def make_parents(path: Path) -> list[Path]:
    """Create the missing folders above ``path``; return them, deepest first, so a failed
    command can remove what it created (an error leaves nothing behind, not even folders)."""
    missing = []
    parent = path.parent
    while not parent.exists():
        missing.append(parent)
        parent = parent.parent
    path.parent.mkdir(parents=True, exist_ok=True)
    return missing


def remove_empty(folders: Iterable[Path]) -> None:
    for folder in folders:
        with contextlib.suppress(OSError):
            folder.rmdir()


def umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _token(*parts: str) -> str:
    return hashlib.sha256("|".join(parts).encode()).hexdigest()[:8]


@functools.cache
def pid_space() -> str:
    """Where this process's pid means something, as ``<space>.<boot>``: a token of the host
    name and pid namespace, then one of the boot (what a Linux system exposes of them; the
    host name elsewhere)."""
    space = [socket.gethostname()]
    with contextlib.suppress(OSError):
        space.append(str(os.stat("/proc/self/ns/pid").st_ino))
    boot = ""
    with contextlib.suppress(OSError):
        boot = Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    return f"{_token(*space)}.{_token(boot)}"


STALE_AFTER_S = 24 * 3600  # staging untouched this long is dead whoever wrote it


def _writer_is_dead(pid_text: str, where: str, entry: Path) -> bool:
    """Staging of this pid space whose writer no longer runs, of this host and namespace from
    an earlier boot (no process of it survives), or anyone's untouched for a day (a writer in
    another container or host cannot be asked; no msfnet output stays in staging that long)."""
    with contextlib.suppress(OSError):
        if time.time() - entry.lstat().st_mtime > STALE_AFTER_S:
            return True
    here_space, _, here_boot = pid_space().partition(".")
    space, _, boot = where.partition(".")
    if where and space != here_space:
        return False  # another machine's or container's: its writer may be running
    if where and boot != here_boot:
        return True  # this machine and namespace, an earlier boot
    return pid_text.isdigit() and not _pid_alive(int(pid_text))


def remove_stale_staging(target: Path) -> None:
    """Remove staging left beside ``target`` by writers that no longer run (kill -9, a power
    cut); staging named without a pid space (older versions) counts as this one's."""
    if target.parent.is_dir():
        _sweep(target.parent, staging_prefix(target))


def remove_stale_staging_in(folder: Path) -> None:
    """:func:`remove_stale_staging` for every target in ``folder``: a command that owns the
    folder (msf-capture's session) sweeps what its killed predecessor was writing, also files
    this run will not write again (a resumed capture left a dead run's session.json staging)."""
    if folder.is_dir():
        _sweep(folder, ".")


def _sweep(parent: Path, prefix: str) -> None:
    for entry in parent.iterdir():
        name = entry.name
        if not name.startswith(prefix) or STAGING_TAG not in name:
            continue
        folder_wide = prefix == "."
        rest = name.partition(STAGING_TAG)[2] if folder_wide else name[len(prefix) :]
        pid_text, at, where = rest.split("-", 1)[0].partition("@")
        if folder_wide and not at:  # an older version's name: its pid is not this host's to ask
            continue
        if _writer_is_dead(pid_text, where, entry):
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


def staging_prefix(target: Path) -> str:
    """What every staging name beside ``target`` starts with; the writer's pid follows."""
    return f".{_short(target.name)}{STAGING_TAG}"


def staging_name(target: Path) -> str:
    return f"{staging_prefix(target)}{os.getpid()}@{pid_space()}-"


def new_staging(target: Path, *, folder: bool) -> Path:
    """A fresh staging folder, or empty file (0600), beside ``target``; a failure (a read-only
    or pseudo file system) names the target the user gave, not the temporary name."""
    try:
        if folder:
            return Path(tempfile.mkdtemp(prefix=staging_name(target), dir=target.parent))
        # the suffix stays (writers such as OpenCV pick the format by it), unless absurd
        suffix = target.suffix if len(os.fsencode(target.suffix)) <= 32 else ""
        fd, name = tempfile.mkstemp(prefix=staging_name(target), suffix=suffix, dir=target.parent)
        os.close(fd)
        return Path(name)
    except OSError as exc:
        # the output itself is not there yet by design: say it cannot be written there
        # ("/proc/x: No such file or directory" read as a missing input)
        raise OSError(
            exc.errno, f"cannot write the output here ({exc.strerror})", str(target)
        ) from exc


@contextmanager
def scratch_folder(target: str | Path) -> Iterator[Path]:
    """A private empty folder beside ``target`` for intermediate files of the command writing
    it (for tools that only work on files, such as onnxruntime's quantiser).

    Always removed on leaving the block, also on errors and signals (with
    :func:`msfnet.common.signals.install_signal_handlers`); named like ``target``'s staging, so
    a folder left by a killed process (``kill -9``) is removed by the next run writing
    ``target``. Beside the target, not in /tmp: same file system and disk space as the output.
    Folders created for it are removed again unless something (the output itself) has been put
    in them meanwhile.
    """
    target = Path(target)
    created = make_parents(target)
    remove_stale_staging(target)
    tmp = new_staging(target, folder=True)
    try:
        yield tmp
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        remove_empty(created)


__all__ = [
    "STAGING_TAG",
    "make_parents",
    "new_staging",
    "remove_empty",
    "remove_stale_staging",
    "scratch_folder",
    "staging_name",
    "staging_prefix",
    "umask",
]
