"""The OpenVINO engine: the same msfnet ONNX file, compiled by OpenVINO's CPU plugin.

Why it is here: on CPUs with native bf16 (AVX-512 bf16 or AMX), ``INFERENCE_PRECISION_HINT=bf16``
runs the fp32 model's convolutions in bf16 (speed and accuracy per CPU: docs/benchmark.md);
ONNX Runtime's CPU provider has no such path on x86. OpenVINO reads the ONNX file directly,
with the dynamic N, H, W kept (one compile serves every tile size). Staged exports are compiled
as four sub-models, one per entry point, and run through the same light-chunked loop as ONNX
Runtime (``staged_loop.run_staged``).

``openvino`` is part of the base install (x86-64 and ARM64 wheels), imported only when an engine
is opened. ``device``: CPU (default), GPU / GPU.N (Intel GPUs, f32 for parity with the CPU) or
NPU (Intel NPUs, their own f16), chosen through ``--device`` (dispatch.resolve_device).

Start-up: OpenVINO parses the file once (``read_openvino``); the msfnet metadata (the graph's
``rt_info["framework"]``) and the staged sub-models come from that parse, so this path starts no
ONNX Runtime session. :func:`import_openvino` leaves out the model converter and its telemetry.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import re
import stat
import sys
import threading
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from msfnet.common.cpu import cache_folder, check_threads
from msfnet.common.errors import InputError
from msfnet.common.privacy import telemetry_allowed
from msfnet.common.vocabulary import opt
from msfnet.runtime.contract import ModelInfo, read_model_info
from msfnet.runtime.engines.base import ModelFile, model_file_path, model_precision, read_model_file
from msfnet.runtime.engines.interrupt import run_interruptible
from msfnet.runtime.engines.method import RunMethod
from msfnet.runtime.engines.ort_session import check_io, check_normals, default_threads
from msfnet.runtime.engines.staged_loop import (
    DEFAULT_CHUNK,
    STAGE_OUTPUTS,
    placeholders,
    run_stages,
)

# OpenVINO's names for the compute precisions
_HINTS = {"fp32": "f32", "bf16": "bf16"}

# Compiled models are kept between processes in OpenVINO's model cache (keyed by the graph, the
# device and OpenVINO's version; a truncated entry is compiled again, other damage is not
# detected). MSFNET_OPENVINO_CACHE turns it off or on (spellings below; unset or empty: on).
CACHE_ENV = "MSFNET_OPENVINO_CACHE"
CACHE_OFF = ("0", "off", "false", "no")
CACHE_ON = ("1", "on", "true", "yes")
# lights per stage call for int8 models on the CPU (staged_loop.DEFAULT_CHUNK elsewhere): each
# stage model keeps an arena sized by its call; 2 lights a call keeps the times, a lower peak.
INT8_CHUNK = 2
_SS_DISABLE = 2  # sigaltstack's flag for "no alternate stack" (Linux)


class _SignalStack(ctypes.Structure):
    _fields_ = (("sp", ctypes.c_void_p), ("flags", ctypes.c_int), ("size", ctypes.c_size_t))


@contextlib.contextmanager
def _own_signal_stack() -> Iterator[None]:
    """Keep this thread's alternate signal stack through a compile. OpenVINO's CPU plugin gives
    the compiling thread a signal stack of its own (on Linux) and puts the previous one back
    when that model is freed: two models freed in the order they were made left the thread on
    freed memory, and the next Ctrl-C crashed the process (Python runs its handlers on that
    stack). Inference runs on other threads (interrupt.py), so the compiling thread needs none.
    Where the old stack cannot be put back (the kernel refuses one too small for the signal
    frame once AMX is in use), the thread is left with none rather than the plugin's."""
    libc: Any = None
    before = _SignalStack()
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            if libc.sigaltstack(None, ctypes.byref(before)) != 0:
                libc = None
        except Exception:  # no usable libc: nothing to keep
            libc = None
    try:
        yield
    finally:
        if libc is not None and libc.sigaltstack(ctypes.byref(before), None) != 0:
            libc.sigaltstack(ctypes.byref(_SignalStack(None, _SS_DISABLE, 0)), None)


