"""choose_engine and resolve_device on faked CPUs, installed-engine sets and device lists (no
model is run here, except where a test says so)."""

from __future__ import annotations

from pathlib import Path

import pytest

from msfnet.common.cpu import CpuInfo
from msfnet.common.errors import InputError
from msfnet.common.vocabulary import speaking_as
from msfnet.runtime.contract import ModelInfo
from msfnet.runtime.engines import dispatch
from msfnet.runtime.engines.dispatch import (
    ACCURACY_BOUND_DEG,
    MEASURED,
    Measured,
    choose_engine,
    default_allowed,
    open_engine,
)

ZEN3 = CpuInfo.from_flags(["avx2", "fma"], model="AMD EPYC 7B13", cores=2)
# AVX-512 bf16 without AMX: Zen 4 (AMD family 25, AVX-512 on 256-bit halves) was measured, Zen
# 5 (family 26) and Intel Cooper Lake were not (dispatch.cpu_class)
_BF16_FLAGS = ["avx2", "avx512f", "avx512_vnni", "avx512_bf16"]
ZEN4 = CpuInfo.from_flags(_BF16_FLAGS, model="AMD EPYC", vendor="AuthenticAMD", family=25)
ZEN5 = CpuInfo.from_flags(
    [*_BF16_FLAGS, "avx_vnni"], model="AMD EPYC", vendor="AuthenticAMD", family=26
)
# Zen 4 under hypervisors that hide some AVX-512 extensions
ZEN4_NO_VNNI = CpuInfo.from_flags(
    ["avx2", "avx512f", "avx512_bf16"], vendor="AuthenticAMD", family=25
)
ZEN4_NO_BF16 = CpuInfo.from_flags(
    ["avx2", "avx512f", "avx512_vnni"], vendor="AuthenticAMD", family=25
)
COOPER = CpuInfo.from_flags(
    _BF16_FLAGS, model="Xeon (Cooper Lake)", vendor="GenuineIntel", family=6
)
ZEN4_NO_VENDOR = CpuInfo.from_flags(_BF16_FLAGS, model="Zen 4, family unknown")
SKYLAKE = CpuInfo.from_flags(["avx2", "avx512f"], model="Xeon (AVX-512, no bf16)")
ARM = CpuInfo.from_flags(["neon", "asimd", "sve"], model="Cortex-A78", vendor="ARM")
ALDER = CpuInfo.from_flags(["avx2", "avx_vnni"], model="Core (AVX-VNNI, no AVX-512)")
AMX = CpuInfo.from_flags(
    [
        "avx2",
        "avx512f",
        "avx512_vnni",
        "avx512_bf16",
        "avx_vnni",
        "amx_bf16",
        "amx_int8",
        "amx_tile",
    ],
    model="Xeon (AMX)",
)
BOTH = {"onnxruntime", "openvino"}
ORT = {"onnxruntime"}


def info(precision: str = "fp32", staged: bool = False) -> ModelInfo:
    return ModelInfo(Path("model.onnx"), 32, 4, None, precision, {}, staged=staged)


FP32, FP32_STAGED = info(), info(staged=True)
FP16W = info("fp32 (fp16-stored weights)")  # the bundled model's metadata
INT8, INT8_STAGED = info("int8-qdq"), info("int8-qdq", staged=True)  # min/max ranges (old)
# an export as msf-export makes it now, like the bundled twin: staged, percentile ranges
TWIN = ModelInfo(
    Path("twin.onnx"),
    32,
    4,
    None,
    "int8-qdq",
    {"msfnet.quantization": '{"ranges_from_percentiles": 12, "reduce_range": true}'},
    staged=True,
)


