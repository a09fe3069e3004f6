"""What this CPU can do fast: the instruction-set features that decide the engine and precision.

Read at run time (the same wheel runs on AVX2-only, AVX-512 + VNNI/bf16 and AMX machines) with
py-cpuinfo; if that fails (odd platform, sandbox without subprocesses), /proc/cpuinfo on Linux,
and otherwise a CpuInfo without features, which simply selects the fp32 path everywhere.

py-cpuinfo probes the CPU in a subprocess, a noticeable share of a full-object msf-run
(docs/benchmark.md). Its answer is kept per boot (``~/.cache/msfnet/cpu-<boot id>.json``; the
CPU cannot change without a reboot, and every new machine or session boots afresh), so later
runs skip the probe.
"""

from __future__ import annotations

import functools
import json
import os
import platform
import stat
import sys
from collections.abc import Iterable
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

from msfnet.common.errors import InputError
from msfnet.common.vocabulary import opt

# The features that matter here, under the names Linux's /proc/cpuinfo uses.
FEATURES = ("avx2", "avx512f", "avx512_vnni", "avx512_bf16", "amx_bf16", "amx_int8", "avx_vnni")

# The smaller CPU classes a proxy run poses as (msfnet.bench.cpu_proxy masks cpuid for every
# library of the process), each with the flags of the newer extensions it keeps. The
# environment variable names the class; the cpuid library reads the same one.
PROXY_ENV = "MSFNET_CPU_PROXY"
PROXY_CLASSES: dict[str, frozenset[str]] = {
    "avx2": frozenset({"avx2"}),  # AMD Zen 2/3, Intel Core before Alder Lake, Atom / N100
    "avx2_vnni": frozenset({"avx2", "avx_vnni"}),  # Intel Alder Lake and later client cores
    "avx512_vnni": frozenset(  # Intel Cascade Lake Xeons
        {"avx2", "avx512f", "avx512dq", "avx512cd", "avx512bw", "avx512vl", "avx512_vnni"}
    ),
}
# Flags a proxy class drops unless it keeps them (prefixes, /proc/cpuinfo spelling)
_PROXY_DROPPED = ("avx512", "amx", "avx_vnni", "avx_ifma", "avx_ne_convert", "avx10")


def _norm(flag: str) -> str:
    # py-cpuinfo spells some flags both ways ("avx512vnni" and "avx512_vnni"): compare without "_"
    return flag.lower().replace("_", "").replace(".", "")


@dataclass(frozen=True)
class CpuInfo:
    model: str
    vendor: str
    cores: int  # cores this process may use (affinity), not the socket's
    avx2: bool = False
    avx512f: bool = False
    avx512_vnni: bool = False
    avx512_bf16: bool = False
    amx_bf16: bool = False
    amx_int8: bool = False
    avx_vnni: bool = False
    family: int | None = None  # the x86 family number (AMD: 25 = Zen 3 / Zen 4, 26 = Zen 5)
    source: str = "none"  # where the flags came from: py-cpuinfo, /proc/cpuinfo or none
    # only some features could be read: py-cpuinfo's own cpuid probe, without the kernel's
    # /proc/cpuinfo, never sees avx512_bf16, AMX or AVX-VNNI (cpuid leaf 7 EDX, sub-leaf 1)
    partial: bool = False
    all_flags: frozenset[str] = field(default_factory=frozenset, repr=False, compare=False)

    @classmethod
    def from_flags(
        cls,
        flags: Iterable[str],
        model: str = "unknown",
        vendor: str = "unknown",
        cores: int = 1,
        source: str = "given",
        family: int | None = None,
    ) -> CpuInfo:
        """Build from any iterable of flag names (either spelling); also how tests fake CPUs."""
        names = [str(f).lower() for f in flags]
        have = {_norm(f) for f in names}
        return cls(
            model=model,
            vendor=vendor,
            cores=cores,
            family=family,
            source=source,
            all_flags=frozenset(names),
            **{name: _norm(name) in have for name in FEATURES},
        )

    @property
    def has_bf16(self) -> bool:
        """Native bf16 arithmetic (dot products in hardware, not emulated in fp32)."""
        return self.avx512_bf16 or self.amx_bf16

    @property
    def has_vnni(self) -> bool:
        """Native int8 dot products (VNNI in AVX-512 or AVX, or AMX tiles)."""
        return self.avx512_vnni or self.avx_vnni or self.amx_int8

    @property
    def has_amx(self) -> bool:
        return self.amx_bf16 or self.amx_int8

    @property
    def avx512_on_halves(self) -> bool:
        """AMD Zen 4 (family 25 with AVX-512): its 512-bit instructions, bf16 and VNNI dot
        products included, run as two 256-bit halves, which moves which precision is fastest
        (engines.dispatch). Zen 3 (also family 25) has no AVX-512; Zen 5 is family 26 (its
        desktop and server parts run 512-bit vectors at full width)."""
        return self.vendor == "AuthenticAMD" and self.family == 25 and self.avx512f

    @property
    def int8_full_range(self) -> bool:
        """Whether int8 QDQ models with full-range (8-bit) weights compute exactly in ONNX
        Runtime here. Without VNNI its u8 x s8 kernels add pairs of products in 16 bits
        (pmaddubsw), which saturate (255 * 127 * 2 > 32767): hundreds of wrong outputs in a
        32 x 32 matmul. 7-bit weights (quantised with reduce_range) stay exact on every CPU."""
        return self.has_vnni

    def features(self) -> list[str]:
        """The FEATURES this CPU has, in FEATURES order (for reports)."""
        return [name for name in FEATURES if getattr(self, name)]

    def as_dict(self) -> dict[str, object]:
        out: dict[str, object] = {
            f.name: getattr(self, f.name) for f in fields(self) if f.name != "all_flags"
        }
        out.update(has_bf16=self.has_bf16, has_vnni=self.has_vnni, has_amx=self.has_amx)
        return out

    @property
    def detected(self) -> bool:
        """Whether any feature could be read at all (else every flag is False by default)."""
        return bool(self.all_flags)

    def summary(self) -> str:
        feats = " ".join(self.features()) or "no AVX2/AVX-512/VNNI/bf16/AMX"
        if not self.detected:
            feats = "features could not be read"
        elif self.partial:
            feats += "; bf16, AMX and AVX-VNNI unknown (no /proc/cpuinfo)"
        return f"{self.model} ({self.vendor}, {self.cores} cores; {feats})"