def compile_stoppable(
    compile_all: Callable[[], dict[str, Any]], fallback: Callable[[], dict[str, Any]] | None
) -> dict[str, Any]:
    """``compile_all()`` where Ctrl-C and SIGTERM reach it: a model OpenVINO compiles for
    minutes (thousands of trivial nodes) held msf-run, deaf to Ctrl-C, as a run of a model that
    never finishes did (interrupt.py; a compile cannot be cancelled, so the process ends once
    the command has said its line). Where it fails, ``fallback()`` if given."""

    def work() -> dict[str, Any]:
        with _own_signal_stack():  # the compiling thread's, see there
            try:
                return compile_all()
            except Exception:
                if fallback is None:
                    raise
                return fallback()

    return run_interruptible(work, cancel=lambda: None)


def compile_cache() -> Path | None:
    """The folder OpenVINO keeps compiled models in (msfnet's user cache, ``openvino/``), or
    None: turned off by MSFNET_OPENVINO_CACHE (``cache_wanted``), or no folder of this user's
    own here (no home, a read-only one, a link, one other users may write into: its entries are
    loaded as they are): then every process compiles, as before. InputError for a value of
    MSFNET_OPENVINO_CACHE that is neither on nor off."""
    if not cache_wanted():
        return None
    try:
        folder = cache_folder() / "openvino"
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        st = os.lstat(folder)
    except (OSError, RuntimeError):
        return None
    mine = not hasattr(os, "getuid") or st.st_uid == os.getuid()
    private = stat.S_ISDIR(st.st_mode) and not st.st_mode & (stat.S_IWGRP | stat.S_IWOTH)
    if not (mine and private and os.access(folder, os.W_OK | os.X_OK)):
        return None
    return folder


def cache_wanted() -> bool:
    """Whether MSFNET_OPENVINO_CACHE leaves the compile cache on: unset, empty or an on spelling
    (CACHE_ON) is on, an off spelling (CACHE_OFF) off, either case-insensitive. Anything else
    is refused (InputError) rather than guessed: a user turning the cache off for its risk
    with a spelling taken for "on" would keep it without being told."""
    raw = os.environ.get(CACHE_ENV, "")
    value = raw.strip().lower()
    if value in ("", *CACHE_ON):
        return True
    if value in CACHE_OFF:
        return False
    raise InputError(
        f"{CACHE_ENV}={raw[:40]!r}: not an on/off value (off: {', '.join(CACHE_OFF)}; "
        f"on: {', '.join(CACHE_ON)}, or empty)"
    )


INSTALL_HINT = "pip install openvino (part of msfnet's base install)"


def import_openvino() -> Any:
    """``openvino``, imported with its usage telemetry off and without its model converter.

    ``import openvino`` with openvino-telemetry installed sends a usage event (forking, and
    waiting for the child at exit); a station should make no network calls of its own. So the
    telemetry package and the converter (``openvino.tools.ovc``, what sends it; the runtime
    never converts) are hidden while OpenVINO is first imported: OpenVINO imports both under
    try / except ImportError. The hiding is process-wide for that moment; a module the program
    had loaded is put back after. ``openvino.convert_model`` still works: the converter is
    imported on first use, its telemetry hidden too. ``MSFNET_TELEMETRY=1`` leaves OpenVINO as
    configured (msfnet.common.privacy); an OpenVINO the program imported itself is left alone."""
    hide = "openvino" not in sys.modules and not telemetry_allowed()
    try:
        with _hidden(TELEMETRY, CONVERTER) if hide else contextlib.nullcontext():
            import openvino
    except ImportError as exc:
        raise InputError(f"the OpenVINO engine needs the openvino package: {INSTALL_HINT}") from exc
    if hide and "convert_model" not in vars(openvino):
        openvino.__getattr__ = _converter_on_demand  # type: ignore[attr-defined]  # PEP 562
    return openvino


TELEMETRY = "openvino_telemetry"
CONVERTER = "openvino.tools.ovc"


@contextlib.contextmanager
def _hidden(*names: str) -> Iterator[None]:
    """Imports of ``names`` fail inside the block (a None entry in sys.modules); modules the
    program had loaded are put back after, the others can be imported normally again."""
    had = {name: sys.modules.get(name) for name in names}
    for name in names:
        sys.modules[name] = None  # type: ignore[assignment]
    try:
        yield
    finally:
        for name, module in had.items():
            if sys.modules.get(name, False) is None:
                if module is None:
                    del sys.modules[name]
                else:
                    sys.modules[name] = module


