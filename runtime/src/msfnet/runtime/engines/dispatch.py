"""Which engine, precision and device run a model here: ``choose_engine`` decides,
``open_engine`` loads.

``choose_engine`` is a pure function of the CPU's features (cpu.CpuInfo), the installed engines,
the model's metadata (fp32 / int8, monolithic / staged) and the requested device, so every rule
below is tested on faked CPUs and engines. Rules, in order:

0. ``--device`` other than cpu (``resolve_device``): CUDA / TensorRT run through ONNX Runtime's
   providers, GPU / NPU through OpenVINO's plugins, the model's own precision (fp32 exports in
   fp32); a device that is not present is an error naming what is, never a silent CPU run.
1. ``--engine`` / ``--precision`` override. An override that cannot be honoured is an error,
   never a silent substitute: bf16 needs OpenVINO (ONNX Runtime's CPU provider has no bf16 path
   on x86) and a CPU with native bf16; int8 needs an int8 export; an int8 export runs only int8.
2. int8 models run int8, through OpenVINO where it was measured as fast as ONNX Runtime int8 or
   faster on this CPU class (``OV_INT8_SPEEDUP``; closer to fp32 there), else through ONNX
   Runtime (its int8 kernels use VNNI / AMX where present and still beat fp32 with AVX2 alone).
3. fp32 models: bf16 through OpenVINO when the CPU has native bf16 (avx512_bf16 or AMX),
   OpenVINO is installed and bf16 is measured within the accuracy bound (``MEASURED``).
4. fp32 models otherwise: fp32 through OpenVINO on the CPU classes where it was measured faster
   than ONNX Runtime fp32 in the same run (``OV_FP32_SPEEDUP``), else ONNX Runtime fp32, the
   fallback (also whenever OpenVINO is missing or cannot compile the model).

The bundled model comes as a pair, fp32 and int8 (``bundled_precision`` picks which one
``Model()`` / ``msf-run`` open when no model is given): int8 where it was measured faster than
the fp32 file's own default on the CPU class: fp32 (no native bf16, or no OpenVINO for it;
``INT8_SPEEDUP``) or bf16 (AMD Zen 4, AVX-512 on 256-bit halves; ``INT8_OVER_BF16``);
fp32 otherwise, and whenever a precision other than int8 or a device is asked for.

A reduced precision is a *default* only within ACCURACY_BOUND_DEG (0.5 deg) mean of ONNX Runtime
fp32 on real data (``MEASURED``, checked by ``default_allowed``); a path above it runs only on
request. The dated measurements behind both tables (commands, CPUs, models) are in
docs/benchmark.md, "Dispatch measurements".
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path

from msfnet.common.cpu import CpuInfo, check_threads
from msfnet.common.errors import InputError
from msfnet.common.vocabulary import opt
from msfnet.runtime.contract import ModelInfo
from msfnet.runtime.engines.base import (
    ENGINES,
    Engine,
    ModelFile,
    check_int8_exact,
    engine_name,
    installed_engines,
    model_precision,
    precision_name,
    read_model_file,
)

ACCURACY_BOUND_DEG = 0.5


@dataclass(frozen=True)
class Measured:
    """Deviation from ORT fp32 on ball crops: light count -> (mean deg, max deg)."""

    deg: dict[int, tuple[float, float]]

    @property
    def worst_mean(self) -> float:
        return max(mean for mean, _ in self.deg.values())


# (engine, precision, staged) -> measurement (docs/benchmark.md, "Dispatch measurements").
# int8: the bundled twin's recipe (percentile ranges, 7-bit weights, OpenVINO's convolution
# outputs in f32); exports with min/max ranges are judged by MINMAX_INT8_MEASURED below.
MEASURED: dict[tuple[str, str, bool], Measured] = {
    ("onnxruntime", "int8", False): Measured({32: (0.265, 1.377), 96: (0.388, 2.723)}),
    ("onnxruntime", "int8", True): Measured({32: (0.310, 1.215), 96: (0.426, 2.725)}),
    ("openvino", "bf16", False): Measured({32: (0.093, 0.331), 96: (0.078, 0.319)}),
    ("openvino", "bf16", True): Measured({32: (0.091, 0.329), 96: (0.076, 0.269)}),
    ("openvino", "int8", False): Measured({32: (0.291, 1.207), 96: (0.396, 2.733)}),
    ("openvino", "int8", True): Measured({32: (0.170, 0.763), 96: (0.295, 2.535)}),
}
# int8 exports with min/max activation ranges (older msf-export: their msfnet.quantization
# metadata counts no ranges set from percentiles), same crops
MINMAX_INT8_MEASURED: dict[tuple[str, bool], Measured] = {
    ("onnxruntime", False): Measured({32: (0.673, 2.934), 96: (0.917, 4.886)}),
    ("onnxruntime", True): Measured({32: (0.673, 2.934), 96: (0.917, 4.886)}),
    ("openvino", False): Measured({32: (0.754, 2.969), 96: (1.004, 4.829)}),
    ("openvino", True): Measured({32: (0.673, 2.933), 96: (0.917, 4.884)}),
}


def _up(deg: float) -> str:
    """``deg`` rounded up to 0.01 for a "within" claim (0.295 reads 0.30, not 0.29)."""
    return f"{math.ceil(round(deg * 100, 6)) / 100:.2f}"


def default_allowed(engine: str, precision: str, staged: bool) -> bool:
    """Whether this path may be chosen without being asked for: fp32 always; a reduced precision
    only when measured within ACCURACY_BOUND_DEG mean of fp32 at every light count measured."""
    if precision == "fp32":
        return True
    m = MEASURED.get((engine, precision, staged))
    return m is not None and m.worst_mean <= ACCURACY_BOUND_DEG


def cpu_class(cpu: CpuInfo) -> str:
    """The CPU class speed measurements are kept for: amx; zen4 (AMD Zen 4: AVX-512 with bf16
    and VNNI on 256-bit halves, CpuInfo.avx512_on_halves); avx512-bf16 (other AVX-512 bf16
    without AMX: AMD Zen 5, Intel Cooper Lake); avx512; avx2; other (no AVX2: old x86 or ARM;
    nothing measured there). A Zen 4 whose hypervisor hides bf16 or VNNI falls to the flag
    classes here (int8_class still names it zen4 while it shows VNNI): the measured figures
    are for the whole chip."""
    if cpu.has_amx:
        return "amx"
    if cpu.avx512_on_halves and cpu.avx512_bf16 and cpu.avx512_vnni:
        return "zen4"
    if cpu.avx512_bf16:
        return "avx512-bf16"
    if cpu.avx512f:
        return "avx512"
    return "avx2" if cpu.avx2 else "other"


# CPU class -> OpenVINO fp32 over ONNX Runtime fp32, same run, same fp32 model, 2 threads, the
# median of interleaved runs (docs/benchmark.md, "Dispatch measurements"). Normals identical
# (0.000 deg). A class missing here keeps ONNX Runtime fp32: nothing was measured there.
OV_FP32_SPEEDUP: dict[str, float] = {
    "avx2": 1.36,  # AMD EPYC, AVX2 only
    "amx": 1.43,  # Intel Xeon with AMX
    "zen4": 1.11,  # AMD EPYC Zen 4, natively
}


def ov_fp32_preferred(cpu: CpuInfo) -> bool:
    """OpenVINO fp32 is the fp32 default on this CPU class: measured faster than ORT fp32."""
    return OV_FP32_SPEEDUP.get(cpu_class(cpu), 0.0) > 1.0


def int8_class(cpu: CpuInfo) -> str:
    """The CPU class int8 speed is kept for: amx; zen4 (AMD Zen 4, measured natively); vnni
    (other AVX-512 VNNI); avx2_vnni (AVX-VNNI on 256-bit vectors, no AVX-512); avx512 (AVX-512
    without VNNI); avx2 (no VNNI: int8 products summed in 16-bit pairs, which 7-bit weights
    keep exact); other (no AVX2)."""
    if cpu.has_amx:
        return "amx"
    if cpu.avx512_on_halves and cpu.avx512_vnni:
        return "zen4"
    if cpu.avx512_vnni:
        return "vnni"
    if cpu.avx_vnni:
        return "avx2_vnni"
    if cpu.avx512f:
        return "avx512"
    return "avx2" if cpu.avx2 else "other"


# int8 class -> an int8 export over the same model in fp32 through the same engine, same run,
# the slower engine's ratio (docs/benchmark.md, "Dispatch measurements": workloads, runs and
# which classes were measured in the cpuid proxy). avx512 (AVX-512 without VNNI) and other
# were not measured: the fp32 file there.
INT8_SPEEDUP: dict[str, float] = {
    "avx2": 1.52,  # OpenVINO 1.52-1.55x, ONNX Runtime 1.89x (7-bit weights)
    "avx2_vnni": 1.74,
    "vnni": 1.96,  # ONNX Runtime 1.96x, OpenVINO 2.11x
    "zen4": 1.70,  # ONNX Runtime 1.92x cat, 1.50x ball; OpenVINO 2.29x / 1.44x
    "amx": 1.80,  # ONNX Runtime 1.80x, OpenVINO 2.98x (bf16 is faster still: 4.7x)
}
# int8 class -> OpenVINO int8 over ONNX Runtime int8: the bundled twin, msf-run end to end,
# the geometric mean of the 12-light psmImages cat and the 8-light full DiLiGenT ball
# (docs/benchmark.md, "Dispatch measurements").
OV_INT8_SPEEDUP: dict[str, float] = {
    "avx2": 1.00,  # cat 5.58 against 5.53 s, ball 2.01 against 2.05 s
    "avx2_vnni": 1.00,  # cat 4.25 / 4.11 s, ball 1.64 / 1.69 s
    "vnni": 1.07,  # cat 3.14 / 3.37 s, ball 1.41 / 1.51 s
    "zen4": 1.19,  # cat 3.39 / 4.35 s, ball 1.77 / 1.95 s
    "amx": 1.24,  # cat 2.70 / 3.47 s, ball 1.16 / 1.37 s
}
# CPU class -> the bundled int8 twin on OpenVINO over the fp32 file in bf16 on OpenVINO, where
# bf16 is the fp32 file's default: above 1 the twin is the default although the CPU has native
# bf16 (both within the accuracy bound). A class missing here (not measured) keeps bf16.
INT8_OVER_BF16: dict[str, float] = {
    "zen4": 1.16,  # AMD EPYC Zen 4, natively: the cat and the 8-light full ball, end to end
    "amx": 0.63,  # Intel Xeon with AMX: bf16 tiles beat int8 on these convolutions
}


# OpenVINO stays the int8 default down to this ratio (the run-to-run spread of the figures
# above) for exports where it was measured the closer to fp32 (ov_int8_closer, from MEASURED)
OV_INT8_MIN_SPEEDUP = 0.95


def ov_int8_closer(info: ModelInfo | None = None) -> bool:
    """Whether OpenVINO's int8 was measured closer to fp32 than ONNX Runtime's for this kind of
    export (``info``; None: the bundled kind, staged with percentile ranges). Mixed-precision
    exports were not measured on OpenVINO: no."""
    if info is not None and info.metadata.get("msfnet.variant") == "int8-mixed":
        return False
    staged = True if info is None else info.staged
    if info is not None and _minmax_int8(info):
        ov = MINMAX_INT8_MEASURED.get(("openvino", staged))
        ort = MINMAX_INT8_MEASURED.get(("onnxruntime", staged))
    else:
        ov = MEASURED.get(("openvino", "int8", staged))
        ort = MEASURED.get(("onnxruntime", "int8", staged))
    return ov is not None and ort is not None and ov.worst_mean < ort.worst_mean


def ov_int8_preferred(cpu: CpuInfo, info: ModelInfo | None = None) -> bool:
    """OpenVINO is the int8 default for this CPU class and export (``info``; None: the bundled
    kind): measured faster than ONNX Runtime int8, or as fast (within OV_INT8_MIN_SPEEDUP) where
    it was also measured closer to fp32 (``ov_int8_closer``)."""
    ratio = OV_INT8_SPEEDUP.get(int8_class(cpu), 0.0)
    return ratio > 1.0 or (ratio >= OV_INT8_MIN_SPEEDUP and ov_int8_closer(info))


# --device names: where each runs (engine) and that engine's name for it
DEVICE_TARGETS = {
    "cpu": ("", ""),  # the CPU rules above
    "cuda": ("onnxruntime", "CUDAExecutionProvider"),
    "tensorrt": ("onnxruntime", "TensorrtExecutionProvider"),
    "gpu": ("openvino", "GPU"),  # Intel integrated / discrete GPU; gpu.1 for the second one
    "npu": ("openvino", "NPU"),  # Intel NPU (Core Ultra)
}
DEVICE_HINTS = {
    "cuda": "it needs the onnxruntime-gpu package and an NVIDIA GPU with its CUDA libraries",
    "tensorrt": "it needs onnxruntime-gpu built with TensorRT and NVIDIA's TensorRT libraries",
    "gpu": "it needs an Intel GPU and its compute runtime (OpenCL / Level Zero driver)",
    "npu": "it needs an Intel NPU (Core Ultra) and its driver",
}


@dataclass(frozen=True)
class Device:
    """A non-CPU device to run on: ``name`` as asked (cuda, tensorrt, gpu, gpu.1, npu), the
    engine that drives it and that engine's name for it (ORT provider or OpenVINO device)."""

    name: str
    engine: str
    target: str


