"""ONNX Runtime session creation for msfnet models, with the metadata check.

Refuses any ONNX file that is not an msfnet export (wrong metadata or I/O names) before it can
produce garbage normals.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from msfnet.common.cpu import MAX_THREADS, check_threads, usable_cores
from msfnet.common.errors import InputError, first_line
from msfnet.common.vocabulary import opt
from msfnet.runtime.contract import ModelInfo, read_model_info
from msfnet.runtime.engines.interrupt import run_interruptible
from msfnet.runtime.engines.method import RunMethod
from msfnet.runtime.engines.staged_loop import (
    DEFAULT_CHUNK,
    STAGE_INPUTS,
    STAGE_OUTPUTS,
    run_staged,
)

if TYPE_CHECKING:
    import onnxruntime as ort

PROVIDER_ALIASES = {
    "cpu": "CPUExecutionProvider",
    "cuda": "CUDAExecutionProvider",
    "tensorrt": "TensorrtExecutionProvider",
    "openvino": "OpenVINOExecutionProvider",
    "dnnl": "DnnlExecutionProvider",
    "coreml": "CoreMLExecutionProvider",
    "directml": "DmlExecutionProvider",
}


# ONNX Runtime's graph optimisation levels by name (GraphOptimizationLevel.ORT_<value>)
GRAPH_OPT_LEVELS = {
    "disable": "DISABLE_ALL",
    "basic": "ENABLE_BASIC",
    "extended": "ENABLE_EXTENDED",
    "all": "ENABLE_ALL",
}


def _ort() -> Any:
    """onnxruntime, imported on first use: a run on OpenVINO never pays its ~30 ms import."""
    import onnxruntime

    return onnxruntime


@dataclass
class ModelSession:
    """An msfnet model in ONNX Runtime (an :class:`~msfnet.runtime.engines.base.Engine`)."""

    session: ort.InferenceSession
    info: ModelInfo
    provider: str
    threads: int | None
    lights_per_call: int = DEFAULT_CHUNK  # staged models only
    name: str = "onnxruntime"

    @property
    def precision(self) -> str:
        return self.info.precision

    @property
    def chunk(self) -> int | None:
        return self.lights_per_call if self.info.staged else None

    def describe(self) -> RunMethod:
        return RunMethod.of_engine(self, provider=self.provider)

    def run(self, images: np.ndarray, lights: np.ndarray) -> np.ndarray:
        """images (1, N, 3, H, W), lights (1, N, 3) float32 -> normals (1, 3, H, W); every
        call stoppable by Ctrl-C (see :mod:`.interrupt`), the result's shape checked."""
        if self.info.staged:
            out = run_staged(_Interruptible(self.session), images, lights, self.lights_per_call)
        else:
            out = _Interruptible(self.session).run(
                ["normals"], {"images": images, "lights": lights}
            )[0]
        check_normals(self.info.path, images, out)
        return out


class _Interruptible:
    """An InferenceSession's ``run`` with a fresh RunOptions per call, whose terminate flag a
    signal sets (ONNX Runtime checks it before every node, inside Loop bodies too)."""

    def __init__(self, session: ort.InferenceSession) -> None:
        self._session = session

    def run(self, output_names: list[str], feeds: Mapping[str, np.ndarray]) -> list[np.ndarray]:
        options = _ort().RunOptions()
        options.log_severity_level = 4  # the "terminate flag" error is ours to report, once

        def stop() -> None:
            options.terminate = True

        return run_interruptible(lambda: self._session.run(output_names, feeds, options), stop)


def resolve_provider(name: str | None) -> str:
    """'cpu', 'cuda', ... or a full ORT provider name; must be installed."""
    provider = PROVIDER_ALIASES.get((name or "cpu").lower(), name or "CPUExecutionProvider")
    available = _ort().get_available_providers()
    if provider not in available:
        raise InputError(
            f"{opt('provider', name, quote=True)}: not available in this onnxruntime build "
            f"(available: {', '.join(available)})",
            option="provider",
        )
    return provider


def default_threads() -> int:
    """Threads when none are asked for: the cores this process may use (common/cpu.py)."""
    return usable_cores()


