"""What every engine offers, and the pieces the engines share (model metadata).

An engine runs an msfnet ONNX file: ``run(images (1, N, 3, H, W), lights (1, N, 3)) -> normals
(1, 3, H, W)``, all float32, and describes itself with ``name``, ``precision``, ``info``
(ModelInfo: the file's metadata), ``threads`` and ``chunk`` (lights per call, staged graphs), so
``infer.choose_plan`` / ``infer.infer_normals`` take any engine where they took a ModelSession.
"""

from __future__ import annotations

import importlib.util
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from msfnet.common.cpu import CpuInfo, detect_cpu
from msfnet.common.errors import InputError
from msfnet.common.vocabulary import opt
from msfnet.runtime.contract import ModelInfo, read_model_info
from msfnet.runtime.engines.method import RunMethod
from msfnet.runtime.engines.ort_session import check_io

ENGINES = ("onnxruntime", "openvino")
ENGINE_ALIASES = {
    "onnxruntime": "onnxruntime",
    "ort": "onnxruntime",
    "openvino": "openvino",
    "ov": "openvino",
}
PRECISIONS = ("fp32", "bf16", "int8")
# the Python module that has to be importable for each engine
ENGINE_MODULES = {"onnxruntime": "onnxruntime", "openvino": "openvino"}


@runtime_checkable
class Engine(Protocol):
    @property
    def name(self) -> str: ...  # one of ENGINES

    @property
    def precision(self) -> str: ...  # fp32, bf16 or int8: the effective one, not the wish

    @property
    def info(self) -> ModelInfo: ...

    @property
    def threads(self) -> int | None: ...

    @property
    def chunk(self) -> int | None: ...  # lights per call through a staged graph, else None

    def run(self, images: np.ndarray, lights: np.ndarray) -> np.ndarray: ...

    def describe(self) -> RunMethod: ...


def engine_name(name: str) -> str:
    """'ort' / 'ov' / full names -> the canonical engine name; InputError if unknown."""
    canonical = ENGINE_ALIASES.get(name.strip().lower())
    if canonical is None:
        raise InputError(
            f"{opt('engine', name, quote=True)}: expected one of {', '.join(ENGINES)} (or ort, ov)",
            option="engine",
        )
    return canonical


def precision_name(name: str) -> str:
    p = name.strip().lower()
    p = {"float32": "fp32", "f32": "fp32", "bfloat16": "bf16", "i8": "int8"}.get(p, p)
    if p not in PRECISIONS:
        raise InputError(
            f"{opt('precision', name, quote=True)}: expected one of {', '.join(PRECISIONS)}",
            option="precision",
        )
    return p


def installed_engines() -> set[str]:
    """Engines whose Python package is importable here (checked without importing it)."""
    found = set()
    for engine, module in ENGINE_MODULES.items():
        try:
            if importlib.util.find_spec(module) is not None:
                found.add(engine)
        except (ImportError, ValueError):  # a broken install or an import hook saying no
            pass
    return found


def model_precision(info: ModelInfo) -> str:
    """'int8' for quantised exports (metadata 'int8-qdq'), 'fp32' otherwise (incl. fp16-stored
    weights, which are computed in fp32)."""
    return "int8" if info.precision.strip().lower().startswith("int8") else "fp32"


@dataclass(frozen=True, eq=False)
class ModelFile:
    """A model file read once: its checked metadata and, when OpenVINO was the reader, OpenVINO's
    graph of it, which the OpenVINO engine compiles instead of parsing the file again. Chosen
    and opened from the same read (dispatch.EngineChoice.file), so ``Model()`` reads a file's
    metadata once."""

    info: ModelInfo
    openvino_graph: Any = None  # an openvino.Model of info.path; None when ONNX Runtime read it


def model_file_path(path: str | Path) -> Path:
    """``path`` as a Path, or InputError when no model file is there (each reader's first check)."""
    path = Path(path)
    if path.is_dir():
        raise InputError("the model is a folder, not a file", path)
    if not path.is_file():
        if path.is_symlink() and not path.exists():
            raise InputError(f"ONNX model not found (a broken link to {os.readlink(path)})", path)
        if os.path.lexists(path):  # a pipe, a device: there, but no file
            raise InputError("not a regular file (expected an .onnx model)", path)
        raise InputError("ONNX model not found", path)
    return path


def read_model_file(path: str | Path) -> ModelInfo:
    """The msfnet metadata of an ONNX file read through ONNX Runtime, without building an
    optimised session (bundled model: ~40 ms in a fresh process, ~20 ms after).

    The reader of the ONNX Runtime path and the fallback of the OpenVINO one (an OpenVINO that
    does not expose ONNX metadata, or a file it cannot read: ``openvino.read_openvino``).
    InputError if missing, corrupt or not msfnet.
    """
    path = model_file_path(path)
    try:
        import onnxruntime as ort
    except ImportError as exc:  # an OpenVINO-only install, and a file OpenVINO could not read
        raise InputError(
            "cannot read this model: OpenVINO could not, and ONNX Runtime, the other reader, "
            "is not installed (pip install onnxruntime)",
            path,
        ) from exc
    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    opts.log_severity_level = 3
    try:
        sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    except Exception as exc:  # InvalidProtobuf, Fail, ... for files that are not ONNX
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise InputError(f"cannot load ONNX model ({first[:200]})", path) from exc
    info = read_model_info(path, dict(sess.get_modelmeta().custom_metadata_map))
    check_io(path, info, {i.name for i in sess.get_inputs()}, {o.name for o in sess.get_outputs()})
    return info


def quantised_full_range(info: ModelInfo) -> bool:
    """Whether an int8 model's weights use all 8 bits (not msf-export's reduce_range): the
    quantisation summary in its metadata says; a model that does not say is taken as full
    range (the quantiser's default)."""
    return info.quantization().get("reduce_range") is not True


def check_int8_exact(info: ModelInfo, cpu: CpuInfo | None = None) -> None:
    """Refuse to run an int8 model where the CPU engines compute wrong numbers: full-range
    weights on a CPU without VNNI (see CpuInfo.int8_full_range). OpenVINO's AVX2 int8
    kernels saturate too (scripts/int8_saturation.py, docs/benchmark.md)."""
    if model_precision(info) != "int8" or not quantised_full_range(info):
        return
    cpu = cpu or detect_cpu()
    if cpu.int8_full_range:
        return
    raise InputError(
        "this int8 model has full-range (8-bit) weights, which the int8 kernels of ONNX "
        "Runtime and OpenVINO saturate on CPUs without VNNI (this one: "
        f"{' '.join(cpu.features()) or 'no AVX2'}): use an fp32 model, or an int8 export "
        "with 7-bit weights (msf-export --weight-bits 7, exact on every CPU)",
        info.path,
    )


__all__ = [
    "ENGINES",
    "PRECISIONS",
    "Engine",
    "ModelFile",
    "check_int8_exact",
    "engine_name",
    "installed_engines",
    "model_file_path",
    "model_precision",
    "precision_name",
    "quantised_full_range",
    "read_model_file",
]
