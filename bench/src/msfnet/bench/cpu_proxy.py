"""Run a command as if on a smaller x86 CPU class: the AVX2-only and VNNI proxies of the speed
issue's targets (docs/benchmark.md).

Why: the targets name CPU classes (AVX2-only edge boxes, VNNI Xeons without bf16) that this
project's machines do not always have. oneDNN's ``ONEDNN_MAX_CPU_ISA`` caps OpenVINO (and
torch's oneDNN) only; ONNX Runtime's kernels and numpy's choose from the ``cpuid`` instruction
themselves, so a same-run comparison of the two engines could not be capped. This module builds
``cpuid_mask.c`` (a small LD_PRELOAD library, compiled once per source version into the user's
cache with the system C compiler) that makes ``cpuid`` trap through Linux's CPUID faulting and
answers it with the class's feature bits, so every library of the process and of its children
that reads cpuid once loaded (numpy, ONNX Runtime, OpenVINO, torch) sees the same smaller CPU;
glibc's string routines, chosen by the loader before, keep the real CPU's. Still a proxy:
caches, clocks and cores are this machine's, and every figure measured under it says so
(``CpuInfo.model`` names the class). ``proxy_env`` checks in a probe process that the library
really loaded (the loader skips a preload it cannot open, silently) and that the host has the
features the class keeps.

``python -m msfnet.bench.cpu_proxy avx2 -- msf-run ...`` runs any command under a class;
``msf-bench --cpu-proxy avx2`` runs the benchmark under one.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import platform
import shutil
import subprocess
import sys
from collections.abc import Mapping
from importlib import resources
from pathlib import Path

from msfnet.common.cpu import FEATURES, PROXY_CLASSES, PROXY_ENV, cache_folder, kernel_flags
from msfnet.common.errors import InputError

SOURCE = "cpuid_mask.c"


def compiler() -> str | None:
    """The C compiler to build the library with: $CC, else cc or gcc on the PATH."""
    for name in (os.environ.get("CC", ""), "cc", "gcc"):
        if name and shutil.which(name):
            return name
    return None


def unavailable_reason() -> str | None:
    """Why no proxy can run here, or None when one can."""
    if sys.platform != "linux" or platform.machine() not in ("x86_64", "AMD64"):
        return f"needs Linux on x86-64 (this is {sys.platform} on {platform.machine()})"
    if "cpuid_fault" not in kernel_flags():
        return "this CPU or hypervisor offers no CPUID faulting (no cpuid_fault in /proc/cpuinfo)"
    if compiler() is None:
        return "no C compiler (cc, gcc or $CC) to build the cpuid library with"
    return None


def _source() -> bytes:
    return resources.files("msfnet.bench").joinpath(SOURCE).read_bytes()


def library(cache: Path | None = None) -> Path:
    """The compiled library, built on first use (one per source version, kept in the cache)."""
    from msfnet.common.files import write_atomic

    reason = unavailable_reason()
    if reason is not None:
        raise InputError(f"--cpu-proxy: {reason}")
    source = _source()
    lib = (cache or cache_folder()) / f"cpuid_mask-{hashlib.sha256(source).hexdigest()[:16]}.so"
    if lib.is_file():
        return lib
    cc = compiler()
    assert cc is not None  # unavailable_reason checked it

    def build(tmp: Path) -> None:
        src = tmp.with_name(tmp.name + ".c")
        try:
            src.write_bytes(source)
            done = subprocess.run(
                [cc, "-O2", "-shared", "-fPIC", "-o", str(tmp), str(src), "-ldl"],
                capture_output=True,
                text=True,
            )
        finally:
            src.unlink(missing_ok=True)
        if done.returncode != 0:
            last = (done.stderr.strip().splitlines() or ["no message"])[-1]
            raise InputError(f"--cpu-proxy: building the cpuid library failed: {last}")

    # concurrent first uses each build and rename a whole file
    return write_atomic(lib, build, output=False)


# Run under the proxy: what this package's detection then reports (proves the preload worked)
_PROBE = "from msfnet.common.cpu import proxy_class; print(proxy_class())"


def proxy_env(cpu_class: str, env: Mapping[str, str] | None = None) -> dict[str, str]:
    """``env`` (default: this process's) with the library preloaded and the class set, checked
    by a short probe process: a preload the loader ignores would measure the whole CPU under
    the proxy's name."""
    if cpu_class not in PROXY_CLASSES:
        raise InputError(
            f"--cpu-proxy {cpu_class}: expected one of {', '.join(sorted(PROXY_CLASSES))}"
        )
    # a proxy removes features: the host must have the FEATURES the class keeps
    missing = (PROXY_CLASSES[cpu_class] & set(FEATURES)) - kernel_flags()
    if missing:
        raise InputError(
            f"--cpu-proxy {cpu_class}: this CPU lacks {', '.join(sorted(missing))}; a proxy "
            "can only remove features"
        )
    out = dict(os.environ if env is None else env)
    lib = str(library())
    if any(c.isspace() or c == ":" for c in lib):  # LD_PRELOAD's separators
        raise InputError(
            f"--cpu-proxy: the library's path {lib!r} holds a space or colon, which LD_PRELOAD "
            "cannot take; set XDG_CACHE_HOME to a folder without"
        )
    preload = [p for p in out.get("LD_PRELOAD", "").replace(":", " ").split() if p]
    out["LD_PRELOAD"] = " ".join([lib, *[p for p in preload if p != lib]])
    out[PROXY_ENV] = cpu_class
    probe = subprocess.run(
        [sys.executable, "-c", _PROBE], env=out, capture_output=True, text=True, timeout=120
    )
    if probe.stdout.strip() != cpu_class:
        last = (probe.stderr.strip().splitlines() or ["no message"])[-1]
        raise InputError(f"--cpu-proxy {cpu_class}: the cpuid library did not load ({last})")
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m msfnet.bench.cpu_proxy",
        description="Run a command as if on a smaller x86 CPU class (cpuid masked for every "
        "library of the command: numpy, ONNX Runtime, OpenVINO, torch). A proxy: caches, "
        "clocks and cores stay this machine's.",
    )
    parser.add_argument("cpu_class", choices=sorted(PROXY_CLASSES), help="the class to pose as")
    parser.add_argument("command", nargs=argparse.REMAINDER, help="-- COMMAND [ARGS...]")
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("give a command after --")
    try:
        env = proxy_env(args.cpu_class)
    except (InputError, OSError) as exc:  # the library's build or its cache folder
        print(f"{parser.prog}: error: {exc}", file=sys.stderr)
        return 2
    try:
        os.execvpe(command[0], command, env)
    except OSError as exc:
        print(f"{parser.prog}: error: {command[0]}: {exc.strerror}", file=sys.stderr)
        return 2
    return 0  # not reached: exec replaced this process


if __name__ == "__main__":
    sys.exit(main())
