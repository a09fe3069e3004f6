"""The station's watch loop: each complete part that appears in a folder judged exactly once.

A part is a sub-folder of the watched folder (hidden names, a staging folder being written,
are not). It is complete when it holds a file named ``READY`` (a capture script that knows
when it is done writes one last), or else when its listing (names, sizes, times) has not
changed between two polls and it reads as a stack. One that stays unreadable and unchanged for
``stale_s`` (a capture that stopped half-way) is recorded as an error and left alone until it
changes (a part whose last record is an error is taken again after a restart).

The output folder holds ``parts.jsonl`` (one JSON line per part taken: its verdict, regions and
per-stage times, or its error) and one folder per judged part (verdict.json, overlay.png),
each written whole. The journal is the state: a part named in it is never taken again, so a
restart neither skips nor repeats a part. A part folder is written before its line; a restart
adds the line of a folder that was written just before a kill, and drops a line cut short by
one. The next complete part is decoded in a background thread while the current one is judged.
The loop stops after the part in hand on SIGTERM or Ctrl-C (a second one stops at once).
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType

import numpy as np

from msfnet.common.cli import flag, positive_float
from msfnet.common.errors import InputError
from msfnet.common.files import folder_lock, json_text, staged_folder, write_text
from msfnet.common.imageio import encode_png
from msfnet.runtime.inspection.station import STAGES, Inspection, Station
from msfnet.runtime.stack import Stack

JOURNAL = "parts.jsonl"
READY = "READY"
STATION_SUMMARY = "station.json"


@dataclass(frozen=True)
class WatchOptions:
    """How the loop watches: ``once``: judge what is complete now and stop; ``poll_s``:
    seconds between looks at the folder; ``stale_s``: how long an unreadable, unchanging part
    is waited for before it is recorded as an error."""

    once: bool = flag(
        False,
        "judge the parts complete now, then stop (exit 0 all pass, 1 a part failed, 2 a "
        "part could not be judged)",
        action="store_true",
    )
    poll_s: float = flag(
        0.2,
        "seconds between looks at the watched folder (default 0.2)",
        name="--poll",
        type=positive_float,
        metavar="S",
    )
    stale_s: float = flag(
        30.0,
        "a part that does not read and has not changed for S seconds is recorded as an "
        "error (default 30)",
        name="--stale",
        type=positive_float,
        metavar="S",
    )


@dataclass(frozen=True)
class PartRecord:
    """One line of the journal."""

    part: str
    verdict: str  # "pass", "fail", "mismatch" (not the reference's part) or "error"
    defects: int = 0
    times_ms: dict[str, float] = field(default_factory=dict)
    regions: tuple[dict[str, object], ...] = ()
    error: str | None = None

    @classmethod
    def of(cls, inspection: Inspection, write_s: float) -> PartRecord:
        v = inspection.verdict.as_dict()
        times = inspection.times.milliseconds() | {"write": round(write_s * 1e3, 2)}
        regions = tuple(dict(r) for r in v["regions"])  # type: ignore[attr-defined]
        return cls(inspection.name, str(v["verdict"]), len(regions), times, regions)

    def line(self) -> str:
        data = {k: v for k, v in self.__dict__.items() if v not in (None, (), {})}
        return json_text(data, indent=None)


@dataclass(frozen=True)
class StageStatistics:
    stage: str
    p50_ms: float
    p99_ms: float
    max_ms: float


@dataclass
class WatchSummary:
    """What a run of the loop did: counts, and each stage's p50 / p99 / max over its parts."""

    passed: int = 0
    failed: int = 0
    mismatched: int = 0
    errors: int = 0
    earlier: int = 0  # parts the journal held when the loop started
    times: dict[str, list[float]] = field(default_factory=dict)
    busy_s: float = 0.0  # wall time spent taking parts (idle polls left out)
    cpu_s: float = 0.0  # process CPU time meanwhile (all threads: decode ahead included)

    def add(self, record: PartRecord) -> None:
        if record.verdict == "error":
            self.errors += 1
            return
        if record.verdict == "pass":
            self.passed += 1
        elif record.verdict == "mismatch":
            self.mismatched += 1
        else:
            self.failed += 1
        for stage, ms in record.times_ms.items():
            self.times.setdefault(stage, []).append(ms)

    @property
    def parts(self) -> int:
        return self.passed + self.failed + self.mismatched + self.errors

    def statistics(self) -> list[StageStatistics]:
        out = []
        for stage in (*STAGES, "write", "total"):
            values = self.times.get(stage)
            if values:
                p50, p99 = (float(v) for v in np.percentile(values, (50, 99)))
                out.append(StageStatistics(stage, round(p50, 2), round(p99, 2), max(values)))
        return out

    @property
    def exit_code(self) -> int:
        """--once's: 2 if a part could not be judged, else 4 if one did not match the
        reference, else 1 if one had defects, else 0."""
        return 2 if self.errors else 4 if self.mismatched else 1 if self.failed else 0

    def as_dict(self) -> dict[str, object]:
        return {
            "parts": self.parts,
            "passed": self.passed,
            "failed": self.failed,
            "mismatched": self.mismatched,
            "errors": self.errors,
            "earlier_parts": self.earlier,
            "busy_wall_s": round(self.busy_s, 3),
            "busy_cpu_s": round(self.cpu_s, 3),
            "stages_ms": [s.__dict__ for s in self.statistics()],
        }

    def lines(self) -> list[str]:
        head = (
            f"judged {self.parts} part(s): {self.passed} pass, {self.failed} fail, "
            f"{self.mismatched} mismatch, {self.errors} error(s)"
        )
        rows = [
            f"  {s.stage:<8} p50 {s.p50_ms:8.1f} ms   p99 {s.p99_ms:8.1f} ms"
            for s in self.statistics()
        ]
        judged = self.passed + self.failed + self.mismatched
        if judged:
            wall, cpu = 1e3 * self.busy_s / judged, 1e3 * self.cpu_s / judged
            rows.append(f"  a part every {wall:.1f} ms wall, {cpu:.1f} ms CPU (decode overlapped)")
        return [head, *rows]


