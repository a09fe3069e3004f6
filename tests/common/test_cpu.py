"""CPU feature detection (common/cpu.py): flag spellings, fallbacks, caching."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from msfnet.common import cpu as cpu_mod
from msfnet.common.cpu import CpuInfo, detect_cpu

ZEN3 = ["fpu", "sse4_2", "avx", "avx2", "fma", "f16c"]
ZEN5 = [*ZEN3, "avx512f", "avx512bw", "avx512vnni", "avx512_bf16"]  # py-cpuinfo mixes spellings
SAPPHIRE = [
    *ZEN3,
    "avx512f",
    "avx512_vnni",
    "avx512_bf16",
    "avx_vnni",
    "amx_bf16",
    "amx_int8",
    "amx_tile",
]


@pytest.mark.parametrize(
    ("flags", "bf16", "vnni", "amx"),
    [
        (ZEN3, False, False, False),
        (ZEN5, True, True, False),
        (SAPPHIRE, True, True, True),
        (["avx2", "avx_vnni"], False, True, False),  # Alder Lake-like: VNNI without AVX-512
        ([], False, False, False),
    ],
)
def test_derived_features(flags: list[str], bf16: bool, vnni: bool, amx: bool) -> None:
    info = CpuInfo.from_flags(flags)
    assert (info.has_bf16, info.has_vnni, info.has_amx) == (bf16, vnni, amx)
    assert info.avx2 == ("avx2" in flags)


def test_both_spellings_are_one_feature() -> None:
    a = CpuInfo.from_flags(["AVX512VNNI", "avx512bf16"])
    b = CpuInfo.from_flags(["avx512_vnni", "avx512_bf16"])
    assert a.avx512_vnni and a.avx512_bf16 and a == b
    # avx_vnni (VEX) and avx512_vnni (EVEX) are different features
    assert not CpuInfo.from_flags(["avx_vnni"]).avx512_vnni


def test_proc_cpuinfo_fallback_parses_first_processor(tmp_path: Path) -> None:
    text = (
        "processor\t: 0\nvendor_id\t: AuthenticAMD\ncpu family\t: 26\nmodel name\t: AMD EPYC 9R45\n"
        "flags\t\t: fpu avx2 avx512f avx512_vnni avx512_bf16\n\n"
        "processor\t: 1\nvendor_id\t: AuthenticAMD\nmodel name\t: AMD EPYC 9R45\n"
        "flags\t\t: fpu avx2\n"
    )
    (tmp_path / "cpuinfo").write_text(text)
    info = cpu_mod._from_proc_cpuinfo(tmp_path / "cpuinfo")
    assert (info.model, info.vendor, info.source) == (
        "AMD EPYC 9R45",
        "AuthenticAMD",
        "/proc/cpuinfo",
    )
    assert info.has_bf16 and info.has_vnni and not info.has_amx
    assert info.family == 26 and not info.avx512_on_halves  # Zen 5: full-width AVX-512


@pytest.mark.parametrize(
    ("family", "expected"), [(25, 25), ("25", None), (True, None), (None, None)]
)
def test_py_cpuinfo_family_is_read_and_odd_values_dropped(
    monkeypatch: pytest.MonkeyPatch, family: object, expected: int | None
) -> None:
    """The normal path: py-cpuinfo's answer, whose integer family makes a Zen 4 a Zen 4."""
    import cpuinfo

    answer = {
        "flags": ["avx2", "avx512f", "avx512_vnni", "avx512_bf16"],
        "brand_raw": "AMD EPYC",
        "vendor_id_raw": "AuthenticAMD",
        "family": family,
    }
    monkeypatch.setattr(cpuinfo, "get_cpu_info", lambda: answer)
    info = cpu_mod._from_py_cpuinfo()
    assert info.family == expected and info.avx512_on_halves is (expected == 25)


