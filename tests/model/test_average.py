"""msf-average: the element-wise mean of checkpoints' weights, written like every checkpoint,
and refusals in one line before anything is written."""

from __future__ import annotations

from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from msfnet.model.average import average_state_dicts, main  # noqa: E402
from msfnet.model.checkpoint import load_model, read_state_dict, save_checkpoint  # noqa: E402
from msfnet.model.network import MSFNet  # noqa: E402


def _checkpoint(path: Path, seed: int) -> Path:
    torch.manual_seed(seed)
    model = MSFNet()
    with torch.no_grad():  # every tensor differs between the inputs, batch-norm's too
        for param in model.parameters():
            param.add_(torch.rand_like(param))
        for name, buf in model.named_buffers():
            if buf.is_floating_point():
                buf.uniform_(0.5, 1.5)
            elif "num_batches" in name:
                buf.fill_(seed)
    return save_checkpoint(model, path)


def test_the_mean_of_each_tensor(tmp_path: Path) -> None:
    paths = [_checkpoint(tmp_path / f"s{i}.pth", seed) for i, seed in enumerate((1, 2, 3))]
    states = [read_state_dict(p) for p in paths]
    mean = average_state_dicts(paths)
    assert set(mean) == set(states[0])
    for key, value in mean.items():
        if value.is_floating_point():
            expected = sum(s[key].double() for s in states) / 3
            assert value.dtype == torch.float32
            assert torch.allclose(value.double(), expected, rtol=0, atol=1e-7), key
            assert not torch.equal(states[0][key], states[1][key]), key  # a real mean
        else:
            assert torch.equal(value, states[0][key]), key  # step counters: the first's


def test_the_mean_of_one_model_twice_predicts_as_it_does(tmp_path: Path) -> None:
    a = _checkpoint(tmp_path / "a.pth", 7)
    b = tmp_path / "b.pth"
    b.write_bytes(a.read_bytes())
    assert main([str(a), str(b), "-o", str(tmp_path / "avg.pth"), "-q"]) == 0
    torch.manual_seed(0)
    images = torch.rand(1, 5, 3, 16, 16)
    lights = torch.nn.functional.normalize(torch.rand(1, 5, 3) + 0.2, dim=-1)
    with torch.no_grad():
        want = load_model(a)(images, lights)
        got = load_model(tmp_path / "avg.pth")(images, lights)
    assert torch.allclose(want, got, rtol=0, atol=1e-6)


def test_fp16_output_and_message(tmp_path: Path, capsys) -> None:
    paths = [str(_checkpoint(tmp_path / f"s{i}.pth", i)) for i in (1, 2)]
    out = tmp_path / "sub" / "avg.pth"
    assert main([*paths, "-o", str(out), "--fp16"]) == 0
    assert "mean of 2 checkpoints" in capsys.readouterr().out
    raw = torch.load(out, map_location="cpu", weights_only=True)
    assert raw["model"] == "MSF_Net"
    assert {v.dtype for v in raw["state_dict"].values() if v.is_floating_point()} == {
        torch.float16}
    load_model(out)  # and it loads strictly


def _refused(argv: list[str], words: str, capfd) -> str:
    assert main(argv) == 2
    lines = capfd.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("msf-average: error: "), lines
    assert words in lines[0], lines
    return lines[0]


def test_refusals_leave_everything_as_it_was(tmp_path: Path, capfd) -> None:
    a = _checkpoint(tmp_path / "a.pth", 1)
    b = _checkpoint(tmp_path / "b.pth", 2)
    junk = tmp_path / "junk.pth"
    junk.write_bytes(b"not a checkpoint")
    partial = tmp_path / "partial.pth"
    torch.save({"state_dict": {"conv.weight": torch.zeros(2)}}, partial)
    existing = tmp_path / "existing.pth"
    existing.write_bytes(b"keep me")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}

    _refused([str(a), "-o", str(tmp_path / "x.pth")], "at least two", capfd)
    _refused([str(a), str(b), "-o", str(a)], "replace an input", capfd)
    _refused([str(a), str(b), "-o", str(existing)], "--overwrite", capfd)
    line = _refused([str(a), str(junk), "-o", str(tmp_path / "x.pth")], "not a", capfd)
    assert str(junk) in line
    line = _refused([str(a), str(partial), "-o", str(tmp_path / "x.pth")], "missing", capfd)
    assert str(partial) in line
    _refused([str(a), str(tmp_path / "gone.pth"), "-o", str(tmp_path / "x.pth")],
             "not found", capfd)

    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_overwrite_replaces_only_the_output(tmp_path: Path) -> None:
    a = _checkpoint(tmp_path / "a.pth", 1)
    b = _checkpoint(tmp_path / "b.pth", 2)
    out = tmp_path / "avg.pth"
    out.write_bytes(b"old")
    assert main([str(a), str(b), "-o", str(out), "--overwrite", "-q"]) == 0
    load_model(out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.pth", "avg.pth", "b.pth"]
