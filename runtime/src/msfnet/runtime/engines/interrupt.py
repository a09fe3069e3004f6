"""Inference that Ctrl-C and SIGTERM can stop, whatever the model does.

ONNX Runtime and OpenVINO run a call in native code: Python's signal handlers only run once the
call returns, so a model that never finishes (a Loop with a huge trip count) held the process
until SIGKILL. Here the call runs in a worker thread while the main thread waits in short,
interruptible steps; on a signal the engine is told to stop (ONNX Runtime's
``RunOptions.terminate``, OpenVINO's ``InferRequest.cancel``) and the signal's exception goes on
up to the command, which prints its one line. An engine that does not stop within GRACE_S
(OpenVINO checks its cancel flag only between nodes, not inside a Loop) would also hang the
interpreter's exit in its destructors: the process then ends with ``os._exit`` once every
``finally`` has run and the command has printed its line.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import TypeVar

from msfnet.common.errors import InputError
from msfnet.common.signals import Terminated

T = TypeVar("T")

GRACE_S = 5.0  # how long a cancelled call may take to return
_POLL_S = 0.2
_hard_exit: list[int] = []  # the exit code, once an engine would not stop
_limits: list[tuple[float, float]] = []  # (monotonic deadline, seconds) of time_limit blocks


class TimeLimit(InputError):
    """An engine compile or call still running when its time limit ran out."""

    def __init__(self, seconds: float) -> None:
        super().__init__(
            f"the model did not finish within the time limit ({seconds:g} s): a model that "
            "never ends, or a limit too short for this stack and CPU"
        )


@contextlib.contextmanager
def time_limit(seconds: float | None) -> Iterator[None]:
    """Engine compiles and calls in the block stop once ``seconds`` have passed since it began
    (TimeLimit, exit 2 in a command); None: no limit. Blocks nest: the earliest deadline wins."""
    if seconds is None:
        yield
        return
    _limits.append((time.monotonic() + seconds, seconds))
    try:
        yield
    finally:
        _limits.pop()


def _check_limit() -> None:
    if _limits:
        deadline, seconds = min(_limits)
        if time.monotonic() > deadline:
            raise TimeLimit(seconds)


def _exit_now() -> None:
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):  # a closed or broken stream: nothing left to say
            stream.flush()
    os._exit(_hard_exit[0])


def _exit_hard_at_exit(exc: BaseException) -> None:
    """End the process without waiting for the stuck native call (see the module notes)."""
    if _hard_exit:
        return
    code = (
        128 + exc.signum
        if isinstance(exc, Terminated)
        else 2
        if isinstance(exc, InputError)
        else 130
    )
    _hard_exit.append(code)
    atexit.register(_exit_now)


def run_interruptible(call: Callable[[], T], cancel: Callable[[], None]) -> T:
    """``call()``, stoppable by a signal through ``cancel()``. Outside the main thread (which
    receives no signals) the call runs directly."""
    if threading.current_thread() is not threading.main_thread():
        return call()
    done = threading.Event()
    result: list[T] = []
    error: list[BaseException] = []

    def work() -> None:
        try:
            result.append(call())
        except BaseException as exc:  # handed to the caller's thread below
            error.append(exc)
        finally:
            done.set()

    worker = threading.Thread(target=work, name="msfnet-inference", daemon=True)
    worker.start()
    try:
        while not done.wait(_POLL_S):
            _check_limit()
    except BaseException as exc:  # a signal or the time limit: stop the engine, then go on
        cancel()
        try:
            stopped = done.wait(GRACE_S)
        except BaseException:  # a second Ctrl-C while waiting: stop waiting
            stopped = False
        if not stopped:
            _exit_hard_at_exit(exc)
        raise
    if error:
        raise error[0]
    return result[0]


__all__ = ["GRACE_S", "TimeLimit", "run_interruptible", "time_limit"]
