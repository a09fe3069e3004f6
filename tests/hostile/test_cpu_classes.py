"""Every CPU class (issue #27, part B, item 16; and item 11): int8 paths that would compute
wrong numbers on a CPU without VNNI (ONNX Runtime's u8 x s8 kernels saturate full-range
weights) are detected from msfnet.common.cpu and avoided or refused; the accuracy command
measures what the CPU can; an int8 export needs a real calibration set.

The CPU is faked (CpuInfo.from_flags), so these hold on AVX2-only, AVX-512 and AMX machines."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from _runtime_helpers import sphere_stack, tiny_msfnet_onnx

from msfnet.common.cpu import CpuInfo
from msfnet.common.errors import InputError
from msfnet.runtime.engines import installed_engines

AVX2 = CpuInfo.from_flags(["avx2", "fma"], model="fake AVX2-only (Zen 2 class)")
VNNI = CpuInfo.from_flags(["avx2", "avx512f", "avx512_vnni"], model="fake AVX-512 VNNI")
AMX = CpuInfo.from_flags(
    ["avx2", "avx512f", "avx512_vnni", "avx512_bf16", "amx_bf16", "amx_int8"], model="fake AMX"
)


def test_the_cpu_says_where_full_range_int8_is_exact() -> None:
    assert not AVX2.int8_full_range
    assert VNNI.int8_full_range and AMX.int8_full_range
    assert CpuInfo.from_flags(["avx2", "avx_vnni"]).int8_full_range  # AVX-VNNI (client cores)


# -- bench/peak.py: the int8 matmul graphs stay exact on every class


@pytest.mark.parametrize(("cpu", "limit"), [(AVX2, 63), (VNNI, 127), (AMX, 127)])
@pytest.mark.parametrize("dtype", ["int8", "qdq"])
def test_peak_int8_graphs_use_weights_the_cpu_computes_exactly(
    cpu: CpuInfo, limit: int, dtype: str
) -> None:
    pytest.importorskip("onnx", reason="needs onnx: the [bench] extra")
    import onnxruntime as ort
    from onnx import load_from_string, numpy_helper

    from msfnet.bench.peak import int8_weight_limit, matmul_onnx

    assert int8_weight_limit(cpu) == limit
    model = matmul_onnx(32, dtype, cpu)
    weights = {t.name: numpy_helper.to_array(t) for t in load_from_string(model).graph.initializer}
    b = weights["B" if dtype == "int8" else "Bq"].astype(np.int64)
    assert np.abs(b).max() == limit  # the whole range the CPU allows, and no more
    if cpu is AVX2:  # 7-bit weights: exact whatever CPU runs this test
        a = np.full((32, 32), 255, np.uint8) if dtype == "int8" else None
        if a is not None:
            sess = ort.InferenceSession(model, providers=["CPUExecutionProvider"])
            got = sess.run(None, {"A": a})[0]
            np.testing.assert_array_equal(got, a.astype(np.int64) @ b)


# -- runtime: a full-range int8 model is refused where ONNX Runtime would saturate


def _int8_model(tmp_path: Path, reduce_range: bool | None) -> Path:
    pytest.importorskip("onnx")
    meta = {"msfnet.precision": "int8-qdq"}
    if reduce_range is not None:
        meta["msfnet.quantization"] = json.dumps({"reduce_range": reduce_range})
    return tiny_msfnet_onnx(tmp_path / f"int8_{reduce_range}.onnx", **meta)


@pytest.mark.parametrize("reduce_range", [None, False])
def test_full_range_int8_is_refused_without_vnni(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, reduce_range: bool | None
) -> None:
    import msfnet.runtime.engines.base as basemod
    import msfnet.runtime.engines.onnxruntime as ortmod

    path = _int8_model(tmp_path, reduce_range)
    monkeypatch.setattr(basemod, "detect_cpu", lambda: AVX2)
    with pytest.raises(InputError, match="saturate on CPUs without VNNI") as e:
        ortmod.open_onnxruntime(path, threads=1)
    # OpenVINO's AVX2 int8 kernels saturate as well (session 23): never advised
    assert e.value.path == path and "--weight-bits 7" in str(e.value)
    assert "--engine openvino" not in str(e.value)
    for cpu in (VNNI, AMX):  # the same file opens where the kernels are exact
        monkeypatch.setattr(basemod, "detect_cpu", lambda cpu=cpu: cpu)
        assert ortmod.open_onnxruntime(path, threads=1).precision == "int8"


def test_full_range_int8_is_refused_on_openvino_too_without_vnni(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """review-dispatch23.md 2 asked for OpenVINO there; its AVX2 int8 convolution gave 252
    off of 624 on full-range weights under the AVX2 proxy (exact natively): refused too."""
    pytest.importorskip("openvino")
    import msfnet.runtime.engines.base as basemod
    from msfnet.runtime.engines.dispatch import EngineChoice, open_engine

    path = _int8_model(tmp_path, False)
    choice = EngineChoice("openvino", "int8", "test", path)
    monkeypatch.setattr(basemod, "detect_cpu", lambda: AVX2)
    with pytest.raises(InputError, match="saturate on CPUs without VNNI"):
        open_engine(choice, threads=1)
    monkeypatch.setattr(basemod, "detect_cpu", lambda: VNNI)
    assert open_engine(choice, threads=1).precision == "int8"


def test_seven_bit_int8_runs_on_every_cpu(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import msfnet.runtime.engines.base as basemod
    import msfnet.runtime.engines.onnxruntime as ortmod

    path = _int8_model(tmp_path, True)
    for cpu in (AVX2, VNNI, AMX):
        monkeypatch.setattr(basemod, "detect_cpu", lambda cpu=cpu: cpu)
        assert ortmod.open_onnxruntime(path, threads=1).precision == "int8"


def test_fp32_models_never_ask_about_int8(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import msfnet.runtime.engines.onnxruntime as ortmod

    pytest.importorskip("onnx")
    import msfnet.runtime.engines.base as basemod

    path = tiny_msfnet_onnx(tmp_path / "fp32.onnx")
    monkeypatch.setattr(basemod, "detect_cpu", lambda: AVX2)
    assert ortmod.open_onnxruntime(path, threads=1).precision == "fp32"


# -- export/quantize.py: 7-bit weights where the exporting CPU lacks VNNI; a real calibration


def _record_quantiser(monkeypatch: pytest.MonkeyPatch, cpu: CpuInfo) -> dict:
    """ONNX Runtime's quantiser replaced by a recorder of its arguments, on a faked CPU."""
    quantization = pytest.importorskip("onnxruntime.quantization")
    import msfnet.common.cpu as cpumod

    seen: dict = {}

    def record(src: str, dst: str, reader: object, **kwargs: object) -> None:
        seen.update(kwargs)
        Path(dst).write_bytes(Path(src).read_bytes())

    monkeypatch.setattr(quantization, "quantize_static", record)
    monkeypatch.setattr(cpumod, "detect_cpu", lambda: cpu)
    return seen