def available_devices(engine: str) -> list[str]:
    """What ``engine`` can run on here: ORT execution providers or OpenVINO device names
    ([] when the engine is not installed). Imports the engine: call only for a --device."""
    try:
        if engine == "onnxruntime":
            import onnxruntime

            return list(onnxruntime.get_available_providers())
        from msfnet.runtime.engines.openvino import import_openvino

        return list(import_openvino().Core().available_devices)
    except (ImportError, InputError):
        return []


def resolve_device(
    name: str | None,
    ort_providers: Iterable[str] | None = None,
    ov_devices: Iterable[str] | None = None,
) -> Device | None:
    """``--device`` -> the Device to run on, None for the CPU. ``ort_providers`` /
    ``ov_devices``: what the engines offer (default: asked, see available_devices; tests pass
    fakes). InputError, in one line, for an unknown name or a device that is not here."""
    if name is None:
        return None
    asked = name.strip().lower()
    base, _, index = asked.partition(".")
    if base not in DEVICE_TARGETS or (
        index and (base not in ("gpu", "npu") or not index.isdigit())
    ):
        raise InputError(
            f"{opt('device', name, quote=True)}: expected one of "
            f"{', '.join(DEVICE_TARGETS)} (gpu.N for the N-th OpenVINO GPU)",
            option="device",
        )
    if base == "cpu":
        return None
    engine, target = DEVICE_TARGETS[base]
    if engine == "onnxruntime":
        have = list(ort_providers if ort_providers is not None else available_devices(engine))
        if target not in have:
            raise InputError(
                f"{opt('device', asked)}: ONNX Runtime has no {target} here (providers: "
                f"{', '.join(have) or 'none'}); {DEVICE_HINTS[base]}",
                option="device",
            )
        return Device(asked, engine, target)
    have = list(ov_devices if ov_devices is not None else available_devices(engine))
    target = target + (f".{index}" if index else "")
    # OpenVINO names one GPU "GPU", several "GPU.0", "GPU.1", ...; "GPU.0" is also the name
    # of a lone "GPU" (OpenVINO accepts it)
    found = [d for d in have if d.upper() == target or d.upper().startswith(target + ".")]
    if not found and index == "0" and base.upper() in (d.upper() for d in have):
        found = [base.upper()]
    if not found:
        raise InputError(
            f"{opt('device', asked)}: OpenVINO sees no {target} here (devices: "
            f"{', '.join(have) or 'none, or OpenVINO is not installed'}); {DEVICE_HINTS[base]}",
            option="device",
        )
    return Device(asked, engine, found[0] if index else target)


