"""The manifest msfnet puts in every output folder: which files it wrote, and which command.

``--overwrite`` replaces a folder only when its manifest lists everything in it (nothing of the
user's is ever deleted), and a command that names itself only when that command wrote it.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path

from msfnet.common.errors import InputError

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


def manifest_text(names: Sequence[str], writer: str) -> str:
    return json.dumps({"files": list(names), "command": writer}) + "\n"


def read_manifest(folder: Path) -> tuple[list[str], str | None] | None:
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
    manifest = read_manifest(folder)
    listed = set(manifest[0]) if manifest else set()
    return sorted(p.name for p in folder.iterdir() if p.name != MANIFEST and p.name not in listed)


def refuse_foreign(folder: Path, command: str | None = None) -> None:
    """--overwrite replaces a folder only if msfnet wrote everything in it, and with
    ``command`` only if that command did (folders from before the manifest named its writer
    stay replaceable)."""
    manifest = read_manifest(folder)
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


__all__ = [
    "API_WRITER",
    "MANIFEST",
    "current_writer",
    "foreign_files",
    "manifest_text",
    "read_manifest",
    "refuse_foreign",
    "writing_as",
]
