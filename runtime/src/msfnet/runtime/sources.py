"""Where stacks come from, and reading the next one while the current one runs.

Shared by the Python API (``Model.stream``) and the batch runner (``msf-run A B C``):

- :func:`expand_stacks`: what a path on the command line (or given to ``stream``) stands for: a
  stack folder or .npz, or a folder of stacks (sub-folders, an ``objects.txt``, or sub-folders
  that share one light file at the top, as psmImages does).
- :func:`decode_ahead`: decoded stacks one at a time, the next one decoded in a background
  thread while the caller works on the current one. A single stack cannot overlap its own
  decoding with inference (the normalisation needs every image of a pixel first), but in a
  sequence of stacks the next one's images can be decoded beside the current inference.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Protocol

from msfnet.common.errors import InputError
from msfnet.runtime.evaluate.datasets import (
    find_objects,
    folder_name,
    has_images,
    lights_file,
    protocol_note,
    protocol_select,
    shared_lights_root,
)
from msfnet.runtime.results.profile import BatchStats, Profile
from msfnet.runtime.stack import LoadOptions, Stack, load_stack, selection
from msfnet.runtime.stack.load import count_images


@dataclass(frozen=True)
class BatchItem:
    """One stack of a batch: its path and its own image selection, from an objects.txt or
    from a benchmark's protocol (DiLiGenT bear: 21-96), which --select overrides (as in
    msf-eval); ``lights``: the light file shared by a folder of stacks (psmImages'
    ``lights.txt`` at the top), which --lights overrides."""

    path: Path
    select: str | None = None
    origin: str = "objects.txt"  # where ``select`` comes from: "objects.txt" or "protocol"
    lights: Path | None = None

    @property
    def name(self) -> str:
        if self.path.suffix.lower() == ".npz":
            return self.path.stem
        return folder_name(self.path)  # "." is the folder's own name

    def options(self, load: LoadOptions) -> LoadOptions:
        """``load`` with this stack's own selection and shared light file, unless the user's
        options already give them."""
        changes: dict[str, object] = {}
        if self.select is not None and load.select is None:
            changes["select"] = self.select
        if self.lights is not None and load.lights is None:
            changes["lights"] = self.lights
        return replace(load, **changes) if changes else load  # type: ignore[arg-type]

    def note(self, load: LoadOptions) -> str | None:
        """The line to print when the benchmark's selection applies (it changes the result,
        so it is never silent)."""
        if self.origin != "protocol" or self.select is None or load.select is not None:
            return None
        return protocol_note(self.path, self.select)

    def describe_input(self, load: LoadOptions) -> dict[str, object]:
        """profile.json's "input": the options in effect and where the selection and the
        light file came from."""
        info = self.options(load).describe()
        if load.select is not None:
            info["select_from"] = "--select"  # a recorded value (docs/run.md), not a message
        elif self.select is not None:
            info["select_from"] = (
                "benchmark protocol" if self.origin == "protocol" else "objects.txt"
            )
        if self.lights is not None and load.lights is None:
            info["lights"] = str(self.lights)
            info["lights_from"] = "the folder of stacks (shared light file)"
        return info


def _is_stack_folder(folder: Path) -> bool:
    return lights_file(folder) is not None or has_images(folder)


def _protocol_item(folder: Path, lights: Path | None = None) -> BatchItem:
    """A stack folder, with its benchmark's selection when its name is a known object's (as
    msf-eval does, however the folder is named on the command line) and the selection fits
    its images: a folder of ours that happens to be called bearPNG but holds 24 images is not
    DiLiGenT's bear, and runs whole."""
    select = protocol_select(folder)
    if select is not None:
        try:
            selection(count_images(folder), select, None)
        except InputError:
            select = None
    return BatchItem(folder, select, "protocol", lights)


def path_item(path: Path) -> BatchItem:
    """One stack given by its path (an element of a stream, ``model(path)``,
    ``msfnet.load_stack(path)``): a folder with its benchmark's selection, as msf-run reads it
    (DiLiGenT bear: 21-96), anything else as it is (an .npz, or a path the loader reports)."""
    return _protocol_item(path) if path.is_dir() else BatchItem(path)


