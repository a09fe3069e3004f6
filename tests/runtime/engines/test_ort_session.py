"""ONNX Runtime sessions: the default thread count is runtime.cpu's usable cores."""

from __future__ import annotations

import os

import pytest

from msfnet.runtime.engines import ort_session as session


def test_default_threads_are_the_usable_cores(monkeypatch: pytest.MonkeyPatch) -> None:
    """One definition of 'usable cores' (common/cpu.py), with its at-least-one guard."""
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(), raising=False)
    assert session.default_threads() == 1
    monkeypatch.setattr(session, "usable_cores", lambda: 7)
    assert session.default_threads() == 7
