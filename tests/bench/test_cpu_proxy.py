"""The CPU-class proxy (bench/cpu_proxy.py, cpuid_mask.c): a run under it sees the smaller
class in every library, real faults still crash, and where no proxy can run it says why."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from msfnet.bench import cpu_proxy
from msfnet.bench.cli import main as bench_main
from msfnet.common.cpu import kernel_flags
from msfnet.common.errors import InputError

REASON = cpu_proxy.unavailable_reason()
needs_proxy = pytest.mark.skipif(REASON is not None, reason=f"no CPU proxy here: {REASON}")

# What numpy, msfnet's detection and OpenVINO's CPU plugin see, one line of JSON
PROBE = """
import json
from numpy._core._multiarray_umath import __cpu_features__ as f
from msfnet.common.cpu import detect_cpu
import openvino
caps = openvino.Core().get_property("CPU", "OPTIMIZATION_CAPABILITIES")
cpu = detect_cpu()
print(json.dumps({"numpy_avx2": f["AVX2"], "numpy_avx512f": f["AVX512F"],
                  "numpy_vnni": f["AVX512VNNI"], "features": cpu.features(),
                  "model": cpu.model, "ov_bf16": "BF16" in caps}))
"""


@pytest.fixture(autouse=True)
def _own_cache(monkeypatch: pytest.MonkeyPatch, tmp_path_factory: pytest.TempPathFactory) -> None:
    """The library and the CPU detection's kept answer in a test folder, not the user's cache."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path_factory.mktemp("cache")))


def _run(cls: str, code: str, tmp_path: Path) -> subprocess.CompletedProcess[str]:
    env = cpu_proxy.proxy_env(cls)
    env["XDG_CACHE_HOME"] = str(tmp_path)  # a fresh detection, not this boot's kept answer
    return subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120
    )


@needs_proxy
@pytest.mark.parametrize(
    ("cls", "avx512f", "vnni", "features"),
    [
        ("avx2", False, False, ["avx2"]),
        pytest.param(
            "avx512_vnni",
            True,
            True,
            ["avx2", "avx512f", "avx512_vnni"],
            # a proxy only removes features: an AVX2-only host cannot pose as this class
            marks=pytest.mark.skipif(
                not {"avx512f", "avx512_vnni"} <= kernel_flags(),
                reason="this CPU has no AVX-512 VNNI to keep",
            ),
        ),
    ],
)
def test_every_library_sees_the_class(
    cls: str, avx512f: bool, vnni: bool, features: list[str], tmp_path: Path
) -> None:
    import json

    done = _run(cls, PROBE, tmp_path)
    assert done.returncode == 0, done.stderr
    seen = json.loads(done.stdout.strip().splitlines()[-1])
    assert seen["numpy_avx2"] is True
    assert (seen["numpy_avx512f"], seen["numpy_vnni"]) == (avx512f, vnni)
    assert seen["features"] == features
    assert seen["model"].endswith(f"as {cls} (cpuid proxy)")
    assert seen["ov_bf16"] is False


@needs_proxy
def test_a_thread_that_blocks_every_signal_survives_cpuid(tmp_path: Path) -> None:
    # the cpuid answer comes through SIGSEGV: a thread blocking it would be killed by its
    # first cpuid (numpy's import runs several)
    code = (
        "import signal, threading\n"
        "def work():\n"
        "    signal.pthread_sigmask(signal.SIG_BLOCK, set(signal.Signals))\n"
        "    import numpy\n"
        "    print('ok')\n"
        "t = threading.Thread(target=work); t.start(); t.join()\n"
    )
    done = _run("avx2", code, tmp_path)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr


@needs_proxy
def test_a_real_fault_still_reaches_the_programs_handler(tmp_path: Path) -> None:
    # faulthandler installs its own SIGSEGV handler after the proxy's: a real fault must still
    # reach it (traceback printed) and kill the process as without the proxy
    code = "import faulthandler, ctypes; faulthandler.enable(); ctypes.string_at(0)"
    done = _run("avx2", code, tmp_path)
    assert done.returncode == -11
    assert "Segmentation fault" in done.stderr


@needs_proxy
def test_kill_segv_kills_a_proxied_process(tmp_path: Path) -> None:
    """A SIGSEGV sent by kill() has no faulting instruction to run again: the proxy's handler
    sends it again under the default action, so it kills at once (it used to kill only at the
    process's next cpuid)."""
    code = "import os, signal, time; os.kill(os.getpid(), signal.SIGSEGV); time.sleep(5)"
    done = _run("avx2", code, tmp_path)
    assert done.returncode == -11, (done.returncode, done.stderr[-300:])


@needs_proxy
def test_the_library_is_built_once_into_the_cache(tmp_path: Path) -> None:
    lib = cpu_proxy.library(tmp_path)
    assert lib.is_file() and lib.parent == tmp_path
    stamp = lib.stat().st_mtime_ns
    assert cpu_proxy.library(tmp_path) == lib and lib.stat().st_mtime_ns == stamp
    assert [p.name for p in tmp_path.iterdir()] == [lib.name]  # no staging or source left


def test_an_unknown_class_is_refused() -> None:
    with pytest.raises(InputError, match="expected one of avx2, avx2_vnni, avx512_vnni"):
        cpu_proxy.proxy_env("avx9000")


def test_msf_bench_says_why_no_proxy_can_run(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(cpu_proxy, "unavailable_reason", lambda: "no CPUID faulting (test)")
    monkeypatch.delenv("LD_PRELOAD", raising=False)
    assert bench_main(["--cpu-proxy", "avx2", "--quick"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == "msf-bench: error: --cpu-proxy: no CPUID faulting (test)"


def test_the_runner_needs_a_command(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        cpu_proxy.main(["avx2"])
    assert exc.value.code == 2
    assert "give a command after --" in capsys.readouterr().err


def test_a_class_the_host_lacks_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(cpu_proxy, "kernel_flags", lambda: frozenset({"avx", "avx2", "fma"}))
    with pytest.raises(InputError, match="this CPU lacks avx512_vnni, avx512f"):
        cpu_proxy.proxy_env("avx512_vnni")


@needs_proxy
def test_a_library_path_ld_preload_cannot_take_is_refused(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    # the loader would ignore it and the run would measure the whole CPU under the proxy's name
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "with space"))
    with pytest.raises(InputError, match="space or colon"):
        cpu_proxy.proxy_env("avx2")


@needs_proxy
def test_a_library_that_does_not_load_is_caught(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    broken = tmp_path / "cpuid_mask-broken.so"
    broken.write_bytes(b"not a shared object")
    monkeypatch.setattr(cpu_proxy, "library", lambda cache=None: broken)
    with pytest.raises(InputError, match="the cpuid library did not load"):
        cpu_proxy.proxy_env("avx2")
