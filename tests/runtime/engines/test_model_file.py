"""A model file is read once per ``Model()`` (engines.base.ModelFile): on the OpenVINO path by
OpenVINO alone (metadata from its ``rt_info``, the staged sub-models cut from the same graph, no
ONNX Runtime session), with every metadata refusal word for word the ONNX Runtime reader's.

Sessions and reads are counted by wrapping ``onnxruntime.InferenceSession`` and
``engines.openvino._read_onnx``; the fake CPUs are the dispatch tests' own kind.
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from _runtime_helpers import tiny_msfnet_onnx

from msfnet.common.cpu import CpuInfo
from msfnet.common.errors import InputError
from msfnet.runtime.api import default_model_path
from msfnet.runtime.contract import ModelInfo
from msfnet.runtime.engines import dispatch, installed_engines, read_model_file
from msfnet.runtime.engines.base import ModelFile
from msfnet.runtime.engines.dispatch import choose_engine, likely_engine, open_engine
from msfnet.runtime.engines.onnxruntime import open_onnxruntime

needs_openvino = pytest.mark.skipif(
    "openvino" not in installed_engines(), reason="openvino not installed"
)

ZEN3 = CpuInfo.from_flags(["avx2", "fma"], model="AVX2 only (OpenVINO fp32 measured faster)")
AMX = CpuInfo.from_flags(["avx2", "avx512f", "avx512_bf16", "amx_bf16", "amx_tile"], model="AMX")
SKYLAKE = CpuInfo.from_flags(["avx2", "avx512f"], model="AVX-512, no bf16 (nothing measured)")
ARM = CpuInfo.from_flags(["neon", "asimd"], model="Cortex-A78", vendor="ARM")
BOTH = {"onnxruntime", "openvino"}


class Counts:
    """How often ONNX Runtime sessions were created and OpenVINO parsed a file."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        import onnxruntime as ort

        self.sessions: list[str] = []
        self.ov_reads: list[str] = []
        real_session = ort.InferenceSession

        def session(path: Any, *args: Any, **kwargs: Any) -> Any:
            self.sessions.append(str(path))
            return real_session(path, *args, **kwargs)

        monkeypatch.setattr(ort, "InferenceSession", session)
        if "openvino" in installed_engines():
            from msfnet.runtime.engines import openvino as ov_engine

            real_read = ov_engine._read_onnx

            def read(ov: Any, path: Path) -> Any:
                self.ov_reads.append(str(path))
                return real_read(ov, path)

            monkeypatch.setattr(ov_engine, "_read_onnx", read)


@needs_openvino
def test_openvino_reads_the_metadata_onnxruntime_reads() -> None:
    from msfnet.runtime.engines.openvino import read_openvino

    file = read_openvino(default_model_path())
    assert file.openvino_graph is not None
    assert file.info == read_model_file(default_model_path())  # every msfnet.* key, the path
    assert file.info.staged and file.info.metadata["msfnet.format"] == "msfnet-normals-v1"


@needs_openvino
def test_the_openvino_path_reads_the_file_once_and_starts_no_onnxruntime(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    counts = Counts(monkeypatch)
    choice = choose_engine(default_model_path(), ZEN3, BOTH)  # OpenVINO fp32 on this class
    assert (choice.engine, choice.precision) == ("openvino", "fp32")
    assert choice.file is not None and choice.file.openvino_graph is not None
    engine = open_engine(choice, 1)
    assert counts.sessions == [] and len(counts.ov_reads) == 1
    assert engine.info is choice.file.info and engine.info.staged
    # the four sub-models cut from the one graph run the staged loop (normals: unit vectors)
    images = np.random.default_rng(0).random((1, 10, 3, 8, 12), dtype=np.float32)
    lights = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (1, 10, 1))
    out = engine.run(images, lights)
    assert out.shape == (1, 3, 8, 12)
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-3)


