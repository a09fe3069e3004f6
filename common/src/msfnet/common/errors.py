"""msfnet's two kinds of failure.

:class:`InputError`: a problem with what the user gave (a file, an option, the data in a stack).
Every command prints it as one line ``<command>: error: <file>: <problem>`` and exits with 2, so
its message must name the offending file or option and say what is wrong.
:class:`MsfError`: msfnet could not do its job with what it was given (an engine failed on the
model or tile, a verification did not pass); printed as one line too, exit 2 like every failure
the user can act on. Only internal errors (bugs) take a command's failure code: 1, or 3 for
msf-inspect, whose 1 is a verdict.
"""

from __future__ import annotations

from pathlib import Path


class MsfError(Exception):
    """msfnet could not complete an operation for a reason that is not the user's input."""


class InputError(Exception):
    """A user-facing problem with an input file or argument."""

    def __init__(
        self, message: str, path: str | Path | None = None, *, option: str | None = None
    ) -> None:
        self.path = None if path is None else Path(path)
        self.message = message
        # the setting refused (its keyword, as ModelOptions / LoadOptions / ... name it), for a
        # caller that reacts to it: e.g. "max_memory_mb" -> retry with a smaller stack
        self.option = option
        super().__init__(f"{path}: {message}" if path is not None else message)


def first_line(exc: BaseException, limit: int = 200) -> str:
    """The first line of an exception's text (libraries raise multi-line messages), or its
    type name when it has none."""
    text = str(exc).strip()
    return text.splitlines()[0][:limit] if text else type(exc).__name__


MAX_LINE = 2000  # characters: a message quoting a 3 MB token from a file stays readable


def one_line(text: str) -> str:
    """Messages are printed as one line: newlines (from a library's text, or a file name with a
    newline in it) become spaces, and a line longer than MAX_LINE is cut in its middle."""
    line = " ".join(str(text).split("\n")).replace("\r", " ")
    if len(line) > MAX_LINE:
        half = MAX_LINE // 2
        line = f"{line[:half]} [... {len(line) - MAX_LINE} characters ...] {line[-half:]}"
    return line