def create_session(
    path: str | Path,
    *,
    threads: int | None = None,
    provider: str | None = None,
    graph_opt: str = "all",
    arena: bool | None = None,
) -> ModelSession:
    """Load an msfnet ONNX model; raise InputError if it is missing, corrupt or not msfnet.

    ``arena`` (ONNX Runtime's CPU memory arena), default: on for staged models, off otherwise.
    Monolithic: the arena grows in doubling chunks and keeps them, so it about doubles the peak
    RSS of a full object at the same speed. Staged: a call's working set is one light chunk, so
    the arena stays small, and without it the many calls per tile re-allocate and page-fault
    (slower). Figures: docs/benchmark.md, "Measurements behind the code's rules".
    """
    path = Path(path)
    if not path.exists():
        raise InputError("ONNX model not found", path)
    if not path.is_file():
        raise InputError("not a file (expected an .onnx model)", path)
    if graph_opt not in GRAPH_OPT_LEVELS:
        raise InputError(
            f"graph optimisation level {graph_opt!r}: expected one of {', '.join(GRAPH_OPT_LEVELS)}"
        )
    threads = threads or default_threads()
    check_threads(threads)  # ONNX Runtime starts every intra-op thread up front
    prov = resolve_provider(provider)
    ort = _ort()
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.graph_optimization_level = getattr(
        ort.GraphOptimizationLevel, "ORT_" + GRAPH_OPT_LEVELS[graph_opt]
    )
    opts.enable_cpu_mem_arena = bool(arena)
    opts.log_severity_level = 3  # keep ORT's warnings off the user's terminal
    providers = [prov] if prov == "CPUExecutionProvider" else [prov, "CPUExecutionProvider"]
    if (
        prov == "TensorrtExecutionProvider"
        and "CUDAExecutionProvider" in ort.get_available_providers()
    ):
        # nodes TensorRT cannot take run on CUDA, not on the CPU (ONNX Runtime's advice)
        providers.insert(1, "CUDAExecutionProvider")
    try:
        sess = ort.InferenceSession(str(path), opts, providers=providers)
    except Exception as exc:  # ORT raises InvalidProtobuf, Fail, ... for bad files
        raise InputError(f"cannot load ONNX model ({first_line(exc)})", path) from exc
    if sess.get_providers()[0] != prov:  # ORT falls back to the CPU when a GPU cannot start
        raise InputError(
            f"{prov} is built in but could not start here (ONNX Runtime ran "
            f"{sess.get_providers()[0]} instead; check the GPU driver and libraries)"
        )
    meta = dict(sess.get_modelmeta().custom_metadata_map)
    info = read_model_info(path, meta)
    if arena is None and info.staged:  # the default depends on the graph: load it again
        return create_session(
            path, threads=threads, provider=provider, graph_opt=graph_opt, arena=True
        )
    check_io(path, info, {i.name for i in sess.get_inputs()}, {o.name for o in sess.get_outputs()})
    return ModelSession(sess, info, prov, threads)


def check_normals(path: Path, images: np.ndarray, normals: object) -> None:
    """A model's answer to images (B, N, 3, H, W) must be normals (B, 3, H, W): a larger one
    would be cropped silently and a smaller one fail deep in the stitching, so any other shape
    is one line naming the model file."""
    want = (images.shape[0], 3, *images.shape[3:5])
    shape = getattr(normals, "shape", None)
    if shape is None or tuple(shape) != want:
        if shape is None:
            got = "no array"
        elif len(shape) == 0:
            got = "() (a single number)"
        else:
            got = "x".join(str(d) for d in shape)
        raise InputError(
            f"the model returned normals of shape {got} for a {want[3]}x{want[2]} input "
            f"(expected {'x'.join(str(d) for d in want)}): not a working msfnet model",
            path,
        )


def check_io(path: Path, info: ModelInfo, inputs: set[str], outputs: set[str]) -> None:
    """The graph's inputs and outputs are msfnet's (plain or staged); InputError otherwise."""
    want_in, want_out = (
        (set(STAGE_INPUTS), set(STAGE_OUTPUTS))
        if info.staged
        else ({"images", "lights"}, {"normals"})
    )
    if inputs != want_in or not want_out <= outputs:
        raise InputError(
            f"not an msfnet {'staged ' if info.staged else ''}model: inputs "
            f"{sorted(inputs)}, outputs {sorted(outputs)} (expected "
            f"{', '.join(sorted(want_in))} -> {', '.join(sorted(want_out))})",
            path,
        )


__all__ = [
    "GRAPH_OPT_LEVELS",
    "MAX_THREADS",
    "ModelSession",
    "check_normals",
    "create_session",
    "default_threads",
    "resolve_provider",
]