def _quantize_with(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, cpu: CpuInfo, stacks: list
) -> dict:
    """quantize_model's choices, with ONNX Runtime's quantiser replaced by a recorder."""
    onnx = pytest.importorskip("onnx")
    from msfnet.export.quantize import quantize_model

    seen = _record_quantiser(monkeypatch, cpu)
    model = onnx.load(str(tiny_msfnet_onnx(tmp_path / "m.onnx")))
    _q, summary = quantize_model(model, stacks, tmp_path, tiles_per_stack=1, lights=8)
    assert summary["reduce_range"] == seen["reduce_range"]
    return seen


@pytest.mark.parametrize(("cpu", "reduced"), [(AVX2, True), (VNNI, False), (AMX, False)])
def test_int8_export_quantises_to_what_the_cpu_computes_exactly(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, cpu: CpuInfo, reduced: bool
) -> None:
    stacks = [sphere_stack(n=8, h=96, w=96)]
    assert _quantize_with(monkeypatch, tmp_path, cpu, stacks)["reduce_range"] is reduced


@pytest.mark.parametrize(("cpu", "bits"), [(AVX2, 8), (AMX, 7), (AVX2, None), (AMX, None)])
def test_the_quantise_pass_hands_weight_bits_to_the_quantiser(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, cpu: CpuInfo, bits: int | None
) -> None:
    """msf-export --weight-bits 7 on a VNNI CPU makes a file for every CPU (the bundled int8
    model); 8 on an AVX2 CPU is the user's call; none: the exporting CPU decides. Through the
    quantise-int8 pass itself, with ONNX Runtime's quantiser replaced by a recorder."""
    onnx = pytest.importorskip("onnx")
    pytest.importorskip("torch", reason="msf-export's passes need the [export] extra")
    from msfnet.export.passes import PASSES, PassContext
    from msfnet.export.variants import ExportOptions, get_variant

    seen = _record_quantiser(monkeypatch, cpu)
    options = ExportOptions(
        weight_bits=bits, calib_tile=32, calib_lights=8, calib_tiles_per_stack=1
    )
    ctx = PassContext(
        model=None,  # type: ignore[arg-type]  # the quantise pass reads no torch network
        variant=get_variant("int8"),
        options=options,
        checkpoint=tmp_path / "m.pth",
        output=tmp_path / "m.onnx",
        stacks=[sphere_stack(n=8, h=96, w=96)],
    )
    model = onnx.load(str(tiny_msfnet_onnx(tmp_path / "tiny.onnx")))
    PASSES["quantise-int8"].run(model, ctx)
    expected = (bits == 7) if bits is not None else not cpu.int8_full_range
    assert seen["reduce_range"] is expected
    summary = ctx.notes["quantization"]
    assert isinstance(summary, dict) and summary["reduce_range"] is expected


