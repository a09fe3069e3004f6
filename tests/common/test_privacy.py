"""The libraries' usage reports are off from the first msfnet import, unless the user asks."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from msfnet.common.privacy import OPT_IN_ENV

# written out, not read from the module: a missing or flipped switch must fail here
OFF = {"DEPTHAI_TELEMETRY": "0", "ORT_DISABLE_TELEMETRY": "1", "RAY_USAGE_STATS_ENABLED": "0"}
SWITCHES = sorted(OFF)
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
    assert _child(SHOW) == str([OFF[n] for n in SWITCHES])


def test_only_msfnet_telemetry_1_leaves_them_alone() -> None:
    assert _child(SHOW, **{OPT_IN_ENV: "1"}) == str([None] * len(SWITCHES))
    for other in ("0", "true", "yes", " 1"):
        assert _child(SHOW, **{OPT_IN_ENV: other}) == str([OFF[n] for n in SWITCHES]), other


def test_a_switch_the_user_set_is_kept_and_an_empty_one_is_not() -> None:
    got = _child(SHOW, ORT_DISABLE_TELEMETRY="0", DEPTHAI_TELEMETRY="")
    assert got == str(["0" if n == "ORT_DISABLE_TELEMETRY" else OFF[n] for n in SWITCHES])


def test_onnx_runtime_keeps_no_event_store(tmp_path: Path) -> None:
    """ONNX Runtime 1.32's Linux build opens an event store and a device id under the cache
    folder in every process that imports it (seen here without the switch); after
    ``import msfnet`` it creates neither, sessions included."""
    pytest.importorskip("onnxruntime")
    code = (
        "import msfnet, onnxruntime as ort\n"
        "from msfnet.runtime.api import default_model_path\n"
        "ort.InferenceSession(str(default_model_path()), providers=['CPUExecutionProvider'])\n"
        "print('ok')"
    )
    env = {"XDG_CACHE_HOME": str(tmp_path), "HOME": str(tmp_path), "TMPDIR": str(tmp_path)}
    assert _child(code, **env) == "ok"
    made = sorted(p.name for p in tmp_path.rglob("*"))
    assert "Microsoft" not in made and ".ses" not in made, made


def test_depthai_keeps_no_telemetry_ids(tmp_path: Path) -> None:
    """depthai 3.12 writes telemetry/tmpIds.json under its cache at import without the switch
    (and looks up its collector)."""
    pytest.importorskip("depthai")
    env = {"XDG_CACHE_HOME": str(tmp_path), "HOME": str(tmp_path)}
    assert _child("import msfnet, depthai; print('ok')", **env) == "ok"
    assert not list(tmp_path.rglob("tmpIds.json")), sorted(p.name for p in tmp_path.rglob("*"))


def test_ray_reports_no_usage_stats() -> None:
    pytest.importorskip("ray")
    code = (
        "import msfnet\n"
        "from ray._common.usage import usage_lib\n"
        "print(usage_lib.usage_stats_enabled())"
    )
    try:
        got = _child(code)
    except AssertionError as exc:  # Ray moved its usage module: nothing to check here
        if "ModuleNotFoundError" in str(exc):
            pytest.skip("this Ray has no ray._common.usage.usage_lib")
        raise
    assert got == "False"
