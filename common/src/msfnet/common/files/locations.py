"""Where an output may go: never over, into or around an input, and never over anything but a
regular file or a folder (which msfnet then only replaces if it wrote it, see ``manifest``).

:func:`check_replaceable` is the one test of what lies at an output's name; every writer runs
it before any work (through :func:`check_output`) and again at the commit, under the folder's
lock, because something else may have been put there meanwhile.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Iterable
from pathlib import Path

from msfnet.common.errors import InputError
from msfnet.common.files.manifest import current_writer, refuse_foreign
from msfnet.common.vocabulary import opt


def resolved(path: str | Path) -> Path:
    return Path(os.path.realpath(path))


def _is_within(inner: Path, outer: Path) -> bool:
    return inner == outer or outer in inner.parents


def same_file(a: str | Path, b: str | Path) -> bool:
    """Two names of one file (a hard link, a symlink): replacing one would still be writing
    "over" the other, as a user sees it. False when either does not exist (yet)."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def _kind(mode: int) -> str:
    for test, name in (
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISFIFO, "a named pipe (FIFO)"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return name
    return "a special file"


def check_replaceable(target: str | Path, *, folder: bool = False) -> None:
    """Refuse, with or without --overwrite, anything at ``target`` an output may not replace:
    a symbolic link (renaming over it would break the user's link, and one to a device or to
    /proc/self/fd/1 is no file at all), a device node, a FIFO or a socket; for a file output
    also a folder, and for a folder output also a file. Nothing there: fine.

    Whether an existing regular file or folder may go is the caller's rule (--overwrite, the
    folder's manifest)."""
    target = Path(target)
    try:
        mode = os.lstat(target).st_mode
    except OSError:  # nothing there, or e.g. a parent that is a file: the caller names that
        return
    if stat.S_ISLNK(mode):
        try:
            where = f" to {os.readlink(target)}"
        except OSError:
            where = ""
        raise InputError(
            f"output is a symbolic link{where}; msfnet never replaces a link, only regular "
            "files and its own folders: remove the link or choose another path",
            target,
        )
    if stat.S_ISDIR(mode):
        if not folder:
            raise InputError("output path is a folder", target)
        return
    if stat.S_ISREG(mode):
        if folder:
            raise InputError("output path exists and is not a folder", target)
        return
    raise InputError(
        f"output is {_kind(mode)}, not a regular file; msfnet never replaces it, not even "
        f"with {opt('overwrite')}: choose another path",
        target,
    )


def _file_ids(folder: Path) -> set[tuple[int, int]]:
    """(device, inode) of every regular file under ``folder``, links not followed."""
    ids = set()
    for where, _dirs, names in os.walk(folder):
        for name in names:
            try:
                st = os.lstat(os.path.join(where, name))
            except OSError:
                continue
            if stat.S_ISREG(st.st_mode):
                ids.add((st.st_dev, st.st_ino))
    return ids


def _file_id(path: Path, *, hard_linked: bool = False) -> tuple[int, int] | None:
    """(device, inode) of the regular file ``path`` names, through links (``hard_linked``:
    only if the file has other names too); None otherwise."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    if not stat.S_ISREG(st.st_mode) or (hard_linked and st.st_nlink < 2):
        return None
    return (st.st_dev, st.st_ino)


def check_not_input(
    target: str | Path,
    inputs: Iterable[str | Path | None] = (),
    *,
    folder: bool = False,
    holding: bool = True,
) -> Path:
    """Refuse an output that is, contains or lies inside an input (symlinks resolved), or an
    existing output folder holding a file that an input is another name of (a hard link).
    ``holding=False`` leaves that last part (a walk of the folder) to the caller
    (:func:`check_not_holding`, which also takes the files stacks read through links).
    Returns the resolved target."""
    target = Path(target)
    real = resolved(target)
    given = [Path(item) for item in inputs if item is not None]
    for item in given:
        src = resolved(item)
        clash = real == src or same_file(real, src) or _is_within(src, real)
        if clash and not os.path.lexists(item):
            # a missing input "inside" the output is a missing input, not an output problem
            raise InputError("not found", item)
        if real == src or same_file(real, src):
            raise InputError(
                f"the output would replace an input ({item}); choose another output path", target
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
    if holding:
        check_not_holding(target, given, folder=folder)
    return real


def check_not_holding(
    target: str | Path,
    inputs: Iterable[str | Path | None] = (),
    reads: Iterable[Path] = (),
    *,
    folder: bool = False,
) -> None:
    """Refuse an existing output folder holding a file that an input is another name of (a
    hard link), or that one of ``reads`` reaches: the files stack folders read from elsewhere
    through links (``stack.linked_reads``; compared as files, one stat each, so a batch of
    many linked stacks is checked in a moment). Walks the folder: :func:`check_output` runs
    it only once the folder is one it would replace."""
    target = Path(target)
    real = resolved(target)
    if not os.path.isdir(real):  # only an existing output folder can hold one
        return
    given = [Path(item) for item in inputs if item is not None]
    linked = {i: item for item in given if (i := _file_id(item, hard_linked=True)) is not None}
    reached = {i: item for item in reads if (i := _file_id(item)) is not None}
    if linked or reached:
        held = _file_ids(real)
        both = next((linked[i] for i in held if i in linked), None)
        if both is not None:
            raise InputError(
                f"the output {'folder ' if folder else ''}holds another name (a hard link) of "
                f"the input {both}; choose another output path",
                target,
            )
        via = next((reached[i] for i in held if i in reached), None)
        if via is not None:
            raise InputError(
                f"the output {'folder ' if folder else ''}contains the input {via} (reached "
                "through a link); choose another output path",
                target,
            )


def check_output(
    target: str | Path,
    inputs: Iterable[str | Path | None] = (),
    *,
    overwrite: bool = False,
    folder: bool = False,
    command: str | None = None,
    reads: Iterable[Path] = (),
) -> Path:
    """Refuse, before any work, an output that would clash with an input or with existing data.
    ``reads``: as for :func:`check_not_holding`.

    ``folder``: the output is a folder of files (replaced only if msfnet wrote all of it, and
    only by the command that wrote it: ``command``, else the one of ``writing_as``; see
    :func:`refuse_foreign`).
    Returns the target as given. Raises InputError naming the path.
    """
    target = Path(target)
    inputs = list(inputs)
    real = check_not_input(target, inputs, folder=folder, holding=False)
    # a link on the way that leads nowhere (dangling, or a loop) would be "File exists" later
    for above in target.parents:
        if os.path.lexists(above) and not os.path.exists(above):
            raise InputError(
                f"cannot create the output: {above} is a link that leads nowhere (dangling, "
                "or a loop of links)",
                target,
            )
    # the nearest existing ancestor must be a writable folder
    parent = real.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise InputError(f"cannot create the output: {parent} is a file, not a folder", target)
    check_replaceable(target, folder=folder)
    if target.exists():
        if folder:
            if any(target.iterdir()):
                if not overwrite:
                    raise InputError(
                        "output folder exists and is not empty; pass "
                        f"{opt('overwrite')} to replace it",
                        target,
                    )
                refuse_foreign(target, current_writer(command))
                # a folder it will replace: does it hold a file an input is (walked only now)
                check_not_holding(target, inputs, reads, folder=folder)
        elif not overwrite:
            raise InputError(f"output exists; pass {opt('overwrite')} to replace it", target)
        # replacing means renaming in the parent folder (and, for a folder, reading it)
        if not os.access(real.parent, os.W_OK):
            raise InputError(f"cannot replace the output: {real.parent} is not writable", target)
    elif not os.access(parent, os.W_OK):
        raise InputError(f"cannot write here: {parent} is not writable", target)
    return target


def numbered_folder(base: str | Path) -> Path:
    """``base``, or ``base-2``, ``base-3``, ...: the first that does not exist yet (re-running a
    command never needs --overwrite and never touches earlier results)."""
    base = Path(base)
    # lexists: a dangling link is taken too (an output is never written over a link)
    if not os.path.lexists(base):
        return base
    i = 2
    while os.path.lexists(base.with_name(f"{base.name}-{i}")):
        i += 1
    return base.with_name(f"{base.name}-{i}")


__all__ = [
    "check_not_holding",
    "check_not_input",
    "check_output",
    "check_replaceable",
    "numbered_folder",
    "resolved",
    "same_file",
]