@pytest.mark.parametrize(
    ("shape", "lights", "words"),
    [
        ((1, 1), 8, r"at least 1024 \(a 32 x 32 patch of object\)"),
        ((24, 24), 8, "at least 1024"),  # a sphere of ~350 pixels
        ((96, 96), 4, "at least 8 per stack"),
    ],
)
def test_int8_calibration_needs_a_minimum_size(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, shape: tuple, lights: int, words: str
) -> None:
    from msfnet.export.quantize import check_calibration

    if shape == (1, 1):
        stack = sphere_stack(n=lights, h=8, w=8).subset(range(lights))
        stack.images, stack.mask, stack.normals_gt = (
            stack.images[:, :1, :1],
            np.ones((1, 1), bool),
            None,
        )
    else:
        stack = sphere_stack(n=lights, h=shape[0], w=shape[1])
    with pytest.raises(InputError, match=words):
        check_calibration([stack])
    with pytest.raises(InputError, match=words):
        _quantize_with(monkeypatch, tmp_path, VNNI, [stack])


# -- bench/accuracy.py: what the CPU can, not a refusal


@pytest.mark.parametrize(
    ("cpu", "skipped"), [(AVX2, "no native bf16 on this CPU"), (AMX, None), (VNNI, "no native")]
)
def test_accuracy_leaves_out_what_the_cpu_cannot_run(
    tmp_path: Path, cpu: CpuInfo, skipped: str | None
) -> None:
    from msfnet.bench.accuracy import EnginePath, unsupported

    model = tiny_msfnet_onnx(tmp_path / "m.onnx") if skipped is None else tmp_path / "x.onnx"
    why = unsupported(EnginePath("openvino", "bf16", "fp32"), model, cpu)
    assert why == skipped if skipped is None else skipped in (why or "")
    assert unsupported(EnginePath("onnxruntime", "fp32", "fp32_staged"), model, cpu) is None


def test_accuracy_skips_full_range_int8_without_vnni(tmp_path: Path) -> None:
    from msfnet.bench.accuracy import EnginePath, unsupported

    path = _int8_model(tmp_path, False)
    ort_int8 = EnginePath("onnxruntime", "int8", "int8")
    assert "saturate" in (unsupported(ort_int8, path, AVX2) or "")
    assert unsupported(ort_int8, path, VNNI) is None
    assert unsupported(ort_int8, _int8_model(tmp_path, True), AVX2) is None
    assert unsupported(EnginePath("openvino", "int8", "int8"), path, AVX2) is None


def test_accuracy_measures_the_rest_on_a_cpu_without_bf16(
    tmp_path: Path, random_onnx: Path
) -> None:
    """The command used to stop at OpenVINO bf16 on an AVX2-only CPU; now that row is left
    out with a line saying why, and the others are measured."""
    from _runtime_helpers import png_stack

    from msfnet.bench.accuracy import EnginePath, measure

    stack_dir = png_stack(tmp_path / "ballPNG", 16, n=8, h=40, w=40)
    lines: list[str] = []
    rows = measure(
        stack_dir,
        {"fp32": random_onnx},
        lights=(8,),
        size=32,
        threads=1,
        paths=(EnginePath("openvino", "bf16", "fp32"), EnginePath("onnxruntime", "fp32", "fp32")),
        log=lines.append,
        cpu=AVX2,
    )
    assert [r["path"] for r in rows] == ["onnxruntime fp32", "onnxruntime fp32"]
    if "openvino" in installed_engines():  # else the row is left out as not installed
        assert any("bf16: skipped (no native bf16" in line for line in lines), lines


def test_an_openvino_only_install_refuses_full_range_int8_without_blaming_the_fallback(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """review-today23.md 5: the refusal ended "ONNX Runtime, the fallback, is not installed"
    (which would refuse it too), after OpenVINO had compiled the model."""
    pytest.importorskip("openvino")
    import msfnet.runtime.engines.base as basemod
    import msfnet.runtime.engines.openvino as ovmod
    from msfnet.runtime.engines import dispatch

    path = _int8_model(tmp_path, False)
    monkeypatch.setattr(basemod, "detect_cpu", lambda: AVX2)
    monkeypatch.setattr(dispatch, "installed_engines", lambda: {"openvino"})
    compiled: list[int] = []
    monkeypatch.setattr(ovmod, "open_openvino", lambda *a, **k: compiled.append(1))
    choice = dispatch.choose_engine(path, AVX2, {"openvino"})
    with pytest.raises(InputError, match="saturate") as e:
        dispatch.open_chosen(choice, 1)
    assert "fallback" not in str(e.value) and not compiled