# The most threads any command starts: ONNX Runtime and OpenVINO create every thread up front,
# so --threads 100000 exhausts the process's thread limit (or runs for many minutes) before the
# first result. Far above any core count this toolkit meets.
MAX_THREADS = 1024


def check_threads(threads: int, option: str | None = None) -> int:
    """``threads`` if it lies in 1..MAX_THREADS: the one bound of every command and engine.
    ``option``: the setting named in the message (default ``threads``, as its reader sets it)."""
    if isinstance(threads, bool) or not isinstance(threads, int) or not 1 <= threads <= MAX_THREADS:
        option = option or opt("threads")
        raise InputError(f"{option} must be an integer in 1..{MAX_THREADS}, got {threads!r}")
    return threads


def usable_cores() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def _is_family(value: object) -> bool:
    """A usable x86 family number: an int (JSON's true / false are ints to Python: not one)."""
    return isinstance(value, int) and not isinstance(value, bool)


def _from_py_cpuinfo() -> CpuInfo:
    import cpuinfo

    data = cpuinfo.get_cpu_info()
    family = data.get("family") if _is_family(data.get("family")) else None
    model, vendor = data.get("brand_raw") or "unknown", data.get("vendor_id_raw") or "unknown"
    flags = data.get("flags") or []
    return CpuInfo.from_flags(flags, model, vendor, usable_cores(), "py-cpuinfo", family)


def _from_proc_cpuinfo(path: Path = Path("/proc/cpuinfo")) -> CpuInfo:
    model = vendor = "unknown"
    family: int | None = None
    flags: list[str] = []
    for line in path.read_text().splitlines():
        key, _, value = line.partition(":")
        key = key.strip()
        if key == "model name" and model == "unknown":
            model = value.strip()
        elif key == "vendor_id" and vendor == "unknown":
            vendor = value.strip()
        elif key == "cpu family" and family is None and value.strip().isdecimal():
            family = int(value.strip())
        elif key == "flags" and not flags:
            flags = value.split()
    return CpuInfo.from_flags(flags, model, vendor, usable_cores(), "/proc/cpuinfo", family)


def kernel_flags() -> frozenset[str]:
    """Every flag the kernel reports for this CPU (/proc/cpuinfo), empty where unreadable."""
    try:
        return _from_proc_cpuinfo().all_flags
    except OSError:
        return frozenset()


CACHE_MAX_BYTES = 1 << 16


def cache_folder() -> Path:
    """msfnet's folder in the user's cache ($XDG_CACHE_HOME, else ~/.cache); RuntimeError
    where no home is known (a container with an unknown uid)."""
    xdg = os.environ.get("XDG_CACHE_HOME", "")
    return (Path(xdg) if os.path.isabs(xdg) else Path.home() / ".cache") / "msfnet"


def cache_path() -> Path | None:
    """Where this boot's py-cpuinfo answer is kept; None where no boot id or no home is known."""
    try:
        boot = Path("/proc/sys/kernel/random/boot_id").read_text().strip()
        folder = cache_folder()
    except (OSError, RuntimeError):  # no boot id; no home (container with an unknown uid)
        return None
    if not boot or not all(c.isalnum() or c == "-" for c in boot):
        return None
    return folder / f"cpu-{boot}.json"


