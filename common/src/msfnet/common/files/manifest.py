"""The manifest msfnet puts in every output folder: which files it wrote, and which command.

``--overwrite`` replaces a folder only when its manifest lists everything in it (nothing of the
user's is ever deleted), and a command that names itself only when that command wrote it.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path

from msfnet.common.errors import InputError
from msfnet.common.vocabulary import opt

MANIFEST = ".msfnet-output.json"

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


def current_writer(command: str | None = None) -> str:
    """``command``, else the one of :func:`writing_as`, else the Python API."""
    return command or _command.get() or API_WRITER


# Writers of the same per-stack result (msf-run saves through Result.save): each may replace
# the other's folder. Every other command replaces only its own.
SAME_OUTPUT = frozenset({"msf-run", API_WRITER})


def manifest_text(names: Sequence[str], writer: str) -> str:
    """``names``: every entry of the folder, sub-folders' contents included, as relative POSIX
    paths (``"tree": true``: a file a user puts inside a sub-folder is then seen as foreign)."""
    return json.dumps({"files": list(names), "command": writer, "tree": True}) + "\n"


def tree_names(folder: Path) -> list[str]:
    """Every entry below ``folder`` (links not followed), as sorted relative POSIX paths."""
    names = []
    for root, dirs, files in os.walk(folder):
        base = Path(root).relative_to(folder)
        names += [(base / n).as_posix() for n in dirs + files]
    return sorted(names)


@dataclass(frozen=True)
class Manifest:
    files: list[str]
    writer: str | None  # absent in folders written before it was recorded
    tree: bool  # lists sub-folders' contents too (older manifests: the top level only)


def read_manifest(folder: Path) -> Manifest | None:
    """An output folder's manifest; None when it is missing or damaged (not JSON, "files"
    not a list of names)."""
    try:
        data = json.loads((folder / MANIFEST).read_text())
    except (OSError, ValueError, RecursionError):  # missing, unreadable, not UTF-8, not JSON
        return None
    if not isinstance(data, dict):
        return None
    files_ = data.get("files")
    if not isinstance(files_, list) or not all(isinstance(f, str) for f in files_):
        return None
    writer = data.get("command")
    return Manifest(files_, writer if isinstance(writer, str) else None, data.get("tree") is True)


def foreign_files(folder: Path) -> list[str]:
    """Entries of an existing output folder that its msfnet manifest does not list (all of
    them when the manifest is missing or damaged), sub-folders included. A manifest of the
    top level only (written before sub-folders were listed) cannot vouch for what is inside
    its sub-folders: they count as foreign."""
    manifest = read_manifest(folder)
    listed = set(manifest.files) if manifest else set()
    if manifest is not None and manifest.tree:
        return [n for n in tree_names(folder) if n != MANIFEST and n not in listed]
    return sorted(
        p.name + ("/" if p.is_dir() and not p.is_symlink() else "")
        for p in folder.iterdir()
        if p.name != MANIFEST
        and (p.name not in listed or (p.is_dir() and not p.is_symlink() and any(p.iterdir())))
    )


def refuse_foreign(folder: Path, command: str | None = None) -> None:
    """--overwrite replaces a folder only if msfnet wrote everything in it, sub-folders
    included, and with ``command`` only if that command (or one writing the same output,
    SAME_OUTPUT) did (folders from before the manifest named its writer stay replaceable)."""
    manifest = read_manifest(folder)
    if manifest is None and (folder / MANIFEST).exists():
        raise InputError(
            f"{opt('overwrite')}: the folder's {MANIFEST} is damaged, so msfnet cannot "
            "tell its own files; refusing to delete anything",
            folder,
            option="overwrite",
        )
    foreign = foreign_files(folder)
    if foreign and manifest is not None and not manifest.tree:
        subs = [f for f in foreign if f.endswith("/") and f[:-1] in manifest.files]
        if subs == foreign:  # only sub-folders msfnet wrote, whose contents it cannot vouch for
            raise InputError(
                f"{opt('overwrite')}: an older msfnet wrote this folder and listed only its top "
                f"level, so what is inside {subs[0]} cannot be told from files of yours; remove "
                "the folder yourself or choose another",
                folder,
                option="overwrite",
            )
    if foreign:
        raise InputError(
            f"{opt('overwrite')}: the folder holds files msfnet did not write (e.g. "
            f"{foreign[0]}); refusing to delete them",
            folder,
            option="overwrite",
        )
    writer = manifest.writer if manifest else None
    if command is None or writer is None or writer == command:
        return
    if writer in SAME_OUTPUT and command in SAME_OUTPUT:
        return
    raise InputError(
        f"{opt('overwrite')}: the folder is {writer}'s output, not {command}'s; "
        "refusing to replace it (choose another folder)",
        folder,
        option="overwrite",
    )


__all__ = [
    "API_WRITER",
    "MANIFEST",
    "SAME_OUTPUT",
    "Manifest",
    "current_writer",
    "foreign_files",
    "manifest_text",
    "read_manifest",
    "refuse_foreign",
    "tree_names",
    "writing_as",
]
