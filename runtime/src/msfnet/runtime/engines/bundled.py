"""Opening the network: the bundled file for this CPU (the fp32 export or its int8 twin) or a
given one, on the engine and precision :mod:`~msfnet.runtime.engines.dispatch` chooses, with
the line that says why."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from msfnet.common.errors import InputError
from msfnet.common.vocabulary import opt
from msfnet.runtime.engines.base import Engine

if TYPE_CHECKING:
    from msfnet.runtime.engines.dispatch import Device

WEIGHTS = Path(__file__).resolve().parents[1] / "weights"


@dataclass(frozen=True)
class EngineRequest:
    """What the caller asked of the engine (ModelOptions' fields of the same names; None:
    this CPU's default)."""

    engine: str | None = None
    precision: str | None = None
    provider: str | None = None
    device: str | None = None
    threads: int | None = None


def default_model_path(precision: str = "fp32") -> Path:
    """The bundled model, shipped with the runtime: the fp32 export
    (msfnet/runtime/weights/msfnet_default.onnx) or its int8 twin (msfnet_default_int8.onnx:
    staged int8, 7-bit weights, exact on every CPU), which ``Model()`` opens where
    engines.dispatch.bundled_precision says it is the faster default."""
    if precision not in ("fp32", "int8"):
        raise InputError(f"bundled model precision {precision!r}: expected fp32 or int8")
    return WEIGHTS / ("msfnet_default.onnx" if precision == "fp32" else "msfnet_default_int8.onnx")


def bundled_model_path() -> Path:
    """The bundled file ``Model()`` opens here when nothing is named (the fp32 export or its
    int8 twin, engines.dispatch.bundled_precision): what msf-bench reports it measured."""
    return bundled_model(EngineRequest())[0]


def bundled_model(req: EngineRequest, device: Device | None = None) -> tuple[Path, str]:
    """The bundled file to open (fp32 or its int8 twin, engines.dispatch.bundled_precision)
    and why; the fp32 file where the int8 one is missing and was not asked for. ``device``:
    ``req.device`` resolved (dispatch.resolve_device)."""
    from msfnet.common.cpu import detect_cpu
    from msfnet.runtime.engines import installed_engines
    from msfnet.runtime.engines.dispatch import BundledChoice, bundled_precision

    pick = bundled_precision(detect_cpu(), installed_engines(), req.engine, req.precision, device)
    if req.provider is not None and req.precision is None:
        pick = BundledChoice("fp32")  # an ONNX Runtime execution provider (a GPU): as a device
    path = default_model_path(pick.precision)
    if not path.is_file() and pick.precision == "int8" and req.precision is None:
        path = default_model_path()
        pick = BundledChoice("fp32", "bundled fp32 model: its int8 twin is not installed")
    if not path.is_file():
        what = "int8 model (its twin)" if pick.precision == "int8" else "model"
        raise InputError(
            f"no model given and no bundled {what} at {path}; export one "
            f"with msf-export, or use least squares ({opt('method', 'l2')})"
        )
    return path, pick.reason


def open_network(path: Path | None, req: EngineRequest) -> tuple[Engine, str]:
    """The engine for ``path`` (None: the bundled pair's file for this CPU and request) and
    the choice line: which engine and precision, and why (the overrides honoured)."""
    from msfnet.common.cpu import detect_cpu
    from msfnet.runtime.engines import installed_engines
    from msfnet.runtime.engines.dispatch import (
        bundled_precision,
        choose_engine,
        open_chosen,
        open_engine,
        resolve_device,
    )

    engine = req.engine
    if req.provider is not None and engine is None:
        engine = "onnxruntime"  # execution providers are ONNX Runtime's
    device = resolve_device(req.device)
    why = ""
    if path is None:
        path, why = bundled_model(req, device)
    choice = choose_engine(
        path, detect_cpu(), installed_engines(), engine, req.precision, device=device
    )
    prefix = f"{why}; " if why else ""
    if req.provider is not None:
        return open_engine(choice, req.threads, provider=req.provider), prefix + choice.reason
    # a default OpenVINO choice falls back to ONNX Runtime if OpenVINO cannot compile the model
    asked = bool(req.engine or req.precision or req.device)
    opened, reason = open_chosen(choice, req.threads, requested=asked)
    if why and opened.name != choice.engine:
        # OpenVINO failed: the bundled file's reason must speak of the engine that runs it
        # (it had claimed OpenVINO's bf16 comparison and its 0.30 deg)
        without = bundled_precision(
            detect_cpu(), installed_engines() - {"openvino"}, engine, req.precision, device
        )
        same = without.precision == choice.precision and without.reason
        prefix = (
            f"{without.reason}; "
            if same
            else f"bundled {choice.precision} model, chosen for OpenVINO; "
        )
    return opened, prefix + reason + _oversubscribed(req.threads, opened.name)


def _oversubscribed(threads: int | None, engine: str) -> str:
    """A note for the choice line when ONNX Runtime is given more threads than this process
    may run at once (an affinity mask, taskset): its threads then wait on each other (OpenVINO's
    do not). Said, not capped: the user's number is run as given."""
    from msfnet.common.cpu import usable_cores

    cores = usable_cores()
    if engine != "onnxruntime" or threads is None or threads <= cores:
        return ""
    return (
        f"; note: {threads} threads on the {cores} CPU{'s' if cores > 1 else ''} this "
        "process may use: extra threads only wait (ONNX Runtime ran 2.35x slower at 8 on 1)"
    )


__all__ = [
    "WEIGHTS",
    "EngineRequest",
    "bundled_model",
    "bundled_model_path",
    "default_model_path",
    "open_network",
]
