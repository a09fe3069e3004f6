"""The ONNX Runtime engine: an ``ort_session.ModelSession`` behind the Engine interface
(composition, so ``ort_session.create_session`` and its callers stay as they are).

Precision is the model's own: fp32 exports run fp32, int8 QDQ exports run ONNX Runtime's int8
kernels (VNNI / AMX where the CPU has them). The CPU provider has no bf16 path on x86.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from msfnet.common.errors import InputError
from msfnet.common.vocabulary import opt
from msfnet.runtime.contract import ModelInfo
from msfnet.runtime.engines.base import check_int8_exact, model_precision, quantised_full_range
from msfnet.runtime.engines.method import RunMethod
from msfnet.runtime.engines.ort_session import ModelSession, create_session


class OrtEngine:
    name = "onnxruntime"

    def __init__(self, session: ModelSession) -> None:
        self.session = session

    @property
    def info(self) -> ModelInfo:
        return self.session.info

    @property
    def precision(self) -> str:
        return model_precision(self.session.info)

    @property
    def threads(self) -> int | None:
        return self.session.threads

    @property
    def provider(self) -> str:
        return self.session.provider

    @property
    def chunk(self) -> int | None:
        return self.session.chunk

    def set_lights_per_call(self, value: int) -> None:
        self.session.lights_per_call = value

    def run(self, images: np.ndarray, lights: np.ndarray) -> np.ndarray:
        return self.session.run(images, lights)

    def describe(self) -> RunMethod:
        return RunMethod.of_engine(self, provider=self.provider)

    def __repr__(self) -> str:
        return f"OrtEngine({self.info.path.name}, {self.precision}, threads={self.threads})"


def open_onnxruntime(
    path: str | Path,
    *,
    threads: int | None = None,
    precision: str | None = None,
    provider: str | None = None,
    chunk: int | None = None,
    info: ModelInfo | None = None,
) -> OrtEngine:
    """Load ``path`` with ONNX Runtime. ``precision``, if given, must be the model's own.
    ``info``: the file's metadata, read already (it decides the memory arena before the one
    load; the session still checks its own metadata and I/O)."""
    arena = info.staged if info is not None else None
    engine = OrtEngine(create_session(path, threads=threads, provider=provider, arena=arena))
    if precision is not None and precision != engine.precision:
        hint = (
            f"OpenVINO ({opt('engine', 'openvino')}) runs fp32 models in bf16"
            if precision == "bf16"
            else "export a model of that precision with msf-export"
        )
        raise InputError(
            f"ONNX Runtime runs this {engine.precision} model in "
            f"{engine.precision}, not {precision}; {hint}",
            engine.info.path,
        )
    check_int8_exact(engine.info)
    if chunk is not None:
        engine.set_lights_per_call(chunk)
    return engine


__all__ = ["OrtEngine", "check_int8_exact", "open_onnxruntime", "quantised_full_range"]
