"""Signals and outputs: a kill (SIGTERM, SIGHUP) unwinds like Ctrl-C, so every ``finally``
removes its staging, and no signal lands between the renames that publish an output.

Used by the atomic writer (msfnet.common.files), every command (msfnet.common.cli) and
msf-train (which turns SIGTERM into "save and stop" instead).
"""

from __future__ import annotations

import contextlib
import os
import signal
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
    for sig, handler in previous.items():
        with contextlib.suppress(ValueError, TypeError):
            signal.signal(sig, handler)  # type: ignore[arg-type]


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


__all__ = ["Terminated", "install_signal_handlers", "restore_signal_handlers", "signals_deferred"]