def _shared_lights_items(folder: Path) -> list[BatchItem] | None:
    """A folder with a light file but no images of its own, whose sub-folders hold images
    (psmImages: ``lights.txt`` at the top, one folder of TGA images per object): a folder of
    stacks sharing that file. A sub-folder with a light file of its own keeps it. None when
    ``folder`` is not such a root."""
    shared = shared_lights_root(folder)
    if shared is None:
        return None
    lights, subs = shared
    resolved = lights.resolve()  # Ray workers do not share the driver's working directory
    return [_protocol_item(d, None if lights_file(d) else resolved) for d in subs]


def expand_stacks(paths: Sequence[Path], *, select_given: bool = False) -> list[BatchItem]:
    """The stacks named on the command line: a stack folder or .npz stands for itself; a folder
    with an objects.txt (msf-eval's format, e.g. ``bearPNG 21-96``), whose sub-folders are
    stacks, or whose sub-folders share its light file stands for those. Names must be unique
    (they name the output folders)."""

    items: list[BatchItem] = []
    for path in paths:
        if path.is_dir() and (path / "objects.txt").is_file():
            objects = find_objects(path, select_given=select_given)
            items += [BatchItem(o.folder, o.select) for o in objects]
        elif path.is_dir() and (shared := _shared_lights_items(path)) is not None:
            items += shared
        elif path.is_dir() and not _is_stack_folder(path):
            subs = [d for d in sorted(path.iterdir()) if d.is_dir() and _is_stack_folder(d)]
            if not subs:
                raise InputError(
                    "neither a stack (images + light_directions.txt) nor a folder "
                    "of stacks (sub-folders holding them, or an objects.txt)",
                    path,
                )
            items += [_protocol_item(d) for d in subs]
        elif path.is_dir():
            items.append(_protocol_item(path))
        else:
            items.append(BatchItem(path))  # an .npz, or a path the loader reports
    names = [i.name for i in items]
    dup = next((n for n in names if names.count(n) > 1), None)
    if dup is not None:
        raise InputError(f"two stacks are named {dup!r}; their output folders would clash")
    return items


StackSource = BatchItem | Stack


@dataclass
class Decoded:
    """One stack of a sequence, decoded (or refused: ``error``), with what it cost."""

    index: int
    item: StackSource
    stack: Stack | None
    error: InputError | None
    decode_s: float  # decoding + real-camera transforms
    wait_s: float  # how long the caller waited for it (decoding not hidden)
    prefetched: bool  # decoded while the caller worked on the previous stack
    beside: bool  # the next stack may be decoding while this one runs (memory budget)

    def options(self, load: LoadOptions) -> LoadOptions:
        return self.item.options(load) if isinstance(self.item, BatchItem) else load

    def describe_input(self, load: LoadOptions) -> dict[str, object]:
        if isinstance(self.item, BatchItem):
            return self.item.describe_input(load)
        return load.describe()


def _decode(item: StackSource, load: LoadOptions) -> Stack:
    if isinstance(item, Stack):
        from msfnet.runtime.stack import prepare_stack

        return prepare_stack(item, load)
    return load_stack(item.path, item.options(load))


_END = object()
# the item, its stack or the InputError that refused it, and the seconds it took
Outcome = tuple[object, Stack | None, InputError | None, float]
_END_OUTCOME: Outcome = (_END, None, None, 0.0)


def _timed_decode(item: object, load: LoadOptions) -> Outcome:
    start = time.perf_counter()
    try:
        stack = _decode(item, load)  # type: ignore[arg-type]
    except InputError as exc:
        return item, None, exc, time.perf_counter() - start
    return item, stack, None, time.perf_counter() - start