@pytest.mark.parametrize(
    ("cpu", "installed", "model", "engine", "precision"),
    [
        # fp32 models: bf16 through OpenVINO only with native bf16 and OpenVINO installed;
        # else OpenVINO fp32 on the classes where it was measured faster (AVX2-only, AMX)
        (ZEN3, BOTH, FP32, "openvino", "fp32"),
        (SKYLAKE, BOTH, FP32, "onnxruntime", "fp32"),  # not measured there
        (ARM, BOTH, FP32, "onnxruntime", "fp32"),
        (ARM, BOTH, FP32_STAGED, "onnxruntime", "fp32"),
        (ZEN3, ORT, FP32, "onnxruntime", "fp32"),
        (ZEN5, BOTH, FP32, "openvino", "bf16"),
        (ZEN5, ORT, FP32, "onnxruntime", "fp32"),
        (ZEN4, BOTH, FP32, "openvino", "bf16"),  # an fp32 export: bf16 (the twin is a file)
        (ZEN4, BOTH, TWIN, "openvino", "int8"),
        (AMX, BOTH, FP32, "openvino", "bf16"),
        (AMX, BOTH, FP16W, "openvino", "bf16"),
        (AMX, BOTH, FP32_STAGED, "openvino", "bf16"),
        (ZEN3, BOTH, FP32_STAGED, "openvino", "fp32"),
        (ZEN3, ORT, FP32_STAGED, "onnxruntime", "fp32"),
        (AMX, ORT, FP32_STAGED, "onnxruntime", "fp32"),
        # int8 models run int8: through OpenVINO on the classes where it was measured as fast as
        # ONNX Runtime int8 or faster (AVX2 without VNNI, VNNI, AMX), else ONNX Runtime
        (ZEN3, BOTH, TWIN, "openvino", "int8"),
        # at par on AVX2 and not measured closer for old min/max exports: ONNX Runtime
        (ZEN3, BOTH, INT8, "onnxruntime", "int8"),
        (ZEN5, BOTH, INT8, "openvino", "int8"),
        (SKYLAKE, BOTH, INT8, "onnxruntime", "int8"),  # AVX-512 without VNNI: not measured
        (AMX, BOTH, INT8_STAGED, "openvino", "int8"),
        (AMX, {"openvino"}, INT8, "openvino", "int8"),
        (ZEN3, ORT, INT8, "onnxruntime", "int8"),
        # only OpenVINO installed, on a class where nothing favours it: still OpenVINO
        (SKYLAKE, {"openvino"}, FP32, "openvino", "fp32"),
        (ARM, {"openvino"}, FP32_STAGED, "openvino", "fp32"),
        (ARM, BOTH, INT8, "onnxruntime", "int8"),  # nothing measured there
    ],
)
def test_defaults(cpu, installed, model, engine, precision) -> None:
    choice = choose_engine(model, cpu, installed)
    assert (choice.engine, choice.precision) == (engine, precision)
    assert choice.reason.startswith(f"{engine} {precision}: ")


def test_reasons_say_why() -> None:
    assert "no native bf16" in choose_engine(FP32, ZEN3, BOTH).reason
    assert "1.36x ONNX Runtime fp32" in choose_engine(FP32, ZEN3, BOTH).reason
    assert "not measured faster" in choose_engine(FP32, ARM, BOTH).reason
    assert "not installed" in choose_engine(FP32, AMX, ORT).reason
    assert "AMX" in choose_engine(FP32, AMX, BOTH).reason
    assert "avx512_bf16" in choose_engine(FP32, ZEN5, BOTH).reason
    assert "emulated" in choose_engine(INT8, ZEN3, BOTH).reason
    assert "VNNI/AMX" in choose_engine(INT8, ZEN5, BOTH).reason


@pytest.mark.parametrize(
    ("cpu", "model", "eng", "prec", "engine", "precision"),
    [
        (ZEN3, FP32, "openvino", None, "openvino", "fp32"),  # OpenVINO without bf16 hardware
        (AMX, FP32, "ov", None, "openvino", "bf16"),  # alias
        (AMX, FP32, "ort", None, "onnxruntime", "fp32"),  # --engine ort keeps fp32
        (AMX, FP32, None, "fp32", "openvino", "fp32"),  # fp32 on the faster fp32 engine
        (ARM, FP32, None, "fp32", "onnxruntime", "fp32"),
        (ZEN4, FP32, None, "fp32", "openvino", "fp32"),  # measured faster on Zen 4
        (ZEN5, FP32, None, "fp32", "onnxruntime", "fp32"),  # not measured on Zen 5
        (ZEN3, FP32, "ort", "fp32", "onnxruntime", "fp32"),
        (AMX, FP32, "openvino", "fp32", "openvino", "fp32"),
        (ZEN5, FP32_STAGED, None, "bf16", "openvino", "bf16"),
        (ZEN3, INT8, "openvino", None, "openvino", "int8"),
        (AMX, INT8, None, "int8", "openvino", "int8"),
        (AMX, INT8, "ort", None, "onnxruntime", "int8"),
        (AMX, FP32, None, "BF16", "openvino", "bf16"),  # case-insensitive
    ],
)
def test_overrides(cpu, model, eng, prec, engine, precision) -> None:
    choice = choose_engine(model, cpu, BOTH, eng, prec)
    assert (choice.engine, choice.precision) == (engine, precision)


@pytest.mark.parametrize(
    ("cpu", "installed", "model", "eng", "prec", "message"),
    [
        (ZEN3, BOTH, FP32, None, "bf16", "no native bf16"),
        (AMX, BOTH, FP32, "onnxruntime", "bf16", "no bf16 path"),
        (AMX, ORT, FP32, None, "bf16", "not installed"),
        (AMX, ORT, FP32, "openvino", None, "not installed"),
        (AMX, BOTH, FP32, None, "int8", "int8 export"),
        (AMX, BOTH, INT8, None, "fp32", "int8 model"),
        (AMX, BOTH, INT8, None, "bf16", "int8 model"),
        (AMX, BOTH, FP32, "tensorrt", None, "expected one of"),
        (AMX, BOTH, FP32, None, "fp16", "expected one of"),
    ],
)
def test_impossible_overrides_are_errors(cpu, installed, model, eng, prec, message) -> None:
    with pytest.raises(InputError, match=message):
        choose_engine(model, cpu, installed, eng, prec)