@dataclass(frozen=True)
class EngineChoice:
    engine: str  # onnxruntime | openvino
    precision: str  # fp32 | bf16 | int8
    reason: str  # one line for logs and profile.json: why this engine and precision
    model: Path | None = None  # the model to open (None when decided from a ModelInfo alone)
    device: Device | None = None  # None: the CPU
    # the read of ``model`` the choice was made from: open_engine opens from it (no second read)
    file: ModelFile | None = field(default=None, compare=False, repr=False)


# int8 exports with their sensitive convs in fp32 (msf-export --variant int8-mixed): mean deg
# from the fp32 graph on DiLiGenT ball / bear / harvest 128 px crops (docs/benchmark.md)
MIXED_INT8_MEASURED = Measured({12: (0.253, 1.66), 96: (0.430, 4.48)})


def _minmax_int8(info: ModelInfo) -> bool:
    """An int8 export whose activation ranges are min/max ones (made before percentile ranges;
    a file without the quantisation summary counts as one)."""
    ranged = info.quantization().get("ranges_from_percentiles")  # damaged: the older kind
    return not (isinstance(ranged, int) and ranged > 0)


def _bound_note(
    engine: str, precision: str, staged: bool, mixed: bool = False, minmax: bool = False
) -> str:
    """A warning for the reason string when a path runs that is no default for accuracy."""
    if mixed:
        return (
            f"; mixed precision: measured {MIXED_INT8_MEASURED.worst_mean:.2f} deg mean from "
            "fp32 on DiLiGenT crops, within the bound"
        )
    if minmax:
        m = MINMAX_INT8_MEASURED.get((engine, staged))
    else:
        m = MEASURED.get((engine, precision, staged))
    if m is None or m.worst_mean <= ACCURACY_BOUND_DEG:
        return ""
    return (
        f"; note: measured {m.worst_mean:.2f} deg mean from fp32 on DiLiGenT ball crops, "
        f"above the {ACCURACY_BOUND_DEG} deg bound for defaults"
    )


