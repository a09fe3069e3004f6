"""What ``Model.stream`` returns: its Results one at a time, and what it did not run.

A prefetching stream has always taken the next item from its source (with a capture loop, a
part already photographed): stopping hands it back (:meth:`Stream.stop`) instead of dropping it.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Generator, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Generic, TypeVar

from msfnet.common.errors import InputError
from msfnet.runtime.sources import BatchItem, Leftovers, StackSource
from msfnet.runtime.stack import Stack

# the API's Result (this module sits below the API: it knows it only as what it yields)
R = TypeVar("R")


@dataclass(frozen=True)
class Skipped:
    """A stack a stream with ``on_error="skip"`` could not read, and why."""

    source: Path | Stack
    error: InputError


def given_source(item: StackSource) -> Path | Stack:
    return item.path if isinstance(item, BatchItem) else item


class Stream(Iterator[R], Generic[R]):
    """An iterator of results (:class:`~msfnet.runtime.api.Result`), one per stack of the
    source.

    ``stop()`` ends it and returns the stacks it took from the source and did not run (at
    most two: one being decoded ahead, and one whose run was interrupted); ``skipped`` lists
    the stacks refused with ``on_error="skip"``. Also a context manager (``with
    model.stream(src) as s:``) that stops it on leaving. Stop it from the thread that
    iterates it (a generator cannot be closed while it runs in another thread): a Stop button
    sets a flag that the loop body or the capture loop checks.
    """

    def __init__(
        self,
        run: Callable[[Leftovers, list[Skipped]], Generator[R, None, None]],
        *,
        warn_unprocessed: bool,
    ) -> None:
        self._taken = Leftovers()
        self.skipped: list[Skipped] = []
        self._results = run(self._taken, self.skipped)
        self._warn = warn_unprocessed  # a generator source: the caller cannot re-read it

    def __iter__(self) -> Stream[R]:
        return self

    def __next__(self) -> R:
        return next(self._results)

    @property
    def unprocessed(self) -> list[Path | Stack]:
        """The stacks taken from the source and not run (filled when the stream stops; a
        pull still waiting on a capture loop adds its item when that arrives)."""
        return [given_source(item) for item in self._taken.items]

    @property
    def pending(self) -> bool:
        """A pull was still inside the source's ``next()`` when the stream stopped (a capture
        loop waiting for its trigger): what it takes will be added to :attr:`unprocessed`."""
        done = self._taken.pending
        return done is not None and not done.is_set()

    def close(self) -> None:
        """End the stream now (:attr:`unprocessed` then says what it had taken)."""
        self._warn = False  # the caller manages the stream: no warning from the finaliser
        self._results.close()

    def stop(self, timeout: float = 1.0) -> list[Path | Stack]:
        """End the stream now and return :attr:`unprocessed`, after giving a source still
        producing its next item (a generator computing it) up to ``timeout`` seconds; a
        capture loop waiting for a trigger is not waited for longer."""
        self.close()
        self._taken.settle(timeout)
        return self.unprocessed

    def __enter__(self) -> Stream[R]:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        # a `break` out of `for r in model.stream(camera())` lands here, the stream unclosed
        try:
            self._results.close()
        except Exception:  # never raise from a finaliser
            return
        if not self._warn:
            return
        # a pull still inside the capture loop warns for its part when it comes
        taken = self._taken.watch(lambda item: _warn_unprocessed([given_source(item).name]))
        if taken:
            _warn_unprocessed([given_source(i).name for i in taken])


def _warn_unprocessed(names: list[str]) -> None:
    warnings.warn(
        f"model.stream stopped with {len(names)} stack(s) taken from the source and not run "
        f"({', '.join(names)}); keep the stream and call its stop() to get them back, or "
        "use prefetch=False",
        RuntimeWarning,
        stacklevel=3,
    )


__all__ = ["Skipped", "Stream"]