def test_a_precision_outside_the_bound_is_no_default(monkeypatch: pytest.MonkeyPatch) -> None:
    # if bf16 were measured 0.6 deg off fp32, the AMX machine would stay on fp32 by default ...
    monkeypatch.setitem(
        MEASURED, ("openvino", "bf16", False), Measured({32: (0.6, 3.0), 96: (0.4, 2.0)})
    )
    assert not default_allowed("openvino", "bf16", False)
    choice = choose_engine(FP32, AMX, BOTH)
    assert (choice.engine, choice.precision) == ("openvino", "fp32")
    assert "accuracy bound" in choice.reason
    # ... but still run bf16 when asked, and the staged graph keeps its own measurement
    assert choose_engine(FP32, AMX, BOTH, None, "bf16").precision == "bf16"
    assert choose_engine(FP32_STAGED, AMX, BOTH).precision == "bf16"


def test_measurements_back_every_default() -> None:
    # each reduced precision a default rule can pick has a measurement at 32 and 96 lights,
    # and the bound is the 0.5 deg
    assert ACCURACY_BOUND_DEG == 0.5
    for staged in (False, True):
        for key in (("openvino", "bf16", staged), ("onnxruntime", "int8", staged)):
            assert set(MEASURED[key].deg) >= {32, 96}, key


def test_choose_from_a_path_reads_metadata(tmp_path: Path) -> None:
    from msfnet.runtime.api import default_model_path

    choice = choose_engine(default_model_path(), ARM, BOTH)
    assert (choice.engine, choice.precision, choice.model) == (
        "onnxruntime",
        "fp32",
        default_model_path(),
    )
    bogus = tmp_path / "x.onnx"
    bogus.write_bytes(b"not onnx")
    with pytest.raises(InputError, match="cannot load"):
        choose_engine(bogus, ARM, BOTH)


def test_open_engine_needs_a_model() -> None:
    with pytest.raises(InputError, match="no model path"):
        open_engine(dispatch.EngineChoice("onnxruntime", "fp32", "test"))
    with pytest.raises(InputError, match="unknown engine"):
        open_engine(dispatch.EngineChoice("tvm", "fp32", "test", Path("m.onnx")))


def test_engine_override_reason_points_at_the_faster_path() -> None:
    with speaking_as("msf-run"):  # the reason names settings as its reader sets them
        assert "--engine openvino" in choose_engine(FP32, AMX, BOTH, "onnxruntime").reason
    assert "engine='openvino'" in choose_engine(FP32, AMX, BOTH, "onnxruntime").reason
    # an int8 export without percentile ranges (made before them) is measured above the bound
    over = choose_engine(INT8, AMX, BOTH, "openvino").reason
    assert "above the 0.5 deg bound" in over and "percentile" in over
    assert "above the 0.5 deg bound" in choose_engine(INT8_STAGED, AMX, BOTH, "openvino").reason
    assert "above" not in choose_engine(FP32, AMX, BOTH).reason  # the bf16 default is within


