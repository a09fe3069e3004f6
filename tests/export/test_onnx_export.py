"""msf-export: checkpoint formats, ONNX parity at many light counts, clean failures."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

from msfnet.export.cli import main as export_main  # noqa: E402
from msfnet.export.onnx_export import random_inputs  # noqa: E402
from msfnet.export.variants import VerificationRow  # noqa: E402
from msfnet.export.verify import compare, file_runner, rendered_cases, torch_runner  # noqa: E402
from msfnet.model.checkpoint import CheckpointError, load_model, read_state_dict  # noqa: E402
from msfnet.model.network import MSFNet  # noqa: E402
from msfnet.runtime.evaluate.metrics import angular_error_deg  # noqa: E402


def _trained_like_net(seed: int = 0) -> MSFNet:
    """Random weights that keep the signal alive through all layers (PyTorch's default init
    shrinks it until the output hardly depends on the input, which would make parity checks
    weak), plus non-trivial batch-norm statistics, like a trained checkpoint."""
    torch.manual_seed(seed)
    net = MSFNet()
    for module in net.modules():
        if isinstance(module, torch.nn.Conv2d | torch.nn.ConvTranspose2d):
            torch.nn.init.kaiming_normal_(module.weight, a=0.1, nonlinearity="leaky_relu")
    for bn in (net.fusion.f_x[1], net.fusion.f_y[1]):
        bn.running_mean.normal_(0, 0.1)
        bn.running_var.uniform_(0.5, 1.5)
        bn.num_batches_tracked.fill_(1000)
    return net.eval()


def _verify(
    net: torch.nn.Module, path: Path, checks: list[tuple[int, int, int]]
) -> list[VerificationRow]:
    """The written file (loaded as the runtime and msf-export's verification load it) against
    PyTorch at each (N, H, W) on rendered objects, with the verifier's own comparison."""
    return compare(file_runner(path, None), torch_runner(net), rendered_cases(checks))


@pytest.fixture(scope="module")
def published_ckpt(tmp_path_factory) -> Path:
    """A checkpoint in the published format: legacy serialisation, DataParallel prefixes."""
    path = tmp_path_factory.mktemp("ckpt") / "checkp_30.pth.tar"
    state = {f"module.{k}": v for k, v in _trained_like_net().state_dict().items()}
    torch.save(
        {"state_dict": state, "model": "MSF_Net"}, path, _use_new_zipfile_serialization=False
    )
    return path


@pytest.fixture(scope="module")
def exported(published_ckpt: Path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("onnx") / "model.onnx"
    assert export_main([str(published_ckpt), "-o", str(out), "--plain"]) == 0
    return out


def test_published_format_loads_strictly(published_ckpt: Path) -> None:
    net = load_model(published_ckpt)
    want = _trained_like_net().state_dict()
    for k, v in net.state_dict().items():
        assert torch.equal(v, want[k]), k


def test_bare_state_dict_and_zip_format_load(tmp_path: Path) -> None:
    path = tmp_path / "bare.pth"
    torch.save(_trained_like_net(1).state_dict(), path)
    assert set(read_state_dict(path)) == set(MSFNet().state_dict())


def test_gpu_saved_tensors_load_on_cpu(tmp_path: Path, monkeypatch) -> None:
    """Storages tagged 'cuda:0' (as saved from a GPU) are mapped to the CPU."""
    path = tmp_path / "gpu.pth"
    monkeypatch.setattr(torch.serialization, "location_tag", lambda storage: "cuda:0")
    torch.save({"state_dict": _trained_like_net(2).state_dict()}, path)
    monkeypatch.undo()
    assert b"cuda:0" in path.read_bytes()
    net = load_model(path)
    assert next(net.parameters()).device.type == "cpu"


def test_pickled_objects_are_refused(tmp_path: Path) -> None:
    path = tmp_path / "evil.pth"
    torch.save({"state_dict": _trained_like_net().state_dict(), "args": Path("/x")}, path)
    with pytest.raises(CheckpointError, match="refusing to unpickle"):
        read_state_dict(path)


def test_onnx_matches_pytorch_at_many_light_counts(published_ckpt: Path, exported: Path) -> None:
    net = load_model(published_ckpt)
    checks = [(3, 32, 32), (7, 28, 44), (32, 16, 24), (96, 24, 32)]  # last three non-square
    results = _verify(net, exported, checks)
    for r in results:
        assert r.max_deg < 0.01 and r.pixels > 100, r
    assert [r.lights for r in results] == [3, 7, 32, 96]


def test_onnx_batch_axis_is_dynamic(published_ckpt: Path, exported: Path) -> None:
    net = load_model(published_ckpt)
    images, lights = random_inputs(3, 5, 16, 16, seed=9)
    session = ort.InferenceSession(str(exported), providers=["CPUExecutionProvider"])
    (out,) = session.run(None, {"images": images, "lights": lights})
    with torch.no_grad():
        want = net(torch.from_numpy(images), torch.from_numpy(lights)).numpy()
    diff = angular_error_deg(out.transpose(0, 2, 3, 1), want.transpose(0, 2, 3, 1))
    assert diff.max() < 0.01


def test_onnx_declares_contract_and_metadata(exported: Path, published_ckpt: Path) -> None:
    import hashlib

    proto = onnx.load(str(exported))
    dims = {
        v.name: [d.dim_param or d.dim_value for d in v.type.tensor_type.shape.dim]
        for v in [*proto.graph.input, *proto.graph.output]
    }
    assert dims == {
        "images": ["batch", "lights", 3, "height", "width"],
        "lights": ["batch", "lights", 3],
        "normals": ["batch", 3, "height", "width"],
    }
    meta = {p.key: p.value for p in proto.metadata_props}
    assert meta["msfnet.train_lights"] == "32"
    assert meta["msfnet.format"] == "msfnet-normals-v1"
    assert (
        meta["msfnet.checkpoint_sha256"] == hashlib.sha256(published_ckpt.read_bytes()).hexdigest()
    )
    assert "sqrt(N / train_lights)" in meta["msfnet.preprocessing"]
    assert proto.opset_import[0].version == 17


def test_static_export_runs_at_its_shape(published_ckpt: Path, tmp_path: Path) -> None:
    out = tmp_path / "static.onnx"
    assert (
        export_main(
            [str(published_ckpt), "-o", str(out), "--static", "5,16,20", "--train-lights", "16"]
        )
        == 0
    )
    proto = onnx.load(str(out))
    assert [d.dim_value for d in proto.graph.input[0].type.tensor_type.shape.dim] == [
        1,
        5,
        3,
        16,
        20,
    ]
    meta = {p.key: p.value for p in proto.metadata_props}
    assert meta["msfnet.static_shape"] == "5,16,20" and meta["msfnet.train_lights"] == "16"


def test_simplified_export_keeps_dynamic_axes(published_ckpt: Path, tmp_path: Path) -> None:
    pytest.importorskip("onnxslim")
    out = tmp_path / "slim.onnx"
    assert export_main([str(published_ckpt), "-o", str(out), "--plain", "--simplify"]) == 0
    net = load_model(published_ckpt)
    assert max(r.max_deg for r in _verify(net, out, [(9, 20, 12)])) < 0.01


def _assert_clean_failure(capsys, args: list[str], out: Path, match: str) -> None:
    assert export_main([*args, "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("msf-export: error:"), err
    assert match in err, err
    assert not out.exists()
    assert not list(out.parent.glob("*.onnx")), "partial ONNX file left behind"


def test_missing_file_fails_cleanly(tmp_path: Path, capsys) -> None:
    _assert_clean_failure(capsys, [str(tmp_path / "nope.pth")], tmp_path / "m.onnx", "not found")


def test_corrupt_file_fails_cleanly(tmp_path: Path, capsys) -> None:
    bad = tmp_path / "corrupt.pth"
    bad.write_bytes(np.random.default_rng(0).bytes(5000))
    _assert_clean_failure(capsys, [str(bad)], tmp_path / "m.onnx", "corrupt.pth")


def test_truncated_checkpoint_fails_cleanly(published_ckpt: Path, tmp_path: Path, capsys) -> None:
    bad = tmp_path / "truncated.pth"
    bad.write_bytes(published_ckpt.read_bytes()[:100_000])
    _assert_clean_failure(capsys, [str(bad)], tmp_path / "m.onnx", "truncated.pth")


def test_wrong_architecture_lists_offending_keys(tmp_path: Path, capsys) -> None:
    state = _trained_like_net().state_dict()
    state.pop("regressor.est_normal.0.weight")
    state["extractor1.conv1.0.weight"] = torch.zeros(64, 3, 3, 3)  # a 3-channel-input net
    state["extra.layer.weight"] = torch.zeros(1)
    bad = tmp_path / "other_net.pth"
    torch.save({"state_dict": state}, bad)
    _assert_clean_failure(capsys, [str(bad)], tmp_path / "m.onnx", "regressor.est_normal")
    # (one line; names the missing, unexpected and mis-shaped keys)


def test_wrong_architecture_message_names_all_problems(tmp_path: Path) -> None:
    state = _trained_like_net().state_dict()
    state.pop("regressor.est_normal.0.weight")
    state["extractor1.conv1.0.weight"] = torch.zeros(64, 3, 3, 3)
    state["extra.layer.weight"] = torch.zeros(1)
    bad = tmp_path / "other_net.pth"
    torch.save(state, bad)
    with pytest.raises(CheckpointError) as info:
        load_model(bad)
    msg = str(info.value)
    assert "missing key(s): regressor.est_normal.0.weight" in msg
    assert "unexpected key(s): extra.layer.weight" in msg
    assert "extractor1.conv1.0.weight (64, 3, 3, 3) != (64, 6, 3, 3)" in msg


def test_not_a_state_dict_fails_cleanly(tmp_path: Path, capsys) -> None:
    bad = tmp_path / "list.pth"
    torch.save([1, 2, 3], bad)
    _assert_clean_failure(capsys, [str(bad)], tmp_path / "m.onnx", "state_dict")


def test_existing_output_is_not_clobbered(published_ckpt: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "taken.onnx"
    out.write_bytes(b"keep me")
    assert export_main([str(published_ckpt), "-o", str(out)]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert out.read_bytes() == b"keep me"


def test_plain_pickle_is_never_executed(tmp_path: Path, capsys) -> None:
    """A pickle that would run code on load is rejected without running it."""
    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):
            return (Path.touch, (marker,))

    bad = tmp_path / "evil.pth"
    bad.write_bytes(pickle.dumps({"state_dict": Evil()}))
    assert export_main([str(bad), "-o", str(tmp_path / "m.onnx")]) == 2
    assert not marker.exists()
    assert "refusing to unpickle" in capsys.readouterr().err


def test_fp16_weight_storage_halves_the_file_and_keeps_parity(
    published_ckpt: Path, exported: Path, tmp_path: Path
) -> None:
    from msfnet.model.checkpoint import save_checkpoint

    half_ckpt = save_checkpoint(load_model(published_ckpt), tmp_path / "half.pth", fp16=True)
    assert half_ckpt.stat().st_size < 0.6 * published_ckpt.stat().st_size
    out = tmp_path / "half.onnx"
    assert export_main([str(half_ckpt), "-o", str(out), "--plain", "--fp16-weights"]) == 0
    assert out.stat().st_size < 0.55 * exported.stat().st_size
    rounded = load_model(half_ckpt)  # fp16 tensors cast back to float32 on load
    assert max(r.max_deg for r in _verify(rounded, out, [(5, 16, 20)])) < 0.01
