"""The libraries' usage reports are off from the first msfnet import, unless the user asks."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from msfnet.common.privacy import LIBRARY_SWITCHES, OPT_IN_ENV

SWITCHES = sorted(LIBRARY_SWITCHES)
SHOW = f"import os, msfnet; print([os.environ.get(n) for n in {SWITCHES!r}])"


def _child(code: str, **env: str) -> str:
    clean = {k: v for k, v in os.environ.items() if k not in (*SWITCHES, OPT_IN_ENV, "CI")}
    done = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=120,
        env={**clean, **env},
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout.strip().splitlines()[-1]


def test_importing_msfnet_turns_the_libraries_telemetry_off() -> None:
    assert _child(SHOW) == str([LIBRARY_SWITCHES[n] for n in SWITCHES])


def test_msfnet_telemetry_1_leaves_them_alone() -> None:
    assert _child(SHOW, **{OPT_IN_ENV: "1"}) == str([None] * len(SWITCHES))


def test_a_switch_the_user_set_is_kept() -> None:
    got = _child(SHOW, ORT_DISABLE_TELEMETRY="0")
    assert got == str(
        ["0" if n == "ORT_DISABLE_TELEMETRY" else LIBRARY_SWITCHES[n] for n in SWITCHES]
    )


def test_an_onnx_runtime_session_keeps_no_event_store(tmp_path: Path) -> None:
    """ONNX Runtime 1.32's Linux build opens an event store and a device id under the cache
    folder in every process that creates a session (seen here without the switch); after
    ``import msfnet`` it creates neither."""
    pytest.importorskip("onnxruntime")
    code = (
        "import msfnet, onnxruntime as ort\n"
        "from msfnet.runtime.api import default_model_path\n"
        "ort.InferenceSession(str(default_model_path()), providers=['CPUExecutionProvider'])\n"
        "print('ok')"
    )
    assert _child(code, XDG_CACHE_HOME=str(tmp_path), HOME=str(tmp_path)) == "ok"
    assert not (tmp_path / "Microsoft").exists(), sorted(p.name for p in tmp_path.rglob("*"))