@pytest.mark.parametrize(
    ("vendor", "family", "flags", "halves"),
    [
        ("AuthenticAMD", 25, ["avx2", "avx512f", "avx512_bf16"], True),  # Zen 4
        ("AuthenticAMD", 25, ["avx2"], False),  # Zen 3: no AVX-512
        ("AuthenticAMD", 26, ["avx2", "avx512f", "avx512_bf16"], False),  # Zen 5
        ("GenuineIntel", 6, ["avx2", "avx512f", "avx512_bf16"], False),  # Cooper Lake
        ("HygonGenuine", 25, ["avx2", "avx512f", "avx512_bf16"], False),  # not AMD's family
        ("AuthenticAMD", None, ["avx2", "avx512f", "avx512_bf16"], False),  # family not known
    ],
)
def test_avx512_on_halves_is_amd_zen4_only(
    vendor: str, family: int | None, flags: list[str], halves: bool
) -> None:
    cpu = CpuInfo.from_flags(flags, vendor=vendor, family=family)
    assert cpu.avx512_on_halves is halves
    # a cpuid proxy poses as a class (its flags), not as this chip: no family
    for name in ("avx2", "avx512_vnni"):
        proxy = cpu_mod.as_proxy(cpu, name)
        assert proxy.family is None and not proxy.avx512_on_halves


def test_detect_falls_back_when_py_cpuinfo_fails(monkeypatch: pytest.MonkeyPatch) -> None:
    def broken() -> CpuInfo:
        raise RuntimeError("no cpuid here")

    monkeypatch.setattr(cpu_mod, "_from_py_cpuinfo", broken)
    monkeypatch.setattr(cpu_mod, "cache_path", lambda: None)  # no answer kept from earlier
    detect_cpu.cache_clear()
    try:
        info = detect_cpu()
        expected = "/proc/cpuinfo" if Path("/proc/cpuinfo").is_file() else "none"
        assert info.source == expected and info.cores >= 1
    finally:
        detect_cpu.cache_clear()


def test_detect_is_cached_and_agrees_with_the_kernel() -> None:
    info = detect_cpu()
    assert detect_cpu() is info
    assert info.cores >= 1 and info.model
    assert info.summary().startswith(info.model)
    if sys.platform.startswith("linux") and Path("/proc/cpuinfo").is_file():
        # two independent readings of the same CPU must agree on every feature that matters
        assert cpu_mod._from_proc_cpuinfo().features() == info.features()