def _int8_note(engine: str, info: ModelInfo) -> str:
    """The bound note of an int8 export: mixed, min/max (older exports) or percentile ranges."""
    mixed = info.metadata.get("msfnet.variant") == "int8-mixed"
    minmax = not mixed and _minmax_int8(info)
    note = _bound_note(engine, "int8", info.staged, mixed, minmax)
    if note and minmax:
        note += " (min/max ranges: an export made now sets percentile ones, within the bound)"
    return note


def _install_hint(engine: str) -> str:
    # OpenVINO is part of the base install: missing means a trimmed or broken environment
    return "pip install openvino" if engine == "openvino" else "pip install onnxruntime"


# What likely_engine assumes before a file is read: the bundled kind of export (fp32, staged).
_FP32_GUESS = ModelInfo(
    path=Path("model.onnx"),
    train_lights=32,
    input_multiple=4,
    static_shape=None,
    precision="fp32",
    metadata={},
    staged=True,
)


def likely_engine(
    cpu: CpuInfo,
    installed: Iterable[str],
    requested_engine: str | None = None,
    requested_precision: str | None = None,
    device: Device | None = None,
) -> str:
    """The engine ``choose_engine`` will pick before the model's metadata is known: its own
    rules applied to an fp32 staged export (the bundled kind; int8 exports are the exception),
    so that engine reads the file and compiles that same read. A wrong guess costs one more
    read, never a wrong choice: the choice itself is made from the metadata; requests the
    rules refuse are left to ONNX Runtime's reader, whose refusals word every error."""
    try:
        choice = choose_engine(
            _FP32_GUESS, cpu, installed, requested_engine, requested_precision, device
        )
    except InputError:
        return "onnxruntime"
    return choice.engine