# ---------------------------------------------------------------- the journal


class Journal:
    """``parts.jsonl`` in the output folder: the parts already taken, and where new lines go."""

    def __init__(self, output: Path) -> None:
        self.path = output / JOURNAL
        self.done: set[str] = set()
        if self.path.is_file():
            self._read()
        else:  # the folder is a station's from its first moment (a restart resumes it)
            self.path.touch()
        self._adopt_written(output)

    def _read(self) -> None:
        text = self.path.read_text(encoding="utf-8")
        whole, _, torn = text.rpartition("\n")
        if torn:  # the last line was cut by a kill: its part is taken again
            with open(self.path, "r+", encoding="utf-8") as f:
                f.truncate(len((whole + "\n").encode()) if whole else 0)
        last: dict[str, str] = {}
        for n, line in enumerate(whole.splitlines(), 1):
            try:
                record = json.loads(line)
                last[str(record["part"])] = str(record["verdict"])
            except (ValueError, KeyError, TypeError):
                raise InputError(f"line {n} is not a station record", self.path) from None
        # a part whose last line is an error is taken again (it may have been completed since)
        self.done.update(part for part, verdict in last.items() if verdict != "error")

    def _adopt_written(self, output: Path) -> None:
        """A part folder written just before a kill, whose line was not: the line, from its
        verdict.json (so the part is not judged twice)."""
        for entry in sorted(output.iterdir()):
            verdict = entry / "verdict.json"
            if entry.name in self.done or entry.name.startswith(".") or not verdict.is_file():
                continue
            try:
                v = json.loads(verdict.read_text(encoding="utf-8"))
            except (OSError, ValueError) as exc:
                raise InputError(f"unreadable ({exc}): remove the folder", verdict) from None
            regions = tuple(v.get("regions") or ())
            self.add(PartRecord(entry.name, str(v.get("verdict")), len(regions), regions=regions))

    def add(self, record: PartRecord) -> None:
        with open(self.path, "a", encoding="utf-8") as f:
            f.write(record.line())
            f.flush()
            os.fsync(f.fileno())
        if record.verdict != "error":
            self.done.add(record.part)


