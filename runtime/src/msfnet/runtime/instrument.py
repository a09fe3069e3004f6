"""Instruments every stage of a run shares: a per-stage timer that announces long steps, and
this process's memory (now and its peak). Lowest of the runtime: estimators, engines and
results all measure with it."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar

STAGES = ("load", "preprocess", "inference", "postprocess", "maps", "total")


# What a person waiting should hear of: the first entry into these stages of a run is
# announced (see announcing); preprocess / postprocess are too short and too many to say.
ANNOUNCED = {
    "load": "reading the stack",
    "inference": "estimating the normals",
    "maps": "inspection maps (albedo, height, curvature)",
}
_listener: ContextVar[Callable[[str], None] | None] = ContextVar("msfnet_stages", default=None)


@contextmanager
def announcing(say: Callable[[str], None]) -> Iterator[None]:
    """Within the block, ``say`` hears each long step as it starts (a command prints it, so a
    run without tiles is not silent for a minute). Per thread and task, like any ContextVar."""
    token = _listener.set(say)
    try:
        yield
    finally:
        _listener.reset(token)


def announce(step: str) -> None:
    """Tell whoever listens (see :func:`announcing`) that ``step`` starts; nothing otherwise."""
    say = _listener.get()
    if say is not None:
        say(step)


class StageTimer:
    """Accumulates wall time per stage name (a stage may be entered many times, e.g. per tile).
    The first entry into a stage of :data:`ANNOUNCED` is announced."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        if stage in ANNOUNCED and stage not in self.seconds:
            announce(ANNOUNCED[stage])
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[stage] = self.seconds.get(stage, 0.0) + time.perf_counter() - start


def memory_in_use_mb() -> float | None:
    """This process's resident memory now (MB), None where it cannot be read
    (least squares and the maps size their work to --max-memory with it). Linux: VmRSS of
    /proc/self/status (psutil's import is ~25 ms of every fresh run); elsewhere psutil."""
    rss = _proc_status_mb("VmRSS:")
    if rss is not None:
        return rss
    try:
        import psutil

        return float(psutil.Process().memory_info().rss) / 2**20
    except Exception:  # no psutil, or a platform where it cannot tell
        return None


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, in MB (0 where the OS does not say).

    Linux: VmHWM (see :func:`_linux_hwm_mb`); other POSIX (macOS, BSD): ru_maxrss (bytes on
    macOS). Windows has no ``resource``: psutil's peak working set. Anywhere else psutil's
    current RSS, a lower bound of the peak, is better than nothing.
    """
    hwm = _linux_hwm_mb()
    if hwm is not None:
        return hwm
    try:
        import resource
    except ImportError:
        return _psutil_peak_mb()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2**20 if sys.platform == "darwin" else peak / 1024


def _linux_hwm_mb() -> float | None:
    """Linux: VmHWM of /proc/self/status, this address space's own peak. ru_maxrss survives
    exec, so a process started from a large parent (a test runner, a notebook) would report the
    parent's size at fork time as its own peak (measured: 4.2 GB against 2.0 GB)."""
    return _proc_status_mb("VmHWM:")


def _proc_status_mb(key: str) -> float | None:
    """A kB field of Linux's /proc/self/status in MB; None elsewhere."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(key):
                    return int(line.split()[1]) / 1024  # kB
    except (OSError, ValueError, IndexError):
        return None
    return None


def _psutil_peak_mb() -> float:
    try:
        import psutil
    except ImportError:  # a dependency, but keep the profile working without it
        return 0.0
    info = psutil.Process().memory_info()
    # peak_wset exists on Windows only; rss (current) elsewhere
    return float(getattr(info, "peak_wset", 0) or info.rss) / 2**20


__all__ = [
    "ANNOUNCED",
    "STAGES",
    "StageTimer",
    "announce",
    "announcing",
    "memory_in_use_mb",
    "peak_rss_mb",
]