_INT8_GUESS = replace(
    _FP32_GUESS,
    path=Path("model_int8.onnx"),
    precision="int8",
    metadata={"msfnet.quantization": '{"ranges_from_percentiles": 1, "reduce_range": true}'},
)


@dataclass(frozen=True)
class BundledChoice:
    """Which of the bundled pair to open: ``precision`` fp32 or int8, and ``reason`` (one
    line, empty for the plain fp32 case) for the choice line of logs and profile.json."""

    precision: str
    reason: str = ""


def bundled_precision(
    cpu: CpuInfo,
    installed: Iterable[str],
    requested_engine: str | None = None,
    requested_precision: str | None = None,
    device: Device | None = None,
) -> BundledChoice:
    """The bundled model's file for this CPU and request. Nothing asked for: int8 where it was
    measured faster than the fp32 file's own default on this CPU class (``INT8_SPEEDUP`` over
    fp32; ``INT8_OVER_BF16`` over bf16, OpenVINO's int8) within the accuracy bound, else
    fp32. ``--precision int8``: the int8 file (any CPU or device); any other request (a
    precision, an engine, a device) keeps the fp32 file. Requests the rules refuse are left
    to ``choose_engine``, which words the error."""
    want = precision_name(requested_precision) if requested_precision else None
    if want == "int8":
        return BundledChoice("int8", f"bundled int8 model: {opt('precision', 'int8')} given")
    if want is not None or device is not None or requested_engine is not None:
        # a named engine alone keeps the fp32 file: `--engine onnxruntime` stays the fp32
        # reference it always was
        return BundledChoice("fp32")
    fp32 = choose_engine(_FP32_GUESS, cpu, installed)  # nothing requested: nothing refused
    int8 = choose_engine(_INT8_GUESS, cpu, installed)
    if fp32.precision == "bf16":  # measured against OpenVINO's int8 only (INT8_OVER_BF16)
        klass = cpu_class(cpu)
        speedup = INT8_OVER_BF16.get(klass, 0.0) if int8.engine == "openvino" else 0.0
    else:
        klass = int8_class(cpu)
        speedup = INT8_SPEEDUP.get(klass, 0.0)
    over = fp32.precision
    if speedup <= 1.0 or not default_allowed(int8.engine, "int8", True):
        return BundledChoice("fp32")
    m = MEASURED[(int8.engine, "int8", True)]
    # features read without /proc/cpuinfo: bf16 unknown, not absent
    unknown = f" ({_no_bf16(cpu)})" if over != "bf16" and not cpu.has_bf16 and cpu.partial else ""
    return BundledChoice(
        "int8",
        f"bundled int8 model: the fp32 one would run in {over} here{unknown}; int8 measured "
        f"{speedup}x {over} on this CPU class ({klass}), within {_up(m.worst_mean)} deg mean "
        f"of fp32 on DiLiGenT ball crops at {' and '.join(map(str, sorted(m.deg)))} lights",
    )


def read_for(path: str | Path, engine: str) -> ModelFile:
    """Read ``path`` with ``engine``'s reader: OpenVINO's keeps its graph for the OpenVINO
    engine to compile; ONNX Runtime's gives the metadata alone (its sessions read the file
    themselves). An OpenVINO that cannot be imported or cannot read the file leaves it to ONNX
    Runtime, whose refusals are the one-line errors of every path."""
    if engine == "openvino":
        from msfnet.runtime.engines.openvino import import_openvino, read_openvino

        try:
            import_openvino()
        except InputError:  # a broken install: open_chosen falls back to ONNX Runtime
            pass
        else:
            return read_openvino(path)
    return ModelFile(read_model_file(path))