def _converter_on_demand(name: str) -> Any:
    """``openvino.convert_model`` for a program that asks for it after msfnet imported
    OpenVINO without its converter."""
    if name != "convert_model":
        raise AttributeError(f"module 'openvino' has no attribute {name!r}")
    with _hidden(TELEMETRY):
        from openvino.tools.ovc import convert_model
    return convert_model


def _effective(compiled: Any) -> str:
    """The precision OpenVINO actually chose (it falls back to f32 where bf16 is emulated)."""
    text = str(compiled.get_property("INFERENCE_PRECISION_HINT")).lower()
    return "bf16" if "bf16" in text or "bfloat16" in text else "fp32"


def _device_precision(compiled: Any, asked: str) -> str:
    """What a GPU / NPU computes: f16 and f32 are named as such; int8 models stay int8."""
    if asked == "int8":
        return "int8"
    try:
        text = str(compiled.get_property("INFERENCE_PRECISION_HINT")).lower()
    except Exception:  # a plugin without the property: its documented default
        return "fp16"
    return "fp16" if "16" in text else "fp32"


class OpenVinoEngine:
    name = "openvino"

    def __init__(
        self,
        compiled: dict[str, Any],
        info: ModelInfo,
        precision: str,
        threads: int,
        chunk: int = DEFAULT_CHUNK,
        device: str = "CPU",
        version: str = "",
        ov: Any = None,
    ) -> None:
        self._ov = ov  # the openvino module (its Tensor wraps the loop's buffer)
        # One call at a time: the infer requests below, and the output tensors _run_stage points
        # at the caller's buffer, belong to one run; two threads sharing them returned silently
        # wrong normals. ONNX Runtime's sessions are safe to share and need no lock.
        self._lock = threading.Lock()
        # output name -> (infer request, names of the inputs it needs)
        self._requests = {
            out: (c.create_infer_request(), [i.get_any_name() for i in c.inputs])
            for out, c in compiled.items()
        }
        self.info = info
        self.precision = precision
        self.threads = threads
        self.lights_per_call = chunk
        self.device = device
        self.version = version

    def _run_output(self, output: str, feeds: Any) -> np.ndarray:
        """A whole graph's normals, copied out of the request (a result outlives the next call)."""
        request, names = self._requests[output]
        inputs = {n: feeds[n] for n in names}
        return run_interruptible(  # Ctrl-C cancels the request (see interrupt.py)
            lambda: request.infer(inputs, share_inputs=True)[0], request.cancel
        )

    def _run_stage(self, output: str, feeds: dict[str, np.ndarray], out: np.ndarray) -> np.ndarray:
        """One chunk of a staged graph (staged_loop.StageCall): on the CPU the request reads its
        inputs where they lie and writes the per-light result straight into ``out`` (the loop's
        feature buffer), not copied there. The chunk's max is taken here by numpy: a ReduceMax
        output in the graph cost OpenVINO more than it saved."""
        request, names = self._requests[output]
        inputs = {n: feeds[n] for n in names}
        direct = self.device.upper().startswith("CPU") and out.flags.c_contiguous
        if direct:
            request.set_output_tensor(0, self._ov.Tensor(out, shared_memory=True))
        result = run_interruptible(
            lambda: request.infer(inputs, share_inputs=True, share_outputs=True), request.cancel
        )
        if not direct or result[0].ctypes.data != out.ctypes.data:  # a plugin kept its own
            out[...] = result[0]
        return out.max(axis=0, keepdims=True)

    def _release_arrays(self) -> None:
        """Point every request away from the arrays of the run just done. A Tensor made from a
        numpy array holds that array, and a request keeps its last tensors: the stage requests'
        inputs and outputs are views of the loop's feature buffer (hundreds of MB at 96
        lights), which would outlive the run and sit beside the next tile's, twice what tiling
        budgets. A request still busy (a cancelled call that did not stop) keeps them: it
        still reads and writes there."""
        spare = placeholders()
        cpu = self.device.upper().startswith("CPU")
        for output, (request, names) in self._requests.items():
            with contextlib.suppress(AttributeError):  # an OpenVINO without the attribute
                # OpenVINO's Python wrapper also keeps the last shared inputs itself
                request._inputs_data = None
            with contextlib.suppress(Exception):  # a busy request refuses: it keeps them
                for index, name in enumerate(names):
                    request.set_input_tensor(index, self._ov.Tensor(spare[name]))
                if output != "normals" and cpu:  # the outputs _run_stage set
                    request.set_output_tensor(0, self._ov.Tensor(spare["max1"]))

    def _final(self, pooled: np.ndarray) -> np.ndarray:
        return self._run_output("normals", {"max3": pooled})

    @property
    def chunk(self) -> int | None:
        return self.lights_per_call if self.info.staged else None

    def run(self, images: np.ndarray, lights: np.ndarray) -> np.ndarray:
        """Like ONNX Runtime's: every call stoppable by Ctrl-C, the result's shape checked."""
        with self._lock:
            try:
                if self.info.staged:
                    out = run_stages(
                        self._run_stage, self._final, images, lights, self.lights_per_call
                    )
                else:
                    out = self._run_output("normals", {"images": images, "lights": lights})
            finally:
                self._release_arrays()
        check_normals(self.info.path, images, out)
        return out

    def describe(self) -> RunMethod:
        return RunMethod.of_engine(self, device=self.device, openvino=self.version)

    def __repr__(self) -> str:
        return f"OpenVinoEngine({self.info.path.name}, {self.precision}, threads={self.threads})"