@needs_openvino
def test_openvino_falls_back_to_onnxruntime_where_it_hides_the_metadata(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from msfnet.runtime.engines import openvino as ov_engine

    monkeypatch.setattr(ov_engine, "_framework_metadata", lambda graph: None)
    counts = Counts(monkeypatch)
    file = ov_engine.read_openvino(default_model_path())
    assert len(counts.sessions) == 1 and len(counts.ov_reads) == 1
    assert file.openvino_graph is not None  # still compiled from this read
    assert file.info == read_model_file(default_model_path())


def _without_metadata(path: Path) -> Path:
    onnx = pytest.importorskip("onnx")
    model = onnx.load(str(tiny_msfnet_onnx(path)))
    del model.metadata_props[:]
    onnx.save(model, str(path))
    return path


def _garbage(path: Path) -> Path:
    path.write_bytes(b"this is not a model\x01\x02" * 8)
    return path


def _folder(path: Path) -> Path:
    path.mkdir()
    return path


# name: a file that is not (a sane) msfnet model; every reader refuses it in the same words
REFUSED = {
    "format version": lambda p: tiny_msfnet_onnx(p, **{"msfnet.format": "msfnet-normals-v2"}),
    "graph kind": lambda p: tiny_msfnet_onnx(p, **{"msfnet.graph": "cascade"}),
    "train lights": lambda p: tiny_msfnet_onnx(p, **{"msfnet.train_lights": "0"}),
    "static shape": lambda p: tiny_msfnet_onnx(p, **{"msfnet.static_shape": "1,6"}),
    "staged I/O": lambda p: tiny_msfnet_onnx(p, **{"msfnet.graph": "staged"}),
    "no metadata": _without_metadata,
    "not ONNX": _garbage,
    "missing": lambda p: p,
    "folder": _folder,
}


def _chosen_file(path: Path) -> ModelFile:
    """What ``Model()`` does first on a CPU where OpenVINO is expected: choose from a path."""
    choice = choose_engine(path, AMX, BOTH)
    assert choice.file is not None
    return choice.file


@needs_openvino
@pytest.mark.parametrize("case", sorted(REFUSED))
def test_openvino_refuses_exactly_what_onnxruntime_refuses(
    tmp_path: Path, capfd: pytest.CaptureFixture[str], case: str
) -> None:
    from msfnet.runtime.engines.openvino import open_openvino, read_openvino

    path = REFUSED[case](tmp_path / "model.onnx")
    with pytest.raises(InputError) as want:
        read_model_file(path)
    capfd.readouterr()
    for read in (read_openvino, open_openvino, _chosen_file):
        with pytest.raises(InputError) as got:
            read(path)
        assert str(got.value) == str(want.value) and got.value.path == path
    assert capfd.readouterr().err == ""  # no parser noise around the one line


@pytest.mark.parametrize("cpu", [ZEN3, AMX, SKYLAKE, ARM], ids=lambda c: c.model)
@pytest.mark.parametrize("staged", [False, True])
def test_the_expected_engine_is_the_chosen_one_for_fp32_models(cpu: CpuInfo, staged: bool) -> None:
    """likely_engine (which reader reads the file) agrees with choose_engine on fp32 models for
    every installed set and request that choose_engine accepts."""
    fp32 = ModelInfo(Path("m.onnx"), 32, 4, None, "fp32", {}, staged=staged)
    installs = [{"onnxruntime"}, BOTH]
    engines = [None, "onnxruntime", "openvino"]
    precisions = [None, "fp32", "bf16"]
    checked = 0
    for installed, engine, precision in itertools.product(installs, engines, precisions):
        try:
            chosen = choose_engine(fp32, cpu, installed, engine, precision).engine
        except InputError:
            continue
        assert likely_engine(cpu, installed, engine, precision) == chosen, (
            installed,
            engine,
            precision,
        )
        checked += 1
    assert checked >= 5


def test_an_int8_request_or_a_device_decides_the_reader() -> None:
    assert likely_engine(AMX, BOTH, requested_precision="int8") == "onnxruntime"
    gpu = dispatch.Device("gpu", "openvino", "GPU")
    assert likely_engine(ARM, BOTH, device=gpu) == "openvino"
    cuda = dispatch.Device("cuda", "onnxruntime", "CUDAExecutionProvider")
    assert likely_engine(AMX, BOTH, device=cuda) == "onnxruntime"
    assert likely_engine(AMX, {"onnxruntime"}) == "onnxruntime"


def test_the_onnxruntime_path_loads_a_staged_model_once_more_than_its_metadata(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Metadata read, then one session: the known graph kind sets the memory arena before the
    load (a staged model was loaded twice when the session had to find that out)."""
    counts = Counts(monkeypatch)
    choice = choose_engine(default_model_path(), ARM, BOTH)
    assert choice.engine == "onnxruntime" and choice.file is not None
    assert choice.file.openvino_graph is None and len(counts.sessions) == 1
    engine = open_engine(choice, 1)
    assert len(counts.sessions) == 2 and engine.info.staged
    assert engine.session.session.get_session_options().enable_cpu_mem_arena
    counts.sessions.clear()
    open_onnxruntime(default_model_path(), threads=1)  # nothing known: it finds out itself
    assert len(counts.sessions) == 2


@needs_openvino
def test_a_model_given_to_open_engine_is_read_not_the_chosen_one(tmp_path: Path) -> None:
    choice = choose_engine(default_model_path(), ZEN3, BOTH)
    tiny = tiny_msfnet_onnx(tmp_path / "tiny.onnx")
    engine = open_engine(choice, 1, model=tiny)
    assert engine.info.path == tiny and not engine.info.staged


def test_a_pipe_named_as_the_model_is_no_file_not_missing(tmp_path: Path) -> None:
    import os

    from msfnet.common.errors import InputError
    from msfnet.runtime.engines.base import model_file_path

    fifo = tmp_path / "model.onnx"
    os.mkfifo(fifo)
    with pytest.raises(InputError, match="not a regular file"):
        model_file_path(fifo)
    with pytest.raises(InputError, match="not found"):
        model_file_path(tmp_path / "absent.onnx")