def choose_engine(
    model: str | Path | ModelInfo | ModelFile,
    cpu: CpuInfo,
    installed: Iterable[str],
    requested_engine: str | None = None,
    requested_precision: str | None = None,
    device: Device | None = None,
) -> EngineChoice:
    """Pick the engine and precision for ``model`` on ``cpu`` (rules in the module docstring).

    ``model``: an msfnet ONNX path (read once, by the engine ``likely_engine`` expects; the
    choice keeps the read for open_engine), a ModelFile or a ModelInfo. ``installed``: engine
    names importable here (engines.installed_engines()). ``device``: resolve_device's answer
    for --device (None: the CPU). Raises InputError for overrides that cannot be honoured.
    """
    installed = list(installed)
    if isinstance(model, ModelInfo):
        file = ModelFile(model)
    elif isinstance(model, ModelFile):
        file = model
    else:
        reader = likely_engine(cpu, installed, requested_engine, requested_precision, device)
        file = read_for(model, reader)
    ask = _Ask(
        file,
        {engine_name(e) for e in installed},
        engine_name(requested_engine) if requested_engine else None,
        precision_name(requested_precision) if requested_precision else None,
    )
    if ask.engine is not None and ask.engine not in ask.have:
        raise InputError(
            f"{opt('engine', ask.engine)}: not installed ({_install_hint(ask.engine)})",
            option="engine",
        )
    if device is not None:  # rule 0: the device decides the engine, the model the precision
        return _on_device(ask, device)
    if ask.own == "int8":
        return _for_int8(ask, cpu)
    return _for_fp32(ask, cpu)


@dataclass(frozen=True)
class _Ask:
    """A model file and what was asked of it: the engines here, the engine and precision
    requested (None: this CPU's default)."""

    file: ModelFile
    have: set[str]
    engine: str | None
    precision: str | None

    @property
    def info(self) -> ModelInfo:
        return self.file.info

    @property
    def own(self) -> str:
        return model_precision(self.info)

    @property
    def what(self) -> str:
        return f"{self.own} {'staged ' if self.info.staged else ''}model"

    def pick(self, engine: str, precision: str, why: str) -> EngineChoice:
        reason = f"{engine} {precision}: {why}"
        return EngineChoice(engine, precision, reason, self.info.path, file=self.file)


def _on_device(ask: _Ask, device: Device) -> EngineChoice:
    if ask.engine is not None and ask.engine != device.engine:
        raise InputError(
            f"{opt('device', device.name)} runs on {device.engine}, "
            f"not {opt('engine', ask.engine)}",
            option="device",
        )
    if device.engine not in ask.have:
        raise InputError(
            f"{opt('device', device.name)}: {device.engine} is not installed "
            f"({_install_hint(device.engine)})",
            option="device",
        )
    own = ask.own
    # an NPU computes fp32 models in f16 (OpenVINO sets no f32 hint there, as it does on a
    # GPU): said, and an explicit fp32 refused rather than quietly not honoured
    computes = "fp16" if own == "fp32" and device.target.upper().startswith("NPU") else own
    if ask.precision not in (None, own) or (ask.precision is not None and computes != own):
        raise InputError(
            f"{opt('precision', ask.precision)}: on {opt('device', device.name)} this {own} "
            f"model runs {computes} (bf16 is a CPU path; int8 needs an int8 export"
            + ("; the NPU computes in f16)" if computes != own else ")")
        )
    note = " (the NPU computes in f16)" if computes != own else ""
    return EngineChoice(
        device.engine,
        own,
        f"{device.engine} {computes} on {device.target}: {opt('device', device.name)} given{note}",
        ask.info.path,
        device,
        ask.file,
    )


def _int8_hardware(cpu: CpuInfo) -> str:
    if cpu.has_vnni:
        return "VNNI/AMX int8 dot products"
    if cpu.avx512f:  # Skylake-SP and the like: AVX-512BW kernels, never timed
        return "no VNNI/AMX: int8 speed not measured on this CPU class"
    if cpu.avx2:
        return "no VNNI/AMX: int8 emulated with AVX2, still faster than fp32"
    return "no AVX2, VNNI or AMX: int8 speed not measured on this CPU"


def _for_int8(ask: _Ask, cpu: CpuInfo) -> EngineChoice:
    """int8 exports: quantised weights and activations, nothing to choose but the engine."""
    info = ask.info
    if ask.precision not in (None, "int8"):
        raise InputError(
            f"{opt('precision', ask.precision)}: this is an int8 model; export an fp32 "
            "model (msf-export without --int8) for fp32 or bf16",
            info.path,
            option="precision",
        )
    hw = _int8_hardware(cpu)
    if ask.engine is not None:
        note = _int8_note(ask.engine, info)
        return ask.pick(ask.engine, "int8", f"{ask.what}, {opt('engine')} given ({hw})" + note)
    klass = int8_class(cpu)
    ov_lead = ov_int8_preferred(cpu, info)
    use_ov = "openvino" in ask.have and (ov_lead or "onnxruntime" not in ask.have)
    engine = "openvino" if use_ov else "onnxruntime"
    if engine == "openvino" and ov_lead:
        hw += (
            f"; OpenVINO measured {OV_INT8_SPEEDUP[klass]:.2f}x ONNX Runtime int8 "
            f"on this CPU class ({klass})"
        )
        if ov_int8_closer(info):
            hw += ", closer to fp32"
    return ask.pick(engine, "int8", f"{ask.what} ({hw})" + _int8_note(engine, info))