def _framework_metadata(graph: Any) -> dict[str, str] | None:
    """The ONNX file's metadata_props as OpenVINO's ONNX reader keeps them (``rt_info``), or None
    where this OpenVINO does not expose them (or the file has none)."""
    try:
        framework = graph.get_rt_info()["framework"]
        if not isinstance(framework, Mapping):
            return None
        return {str(k): str(v.astype(str)) for k, v in framework.items()}
    except Exception:  # older OpenVINO: no such key, or values it will not give as text
        return None


def _names(ports: Any) -> set[str]:
    """Every tensor name of a graph's inputs or outputs (OpenVINO may give a tensor aliases)."""
    return {name for port in ports for name in port.get_names()}


def _read_onnx(ov: Any, path: Path) -> Any:
    """OpenVINO's graph of an ONNX file, through its ONNX reader alone: ``Core.read_model`` would
    offer a file that is not ONNX to every reader, and the TensorFlow one prints parse errors
    on stderr. Raises whatever OpenVINO raises for a file it cannot read."""
    onnx = ov.frontend.FrontEndManager().load_by_framework("onnx")
    if not onnx.supported(str(path)):
        raise ValueError("not an ONNX file")
    return onnx.convert(onnx.load(str(path)))


def read_openvino(path: str | Path) -> ModelFile:
    """Read an msfnet ONNX file with OpenVINO: its checked metadata and the graph to compile.

    The metadata checks are ``read_model_file``'s (contract.read_model_info, then the graph's
    input and output names). Where OpenVINO cannot read the file, does not expose its metadata
    or finds it wanting, ``read_model_file`` (ONNX Runtime) has the last word: so this reader
    refuses exactly what that one refuses, in the same line, and costs an ONNX Runtime session
    only then. InputError if openvino is missing, or the file is missing, corrupt or not msfnet,
    or MSFNET_OPENVINO_CACHE has a value that is neither on nor off.
    """
    path = model_file_path(path)
    ov = import_openvino()
    # checked here, with the choice of engine, too: from open_openvino alone a default choice
    # would fall back to ONNX Runtime (dispatch.open_chosen) and the typo would go unrefused
    cache_wanted()
    try:
        graph = _read_onnx(ov, path)
    except Exception:  # not ONNX, or nothing OpenVINO parses: ONNX Runtime says which
        return ModelFile(read_model_file(path))
    meta = _framework_metadata(graph)
    if meta is not None:
        try:
            info = read_model_info(path, meta)
            check_io(path, info, _names(graph.inputs), _names(graph.outputs))
            return ModelFile(info, graph)
        except InputError:
            pass  # ONNX Runtime's verdict below, word for word
    return ModelFile(read_model_file(path), graph)


