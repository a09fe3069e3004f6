"""Signals and outputs: a kill (SIGTERM, SIGHUP) unwinds like Ctrl-C, so every ``finally``
removes its staging, and no signal lands between the renames that publish an output.

Used by the atomic writer (msfnet.common.files), every command (msfnet.common.cli) and
msf-train (which turns SIGTERM into "save and stop" instead).
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

_SIGNALS = tuple(getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n))


class Terminated(BaseException):
    """SIGTERM/SIGHUP arrived: unwinds like Ctrl-C so every ``finally`` cleans up."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def _raise_terminated(signum: int, frame: object) -> None:
    raise Terminated(signum)


class _Command:
    """Where the command of this process stands, for the SIGINT handlers below."""

    guarded = False  # an msf-* program: guard_startup took Ctrl-C over
    started = False  # run_command has taken over Ctrl-C
    done = False  # ... and has finished: it said what happened


def _interrupted_at_startup(signum: int, frame: object) -> None:
    if _Command.done:  # after the command's own last line, exiting: nothing more to say
        return
    prog = os.path.basename(sys.argv[0]) or "msfnet"
    what = "interrupted" if signum == signal.SIGINT else f"terminated (signal {signum})"
    with contextlib.suppress(OSError):  # os.write: print is not safe inside a handler
        os.write(2, f"{prog}: {what} while starting; nothing was written\n".encode())
    os._exit(128 + signum)


def guard_startup() -> None:
    """Ctrl-C while an msfnet command is still importing (seconds: numpy, OpenCV, ONNX Runtime)
    printed Python's 22-57 line traceback, and SIGTERM / SIGHUP ended it without a word: from
    the first msfnet import of a command's process on, each is one line and exit 128 + signal;
    :func:`interrupt_once` takes over when the command's body starts. Only in the main process
    of an ``msf-*`` program, and only where the signal has its default meaning (a background
    job's ignored SIGINT stays ignored):
    a Python program importing msfnet keeps its own Ctrl-C."""
    if not os.path.basename(sys.argv[0] if sys.argv else "").startswith("msf-"):
        return
    if threading.current_thread() is not threading.main_thread():
        return
    # a worker the command started has multiprocessing loaded already; importing it here
    # would cost the guard tens of ms of the start-up it protects
    multiprocessing = sys.modules.get("multiprocessing")
    if multiprocessing is not None and multiprocessing.parent_process() is not None:
        return
    for signum in _SIGNALS:  # a kill while importing said nothing either
        now = signal.getsignal(signum)
        if now is signal.default_int_handler or now is signal.SIG_DFL:
            with contextlib.suppress(ValueError):
                signal.signal(signum, _interrupted_at_startup)
                _Command.guarded = True


@contextmanager
def interrupt_once() -> Iterator[None]:
    """Ctrl-C in the block raises KeyboardInterrupt once; another Ctrl-C while that unwinds
    (removing staging, printing the one line) is ignored, so the cleanup finishes and no
    second traceback follows (a double Ctrl-C printed 17 lines). An ignored SIGINT stays
    ignored."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.getsignal(signal.SIGINT)
    if previous is signal.SIG_IGN:
        yield
        return
    hit = False

    def on_sigint(signum: int, frame: object) -> None:
        nonlocal hit
        if hit:
            return
        hit = True
        raise KeyboardInterrupt

    signal.signal(signal.SIGINT, on_sigint)
    outermost = not _Command.started
    _Command.started = True
    try:
        yield
    finally:
        if outermost:
            _Command.started, _Command.done = False, True
        # An msf-* program only exits after its command: a Ctrl-C now would kill it while
        # Python shuts down (which puts the default handler back), so it is ignored.
        after = signal.SIG_IGN if outermost and _Command.guarded else previous
        with contextlib.suppress(ValueError, TypeError):
            signal.signal(signal.SIGINT, after)  # type: ignore[arg-type]


def install_signal_handlers() -> dict[int, object]:
    """Turn SIGTERM (and SIGHUP) into an exception, so staged outputs are removed on a kill.

    Returns the previous handlers (for :func:`restore_signal_handlers`). A signal the caller
    ignores (``nohup``) stays ignored."""
    previous: dict[int, object] = {}
    for name in ("SIGTERM", "SIGHUP"):
        sig = getattr(signal, name, None)
        if sig is None or signal.getsignal(sig) is signal.SIG_IGN:
            continue
        # outside the main thread this raises ValueError: keep the default behaviour there
        with contextlib.suppress(ValueError):
            previous[sig] = signal.signal(sig, _raise_terminated)
    return previous


def restore_signal_handlers(previous: dict[int, object]) -> None:
    """Put back the handlers :func:`install_signal_handlers` replaced.

    Once an msf-* program's command has finished and said its last line, the process only
    exits: a SIGTERM / SIGHUP then (Python's shutdown can take a moment with an engine
    loaded) would have killed it with 143 and no word although its outputs were complete,
    and a supervisor reads 143 as a failed run. Such a signal is ignored from then on, as
    Ctrl-C is; in-process callers get their own handlers back."""
    exiting = _Command.guarded and _Command.done
    for sig, handler in previous.items():
        with contextlib.suppress(ValueError, TypeError):
            signal.signal(sig, signal.SIG_IGN if exiting else handler)  # type: ignore[arg-type]


@contextmanager
def signals_deferred() -> Iterator[None]:
    """Hold Ctrl-C/SIGTERM/SIGHUP until the block is done, then act on the first one.

    A renaming sequence interrupted half-way could leave an old output moved aside and the new
    one not yet in place. Swapping the Python-level handlers (not the thread mask) also covers
    signals the kernel delivers to a native worker thread (ONNX Runtime's, for instance).
    """
    if threading.current_thread() is not threading.main_thread():
        yield  # handlers can only be changed (and only run) in the main thread
        return
    pending: list[int] = []
    old = {
        sig: signal.signal(sig, lambda signum, frame: pending.append(signum)) for sig in _SIGNALS
    }
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
        if pending:
            handler = old[pending[0]]
            if callable(handler):
                handler(pending[0], None)
            elif handler == signal.SIG_DFL:
                os.kill(os.getpid(), pending[0])


__all__ = [
    "Terminated",
    "guard_startup",
    "install_signal_handlers",
    "interrupt_once",
    "restore_signal_handlers",
    "signals_deferred",
]
