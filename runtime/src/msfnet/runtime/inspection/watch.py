"""The station's watch loop (``msf-inspect --watch``): each complete part that appears in a
folder judged exactly once; docs/run.md, "Inspection station: msf-inspect --watch".

A part is a sub-folder, complete when it holds ``READY`` or its listing is unchanged between
two polls. The output folder holds ``parts.jsonl`` (one line per attempt, a part's last line
stands: the journal is the state a restart resumes from) and one folder per judged part, each
written whole.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import signal
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType

import numpy as np

from msfnet.common.cli import positive_float
from msfnet.common.errors import InputError
from msfnet.common.files import folder_lock, json_text, staged_folder, write_text
from msfnet.common.imageio import encode_png
from msfnet.common.vocabulary import flag, options_type
from msfnet.runtime.inspection.defects import deviation_picture
from msfnet.runtime.inspection.station import STAGES, Inspection, Station
from msfnet.runtime.stack import Stack

JOURNAL = "parts.jsonl"
READY = "READY"
STATION_SUMMARY = "station.json"
SETTINGS = "settings.json"  # what decides the verdicts: a restart must give the same


@options_type
@dataclass(frozen=True)
class WatchOptions:
    """How the loop watches (each field's help says what it does)."""

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

    part: str  # its output folder's name: the folder's, or "name~2" for a name used again
    verdict: str  # "pass", "fail", "mismatch" (not the reference's part) or "error"
    defects: int = 0
    times_ms: dict[str, float] = field(default_factory=dict)
    regions: tuple[dict[str, object], ...] = ()
    error: str | None = None
    folder: str | None = None  # the watched sub-folder, where it differs from ``part``
    # the folder's identity when judged (inode and modification time): a new folder under an
    # old name, or one changed since, differs
    identity: str | None = None

    @classmethod
    def of(cls, inspection: Inspection, write_s: float, taken: Taken) -> PartRecord:
        v = inspection.verdict.as_dict()
        times = inspection.times.milliseconds() | {"write": round(write_s * 1e3, 2)}
        regions = tuple(dict(r) for r in v["regions"])  # type: ignore[attr-defined]
        verdict = str(v["verdict"])
        return cls(taken.name, verdict, len(regions), times, regions, None, *taken.identity)

    @classmethod
    def failure(cls, taken: Taken, why: str) -> PartRecord:
        return cls(taken.name, "error", error=why, folder=taken.identity[0])

    @property
    def source(self) -> str:
        return self.folder or self.part

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
    # --once: the last verdict of each part now in the watched folder (this run's or an
    # earlier one's), what its exit code says
    present: dict[str, str] | None = None

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
        """--once's, over the parts in the folder (``present``; else this run's): 2 if a part
        could not be judged, else 4 if one did not match the reference, else 1 if one had
        defects, else 0."""
        counts = {"error": self.errors, "mismatch": self.mismatched, "fail": self.failed}
        words = {w for w, n in counts.items() if n}
        if self.present is not None:
            words = set(self.present.values())
        return 2 if "error" in words else 4 if "mismatch" in words else 1 if "fail" in words else 0

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
    """``parts.jsonl`` in the output folder: the parts already judged, and where new lines go.
    ``judged``: watched folder name -> the identity of the folder judged under it (None: not
    known); ``names``: the output names taken; ``last``: each folder's last verdict."""

    def __init__(self, output: Path) -> None:
        self.path = output / JOURNAL
        self.judged: dict[str, str | None] = {}
        self.names: set[str] = set()
        self.last: dict[str, str] = {}
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
        for n, line in enumerate(whole.splitlines(), 1):
            try:
                data = json.loads(line)
                part, verdict = str(data["part"]), str(data["verdict"])
                folder, identity = data.get("folder"), data.get("identity")
            except (ValueError, KeyError, TypeError, AttributeError):
                raise InputError(f"line {n} is not a station record", self.path) from None
            self._note(part, verdict, None if folder is None else str(folder), identity)

    def _note(self, part: str, verdict: str, folder: str | None, identity: object) -> None:
        source = folder or part
        self.last[source] = verdict
        # a part whose last record is an error is taken again (it may be complete now)
        if verdict != "error":
            self.judged[source] = identity if isinstance(identity, str) else None
            self.names.add(part)

    def _adopt_written(self, output: Path) -> None:
        """A part folder written just before a kill, whose line was not: the line, from its
        verdict.json (so the part is not judged twice)."""
        for entry in sorted(output.iterdir()):
            verdict = entry / "verdict.json"
            if entry.name in self.names or entry.name.startswith(".") or not verdict.is_file():
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
        self._note(record.part, record.verdict, record.folder, record.identity)


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


# names a part folder being written under, to be renamed when done: never a part
TEMPORARY = (".tmp", ".part", ".partial", ".incomplete", "~")
RESERVED = (JOURNAL, STATION_SUMMARY, SETTINGS)  # the station's own files in its output folder


@dataclass(frozen=True)
class Taken:
    """A part taken: its folder, and the output name it is judged under."""

    path: Path
    name: str
    fingerprint: str | None

    @property
    def identity(self) -> tuple[str | None, str | None]:
        """(the folder's name where the output name differs, else None; its fingerprint)."""
        return (self.path.name if self.name != self.path.name else None, self.fingerprint)


def _fingerprint(entry: os.DirEntry[str]) -> str:
    """A folder's identity: its inode and last change of its entries (a folder removed and
    made again may get the same inode, not the same time)."""
    try:
        st = entry.stat()
    except OSError:
        return ""
    return f"{st.st_ino}:{st.st_mtime_ns}"


class PartFinder:
    """The complete parts in the watched folder, in name order, each offered until taken."""

    def __init__(
        self, folder: Path, options: WatchOptions, journal: Journal, skip: tuple[Path, ...]
    ) -> None:
        self.folder = folder
        self.options = options
        self.journal = journal
        self.seen: dict[str, _Seen] = {}
        self.fingerprints: dict[str, str] = {}
        self._skip = {os.path.realpath(p) for p in skip}

    def candidates(self) -> list[Path]:
        try:
            entries = sorted(os.scandir(self.folder), key=lambda e: e.name)
        except FileNotFoundError:
            raise InputError("the watched folder is gone", self.folder) from None
        except OSError as exc:  # a network share's hiccup (ESTALE, EIO): the next look retries
            if not self.options.once:
                warnings.warn(f"{self.folder}: cannot list ({exc}); trying again", stacklevel=2)
                return []
            raise InputError(f"cannot list the folder ({exc})", self.folder) from None
        out = []
        for e in entries:
            if e.name.startswith(".") or e.name.endswith(TEMPORARY) or not e.is_dir():
                continue
            judged = self.journal.judged.get(e.name, "")
            mark = _fingerprint(e)
            if judged != "" and (judged is None or judged == mark):
                continue  # judged already (a new folder under the name is another part)
            if os.path.realpath(e.path) in self._skip:
                continue
            self.fingerprints[e.name] = mark
            out.append(Path(e.path))
        return out

    def take(self, path: Path) -> Taken:
        """The part at ``path`` with the name it is judged under: its own, or "name~2", ...
        when the name was judged before (a folder name used again) or is the station's."""
        name, k = path.name, 1
        while name in self.journal.names or name in RESERVED:
            k += 1
            name = f"{path.name}~{k}"
        return Taken(path, name, self.fingerprints.get(path.name))

    def present(self) -> dict[str, str]:
        """The last verdict of each part folder now in the watched folder."""
        with os.scandir(self.folder) as it:
            here = {e.name for e in it if e.is_dir()}
        return {name: v for name, v in self.journal.last.items() if name in here}

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
                if not any(n == READY for n, *_ in listing):
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
        encode_png(tmp / "deviation.png", deviation_picture(inspection.verdict))
    return time.perf_counter() - start


_WATCHED: set[str] = set()  # output folders a watch loop of this process writes
_WATCHED_LOCK = threading.Lock()


@contextlib.contextmanager
def _one_station(output: Path) -> Iterator[None]:
    """One loop per output folder: another process is kept out by the folder's lock, another
    thread of this one (for which that lock is re-entrant) here."""
    key = os.path.realpath(output)
    with _WATCHED_LOCK:
        if key in _WATCHED:
            raise InputError("another station of this process writes here", output)
        _WATCHED.add(key)
    try:
        with folder_lock(output, "msf-inspect --watch"):
            yield
    finally:
        with _WATCHED_LOCK:
            _WATCHED.discard(key)


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
    with _one_station(output):
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
    _check_settings(output, station.settings())
    summary = WatchSummary(earlier=len(journal.names))
    finder = PartFinder(folder, options, journal, (*skip, output))
    stop = _Stop()

    def record(rec: PartRecord) -> None:
        journal.add(rec)
        summary.add(rec)
        report(rec)

    pool = ThreadPoolExecutor(1, thread_name_prefix="decode")
    finished = False
    try:
        with stop.on_signals():
            looks = 0
            while not stop.event.is_set():
                now = time.monotonic()
                parts = [finder.take(p) for p in finder.ready(now)]
                looks += 1
                for path, why in finder.stale(now):
                    record(PartRecord.failure(finder.take(path), why))
                wall, cpu = time.perf_counter(), time.process_time()
                _judge_all(station, parts, pool, finder, record, stop.event, output)
                if parts:
                    summary.busy_s += time.perf_counter() - wall
                    summary.cpu_s += time.process_time() - cpu
                # --once: a second look, a poll later, takes the parts that have not changed
                if options.once and looks >= 2:
                    break
                stop.event.wait(options.poll_s)
        finished = True
    finally:
        # a second signal stops at once: the decode ahead (a stalled read) is not waited for
        pool.shutdown(wait=finished, cancel_futures=True)
    if options.once and not stop.event.is_set():
        summary.present = finder.present()
    write_text(output / STATION_SUMMARY, json_text(summary.as_dict()))
    return summary


def _check_settings(output: Path, settings: dict[str, object]) -> None:
    """A station folder's verdicts are all made alike: its settings are written when it
    starts, and a restart with other ones (another rule, reference, zones or model) refused."""
    path = output / SETTINGS
    text = json_text(settings)
    if not path.is_file():
        if (output / JOURNAL).is_file() and (output / JOURNAL).stat().st_size:
            return  # a folder of an earlier version, without settings: resumed as it is
        write_text(path, text)
        return
    try:
        held = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise InputError(f"unreadable ({exc}): remove it to start afresh", path) from None
    now = json.loads(text)
    differ = sorted(k for k in set(held) | set(now) if held.get(k) != now.get(k))
    if differ:
        raise InputError(
            f"this station folder was started with other settings ({', '.join(differ)}): its "
            "verdicts would not compare; give a new -o (or the same settings)",
            output,
        )


MAX_FAILING = 3  # parts in a row failing inside the tool: a fault of the station, not a part's


def _judge_all(
    station: Station,
    parts: list[Taken],
    pool: ThreadPoolExecutor,
    finder: PartFinder,
    record: Callable[[PartRecord], None],
    stop: threading.Event,
    output: Path,
) -> None:
    """Judge ``parts`` in order, decoding each next one while the current one is judged. A
    part the tool fails on (not bad input) is recorded as an error and the loop goes on,
    unless MAX_FAILING in a row do."""
    ahead: Future[Decoded] | None = None
    failing = 0
    for i, taken in enumerate(parts):
        if stop.is_set():
            break
        decoding = ahead or pool.submit(station.read, taken.path)
        ahead = pool.submit(station.read, parts[i + 1].path) if i + 1 < len(parts) else None
        try:
            stack, decode_s = decoding.result()
            inspection = station.judge(stack, taken.name, decode_s)
            write_s = _write_part(output, inspection)
        except InputError as exc:
            if finder.failed(taken.path, exc, time.monotonic()):
                record(PartRecord.failure(taken, str(exc)))
            continue
        except Exception as exc:
            failing += 1
            if failing >= MAX_FAILING:
                raise
            finder.failed(taken.path, InputError(str(exc)), math.inf)
            record(PartRecord.failure(taken, f"internal error: {type(exc).__name__}: {exc}"))
            continue
        failing = 0
        record(PartRecord.of(inspection, write_s, taken))
    if ahead is not None:
        ahead.cancel()


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
