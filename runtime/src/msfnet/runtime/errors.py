"""The one exception type for problems with user input (files, arguments, data).

Every CLI catches :class:`InputError` and prints ``msf-xxx: error: <message>`` on one line with a
non-zero exit, so messages must name the offending file and say what is wrong with it.
"""

from __future__ import annotations

from pathlib import Path


class InputError(Exception):
    """A user-facing problem with an input file or argument."""

    def __init__(self, message: str, path: str | Path | None = None) -> None:
        self.path = None if path is None else Path(path)
        super().__init__(f"{path}: {message}" if path is not None else message)
