"""Engines that run an msfnet ONNX model: ONNX Runtime (always installed) and OpenVINO (optional).

Each offers ``run(images, lights) -> normals``, ``info``, ``name``, ``precision``, ``threads``
and ``chunk`` (see base.Engine). Which engine and precision to use on this CPU is decided in
``msfnet.runtime.engines.dispatch``.
"""

from msfnet.runtime.engines.base import (
    ENGINES,
    PRECISIONS,
    Engine,
    engine_name,
    installed_engines,
    model_precision,
    precision_name,
    read_model_file,
)
from msfnet.runtime.engines.onnxruntime import OrtEngine, open_onnxruntime


def open_openvino(*args, **kwargs):  # type: ignore[no-untyped-def]
    """Lazy: importing this package must not import openvino (see engines/openvino.py)."""
    from msfnet.runtime.engines.openvino import open_openvino as _open

    return _open(*args, **kwargs)


__all__ = [
    "ENGINES",
    "PRECISIONS",
    "Engine",
    "OrtEngine",
    "engine_name",
    "installed_engines",
    "model_precision",
    "open_onnxruntime",
    "open_openvino",
    "precision_name",
    "read_model_file",
]
