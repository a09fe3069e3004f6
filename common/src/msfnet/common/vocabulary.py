"""One vocabulary for settings: each user-set option is declared once, on the options type that
holds it, with :func:`flag`; a message names it with :func:`opt`, which writes it the way its
reader sets it: ``--max-memory 512`` under a command, ``max_memory_mb=512`` from Python.

The library's messages therefore never spell a command-line flag themselves, and the Python
API needs no translation of them (tests/test_vocabulary_contract.py holds that rule).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import PurePath
from typing import Any, TypeVar


@dataclasses.dataclass(frozen=True)
class Flag:
    """How one field of an options dataclass appears on a command line. The flag's value is
    stored under the field's name, so ``options_from_args`` can build the options back.

    ``name``: the flag (default ``--field-name``); ``action="store_true"`` for booleans,
    ``"store_false"`` for a ``--no-...`` switch of a field that defaults to True; ``type``
    converts and validates the text (an ``argparse.ArgumentTypeError`` becomes the usual
    one-line error). ``category``: which group of a command's options it belongs to (a
    command that takes another's options asks the category, not a list of names)."""

    help: str
    name: str | None = None
    aliases: tuple[str, ...] = ()
    type: Callable[[str], Any] | None = None
    choices: tuple[str, ...] | None = None
    metavar: str | tuple[str, ...] | None = None
    action: str | None = None
    nargs: int | str | None = None
    const: Any = None  # the value of a bare flag whose value is optional (nargs="?")
    required: bool = False  # a field without a default that the command line must give
    category: str = ""

    def flag_name(self, field_name: str) -> str:
        return self.name or "--" + field_name.replace("_", "-")


def flag(default: Any, help: str, **spec: Any) -> Any:
    """A dataclass field with its command-line spelling (see :class:`Flag`)."""
    return dataclasses.field(default=default, metadata={"flag": Flag(help, **spec)})


@dataclasses.dataclass(frozen=True)
class Word:
    """How one setting is spelled on each front end."""

    flag: str  # "--max-memory", "--no-detail-fusion"
    keyword: str  # "max_memory_mb"
    action: str | None = None  # "store_true" / "store_false": a switch, no value


_WORDS: dict[str, Word] = {}
T = TypeVar("T")


def declare(keyword: str, flag_name: str, action: str | None = None) -> None:
    """Name a setting that no options type holds (``overwrite`` of a save, ``repeat`` of a
    timing). A keyword has one spelling everywhere: a second, different one is a bug."""
    word = Word(flag_name, keyword, action)
    if _WORDS.setdefault(keyword, word) != word:
        raise TypeError(f"{keyword!r} is spelled {_WORDS[keyword].flag} and {flag_name}")


def options_type(cls: type[T]) -> type[T]:
    """Class decorator for an options dataclass: its flagged fields join the vocabulary."""
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        spec = f.metadata.get("flag")
        if spec is not None:
            declare(f.name, spec.flag_name(f.name), spec.action)
    return cls


# a setting of every command that writes outputs, held by no options type
declare("overwrite", "--overwrite", "store_true")


def word(keyword: str) -> Word:
    """The setting ``keyword`` (a field's name). One declared nowhere is spelled by the rule
    (``--max-lights``); tests/test_vocabulary_contract.py checks that every name a message
    uses is declared, and declared where the message's module sees it."""
    return _WORDS.get(keyword) or Word("--" + keyword.replace("_", "-"), keyword)


# The command speaking (msf-run, ...), None from Python. Process-wide, not per context: a
# command's decode threads and worker pools speak as the command too.
_front: str | None = None


@contextmanager
def speaking_as(command: str) -> Iterator[None]:
    """Messages made inside the block name settings as ``command``'s flags."""
    global _front
    previous, _front = _front, command
    try:
        yield
    finally:
        _front = previous


_NOTHING: Any = object()


class verbatim(str):  # lower case: used as a function, opt("depth", verbatim(f"{d:.2g}"))
    """A value written as it is on both front ends (a number formatted by the message)."""

    def __repr__(self) -> str:
        return str(self)


def opt(keyword: str, value: Any = _NOTHING, *, quote: bool = False) -> str:
    """The setting ``keyword`` (with ``value``) as its reader writes it: ``--select 21-96`` or
    ``select='21-96'``. A switch is itself (``--overwrite`` / ``overwrite=True``); ``quote``
    writes a text value quoted on the command line too (``--select '1,,3'``)."""
    w = word(keyword)
    if isinstance(value, float):  # 512.0 MB reads as 512 on both fronts
        value = verbatim(f"{value:g}")
    if _front is not None:
        if value is _NOTHING or w.action is not None:
            return w.flag
        return f"{w.flag} {value!r}" if quote else f"{w.flag} {value}"
    if w.action is not None and value is _NOTHING:
        return f"{keyword}={w.action == 'store_true'}"
    if value is _NOTHING:
        return keyword
    return f"{keyword}={str(value)!r}" if isinstance(value, PurePath) else f"{keyword}={value!r}"


__all__ = [
    "Flag",
    "Word",
    "declare",
    "flag",
    "opt",
    "options_type",
    "speaking_as",
    "verbatim",
    "word",
]