def test_the_probe_is_kept_per_boot_and_a_damaged_copy_is_ignored(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    if cpu_mod.cache_path() is None:
        pytest.skip("no boot id on this platform: nothing is kept")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    probes: list[int] = []
    fake = CpuInfo.from_flags(
        ["avx2", "avx512_bf16", "amx_bf16"],
        model="Fake Xeon",
        vendor="GenuineIntel",
        source="py-cpuinfo",
        family=6,
    )

    def probe() -> CpuInfo:
        probes.append(1)
        return fake

    monkeypatch.setattr(cpu_mod, "_from_py_cpuinfo", probe)
    try:
        for _ in range(2):  # two "processes": the second reads the kept answer
            detect_cpu.cache_clear()
            info = detect_cpu()
            assert (info.model, info.features(), info.source, info.family) == (
                "Fake Xeon",
                ["avx2", "avx512_bf16", "amx_bf16"],
                "py-cpuinfo",
                6,
            )
        assert len(probes) == 1
        path = cpu_mod.cache_path()
        assert path is not None and path.parent == tmp_path / "msfnet"
        old = '{"flags": ["avx2"], "model": "x", "vendor": "y"}'  # an older msfnet's: no family
        bad = '{"flags": ["avx2"], "model": "x", "vendor": "y", "family": "25"}'
        for damage in (
            "{not json",
            '{"flags": [], "model": "x", "vendor": "y"}',
            "[1, 2]",
            old,
            bad,
        ):
            path.write_text(damage)
            detect_cpu.cache_clear()
            assert detect_cpu().model == "Fake Xeon"  # probed again and rewritten
        assert len(probes) == 6
    finally:
        detect_cpu.cache_clear()


def test_no_home_and_odd_cache_files_only_cost_the_probe(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    if cpu_mod.cache_path() is None:
        pytest.skip("no boot id on this platform: nothing is kept")
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)

    def no_home() -> Path:
        raise RuntimeError("Could not determine home directory")

    monkeypatch.setattr(Path, "home", staticmethod(no_home))
    assert cpu_mod.cache_path() is None  # and detection still works, without a cache
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/dir")  # ignored: not absolute
    assert cpu_mod.cache_path() is None
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    path = cpu_mod.cache_path()
    assert path is not None
    path.parent.mkdir(parents=True)
    os.mkfifo(path)  # a pipe where the file should be: never waited on
    assert cpu_mod._read_cache(path) is None
    path.unlink()
    target = tmp_path / "elsewhere.json"
    target.write_text('{"flags": ["amx_bf16"], "model": "x", "vendor": "y"}')
    path.symlink_to(target)  # a link is not followed
    assert cpu_mod._read_cache(path) is None
    path.unlink()
    (path.parent / "cpu-old-boot.json").write_text("{}")
    from msfnet.common import files

    files.forget_written()
    cpu_mod._write_cache(path, CpuInfo.from_flags(["avx2"], model="m", vendor="v"))
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # earlier boots removed
    assert files.written_outputs() == []  # a cache, never reported as a command's output
    info = cpu_mod._read_cache(path)
    assert info is not None and info.features() == ["avx2"]


@pytest.mark.parametrize(
    ("name", "features"),
    [
        ("avx2", ["avx2"]),
        ("avx2_vnni", ["avx2", "avx_vnni"]),
        ("avx512_vnni", ["avx2", "avx512f", "avx512_vnni"]),
    ],
)
def test_a_proxy_class_shows_only_its_features(name: str, features: list[str]) -> None:
    real = CpuInfo.from_flags(SAPPHIRE, model="Xeon", vendor="GenuineIntel", cores=2)
    shown = cpu_mod.as_proxy(real, name)
    assert shown.features() == features
    assert not shown.has_bf16 and not shown.has_amx
    assert shown.model == f"Xeon, as {name} (cpuid proxy)"  # every figure names the proxy
    assert not any(f.startswith("amx") for f in shown.all_flags)
    assert {"fpu", "sse4_2", "fma"} <= shown.all_flags  # older extensions stay


def test_the_proxy_variable_alone_changes_nothing(monkeypatch: pytest.MonkeyPatch) -> None:
    # without the cpuid library the libraries see the whole CPU, so detection must too
    monkeypatch.setenv(cpu_mod.PROXY_ENV, "avx2")
    monkeypatch.delenv("LD_PRELOAD", raising=False)
    assert cpu_mod.proxy_class() is None
    monkeypatch.setenv("LD_PRELOAD", "/x/cpuid_mask-0123.so")
    # named but not loaded (the loader skips a preload it cannot open): still the whole CPU
    assert cpu_mod.proxy_class() is None
    monkeypatch.setattr(cpu_mod, "_cpuid_library_mapped", lambda: True)
    assert cpu_mod.proxy_class() == "avx2"
    monkeypatch.setenv(cpu_mod.PROXY_ENV, "avx9000")
    assert cpu_mod.proxy_class() is None


def test_a_probe_without_proc_cpuinfo_is_marked_partial_and_not_kept(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """review-dispatch23.md 1: py-cpuinfo's cpuid probe alone lacks avx512_bf16 / AMX /
    AVX-VNNI; kept as this boot's answer, every later run lost bf16."""
    if cpu_mod.cache_path() is None or not sys.platform.startswith("linux"):
        pytest.skip("no boot id / not Linux: nothing is kept")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    cpuid_only = CpuInfo.from_flags(["avx2", "avx512f"], model="Fake EPYC", source="py-cpuinfo")
    monkeypatch.setattr(cpu_mod, "_from_py_cpuinfo", lambda: cpuid_only)
    monkeypatch.setattr(cpu_mod, "kernel_flags", lambda: frozenset())
    try:
        detect_cpu.cache_clear()
        info = detect_cpu()
        assert info.partial and info.avx512f and not info.has_bf16
        assert "bf16, AMX and AVX-VNNI unknown" in info.summary()
        assert not (tmp_path / "msfnet").exists() or not any((tmp_path / "msfnet").iterdir())
        monkeypatch.setattr(cpu_mod, "kernel_flags", lambda: frozenset({"avx2"}))
        detect_cpu.cache_clear()
        assert not detect_cpu().partial  # /proc/cpuinfo readable: whole, and kept
        assert any((tmp_path / "msfnet").glob("cpu-*.json"))
    finally:
        detect_cpu.cache_clear()