@dataclass
class Leftovers:
    """What a sequence stopped early had taken from its source and not handed out, in order.
    ``pending``: set once a pull that was still inside the source's ``next()`` at the stop
    is over (its item, if any, then in ``items``)."""

    items: list[StackSource] = field(default_factory=list)
    pending: threading.Event | None = None
    # called with an item a pull took after the stop, when whoever stopped the sequence is
    # gone (Stream's finaliser): the item must not vanish unseen
    late: Callable[[StackSource], None] | None = None

    lock: threading.Lock = field(default_factory=threading.Lock)

    def add(self, item: StackSource, *, late: bool = False) -> None:
        with self.lock:
            self.items.append(item)
            notify = self.late if late else None
        if notify is not None:
            notify(item)

    def watch(self, late: Callable[[StackSource], None]) -> list[StackSource]:
        """The items so far, and ``late`` for any added later by a pull still running
        (atomically: none falls between the two)."""
        with self.lock:
            self.late = late
            return list(self.items)

    def settle(self, timeout: float) -> None:
        """Give a pull still inside the source up to ``timeout`` s to finish."""
        if self.pending is not None and timeout > 0:
            self.pending.wait(timeout)


class _Pull:
    """The source's next item and its decoded stack, fetched in a daemon thread.

    An error of the source itself (a capture loop failing) is re-raised by :meth:`result`; a
    stack that cannot be read comes back as its InputError. ``waiting_on_source``: the thread
    is inside the source's ``next()`` (a capture loop waiting for its trigger), which nothing
    can interrupt: a stopped sequence does not wait for it (a daemon thread, never joined, so
    neither leaving a loop nor ending the interpreter hangs on a camera that never fires).
    An item it takes after the sequence stopped is not decoded but kept in ``leftovers``."""

    def __init__(
        self, source: Iterator[StackSource], load: LoadOptions, leftovers: Leftovers
    ) -> None:
        self._source, self._load, self._leftovers = source, load, leftovers
        self._done = threading.Event()
        self._outcome: Outcome | None = None
        self._raised: BaseException | None = None
        self._item: object | None = None  # taken from the source, not yet handed out
        self._lock = threading.Lock()
        self.waiting_on_source = True
        self.abandoned = False
        self._thread = threading.Thread(target=self._work, name="msf-decode", daemon=True)
        self._thread.start()

    def _work(self) -> None:
        try:
            item = next(self._source, _END)
        except BaseException as exc:  # the source's own failure: re-raised in the caller's
            self._raised = exc
            self.waiting_on_source = False
            self._done.set()
            return
        with self._lock:  # against stop(): the item is handed over exactly once
            self.waiting_on_source = False
            self._item = None if item is _END else item
            if self.abandoned:  # stopped meanwhile: keep what was taken, decode nothing
                if self._item is not None:
                    self._leftovers.add(self._item, late=True)  # type: ignore[arg-type]
                self._item = None
                self._done.set()
                return
        try:
            self._outcome = _END_OUTCOME if item is _END else _timed_decode(item, self._load)
        except BaseException as exc:  # e.g. MemoryError: re-raised, the item kept
            self._raised = exc
        finally:
            self._done.set()

    def result(self) -> Outcome:
        self._done.wait()  # a lock wait: Ctrl-C interrupts it
        if self._raised is not None:
            if self._item is not None:  # taken, not decoded: the caller gets it back
                self._leftovers.add(self._item)  # type: ignore[arg-type]
                self._item = None
            raise self._raised
        assert self._outcome is not None
        self._item = None  # handed out
        return self._outcome

    def stop(self) -> None:
        """The sequence stopped: what this pull took goes to the leftovers. A pull decoding a
        stack is waited for (seconds at most, and its memory is then freed); one waiting on
        the source is left to finish in the background."""
        with self._lock:
            self.abandoned = True
            waiting = self.waiting_on_source
            if waiting:
                self._leftovers.pending = self._done
        if waiting:
            return
        self._done.wait()
        if self._item is not None:
            self._leftovers.add(self._item)  # type: ignore[arg-type]
            self._item = None
        self._outcome = None


def _pull_here(source: Iterator[StackSource], load: LoadOptions, leftovers: Leftovers) -> Outcome:
    item = next(source, _END)
    if item is _END:
        return _END_OUTCOME
    try:
        return _timed_decode(item, load)
    except BaseException:  # Ctrl-C while decoding, MemoryError: the caller gets it back
        leftovers.add(item)  # type: ignore[arg-type]
        raise