# ---------------------------------------------------------------- finding complete parts


def _listing(folder: Path) -> tuple[tuple[str, int, int], ...]:
    with os.scandir(folder) as it:
        return tuple(sorted((e.name, *_size_time(e)) for e in it))


def _size_time(entry: os.DirEntry[str]) -> tuple[int, int]:
    try:
        st = entry.stat()
    except OSError:  # removed between the listing and the look
        return (-1, -1)
    return (st.st_size, st.st_mtime_ns)


@dataclass
class _Seen:
    listing: tuple[tuple[str, int, int], ...]
    since: float  # when the listing last changed
    failed: str | None = None  # why it did not read, at this listing
    recorded: bool = False  # its error is in the journal: not again until it changes


class PartFinder:
    """The complete parts in the watched folder, in name order, each offered until taken."""

    def __init__(
        self, folder: Path, options: WatchOptions, done: set[str], skip: tuple[Path, ...]
    ) -> None:
        self.folder = folder
        self.options = options
        self.done = done
        self.seen: dict[str, _Seen] = {}
        self._skip = {os.path.realpath(p) for p in skip}

    def candidates(self) -> list[Path]:
        try:
            entries = sorted(os.scandir(self.folder), key=lambda e: e.name)
        except FileNotFoundError:
            raise InputError("the watched folder is gone", self.folder) from None
        out = []
        for e in entries:
            if e.name.startswith(".") or e.name in self.done or not e.is_dir():
                continue
            if os.path.realpath(e.path) in self._skip:
                continue
            out.append(Path(e.path))
        return out

    def ready(self, now: float) -> list[Path]:
        """The parts to take now (and forget the state of parts no longer there)."""
        found = self.candidates()
        names = {p.name for p in found}
        for gone in set(self.seen) - names:
            del self.seen[gone]
        out = []
        for path in found:
            try:
                listing = _listing(path)
            except OSError:
                continue
            seen = self.seen.get(path.name)
            if seen is None or seen.listing != listing:
                self.seen[path.name] = seen = _Seen(listing, now)
                if not (self.options.once or any(n == READY for n, *_ in listing)):
                    continue  # changed since the last look: it may still be being written
            if seen.failed is None:
                out.append(path)
        return out

    def failed(self, path: Path, why: InputError, now: float) -> bool:
        """A part that did not read: True when it is given up (an error to record, once per
        state of its folder), False while it may still be completing. Either way it is not
        offered again until its folder changes."""
        seen = self.seen.setdefault(path.name, _Seen((), now))
        seen.failed = str(why)
        marked = any(n == READY for n, *_ in seen.listing)
        if self.options.once or marked or now - seen.since >= self.options.stale_s:
            seen.recorded = True
        return seen.recorded

    def stale(self, now: float) -> list[tuple[Path, str]]:
        """Parts that failed to read and have not changed for ``stale_s`` (each returned once
        per state of its folder)."""
        out = []
        for name, seen in self.seen.items():
            waited = now - seen.since >= self.options.stale_s
            if seen.failed is not None and not seen.recorded and waited:
                seen.recorded = True
                out.append((self.folder / name, seen.failed))
        return out


# ---------------------------------------------------------------- the loop


class _Stop:
    """SIGTERM / Ctrl-C: the first one stops the loop after the part in hand, a second one at
    once (as the command's own handlers would)."""

    def __init__(self) -> None:
        self.event = threading.Event()

    @contextlib.contextmanager
    def on_signals(self) -> Iterator[None]:
        if threading.current_thread() is not threading.main_thread():
            yield
            return
        names = ("SIGINT", "SIGTERM", "SIGHUP")
        sigs = [getattr(signal, n) for n in names if hasattr(signal, n)]
        previous = {s: signal.getsignal(s) for s in sigs}

        def handler(signum: int, frame: FrameType | None) -> None:
            if self.event.is_set():
                old = previous[signum]
                if callable(old):
                    old(signum, frame)
                raise KeyboardInterrupt
            self.event.set()

        for s in sigs:
            if previous[s] is not signal.SIG_IGN:
                signal.signal(s, handler)
        try:
            yield
        finally:
            for s, old in previous.items():
                with contextlib.suppress(ValueError, TypeError):
                    signal.signal(s, old)  # type: ignore[arg-type]


