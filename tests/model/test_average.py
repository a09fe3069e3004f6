"""msf-average: the element-wise mean of checkpoints' weights, written like every checkpoint,
and refusals in one line before anything is written."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from msfnet.model.average import average_state_dicts, main  # noqa: E402
from msfnet.model.checkpoint import load_model, read_state_dict, save_checkpoint  # noqa: E402
from msfnet.model.network import MSFNet  # noqa: E402


def _model(seed: int, **options: bool) -> MSFNet:
    torch.manual_seed(seed)
    model = MSFNet(**options)
    with torch.no_grad():  # every tensor differs between the inputs, batch-norm's too
        for param in model.parameters():
            param.add_(torch.rand_like(param))
        for name, buf in model.named_buffers():
            if buf.is_floating_point():
                buf.uniform_(0.5, 1.5)
            elif "num_batches" in name:
                buf.fill_(seed)
    return model


def _checkpoint(path: Path, seed: int, **options: bool) -> Path:
    return save_checkpoint(_model(seed, **options), path)


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


def test_fp16_and_data_parallel_inputs_average_like_the_others(tmp_path: Path) -> None:
    """Published checkpoints come with ``module.`` prefixes; msf-train's bundled ones in fp16."""
    a, b = _model(1), _model(2)
    half = save_checkpoint(a, tmp_path / "a16.pth", fp16=True)
    prefixed = tmp_path / "b_dp.pth"
    torch.save({"state_dict": {f"module.{k}": v for k, v in b.state_dict().items()}}, prefixed)
    mean = average_state_dicts([half, prefixed])
    for key, value in b.state_dict().items():
        if value.is_floating_point():
            expected = (a.state_dict()[key].half().double() + value.double()) / 2
            assert torch.allclose(mean[key].double(), expected, rtol=0, atol=1e-7), key


@pytest.mark.parametrize("options", [{"mff": False}, {"mfe": False}])
def test_ablation_snapshots_average_too(tmp_path: Path, options: dict[str, bool]) -> None:
    paths = [str(_checkpoint(tmp_path / f"s{seed}.pth", seed, **options)) for seed in (1, 2)]
    out = tmp_path / "avg.pth"
    assert main([*paths, "-o", str(out), "-q"]) == 0
    mean = read_state_dict(out)
    assert set(mean) == set(MSFNet(**options).state_dict())
    load_model(out, **options)


def test_the_mean_of_two_copies_predicts_as_the_model_does(tmp_path: Path) -> None:
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


def test_fp16_output_message_and_provenance(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    paths = [str(_checkpoint(tmp_path / f"s{i}.pth", i)) for i in (1, 2)]
    out = tmp_path / "sub" / "avg.pth"
    assert main([*paths, "-o", str(out), "--fp16"]) == 0
    assert "mean of 2 checkpoints" in capsys.readouterr().out
    raw = torch.load(out, map_location="cpu", weights_only=True)
    assert raw["model"] == "MSF_Net" and raw["averaged_from"] == paths
    assert {v.dtype for v in raw["state_dict"].values() if v.is_floating_point()} == {torch.float16}
    load_model(out)  # and it loads strictly


def _refused(argv: list[str], words: str, capfd: pytest.CaptureFixture[str]) -> str:
    assert main(argv) == 2
    lines = capfd.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("msf-average: error: "), lines
    assert words in lines[0], lines
    return lines[0]


def test_refusals_leave_everything_as_it_was(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    a = _checkpoint(tmp_path / "a.pth", 1)
    b = _checkpoint(tmp_path / "b.pth", 2)
    no_fusion = _checkpoint(tmp_path / "nofusion.pth", 3, mff=False)
    junk = tmp_path / "junk.pth"
    junk.write_bytes(b"not a checkpoint")
    broken = _model(4)
    with torch.no_grad():
        broken.regressor.deconv1[0].weight[0, 0, 0, 0] = float("nan")
    nan = save_checkpoint(broken, tmp_path / "nan.pth")
    existing = tmp_path / "existing.pth"
    existing.write_bytes(b"keep me")
    (tmp_path / "link.pth").symlink_to(a)
    os.link(b, tmp_path / "hard.pth")
    (tmp_path / "folder.pth").mkdir()
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()}
    x = str(tmp_path / "x.pth")

    _refused([str(a), "-o", x], "at least two", capfd)
    _refused([str(a), str(b), "-o", str(a)], "replace an input", capfd)
    _refused([str(a), str(b), "-o", str(existing)], "--overwrite", capfd)
    for twice in ("link.pth", "hard.pth"):
        line = _refused([str(a), str(b), str(tmp_path / twice), "-o", x], "given twice", capfd)
        assert twice in line
    for bad, words in (
        (junk, "not a PyTorch checkpoint"),
        (no_fusion, "missing key"),
        (nan, "NaN"),
        (tmp_path / "gone.pth", "not found"),
        (tmp_path / "folder.pth", "is a folder"),
    ):
        line = _refused([str(a), str(bad), "-o", x], words, capfd)
        assert f"error: {bad}: " in line

    assert {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()} == before
    assert not Path(x).exists()


def test_overwrite_replaces_only_the_output(tmp_path: Path) -> None:
    a = _checkpoint(tmp_path / "a.pth", 1)
    b = _checkpoint(tmp_path / "b.pth", 2)
    out = tmp_path / "avg.pth"
    _checkpoint(out, 3)  # an earlier average
    assert main([str(a), str(b), "-o", str(out), "--overwrite", "-q"]) == 0
    load_model(out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.pth", "avg.pth", "b.pth"]


def test_overwrite_never_replaces_a_file_that_is_no_checkpoint(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """-o notes.txt --overwrite replaced the user's text with a checkpoint."""
    a = _checkpoint(tmp_path / "a.pth", 1)
    b = _checkpoint(tmp_path / "b.pth", 2)
    notes = tmp_path / "notes.txt"
    notes.write_text("measurements\n")
    _refused([str(a), str(b), "-o", str(notes), "--overwrite"], "replaces only an earlier", capfd)
    assert notes.read_text() == "measurements\n"
    import zipfile

    doc = tmp_path / "thesis.docx"  # a zip, as torch.save's files are
    with zipfile.ZipFile(doc, "w") as z:
        z.writestr("word/document.xml", "chapter 1")
    before = doc.read_bytes()
    _refused([str(a), str(b), "-o", str(doc), "--overwrite"], "replaces only an earlier", capfd)
    assert doc.read_bytes() == before
    empty = tmp_path / "empty.pth"
    empty.touch()  # nothing to lose
    assert main([str(a), str(b), "-o", str(empty), "--overwrite", "-q"]) == 0
    load_model(empty)


def test_help_does_not_import_torch() -> None:
    """--help and argument errors must work (and fast) on an edge install without torch."""
    import subprocess
    import sys

    code = (
        "import sys; from msfnet.model.average import main\n"
        "try:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
        "assert 'torch' not in sys.modules, 'torch imported'"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