# ops whose input an int8 QDQ export quantises (OpenVINO's names): a requantisation is kept
# wherever it is the only one in front of such an op
_QUANTISED_INPUTS = frozenset(
    {"Convolution", "GroupConvolution", "ConvolutionBackpropData", "MatMul"}
)
# ops a requantised convolution output may pass through before the next layer's own FakeQuantize
_PASS_THROUGH = frozenset(
    {"PRelu", "Relu", "Concat", "DepthToSpace", "Reshape", "Add", "Multiply", "Sigmoid"}
)


def _constant(value: Any, depth: int = 8) -> bool:
    """Whether ``value`` depends on no input's values: a Constant, or a few ops on Constants and
    shapes (a dequantised bias is Constant -> Convert -> Multiply, reshaped to the rank of the
    convolution's output: a ShapeOf of it)."""
    node = value.get_node()
    kind = node.get_type_name()
    if kind in ("Constant", "ShapeOf"):
        return True
    if kind == "Parameter" or depth == 0 or node.get_input_size() == 0:
        return False
    return all(_constant(v, depth - 1) for v in node.input_values())


def _conv_output(fq: Any) -> bool:
    """Whether a FakeQuantize requantises a convolution's output, directly or after its bias
    (an Add of a constant: not a residual Add of two branches)."""
    node = fq.input_value(0).get_node()
    if node.get_type_name() == "Add":
        if not _constant(node.input_value(1)):
            return False
        node = node.input_value(0).get_node()
    return bool(node.get_type_name() in _QUANTISED_INPUTS - {"MatMul"})


def _only_consumer(node: Any, kind: str) -> Any | None:
    """``node``'s single consumer if it is a ``kind`` reading it as its first input, else None."""
    targets = list(node.output(0).get_target_inputs())
    if len(targets) != 1 or targets[0].get_index() != 0:
        return None
    consumer = targets[0].get_node()
    return consumer if consumer.get_type_name() == kind else None


def _dequantised(fq: Any) -> Any | None:
    """The Multiply that ends the DequantizeLinear after ``fq`` as OpenVINO's ONNX reader writes
    it (Convert to 8 bits, Convert back, an optional Subtract of a constant zero point, a
    Multiply by a constant scale), or None where the graph there is anything else: an op of
    the model itself is never taken for part of the pair."""
    narrow = _only_consumer(fq, "Convert")
    if narrow is None or narrow.get_output_element_type(0).bitwidth != 8:
        return None
    node = _only_consumer(narrow, "Convert")
    if node is None:
        return None
    zero_point = _only_consumer(node, "Subtract")
    if zero_point is not None:
        if not _constant(zero_point.input_value(1)):
            return None
        node = zero_point
    scale = _only_consumer(node, "Multiply")
    if scale is None or not _constant(scale.input_value(1)):
        return None
    return scale


def _requantised_again(port: Any) -> bool:
    """Whether every path from ``port`` meets another FakeQuantize (or a graph output) before
    any op that reads int8: so dropping the quantisation in front of it keeps every int8
    convolution int8."""
    stack, seen = [port], set()
    while stack:
        for target in stack.pop().get_target_inputs():
            node = target.get_node()
            kind = node.get_type_name()
            if kind in ("FakeQuantize", "Result") or node.get_name() in seen:
                continue
            if kind not in _PASS_THROUGH:
                return False
            seen.add(node.get_name())
            stack.extend(node.outputs())
    return True


def drop_output_requantisation(graph: Any) -> int:
    """Remove, in place, the quantise-dequantise pairs an int8 QDQ export puts on convolution
    outputs where the next layer quantises its own input again; returns how many.

    Why: those pairs only round a convolution's f32 result to 8 bits and back, and OpenVINO's
    CPU plugin runs them as separate kernels; the convolution stays int8 through its input and
    weight quantisation, and runs faster and closer to fp32 without them. ONNX Runtime needs
    the pairs for its int8 fusion: the file keeps them, this edits OpenVINO's graph only. Only
    the exact FakeQuantize -> Convert -> Convert -> [Subtract] -> Multiply shape is removed."""
    dropped = 0
    for fq in graph.get_ordered_ops():
        if fq.get_type_name() != "FakeQuantize" or not _conv_output(fq):
            continue
        last = _dequantised(fq)
        if last is None or not _requantised_again(last.output(0)):
            continue
        last.output(0).replace(fq.input_value(0))
        dropped += 1
    if dropped:
        graph.validate_nodes_and_infer_types()
    return dropped