def test_a_precision_outside_the_bound_falls_to_fp32_on_the_faster_engine(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # bf16 out of bound on AMX: fp32 then, on OpenVINO (measured faster there) ...
    monkeypatch.setitem(
        MEASURED, ("openvino", "bf16", False), Measured({32: (0.6, 3.0), 96: (0.4, 2.0)})
    )
    assert choose_engine(FP32, AMX, BOTH).engine == "openvino"
    # ... and on ONNX Runtime where no speed-up was measured for the class
    monkeypatch.setitem(dispatch.OV_FP32_SPEEDUP, "amx", 0.9)
    assert choose_engine(FP32, AMX, BOTH).engine == "onnxruntime"


@pytest.mark.parametrize(
    ("cpu", "klass"),
    [
        (ZEN3, "avx2"),
        (ZEN4, "zen4"),
        (ZEN5, "avx512-bf16"),
        (COOPER, "avx512-bf16"),
        (ZEN4_NO_VENDOR, "avx512-bf16"),
        (SKYLAKE, "avx512"),
        (AMX, "amx"),
        (ARM, "other"),
    ],
)
def test_cpu_classes(cpu, klass) -> None:
    assert dispatch.cpu_class(cpu) == klass
    assert dispatch.ov_fp32_preferred(cpu) == (klass in ("avx2", "amx", "zen4"))


CUDA_ORT = ["TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"]
CPU_ORT = ["CPUExecutionProvider"]


@pytest.mark.parametrize(
    ("name", "providers", "ov", "engine", "target"),
    [
        ("cuda", CUDA_ORT, ["CPU"], "onnxruntime", "CUDAExecutionProvider"),
        ("TensorRT", CUDA_ORT, [], "onnxruntime", "TensorrtExecutionProvider"),
        ("gpu", CPU_ORT, ["CPU", "GPU"], "openvino", "GPU"),
        ("gpu", CPU_ORT, ["CPU", "GPU.0", "GPU.1"], "openvino", "GPU"),
        ("gpu.1", CPU_ORT, ["CPU", "GPU.0", "GPU.1"], "openvino", "GPU.1"),
        ("npu", CPU_ORT, ["CPU", "NPU"], "openvino", "NPU"),
        # OpenVINO's name of a lone GPU / NPU accepts ".0" (review-dispatch23.md 9)
        ("gpu.0", CPU_ORT, ["CPU", "GPU"], "openvino", "GPU"),
        ("npu.0", CPU_ORT, ["CPU", "NPU"], "openvino", "NPU"),
    ],
)
def test_devices_resolve_to_their_engine(name, providers, ov, engine, target) -> None:
    device = dispatch.resolve_device(name, providers, ov)
    assert device is not None
    assert (device.engine, device.target) == (engine, target)
    choice = choose_engine(FP32_STAGED, AMX, BOTH, device=device)
    # the device's engine, the model's precision (no bf16 off the CPU), said in the reason
    assert (choice.engine, choice.precision, choice.device) == (engine, "fp32", device)
    assert f"device={device.name!r} given" in choice.reason  # from Python: the keyword
    assert choose_engine(INT8, AMX, BOTH, device=device).precision == "int8"


def test_cpu_is_no_device() -> None:
    assert dispatch.resolve_device(None, [], []) is None
    assert dispatch.resolve_device("CPU", [], []) is None


@pytest.mark.parametrize(
    ("name", "providers", "ov", "message"),
    [
        ("cuda", CPU_ORT, ["CPU"], "ONNX Runtime has no CUDAExecutionProvider here"),
        ("tensorrt", CPU_ORT, ["CPU"], "onnxruntime-gpu built with TensorRT"),
        ("gpu", CPU_ORT, ["CPU"], "OpenVINO sees no GPU here .devices: CPU."),
        ("gpu.2", CPU_ORT, ["CPU", "GPU.0", "GPU.1"], "no GPU.2 here"),
        ("npu", CPU_ORT, [], "none, or OpenVINO is not installed"),
        ("tpu", CPU_ORT, [], "expected one of cpu, cuda, tensorrt, gpu, npu"),
        ("cuda.1", CUDA_ORT, [], "expected one of"),
    ],
)
def test_absent_devices_are_one_line_refusals(name, providers, ov, message) -> None:
    with pytest.raises(InputError, match=message) as err:
        dispatch.resolve_device(name, providers, ov)
    assert "\n" not in str(err.value)


def test_device_conflicts_are_errors() -> None:
    cuda = dispatch.Device("cuda", "onnxruntime", "CUDAExecutionProvider")
    gpu = dispatch.Device("gpu", "openvino", "GPU")
    with (
        speaking_as("msf-run"),
        pytest.raises(
            InputError, match=r"^--device cuda runs on onnxruntime, not --engine openvino$"
        ),
    ):
        choose_engine(FP32, AMX, BOTH, "openvino", device=cuda)
    with pytest.raises(InputError, match="bf16 is a CPU path"):
        choose_engine(FP32, AMX, BOTH, None, "bf16", device=gpu)
    with pytest.raises(InputError, match="openvino is not installed"):
        choose_engine(FP32, AMX, ORT, device=gpu)


def test_this_machine_refuses_absent_devices_in_one_line() -> None:
    # no GPU or NPU here (CI, this machine): the real availability query says so in one line;
    # where one is present the device resolves instead
    for name in ("cuda", "tensorrt", "gpu", "npu"):
        try:
            with speaking_as("msf-run"):
                device = dispatch.resolve_device(name)
        except InputError as exc:
            assert "\n" not in str(exc) and f"--device {name}" in str(exc)
        else:
            assert device is not None and device.name == name


def test_open_chosen_falls_back_to_ort_only_for_defaults(monkeypatch: pytest.MonkeyPatch) -> None:
    from msfnet.runtime.api import default_model_path

    def broken(*args, **kwargs):
        raise InputError("OpenVINO cannot compile this model for CPU (RuntimeError: test)")

    monkeypatch.setattr("msfnet.runtime.engines.openvino.open_openvino", broken)
    choice = choose_engine(default_model_path(), ZEN3, BOTH)
    assert choice.engine == "openvino"
    engine, reason = dispatch.open_chosen(choice, 1)
    assert engine.name == "onnxruntime" and engine.precision == "fp32"
    assert reason.startswith("onnxruntime fp32: fallback, OpenVINO failed")
    with pytest.raises(InputError, match="cannot compile"):
        dispatch.open_chosen(choice, 1, requested=True)
    # an OpenVINO-only install: OpenVINO's failure in one line, not "internal error:
    # ModuleNotFoundError" (review-dispatch23.md 6)
    monkeypatch.setattr(dispatch, "installed_engines", lambda: {"openvino"})
    with pytest.raises(InputError, match=r"cannot compile .*ONNX Runtime, the fallback, is not"):
        dispatch.open_chosen(choice, 1)


def test_a_file_openvino_cannot_read_without_onnx_runtime_is_one_error(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    import sys

    from msfnet.runtime.engines import read_model_file

    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"not a model")
    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # import onnxruntime fails
    with pytest.raises(InputError, match="ONNX Runtime, the other reader, is not installed"):
        read_model_file(garbage)


@pytest.mark.filterwarnings("ignore:Specified provider")
def test_a_gpu_provider_that_cannot_start_is_no_silent_cpu_run(monkeypatch, tmp_path) -> None:
    # an onnxruntime build that lists CUDA but cannot start it (no driver): ONNX Runtime itself
    # would carry on on the CPU; msfnet refuses in one line
    import onnxruntime
    from _runtime_helpers import tiny_msfnet_onnx

    listed = [*onnxruntime.get_available_providers(), "CUDAExecutionProvider"]
    monkeypatch.setattr(onnxruntime, "get_available_providers", lambda: listed)
    device = dispatch.resolve_device("cuda")
    assert device is not None
    model = tiny_msfnet_onnx(tmp_path / "tiny.onnx")
    choice = choose_engine(model, AMX, BOTH, device=device)
    with pytest.raises(InputError, match="CUDAExecutionProvider is built in but could not start"):
        open_engine(choice, 1)


def test_a_mixed_precision_int8_export_is_said_to_be_within_the_bound() -> None:
    mixed = ModelInfo(
        Path("m.onnx"), 32, 4, None, "int8-qdq", {"msfnet.variant": "int8-mixed"}, staged=False
    )
    reason = choose_engine(mixed, AMX, BOTH).reason
    assert "mixed precision" in reason and "within the bound" in reason and "above" not in reason
    assert "above the 0.5 deg bound" in choose_engine(INT8, AMX, BOTH).reason


@pytest.mark.parametrize("threads", [0, 1025, True])
def test_open_engine_bounds_threads_with_the_shared_constant(threads: int) -> None:
    """The bound is common.cpu.MAX_THREADS, checked before any file is touched (bool too)."""
    from msfnet.common.cpu import MAX_THREADS

    choice = dispatch.EngineChoice("onnxruntime", "fp32", "test", Path("missing.onnx"))
    with pytest.raises(InputError, match=rf"threads must be an integer in 1\.\.{MAX_THREADS}"):
        open_engine(choice, threads)


@pytest.mark.parametrize("staged", [False, True])
@pytest.mark.parametrize("engine", ["onnxruntime", "openvino"])
def test_an_int8_export_with_percentile_ranges_is_within_the_bound(
    engine: str, staged: bool
) -> None:
    import json

    summary = {
        "msfnet.quantization": json.dumps({"method": "percentile", "ranges_from_percentiles": 24})
    }
    model = ModelInfo(Path("m.onnx"), 32, 4, None, "int8-qdq", summary, staged=staged)
    reason = choose_engine(model, AMX, BOTH, engine).reason
    assert "above" not in reason and "min/max" not in reason
    assert default_allowed(engine, "int8", staged)
    # older exports (min/max ranges; ORT's own percentile calibrator also wrote "percentile")
    # and damaged metadata, nested deep enough to stop json too
    for damaged in (
        "{not json",
        json.dumps({"method": "minmax"}),
        json.dumps({"method": "percentile"}),
        json.dumps([1]),
        "[" * 100_000,
    ):
        old = ModelInfo(
            Path("m.onnx"), 32, 4, None, "int8-qdq", {"msfnet.quantization": damaged}, staged
        )
        assert "above the 0.5 deg bound" in choose_engine(old, AMX, BOTH, engine).reason


def test_int8_classes() -> None:
    assert [dispatch.int8_class(c) for c in (ZEN3, SKYLAKE, ZEN5, AMX, ARM, ALDER, ZEN4)] == [
        "avx2",
        "avx512",
        "vnni",
        "amx",
        "other",
        "avx2_vnni",
        "zen4",
    ]
    assert "int8 speed not measured" in choose_engine(INT8, ARM, BOTH).reason
    # AVX-512 without VNNI runs AVX-512BW kernels there, never timed (review-dispatch23.md 12)
    assert "int8 speed not measured on this CPU class" in choose_engine(INT8, SKYLAKE, BOTH).reason
    assert "emulated with AVX2" in choose_engine(INT8, ZEN3, BOTH).reason
    reason = choose_engine(TWIN, ZEN3, BOTH).reason
    assert "OpenVINO measured 1.00x ONNX Runtime int8" in reason and "(avx2)" in reason
    assert "closer to fp32" in reason
    # faster but not measured closer (old min/max exports on VNNI): no such claim
    reason = choose_engine(INT8_STAGED, ZEN5, BOTH).reason
    vnni = dispatch.OV_INT8_SPEEDUP["vnni"]
    assert f"OpenVINO measured {vnni:.2f}x" in reason and "closer to fp32" not in reason


@pytest.mark.parametrize(("ratio", "engine"), [(0.96, "openvino"), (0.94, "onnxruntime")])
def test_openvino_int8_stays_the_default_within_the_spread_of_its_measurement(
    monkeypatch: pytest.MonkeyPatch, ratio: float, engine: str
) -> None:
    """At the same speed OpenVINO int8 is the closer to fp32: it is kept down to
    OV_INT8_MIN_SPEEDUP, and ONNX Runtime takes over below."""
    monkeypatch.setitem(dispatch.OV_INT8_SPEEDUP, "avx2", ratio)
    assert choose_engine(TWIN, ZEN3, BOTH).engine == engine
    # kinds of export where OpenVINO was not measured closer need it faster
    assert choose_engine(INT8_STAGED, ZEN3, BOTH).engine == "onnxruntime"
    assert dispatch.ov_int8_closer(TWIN) and dispatch.ov_int8_closer(None)
    assert not dispatch.ov_int8_closer(INT8) and not dispatch.ov_int8_closer(INT8_STAGED)
    assert (
        dispatch.MEASURED[("openvino", "int8", True)].worst_mean
        < dispatch.MEASURED[("onnxruntime", "int8", True)].worst_mean
    )


@pytest.mark.parametrize(
    ("cpu", "installed", "eng", "prec", "device", "precision"),
    [
        # int8 where the fp32 file would run fp32 and int8 was measured faster on the class
        (ZEN3, BOTH, None, None, None, "int8"),
        (ZEN3, ORT, None, None, None, "int8"),
        (SKYLAKE, BOTH, None, None, None, "fp32"),  # AVX-512 without VNNI: not measured
        (ALDER, BOTH, None, None, None, "int8"),  # AVX-VNNI
        (AMX, ORT, None, None, None, "int8"),  # bf16 needs OpenVINO: ORT int8 beats ORT fp32
        # a named engine alone keeps the fp32 file (--engine onnxruntime: the fp32 reference)
        (ZEN3, BOTH, "onnxruntime", None, None, "fp32"),
        (ZEN3, BOTH, "openvino", None, None, "fp32"),
        (AMX, BOTH, "onnxruntime", None, None, "fp32"),
        # native bf16 through OpenVINO is faster still: the fp32 file
        (AMX, BOTH, None, None, None, "fp32"),
        (ZEN5, BOTH, None, None, None, "fp32"),
        (ZEN5, BOTH, "openvino", None, None, "fp32"),
        (ZEN5, ORT, None, None, None, "int8"),
        # Zen 4: bf16 on 256-bit halves, the int8 twin on OpenVINO measured faster than bf16
        (ZEN4, BOTH, None, None, None, "int8"),
        (ZEN4, {"openvino"}, None, None, None, "int8"),
        (ZEN4, ORT, None, None, None, "int8"),  # no bf16 without OpenVINO: over ORT fp32
        (ZEN4, BOTH, "openvino", None, None, "fp32"),
        (ZEN4, BOTH, None, "bf16", None, "fp32"),
        (ZEN4, BOTH, None, None, dispatch.Device("gpu", "openvino", "GPU"), "fp32"),
        # the same flags, not measured (Cooper Lake; a Zen 4 whose family is not known): bf16
        (COOPER, BOTH, None, None, None, "fp32"),
        (ZEN4_NO_VENDOR, BOTH, None, None, None, "fp32"),
        (ARM, BOTH, None, None, None, "fp32"),  # nothing measured there
        # a precision asked for decides; a device runs the portable fp32 file
        (ZEN3, BOTH, None, "fp32", None, "fp32"),
        (ZEN3, BOTH, None, "FP32", None, "fp32"),
        (AMX, BOTH, None, "bf16", None, "fp32"),
        (AMX, BOTH, None, "int8", None, "int8"),
        (ARM, BOTH, None, "int8", None, "int8"),
        (ZEN3, BOTH, None, None, dispatch.Device("cuda", "onnxruntime", "CUDA"), "fp32"),
        (ZEN3, BOTH, None, "int8", dispatch.Device("gpu", "openvino", "GPU"), "int8"),
        # an engine that is not installed: the fp32 file, choose_engine words the error
        (ZEN3, ORT, "openvino", None, None, "fp32"),
    ],
)
def test_the_bundled_pair(cpu, installed, eng, prec, device, precision) -> None:
    pick = dispatch.bundled_precision(cpu, installed, eng, prec, device)
    assert pick.precision == precision
    if precision == "int8" and prec is None and "openvino" in installed and cpu.has_bf16:
        klass = dispatch.cpu_class(cpu)
        assert f"int8 measured {dispatch.INT8_OVER_BF16[klass]}x bf16" in pick.reason
        assert "would run in bf16 here" in pick.reason and f"({klass})" in pick.reason
    elif precision == "int8" and prec is None:
        klass = dispatch.int8_class(cpu)
        assert f"int8 measured {dispatch.INT8_SPEEDUP[klass]}x fp32" in pick.reason
        assert "would run in fp32 here" in pick.reason and f"({klass})" in pick.reason
    elif precision == "fp32":
        assert pick.reason == ""


def test_the_bundled_int8_file_is_no_default_outside_the_bound(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    assert dispatch.bundled_precision(ZEN3, BOTH).precision == "int8"
    monkeypatch.setitem(dispatch.OV_INT8_SPEEDUP, "avx2", 1.1)  # OpenVINO on its speed alone
    worse = Measured({32: (0.4, 2.0), 96: (0.6, 3.0)})
    monkeypatch.setitem(MEASURED, ("openvino", "int8", True), worse)
    assert dispatch.bundled_precision(ZEN3, BOTH).precision == "fp32"
    assert dispatch.bundled_precision(ZEN3, ORT).precision == "int8"  # ORT's is within
    monkeypatch.setitem(dispatch.INT8_SPEEDUP, "avx2", 0.9)
    assert dispatch.bundled_precision(ZEN3, ORT).precision == "fp32"


@pytest.mark.parametrize(
    ("cpu", "klass", "int8", "bundled"),
    [
        (ZEN4, "zen4", "zen4", "int8"),
        # bf16 without VNNI: not the chip measured for int8 over bf16; bf16 stays
        (ZEN4_NO_VNNI, "avx512-bf16", "avx512", "fp32"),
        # no bf16 shown: the flag class for fp32 engines, the chip's own int8 figures
        (ZEN4_NO_BF16, "avx512", "zen4", "int8"),
        (ZEN4_NO_VENDOR, "avx512-bf16", "vnni", "fp32"),
    ],
)
def test_zen4_needs_its_family_and_the_extensions_it_was_measured_with(
    cpu: CpuInfo, klass: str, int8: str, bundled: str
) -> None:
    assert (dispatch.cpu_class(cpu), dispatch.int8_class(cpu)) == (klass, int8)
    assert dispatch.bundled_precision(cpu, BOTH).precision == bundled


def test_the_bundled_int8_file_over_bf16_only_where_measured_faster(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """On a bf16 CPU the twin replaces bf16 only where OpenVINO's int8 was measured faster than
    bf16 on the class (above 1, not at 1), and only within the bound."""
    assert dispatch.INT8_OVER_BF16["zen4"] > 1.0 > dispatch.INT8_OVER_BF16["amx"]
    assert "avx512-bf16" not in dispatch.INT8_OVER_BF16  # Zen 5, Cooper Lake: not measured
    assert dispatch.bundled_precision(ZEN4, BOTH).precision == "int8"
    monkeypatch.setitem(dispatch.INT8_OVER_BF16, "zen4", 1.0)
    assert dispatch.bundled_precision(ZEN4, BOTH).precision == "fp32"
    monkeypatch.setitem(dispatch.INT8_OVER_BF16, "zen4", 1.2)
    monkeypatch.setitem(dispatch.INT8_OVER_BF16, "amx", 1.2)
    assert dispatch.bundled_precision(AMX, BOTH).precision == "int8"
    # measured against OpenVINO's int8: where ONNX Runtime would run the twin, bf16 stays
    monkeypatch.setitem(dispatch.OV_INT8_SPEEDUP, "zen4", 0.5)
    assert dispatch.bundled_precision(ZEN4, BOTH).precision == "fp32"
    monkeypatch.setitem(dispatch.OV_INT8_SPEEDUP, "zen4", 1.2)
    worse = Measured({32: (0.4, 2.0), 96: (0.6, 3.0)})
    monkeypatch.setitem(MEASURED, ("openvino", "int8", True), worse)
    assert dispatch.bundled_precision(ZEN4, BOTH).precision == "fp32"
    # and what each file then runs as: the twin on OpenVINO int8, an fp32 export in bf16
    monkeypatch.undo()
    pick = dispatch.bundled_precision(ZEN4, BOTH)
    assert pick.precision == "int8" and "(zen4)" in pick.reason
    twin = choose_engine(TWIN, ZEN4, BOTH)
    assert (twin.engine, twin.precision) == ("openvino", "int8") and "(zen4)" in twin.reason
    assert choose_engine(FP32_STAGED, ZEN4, BOTH).precision == "bf16"
    assert choose_engine(FP32_STAGED, ZEN5, BOTH).precision == "bf16"


def test_within_claims_round_up() -> None:
    """A "within" figure never understates the measurement (0.295 deg reads 0.30)."""
    assert MEASURED[("openvino", "int8", True)].worst_mean == 0.295
    assert "within 0.30 deg mean" in dispatch.bundled_precision(ZEN3, BOTH).reason
    assert [dispatch._up(x) for x in (0.29, 0.2901, 0.0915, 0.5)] == [
        "0.29",
        "0.30",
        "0.10",
        "0.50",
    ]


def test_the_reason_says_when_the_cpus_features_were_not_all_read() -> None:
    """review-dispatch23.md 1, 8 and 12: "no native bf16 on this CPU" was said of a CPU whose
    features could not be read, of one read without /proc/cpuinfo (cpuid alone lacks bf16),
    and of an Arm CPU that has bf16."""
    from dataclasses import replace

    blind = CpuInfo(model="unknown", vendor="unknown", cores=2)
    assert "CPU features could not be read" in choose_engine(FP32, blind, BOTH).reason
    partial = replace(CpuInfo.from_flags(["avx2", "avx512f"]), partial=True)
    assert "native bf16 unknown here" in choose_engine(FP32, partial, BOTH).reason
    zen4_blind = replace(ZEN4_NO_BF16, partial=True)  # the default, int8, line says so too
    assert "native bf16 unknown here" in dispatch.bundled_precision(zen4_blind, BOTH).reason
    graviton = CpuInfo.from_flags(["asimd", "sve", "bf16"], vendor="ARM")
    assert "bf16 on this Arm CPU not measured" in choose_engine(FP32, graviton, BOTH).reason
    assert "no native bf16 on this CPU" in choose_engine(FP32, ZEN3, BOTH).reason


def test_after_an_openvino_fallback_the_bundled_reason_speaks_of_onnx_runtime(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """It kept OpenVINO's claims (int8 1.16x bf16, 0.30 deg) while ONNX Runtime int8 ran."""
    import msfnet.common.cpu as cpumod
    from msfnet.runtime.engines.bundled import EngineRequest, open_network

    def broken(*args, **kwargs):
        raise InputError("OpenVINO cannot compile this model for CPU (RuntimeError: test)")

    monkeypatch.setattr("msfnet.runtime.engines.openvino.open_openvino", broken)
    monkeypatch.setattr(cpumod, "detect_cpu", lambda: ZEN4)
    engine, reason = open_network(None, EngineRequest(threads=1))
    assert engine.name == "onnxruntime" and engine.precision == "int8"
    assert "bf16" not in reason.split("; onnxruntime int8")[0]
    assert "0.30 deg" not in reason and "OpenVINO failed" in reason


def test_an_npu_says_it_computes_in_fp16_and_refuses_fp32() -> None:
    """It said "openvino fp32 on NPU" and took --precision fp32, and ran f16 (review 3)."""
    npu = dispatch.resolve_device("npu", CPU_ORT, ["CPU", "NPU"])
    choice = choose_engine(FP32_STAGED, AMX, BOTH, device=npu)
    assert choice.reason.startswith("openvino fp16 on NPU") and "computes in f16" in choice.reason
    with pytest.raises(InputError, match="runs fp16"):
        choose_engine(FP32_STAGED, AMX, BOTH, "openvino", "fp32", device=npu)
    gpu = dispatch.resolve_device("gpu", CPU_ORT, ["CPU", "GPU"])
    assert choose_engine(FP32_STAGED, AMX, BOTH, None, "fp32", device=gpu).precision == "fp32"


def test_more_threads_than_usable_cpus_are_noted(monkeypatch: pytest.MonkeyPatch) -> None:
    """--threads 8 under taskset -c 0 ran ONNX Runtime 2.35x slower, without a word."""
    import msfnet.common.cpu as cpumod
    from msfnet.runtime.engines.bundled import EngineRequest, open_network

    monkeypatch.setattr(cpumod, "usable_cores", lambda: 1)
    reason = open_network(None, EngineRequest(threads=2, engine="onnxruntime"))[1]
    assert "note: 2 threads on the 1 CPU this process may use" in reason
    assert "note:" not in open_network(None, EngineRequest(threads=1))[1]
    # OpenVINO was measured not to slow down: nothing to note
    ov = open_network(None, EngineRequest(threads=2, engine="openvino"))[1]
    assert "note:" not in ov