def _asked_bf16(ask: _Ask, cpu: CpuInfo) -> EngineChoice:
    if ask.engine == "onnxruntime":
        raise InputError(
            f"{opt('precision', 'bf16')}: ONNX Runtime's CPU provider has no bf16 path; "
            f"use {opt('engine', 'openvino')}",
            option="precision",
        )
    if "openvino" not in ask.have:
        raise InputError(
            f"{opt('precision', 'bf16')} runs on OpenVINO, which is not installed "
            f"({_install_hint('openvino')})",
            option="precision",
        )
    if not cpu.has_bf16:
        raise InputError(
            f"{opt('precision', 'bf16')}: this CPU ({cpu.model}) has no native bf16 "
            "(avx512_bf16 or AMX); bf16 would be emulated, slower than fp32",
            option="precision",
        )
    why = f"{ask.what}, {opt('precision', 'bf16')} given"
    return ask.pick("openvino", "bf16", why + _bound_note("openvino", "bf16", ask.info.staged))


def _for_fp32(ask: _Ask, cpu: CpuInfo) -> EngineChoice:
    """fp32 exports: bf16 where the CPU has it natively and it was measured within the
    bound, OpenVINO fp32 where it was measured faster, else ONNX Runtime fp32."""
    info, what, have, want_engine = ask.info, ask.what, ask.have, ask.engine
    if ask.precision == "int8":
        raise InputError(
            f"{opt('precision', 'int8')} needs an int8 export (msf-export --int8); "
            "this model is fp32",
            info.path,
            option="precision",
        )
    if ask.precision == "bf16":
        return _asked_bf16(ask, cpu)
    ov_fp32 = "openvino" in have and ov_fp32_preferred(cpu)
    speedup = OV_FP32_SPEEDUP.get(cpu_class(cpu))
    ov_why = f"measured {speedup}x ONNX Runtime fp32 on this CPU class ({cpu_class(cpu)})"
    pick = ask.pick
    if ask.precision == "fp32":
        given = f"{what}, {opt('precision', 'fp32')}"
        if want_engine is not None:
            return pick(want_engine, "fp32", f"{given} and {opt('engine')} given")
        if ov_fp32:
            return pick("openvino", "fp32", f"{given} given; {ov_why}")
        return pick("onnxruntime", "fp32", f"{given} given")

    # no precision asked for: the fastest default within the accuracy bound
    bf16_ok = default_allowed("openvino", "bf16", info.staged)
    if want_engine in (None, "openvino") and "openvino" in have and cpu.has_bf16 and bf16_ok:
        m = MEASURED[("openvino", "bf16", info.staged)]
        return pick(
            "openvino",
            "bf16",
            f"{what}; CPU has native bf16 "
            f"({'AMX' if cpu.amx_bf16 else 'avx512_bf16'}); measured within "
            f"{_up(m.worst_mean)} deg mean of fp32 on DiLiGenT ball crops",
        )
    if want_engine is not None:
        if not cpu.has_bf16:
            note = f"; {_no_bf16(cpu)}"
        elif want_engine == "onnxruntime":
            note = f"; bf16 on this CPU would need {opt('engine', 'openvino')}"
        else:
            note = ""
        return pick(want_engine, "fp32", f"{what}, {opt('engine')} given{note}")
    if not cpu.has_bf16:
        why = _no_bf16(cpu)
    elif "openvino" not in have:
        why = f"CPU has native bf16 but OpenVINO is not installed ({_install_hint('openvino')})"
    else:
        why = "OpenVINO bf16 not measured within the accuracy bound for this graph"
    if ov_fp32:
        return pick("openvino", "fp32", f"{what}; {why}; {ov_why}")
    if "openvino" not in have:
        return pick("onnxruntime", "fp32", f"{what}; {why}")
    if "onnxruntime" not in have:  # a trimmed install: the engine that is here
        return pick("openvino", "fp32", f"{what}; {why}; ONNX Runtime is not installed")
    return pick(
        "onnxruntime",
        "fp32",
        f"{what}; {why}; OpenVINO fp32 not measured faster on this CPU class ({cpu_class(cpu)})",
    )