def decode_ahead(
    items: Iterable[StackSource],
    load: LoadOptions,
    *,
    prefetch: bool = True,
    total: int | None = None,
    unprocessed: Leftovers | None = None,
) -> Iterator[Decoded]:
    """The decoded stacks of ``items``, in order, one at a time.

    With ``prefetch`` a background thread advances ``items`` and decodes the next stack as
    soon as the current one is handed out, so it decodes while the caller works on the
    current one: at most two stacks are in memory, and ``items`` is never advanced by two
    threads at once (a capture loop may be a generator). Without, everything happens in the
    caller's thread when the next stack is asked for. ``total``: the number of items when
    known (a list), so the last stack is known to have nothing decoding beside it.

    ``unprocessed``: where a sequence stopped early (break, Ctrl-C, an error) puts the item
    it had already taken from ``items`` and not handed out, so that a capture loop's part is
    never lost unseen (a pull still waiting on the source adds its item when it comes).
    """
    source = iter(items)
    leftovers = Leftovers() if unprocessed is None else unprocessed
    upcoming = _Pull(source, load, leftovers) if prefetch else None
    finished = False
    try:
        index = 0
        while True:
            waited = time.perf_counter()
            if upcoming is not None:
                item, stack, error, decode_s = upcoming.result()
            else:
                item, stack, error, decode_s = _pull_here(source, load, leftovers)
            wait_s = time.perf_counter() - waited
            if item is _END:
                finished = True
                return
            more = total is None or index + 1 < total
            upcoming = _Pull(source, load, leftovers) if prefetch and more else None
            yield Decoded(
                index,
                item,  # type: ignore[arg-type]
                stack,
                error,
                decode_s,
                wait_s,
                prefetched=prefetch and index > 0,
                beside=upcoming is not None,
            )
            if prefetch and upcoming is None:
                finished = True
                return  # the known last one
            index += 1
    finally:
        if upcoming is not None and not finished:
            upcoming.stop()


class _Timed(Protocol):
    timings: Profile
    input: dict[str, object] | None
    batch: BatchStats | None


def record_decode(result: _Timed, decoded: Decoded, load: LoadOptions) -> None:
    """What ``model(path, load)`` records itself, for a stack decoded ahead: the decoding in
    the latency profile, the options in effect (auto-mask -> mask.png on save), batch
    timings."""
    runs = result.timings.runs
    if runs:  # the profile shows what the stack cost, decoding included
        runs[-1]["load"] = decoded.decode_s
        runs[-1]["total"] = runs[-1].get("total", 0.0) + decoded.decode_s
    result.input = decoded.describe_input(load)
    result.batch = BatchStats(
        decoded.decode_s, wait_s=decoded.wait_s, prefetched=decoded.prefetched
    )


def stream_items(
    source: object, *, select_given: bool = False
) -> tuple[Iterable[StackSource], int | None]:
    """What ``Model.stream`` accepts, as stack sources and their count (None: unknown): a path
    (a stack, or a folder of stacks as msf-run reads it), a Stack, or any iterable of paths
    and Stacks (a list, a generator, a capture loop)."""
    if isinstance(source, Stack):
        return [source], 1
    if isinstance(source, (str, os.PathLike)):
        found = expand_stacks([Path(source)], select_given=select_given)
        return found, len(found)
    if isinstance(source, (bytes, dict)) or not isinstance(source, Iterable):
        raise InputError(
            f"stream() takes a stack path, a folder of stacks, a Stack, or an iterable of "
            f"paths and Stacks; got {type(source).__name__}"
        )

    def each() -> Iterator[StackSource]:
        for element in source:  # type: ignore[attr-defined]
            if isinstance(element, Stack):
                yield element
            elif isinstance(element, (str, os.PathLike)):
                yield path_item(Path(element))
            else:
                raise InputError(
                    f"stream(): an element of type {type(element).__name__}; expected a "
                    "stack path or a Stack"
                )

    return each(), len(source) if isinstance(source, Sequence) else None


__all__ = [
    "BatchItem",
    "Decoded",
    "Leftovers",
    "StackSource",
    "decode_ahead",
    "expand_stacks",
    "path_item",
    "record_decode",
    "stream_items",
]