Decoded = tuple[Stack, float]


def _write_part(output: Path, inspection: Inspection) -> float:
    start = time.perf_counter()
    with staged_folder(output / inspection.name) as tmp:
        (tmp / "verdict.json").write_text(inspection.verdict.json_text(), encoding="utf-8")
        (tmp / "regions.csv").write_text(inspection.verdict.csv_text(), encoding="utf-8")
        encode_png(tmp / "overlay.png", inspection.overlay())
    return time.perf_counter() - start


def watch(
    station: Station,
    folder: Path,
    output: Path,
    options: WatchOptions | None = None,
    *,
    skip: tuple[Path, ...] = (),
    report: Callable[[PartRecord], None] = lambda record: None,
) -> WatchSummary:
    """Judge each complete part that appears in ``folder`` into ``output`` until stopped (or,
    with ``options.once``, until the parts complete now are judged). ``skip``: folders inside
    ``folder`` that are not parts (a reference); ``report`` is called with each part's record
    as it is written."""
    options = options or WatchOptions()
    with folder_lock(output, "msf-inspect --watch"):  # one station per folder
        return _watch(station, folder, output, options, skip, report)


def _watch(
    station: Station,
    folder: Path,
    output: Path,
    options: WatchOptions,
    skip: tuple[Path, ...],
    report: Callable[[PartRecord], None],
) -> WatchSummary:
    journal = Journal(output)
    summary = WatchSummary(earlier=len(journal.done))
    finder = PartFinder(folder, options, journal.done, (*skip, output))
    stop = _Stop()

    def record(rec: PartRecord) -> None:
        journal.add(rec)
        summary.add(rec)
        report(rec)

    with stop.on_signals(), ThreadPoolExecutor(1, thread_name_prefix="decode") as pool:
        while not stop.event.is_set():
            now = time.monotonic()
            parts = finder.ready(now)
            for path, why in finder.stale(now):
                record(PartRecord(path.name, "error", error=why))
            wall, cpu = time.perf_counter(), time.process_time()
            _judge_all(station, parts, pool, finder, record, stop.event, output)
            if parts:
                summary.busy_s += time.perf_counter() - wall
                summary.cpu_s += time.process_time() - cpu
            if options.once:
                break
            stop.event.wait(options.poll_s)
    _write_summary(output, summary)
    return summary


def _judge_all(
    station: Station,
    parts: list[Path],
    pool: ThreadPoolExecutor,
    finder: PartFinder,
    record: Callable[[PartRecord], None],
    stop: threading.Event,
    output: Path,
) -> None:
    """Judge ``parts`` in order, decoding each next one while the current one is judged."""
    ahead: Future[Decoded] | None = None
    for i, path in enumerate(parts):
        if stop.is_set():
            break
        decoding = ahead or pool.submit(station.read, path)
        ahead = pool.submit(station.read, parts[i + 1]) if i + 1 < len(parts) else None
        try:
            stack, decode_s = decoding.result()
            inspection = station.judge(stack, path.name, decode_s)
            write_s = _write_part(output, inspection)
        except InputError as exc:
            if finder.failed(path, exc, time.monotonic()):
                record(PartRecord(path.name, "error", error=str(exc)))
            continue
        record(PartRecord.of(inspection, write_s))
    if ahead is not None:
        ahead.cancel()


def _write_summary(output: Path, summary: WatchSummary) -> None:
    write_text(output / STATION_SUMMARY, json_text(summary.as_dict()))


__all__ = [
    "JOURNAL",
    "READY",
    "PartFinder",
    "PartRecord",
    "StageStatistics",
    "WatchOptions",
    "WatchSummary",
    "watch",
]
