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
from contextvars import ContextVar
from typing import TypeVar

from msfnet.common.errors import InputError, MsfError
from msfnet.common.signals import Terminated

T = TypeVar("T")

GRACE_S = 5.0  # how long a cancelled call may take to return
_POLL_S = 0.2
_hard_exit: list[int] = []  # the exit code, once an engine would not stop
# (monotonic deadline, seconds) of the time_limit blocks this thread / task is in
_limits: ContextVar[tuple[tuple[float, float], ...]] = ContextVar("msfnet_limits", default=())


def _limit_text(seconds: float) -> str:
    return f"the model did not finish within the time limit ({seconds:g} s)"


class TimeLimit(InputError):
    """An engine compile or call still running when its time limit ran out (and stopped)."""

    def __init__(self, seconds: float) -> None:
        super().__init__(
            f"{_limit_text(seconds)}: a model that never ends, or a limit too short for this "
            "stack and CPU"
        )
        self.seconds = seconds

    def __reduce__(self) -> tuple[type, tuple[float]]:  # pickled whole (process pools)
        return (type(self), (self.seconds,))


class EngineStuck(MsfError):
    """The engine did not stop when its time limit ran out: it cannot run another stack (a
    batch or stream stops here), and the process ends after the command's line."""


@contextlib.contextmanager
def time_limit(seconds: float | None) -> Iterator[None]:
    """Engine compiles and calls in the block, in this thread, stop once ``seconds`` have
    passed since it began (TimeLimit, exit 2 in a command); None: no limit. Blocks nest: the
    earliest deadline wins."""
    if seconds is None:
        yield
        return
    token = _limits.set((*_limits.get(), (time.monotonic() + seconds, seconds)))
    try:
        yield
    finally:
        _limits.reset(token)


def _check_limit(limits: tuple[tuple[float, float], ...]) -> None:
    if limits:
        deadline, seconds = min(limits)
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
    """``call()``, stoppable by a signal or its time limit through ``cancel()``. Outside the
    main thread (which alone receives signals) and without a limit, the call runs directly."""
    limits = _limits.get()
    if threading.current_thread() is not threading.main_thread() and not limits:
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
            _check_limit(limits)
    except BaseException as exc:  # a signal or the time limit: stop the engine, then go on
        cancel()
        try:
            stopped = done.wait(GRACE_S)
        except BaseException:  # a second Ctrl-C while waiting: stop waiting
            stopped = False
        if not stopped:
            _exit_hard_at_exit(exc)
            if isinstance(exc, TimeLimit):  # not one stack's failure: the engine is busy
                raise EngineStuck(
                    f"{_limit_text(exc.seconds)} and did not stop when told to; the "
                    "process ends after this line"
                ) from exc
        raise
    if error:
        raise error[0]
    return result[0]


__all__ = ["GRACE_S", "EngineStuck", "TimeLimit", "run_interruptible", "time_limit"]
