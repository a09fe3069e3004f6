"""One bench row in a fresh process (its peak memory its own), within msf-bench's time limit.

``msf-bench --timeout S`` holds every row, cell and rung to S seconds: a model whose Loop never
ends (or that compiles for hours) made the whole benchmark hang. A row past its limit is killed
and reported as failed; the benchmark goes on with the next.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")
_limit: ContextVar[float | None] = ContextVar("msfnet_bench_row_limit", default=None)


@contextmanager
def row_time_limit(seconds: float | None) -> Iterator[None]:
    """Every row started in the block gets ``seconds`` (None: no limit)."""
    token = _limit.set(seconds)
    try:
        yield
    finally:
        _limit.reset(token)


def row_limit() -> float | None:
    """The time limit of the rows started now (None: none)."""
    return _limit.get()


def timed_runs(call: Callable[[], T], repeats: int) -> tuple[list[float], T | None]:
    """The wall seconds of ``repeats`` calls of ``call``, and the last call's result."""
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = call()
        times.append(time.perf_counter() - t0)
    return times, out


def run_process(argv: list[str]) -> subprocess.CompletedProcess[str] | str:
    """``argv`` run to its end, or the line saying it was stopped at the time limit."""
    limit = _limit.get()
    try:
        return subprocess.run(argv, capture_output=True, text=True, timeout=limit)
    except subprocess.TimeoutExpired:  # subprocess.run has killed it
        return f"did not finish within the time limit ({limit:g} s)"


def run_module(module: str, spec: dict, spec_file: Path) -> dict:
    """``python -m module spec_file`` in a fresh process; the worker writes its answer to
    ``spec["result"]``. {"error": its last stderr line, or the time limit} if it failed."""
    spec_file.write_text(json.dumps(spec))
    proc = run_process([sys.executable, "-m", module, str(spec_file)])
    if isinstance(proc, str):
        return {"error": proc}
    if proc.returncode != 0:
        return {"error": (proc.stderr.strip().splitlines() or ["failed"])[-1][:300]}
    return json.loads(Path(spec["result"]).read_text())


__all__ = ["row_limit", "row_time_limit", "run_module", "run_process", "timed_runs"]