def _no_bf16(cpu: CpuInfo) -> str:
    """Why the bf16 path is not taken, as far as the CPU's features say."""
    if not cpu.detected:
        return "CPU features could not be read (py-cpuinfo and /proc/cpuinfo failed): fp32"
    if cpu.partial:
        return "native bf16 unknown here (/proc/cpuinfo unreadable; cpuid alone lacks it)"
    if "bf16" in cpu.all_flags:  # Arm's name (Neoverse V1, Graviton 3): not OpenVINO's x86 path
        return "bf16 on this Arm CPU not measured"
    return "no native bf16 on this CPU"


def open_engine(
    choice: EngineChoice,
    threads: int | None = None,
    *,
    chunk: int | None = None,
    provider: str | None = None,
    model: str | Path | None = None,
) -> Engine:
    """Load the chosen engine. ``threads``: None = the cores this process may use. ``provider``
    (ONNX Runtime only): e.g. 'cuda' (``choice.device`` sets it too). ``model`` overrides
    ``choice.model``. The model file is not read again where the choice was made from a read
    of it (``choice.file``)."""
    path = model if model is not None else choice.model
    file = choice.file if path is not None and Path(path) == choice.model else None
    if threads is not None:
        check_threads(threads)  # the one bound (common.cpu.MAX_THREADS) of every engine
    if path is None:
        raise InputError("open_engine: no model path (give model=... or choose from a path)")
    device = choice.device
    if choice.engine == "onnxruntime":
        from msfnet.runtime.engines.onnxruntime import open_onnxruntime

        if device is not None:
            provider = device.target
        return open_onnxruntime(
            path,
            threads=threads,
            precision=choice.precision,
            provider=provider,
            chunk=chunk,
            info=file.info if file is not None else None,
        )
    if choice.engine == "openvino":
        if provider not in (None, "cpu"):
            raise InputError(
                f"{opt('provider', provider)}: ONNX Runtime only "
                f"(use {opt('device')} for OpenVINO)",
                option="provider",
            )
        from msfnet.runtime.engines.openvino import open_openvino

        if device is None and file is not None:  # its CPU kernels saturate as ONNX Runtime's
            check_int8_exact(file.info)  # do: refused before the compile
        opened = open_openvino(
            path,
            threads=threads,
            precision=choice.precision,
            chunk=chunk,
            device=device.target if device is not None else "CPU",
            file=file,
        )
        if device is None and file is None:
            check_int8_exact(opened.info)
        return opened
    raise InputError(f"unknown engine {choice.engine!r} (known: {', '.join(ENGINES)})")


def open_chosen(
    choice: EngineChoice,
    threads: int | None = None,
    *,
    chunk: int | None = None,
    requested: bool = False,
) -> tuple[Engine, str]:
    """``open_engine``, with ONNX Runtime fp32 as the fallback for a *default* OpenVINO CPU
    choice that OpenVINO cannot compile (``requested``: the user named the engine, precision or
    device, and a failure is theirs to see). Returns the engine and the reason line."""
    if choice.file is not None and choice.device is None:
        # refused by both engines alike: no fallback to speak of (nor one to miss)
        check_int8_exact(choice.file.info)
    try:
        return open_engine(choice, threads, chunk=chunk), choice.reason
    except InputError as exc:
        if requested or choice.engine != "openvino" or choice.device is not None:
            raise
        if "onnxruntime" not in installed_engines():  # an OpenVINO-only install
            raise InputError(
                f"{exc.message}; ONNX Runtime, the fallback, is not installed", exc.path
            ) from exc
        precision = "int8" if choice.precision == "int8" else "fp32"
        fallback = EngineChoice("onnxruntime", precision, "", choice.model, file=choice.file)
        engine = open_engine(fallback, threads, chunk=chunk)
        return engine, f"onnxruntime {precision}: fallback, OpenVINO failed ({exc})"


__all__ = [
    "ACCURACY_BOUND_DEG",
    "DEVICE_TARGETS",
    "INT8_OVER_BF16",
    "INT8_SPEEDUP",
    "MEASURED",
    "MINMAX_INT8_MEASURED",
    "MIXED_INT8_MEASURED",
    "OV_FP32_SPEEDUP",
    "OV_INT8_MIN_SPEEDUP",
    "OV_INT8_SPEEDUP",
    "BundledChoice",
    "Device",
    "EngineChoice",
    "Measured",
    "available_devices",
    "bundled_precision",
    "choose_engine",
    "cpu_class",
    "default_allowed",
    "int8_class",
    "likely_engine",
    "open_chosen",
    "open_engine",
    "ov_fp32_preferred",
    "ov_int8_closer",
    "ov_int8_preferred",
    "read_for",
    "resolve_device",
]
