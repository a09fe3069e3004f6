"""Which engine and precision run a model on this CPU: ``choose_engine`` decides, ``open_engine``
loads.

``choose_engine`` is a pure function of the CPU's features (cpu.CpuInfo), the installed engines
and the model's metadata (fp32 / int8, monolithic / staged), so every rule below is tested on
faked CPUs. Rules, in order:

1. ``--engine`` / ``--precision`` override. An override that cannot be honoured is an error,
   never a silent substitute: bf16 needs OpenVINO (ONNX Runtime's CPU provider has no bf16 path
   on x86) and a CPU with native bf16; int8 needs an int8 export; an int8 export runs only int8.
2. int8 models run int8. Default engine: ONNX Runtime (its QLinearConv kernels use VNNI / AMX
   where present; without them int8 is emulated with AVX2 and still measured 1.56x fp32 on
   Zen 3). OpenVINO runs them on request (``--engine openvino``).
3. fp32 models: bf16 through OpenVINO when the CPU has native bf16 (avx512_bf16 or AMX) and
   OpenVINO is installed; plain and staged graphs alike.
4. Otherwise fp32 through ONNX Runtime.

A precision is a *default* only within ACCURACY_BOUND_DEG (0.5 deg) mean of ONNX Runtime fp32
on real data (MEASURED, checked by ``default_allowed``); a path above it runs only on request.
Measured with ``python -m msfnet.bench.accuracy --models DIR`` on the AMX machine (Intel Xeon,
AMX bf16/int8, AVX-512 bf16/VNNI, 2 cores, onnxruntime 1.32, openvino 2026.4), the bundled model
of 2026-11-23, int8 exports calibrated on psmImages cat, owl and horse (never on the validation
objects), DiLiGenT ballPNG 128x128 crop centred on the ball, mean / max deg vs ORT fp32 over the
mask, speed as the same-run ratio to ORT fp32 (median of the timed runs after a warm-up; the
machine is shared, so ratios, not seconds):

    path (model)                   32 lights        96 lights        x ORT fp32, same run:
                                   mean / max deg   mean / max deg   32 lights; 96 lights
    ORT fp32 staged                0.000 / 0.000    0.000 / 0.000     1.05;  1.03
    ORT int8 (QDQ)       opt-in    0.673 / 2.93     0.917 / 4.89      2.01;  2.02
    ORT int8 staged      opt-in    0.673 / 2.93     0.917 / 4.89      2.21;  2.24
    OpenVINO fp32                  0.000 / 0.000    0.000 / 0.000     1.43;  1.32
    OpenVINO bf16        default   0.093 / 0.331    0.078 / 0.319     6.56;  6.31
    OpenVINO bf16 staged default   0.091 / 0.329    0.076 / 0.269     5.46;  5.17
    OpenVINO int8 (QDQ)  opt-in    0.754 / 2.97     1.004 / 4.83      4.21;  3.93
    OpenVINO int8 staged opt-in    0.673 / 2.93     0.917 / 4.88      4.13;  4.10

(The model of 2026-11-22, measured the same way: int8 0.71 / 0.94 deg mean, bf16 0.08 / 0.07.)
The CPU-trained model bundled before 2026-11-22 stayed within the bound in int8 (ORT 0.32 / 0.44 deg
mean); the sharper H100-trained models since 2026-11-22 do not (for that one, calibrating on all
six psmImages objects made it worse, 0.86 deg on held-out calibration tiles), so int8 is now
opt-in everywhere and an int8 export runs only when asked for (rule 2: an int8 file is itself
the request). OpenVINO bf16 is the fastest path and 7-12x closer to fp32 than int8. Plain
OpenVINO bf16 beat staged in every run so far (here by 1.1-1.35x; 1.5-2x in an earlier
interleaved run): staged graphs save memory, not time, on this engine. The field notes measured
OpenVINO bf16 at 3.31x ORT fp32 (0.087 deg mean) on Zen 5 (avx512_bf16, no AMX).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from msfnet.common.cpu import CpuInfo
from msfnet.common.errors import InputError
from msfnet.runtime.contract import ModelInfo
from msfnet.runtime.engines.base import (
    ENGINES,
    Engine,
    engine_name,
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


# (engine, precision, staged) -> measurement (the table in the module docstring)
MEASURED: dict[tuple[str, str, bool], Measured] = {
    ("onnxruntime", "int8", False): Measured({32: (0.673, 2.934), 96: (0.917, 4.886)}),
    ("onnxruntime", "int8", True): Measured({32: (0.673, 2.934), 96: (0.917, 4.886)}),
    ("openvino", "bf16", False): Measured({32: (0.093, 0.331), 96: (0.078, 0.319)}),
    ("openvino", "bf16", True): Measured({32: (0.091, 0.329), 96: (0.076, 0.269)}),
    ("openvino", "int8", False): Measured({32: (0.754, 2.969), 96: (1.004, 4.829)}),
    ("openvino", "int8", True): Measured({32: (0.673, 2.933), 96: (0.917, 4.884)}),
}


def default_allowed(engine: str, precision: str, staged: bool) -> bool:
    """Whether this path may be chosen without being asked for: fp32 always; a reduced precision
    only when measured within ACCURACY_BOUND_DEG mean of fp32 at every light count measured."""
    if precision == "fp32":
        return True
    m = MEASURED.get((engine, precision, staged))
    return m is not None and m.worst_mean <= ACCURACY_BOUND_DEG


@dataclass(frozen=True)
class EngineChoice:
    engine: str  # onnxruntime | openvino
    precision: str  # fp32 | bf16 | int8
    reason: str  # one line for logs and profile.json: why this engine and precision
    model: Path | None = None  # the model to open (None when decided from a ModelInfo alone)


def _bound_note(engine: str, precision: str, staged: bool) -> str:
    """A warning for the reason string when a path runs that is no default for accuracy."""
    m = MEASURED.get((engine, precision, staged))
    if m is None or m.worst_mean <= ACCURACY_BOUND_DEG:
        return ""
    return (
        f"; note: measured {m.worst_mean:.2f} deg mean from fp32 on DiLiGenT ball crops, "
        f"above the {ACCURACY_BOUND_DEG} deg bound for defaults"
    )


def _install_hint(engine: str) -> str:
    return "pip install 'msfnet[openvino]'" if engine == "openvino" else "pip install onnxruntime"


def choose_engine(
    model: str | Path | ModelInfo,
    cpu: CpuInfo,
    installed: Iterable[str],
    requested_engine: str | None = None,
    requested_precision: str | None = None,
) -> EngineChoice:
    """Pick the engine and precision for ``model`` on ``cpu`` (rules in the module docstring).

    ``model``: an msfnet ONNX path (its metadata is read) or its ModelInfo. ``installed``: engine
    names importable here (engines.installed_engines()). Raises InputError for overrides that
    cannot be honoured.
    """
    info = model if isinstance(model, ModelInfo) else read_model_file(model)
    have = {engine_name(e) for e in installed}
    want_engine = engine_name(requested_engine) if requested_engine else None
    want_prec = precision_name(requested_precision) if requested_precision else None
    own = model_precision(info)
    graph = "staged " if info.staged else ""
    what = f"{own} {graph}model"

    if want_engine is not None and want_engine not in have:
        raise InputError(f"--engine {want_engine}: not installed ({_install_hint(want_engine)})")

    def pick(engine: str, precision: str, why: str) -> EngineChoice:
        return EngineChoice(engine, precision, f"{engine} {precision}: {why}", info.path)

    # int8 exports: quantised weights and activations, nothing else to choose but the engine
    if own == "int8":
        if want_prec not in (None, "int8"):
            raise InputError(
                f"--precision {want_prec}: this is an int8 model; export an fp32 "
                "model (msf-export without --int8) for fp32 or bf16",
                info.path,
            )
        hw = (
            "VNNI/AMX int8 dot products"
            if cpu.has_vnni
            else "no VNNI/AMX: int8 emulated with AVX2, still faster than fp32"
        )
        if want_engine is not None:
            return pick(
                want_engine,
                "int8",
                f"{what}, --engine given ({hw})" + _bound_note(want_engine, "int8", info.staged),
            )
        engine = "onnxruntime" if "onnxruntime" in have else "openvino"
        return pick(engine, "int8", f"{what} ({hw})" + _bound_note(engine, "int8", info.staged))

    # fp32 exports
    if want_prec == "int8":
        raise InputError(
            "--precision int8 needs an int8 export (msf-export --int8); this model is fp32",
            info.path,
        )
    if want_prec == "bf16":
        if want_engine == "onnxruntime":
            raise InputError(
                "--precision bf16: ONNX Runtime's CPU provider has no bf16 path; "
                "use --engine openvino"
            )
        if "openvino" not in have:
            raise InputError(
                f"--precision bf16 runs on OpenVINO, which is not installed "
                f"({_install_hint('openvino')})"
            )
        if not cpu.has_bf16:
            raise InputError(
                f"--precision bf16: this CPU ({cpu.model}) has no native bf16 "
                "(avx512_bf16 or AMX); bf16 would be emulated, slower than fp32"
            )
        return pick(
            "openvino",
            "bf16",
            f"{what}, --precision bf16 given" + _bound_note("openvino", "bf16", info.staged),
        )
    if want_prec == "fp32":
        engine = want_engine or "onnxruntime"
        return pick(engine, "fp32", f"{what}, --precision fp32 given")

    # no precision asked for: the fastest default within the accuracy bound
    bf16_ok = default_allowed("openvino", "bf16", info.staged)
    if want_engine in (None, "openvino") and "openvino" in have and cpu.has_bf16 and bf16_ok:
        m = MEASURED[("openvino", "bf16", info.staged)]
        return pick(
            "openvino",
            "bf16",
            f"{what}; CPU has native bf16 "
            f"({'AMX' if cpu.amx_bf16 else 'avx512_bf16'}); measured within "
            f"{m.worst_mean:.2f} deg mean of fp32 on DiLiGenT ball crops",
        )
    if want_engine is not None:
        if not cpu.has_bf16:
            note = "; no native bf16 on this CPU"
        elif want_engine == "onnxruntime":
            note = "; bf16 on this CPU would need --engine openvino"
        else:
            note = ""
        return pick(want_engine, "fp32", f"{what}, --engine given{note}")
    if not cpu.has_bf16:
        why = "no native bf16 on this CPU"
    elif "openvino" not in have:
        why = f"CPU has native bf16 but OpenVINO is not installed ({_install_hint('openvino')})"
    else:
        why = "OpenVINO bf16 not measured within the accuracy bound for this graph"
    return pick("onnxruntime", "fp32", f"{what}; {why}")


def open_engine(
    choice: EngineChoice,
    threads: int | None = None,
    *,
    chunk: int | None = None,
    provider: str | None = None,
    model: str | Path | None = None,
) -> Engine:
    """Load the chosen engine. ``threads``: None = the cores this process may use. ``provider``
    (ONNX Runtime only): e.g. 'cuda'. ``model`` overrides ``choice.model``."""
    path = model if model is not None else choice.model
    if threads is not None and not 1 <= threads <= 1024:
        raise InputError(f"--threads {threads}: expected 1..1024")
    if path is None:
        raise InputError("open_engine: no model path (give model=... or choose from a path)")
    if choice.engine == "onnxruntime":
        from msfnet.runtime.engines.onnxruntime import open_onnxruntime

        return open_onnxruntime(
            path, threads=threads, precision=choice.precision, provider=provider, chunk=chunk
        )
    if choice.engine == "openvino":
        if provider not in (None, "cpu"):
            raise InputError(f"--provider {provider}: ONNX Runtime only (OpenVINO runs on CPU)")
        from msfnet.runtime.engines.openvino import open_openvino

        return open_openvino(path, threads=threads, precision=choice.precision, chunk=chunk)
    raise InputError(f"unknown engine {choice.engine!r} (known: {', '.join(ENGINES)})")


__all__ = [
    "ACCURACY_BOUND_DEG",
    "MEASURED",
    "EngineChoice",
    "Measured",
    "choose_engine",
    "default_allowed",
    "open_engine",
]