def _read_cache(path: Path) -> CpuInfo | None:
    """The kept answer, if it is a small regular file holding one (never follows a link or
    waits on a pipe); anything else means: probe again."""
    try:
        flags = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0)
        fd = os.open(path, flags)
    except OSError:
        return None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or st.st_size > CACHE_MAX_BYTES:
            return None
        data = json.loads(os.read(fd, CACHE_MAX_BYTES).decode())
        # a file without "family" was kept by an older msfnet: probe again
        flags, model, vendor, family = data["flags"], data["model"], data["vendor"], data["family"]
    except (OSError, ValueError, KeyError, TypeError):  # damaged: probe again
        return None
    finally:
        os.close(fd)
    if not (
        isinstance(flags, list)
        and flags
        and all(isinstance(f, str) for f in flags)
        and isinstance(model, str)
        and isinstance(vendor, str)
        and (family is None or _is_family(family))
    ):
        return None
    return CpuInfo.from_flags(flags, model, vendor, usable_cores(), "py-cpuinfo", family)


def _write_cache(path: Path, info: CpuInfo) -> None:
    """Through the one atomic writer (concurrent writers each put a whole file in place), as no
    command output; the files of earlier boots are removed."""
    from msfnet.common.files import write_json

    try:
        for old in path.parent.glob("cpu-*.json"):
            if old != path:
                old.unlink(missing_ok=True)
        record = {"flags": sorted(info.all_flags), "model": info.model, "vendor": info.vendor}
        write_json(path, {**record, "family": info.family}, output=False)
    except (OSError, InputError):  # a read-only home, or a link or pipe at the cache's name:
        pass  # only costs the probe next time


def _cpuid_library_mapped(maps: Path = Path("/proc/self/maps")) -> bool:
    """Whether the cpuid library is in this process (the loader ignores a preload it cannot
    open, so LD_PRELOAD naming it proves nothing)."""
    try:
        return "cpuid_mask-" in maps.read_text()
    except OSError:
        return False


def proxy_class() -> str | None:
    """The class this process poses as: named in PROXY_ENV with the cpuid library loaded (the
    variable alone changes nothing the libraries see, so it changes nothing here either)."""
    name = os.environ.get(PROXY_ENV)
    if name not in PROXY_CLASSES or "cpuid_mask" not in os.environ.get("LD_PRELOAD", ""):
        return None
    return name if _cpuid_library_mapped() else None


def as_proxy(info: CpuInfo, name: str) -> CpuInfo:
    """``info`` as the proxy class ``name`` shows it: the features it lacks removed, and the
    model says it is a proxy (every figure states the CPU it ran on)."""
    keep = {_norm(k) for k in PROXY_CLASSES[name]}
    flags = [f for f in info.all_flags if not f.startswith(_PROXY_DROPPED) or _norm(f) in keep]
    return CpuInfo.from_flags(
        flags,
        model=f"{info.model}, as {name} (cpuid proxy)",
        vendor=info.vendor,
        cores=info.cores,
        source=info.source,
        family=None,  # a proxy poses as a class, not as this chip: dispatch by its flags alone
    )


@functools.lru_cache(maxsize=1)
def detect_cpu() -> CpuInfo:
    """This machine's CpuInfo (as a proxy class shows it, under one), computed once per process
    and kept per boot on disk."""
    info = _detect()
    name = proxy_class()
    return info if name is None else as_proxy(info, name)


def _detect() -> CpuInfo:
    cache = cache_path()
    cached = _read_cache(cache) if cache is not None else None
    if cached is not None:
        return cached
    try:
        info = _from_py_cpuinfo()
        if info.all_flags:
            if sys.platform.startswith("linux") and not kernel_flags():
                # a sandbox hiding /proc/cpuinfo: said, and never kept, or every later run
                # of this boot would have lost bf16 too (ONNX Runtime fp32 on a bf16 CPU)
                return replace(info, partial=True)
            if cache is not None:
                _write_cache(cache, info)
            return info
    except Exception:  # any failure there (import, subprocess, parsing): use the fallback
        pass
    try:
        return _from_proc_cpuinfo()
    except OSError:
        return CpuInfo(
            model=platform.processor() or platform.machine() or "unknown",
            vendor="unknown",
            cores=usable_cores(),
        )


__all__ = [
    "FEATURES",
    "MAX_THREADS",
    "PROXY_CLASSES",
    "PROXY_ENV",
    "CpuInfo",
    "as_proxy",
    "cache_folder",
    "cache_path",
    "check_threads",
    "detect_cpu",
    "kernel_flags",
    "proxy_class",
    "usable_cores",
]