def _sub_model(ov: Any, model: Any, output: str) -> Any:
    """The part of a staged graph that computes ``output``, with only the inputs it uses (so a
    call computes one stage, and no placeholders are fed). The four sub-models share ``model``'s
    nodes; compiling copies them, so one read of the file serves all four."""
    result = next(r for r in model.get_results() if output in r.input_value(0).get_names())
    # the parameters this output depends on: walk the graph upwards from the result
    needed, stack, seen = [], [result], set()
    while stack:
        node = stack.pop()
        # get_name() is unique per node; id() of the short-lived Python wrappers is not
        if node.get_name() in seen:
            continue
        seen.add(node.get_name())
        if node.get_type_name() == "Parameter":
            needed.append(node)
        stack.extend(v.get_node() for v in node.input_values())
    order = {p.get_friendly_name(): k for k, p in enumerate(model.get_parameters())}
    needed.sort(key=lambda p: order[p.get_friendly_name()])
    return ov.Model([result], needed, output)


# OpenVINO starts a message with one "Exception from <source file>:<line>:" line per layer it
# passed through (core, plugin, ...): the first line never says what went wrong
_LOCATION = re.compile(r"Exception from \S.*:\d+:")


def openvino_cause(exc: BaseException, limit: int = 300) -> str:
    """The cause in an OpenVINO exception's text, as one line of at most ~``limit`` characters:
    its last lines that are not location lines (as many as fit; the last one cut if it alone is
    longer), or "" where the text has none."""
    lines = [line.strip() for line in str(exc).splitlines()]
    said = [line for line in lines if line and not _LOCATION.fullmatch(line)]
    if not said:
        return ""
    cause = said.pop()
    if len(cause) > limit:
        return cause[:limit] + " ..."
    while said and len(said[-1]) + 1 + len(cause) <= limit:
        cause = f"{said.pop()} {cause}"
    return cause


def _check_precision(own: str, precision: str, info: ModelInfo) -> None:
    """The precision asked for against the model's own: an int8 model runs int8 only, and an
    fp32 one never int8."""
    if own == "int8" and precision != "int8":
        raise InputError(
            f"this is an int8 model; precision {precision} needs an fp32 export", info.path
        )
    if own == "fp32" and precision == "int8":
        raise InputError(
            "int8 needs an int8 export (msf-export --int8); this model is fp32", info.path
        )


def _compile_properties(
    device: str, precision: str, threads: int, config: dict[str, Any] | None
) -> dict[str, Any]:
    """OpenVINO's compile properties for ``device`` and ``precision`` (``config`` on top);
    InputError for bf16 anywhere but on the CPU."""
    if device.upper().startswith("CPU"):
        props: dict[str, Any] = {
            "INFERENCE_PRECISION_HINT": _HINTS["fp32" if precision == "int8" else precision],
            "INFERENCE_NUM_THREADS": threads,
            "PERFORMANCE_HINT": "LATENCY",
            "NUM_STREAMS": 1,  # one request at a time: all threads on it
        }
    elif precision == "bf16":
        raise InputError(
            f"{opt('precision', 'bf16')} is a CPU path; {device} runs the model's precision",
            option="precision",
        )
    elif device.upper().startswith("GPU"):
        # GPUs default to f16; f32 keeps the parity with CPU fp32 that --device promises
        props = {"INFERENCE_PRECISION_HINT": "f32", "PERFORMANCE_HINT": "LATENCY"}
    else:  # NPU: its own precision (f16 compute), no CPU threading properties
        props = {"PERFORMANCE_HINT": "LATENCY"}
    props.update(config or {})
    return props


def _compile(
    ov: Any, file: ModelFile, device: str, props: dict[str, Any], drop_requantisation: bool
) -> dict[str, Any]:
    """The file's graph compiled for ``device`` (through the compile cache where there is
    one): output name -> compiled model, one per stage of a staged export, else "normals".
    ``drop_requantisation``: compile the graph with ``drop_output_requantisation`` applied.
    InputError where OpenVINO cannot compile it."""
    info = file.info
    cache = compile_cache() if "CACHE_DIR" not in props else None
    core = ov.Core()
    if cache is not None:
        # a model loaded from the cache otherwise reads its weights from the mapped entry at
        # every call: another process rewriting that entry turned a running engine's normals
        # into NaN; read into memory it costs nothing measurable
        with contextlib.suppress(Exception):
            core.set_property({"ENABLE_MMAP": False})

    def compile_all(graph: Any, props: dict[str, Any]) -> dict[str, Any]:
        if info.staged:
            return {
                out: core.compile_model(_sub_model(ov, graph, out), device, props)
                for out in STAGE_OUTPUTS
            }
        return {"normals": core.compile_model(graph, device, props)}

    try:
        graph = file.openvino_graph
        if graph is None:  # read by ONNX Runtime (or unreadable to OpenVINO: fails here)
            graph = _read_onnx(ov, info.path)
        if drop_requantisation:
            graph = graph.clone()  # the file's graph stays as read
            drop_output_requantisation(graph)
        cached = {**props, "CACHE_DIR": str(cache)} if cache else props
        return compile_stoppable(
            lambda: compile_all(graph, cached),
            # the cache is a speed-up, never a new way to fail: without it, as before
            (lambda: compile_all(graph, props)) if cache else None,
        )
    except InputError:
        raise
    except Exception as exc:  # OpenVINO raises RuntimeError with long multi-line texts
        cause = openvino_cause(exc)
        raise InputError(
            f"OpenVINO cannot compile this model for {device} "
            f"({type(exc).__name__}{': ' + cause if cause else ''})",
            info.path,
        ) from exc


def _computed_precision(compiled: dict[str, Any], device: str, precision: str) -> str:
    """The precision the compiled models compute in; InputError for bf16 on a CPU where
    OpenVINO would not run it natively."""
    effective = _effective(next(iter(compiled.values())))
    if not device.upper().startswith("CPU"):
        effective = _device_precision(next(iter(compiled.values())), precision)
    elif precision == "bf16" and effective != "bf16":
        raise InputError(
            "OpenVINO runs bf16 only on CPUs with native bf16 (AVX-512 bf16 or "
            f"AMX); here it would compute {effective}: use {opt('precision', 'fp32')}"
        )
    return effective


def open_openvino(
    path: str | Path,
    *,
    threads: int | None = None,
    precision: str | None = None,
    chunk: int | None = None,
    device: str = "CPU",
    config: dict[str, Any] | None = None,
    file: ModelFile | None = None,
    requantise_outputs: bool = False,
) -> OpenVinoEngine:
    """Compile ``path`` with OpenVINO. ``precision``: fp32 or bf16 for fp32 models (default
    fp32), int8 (the default) for int8 QDQ models, whose non-quantised layers then run fp32.
    ``file``: ``path`` already read (by ``read_openvino``, or ONNX Runtime's metadata alone),
    so it is not read again. On the CPU an int8 model's convolution outputs stay f32 where the
    next layer quantises its input again (``drop_output_requantisation``: faster and closer to
    fp32); ``requantise_outputs=True`` runs the file's graph as it is.

    Raises InputError when openvino is missing, the file is not an msfnet model, or bf16 is
    asked for on a CPU where OpenVINO does not run bf16 natively.
    """
    ov = import_openvino()
    if file is None:
        file = read_openvino(path)
    info = file.info
    own = model_precision(info)
    precision = precision or own
    _check_precision(own, precision, info)
    threads = threads or default_threads()
    check_threads(threads)  # OpenVINO, too, starts its threads up front
    props = _compile_properties(device, precision, threads, config)
    cpu = device.upper().startswith("CPU")
    compiled = _compile(ov, file, device, props, own == "int8" and not requantise_outputs and cpu)
    effective = _computed_precision(compiled, device, precision)
    version = getattr(ov, "__version__", "") or str(ov.get_version())
    return OpenVinoEngine(
        compiled,
        info,
        precision if precision == "int8" else effective,
        threads,
        chunk or (INT8_CHUNK if own == "int8" and cpu else DEFAULT_CHUNK),
        device,
        version,
        ov,
    )


__all__ = [
    "CACHE_ENV",
    "CACHE_OFF",
    "CACHE_ON",
    "INSTALL_HINT",
    "INT8_CHUNK",
    "OpenVinoEngine",
    "cache_wanted",
    "compile_cache",
    "drop_output_requantisation",
    "import_openvino",
    "open_openvino",
    "openvino_cause",
    "read_openvino",
]
