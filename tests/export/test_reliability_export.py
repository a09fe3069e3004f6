"""msf-export against the issue-13 rules (the cases that once failed), now that it runs on the
shared helpers (common/cli.py, common/files.py) like every other command."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from msfnet.export.cli import main  # noqa: E402


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from msfnet.model.checkpoint import save_checkpoint
    from msfnet.model.network import MSFNet

    torch.manual_seed(0)
    return save_checkpoint(MSFNet(), tmp_path_factory.mktemp("ckpt") / "x.pth")


def _one_line_exit_2(capfd, code: int) -> str:
    err = capfd.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert len(err) == 1 and err[0].startswith("msf-export: error: "), err
    return err[0]


def _run(argv: list[str]) -> int:
    try:
        return main(argv)
    except SystemExit as exc:
        return int(exc.code or 0)


def test_train_lights_zero_is_one_line(ckpt: Path, tmp_path: Path, capfd) -> None:
    _one_line_exit_2(
        capfd, _run([str(ckpt), "-o", str(tmp_path / "m.onnx"), "--train-lights", "0"])
    )
    assert list(tmp_path.iterdir()) == []


def test_static_foo_is_one_line(ckpt: Path, tmp_path: Path, capfd) -> None:
    """StaticShape.parse raises InputError inside argparse: a traceback today."""
    _one_line_exit_2(capfd, _run([str(ckpt), "-o", str(tmp_path / "m.onnx"), "--static", "foo"]))


def test_ctrl_c_is_one_line_exit_130(ckpt: Path, tmp_path: Path, monkeypatch, capfd) -> None:
    import msfnet.export.pipeline as pipeline

    def interrupted(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "export_variant", interrupted)
    try:
        code = _run([str(ckpt), "-o", str(tmp_path / "m.onnx")])
    except KeyboardInterrupt:  # would stop pytest itself
        pytest.fail("Ctrl-C escaped msf-export as a traceback")
    assert code == 130
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "interrupted" in err[0], err


class _SignalledImport:
    """A meta-path finder for ``onnxruntime`` that fails as a SIGTERM landing inside the C
    extension's import does: "ImportError: initialization failed", caused by the signal."""

    def find_spec(self, name: str, path: object = None, target: object = None) -> None:
        if name == "onnxruntime":
            from msfnet.common.signals import Terminated

            raise ImportError("initialization failed") from Terminated(signal.SIGTERM)
        return None


def test_sigterm_inside_the_onnxruntime_import_is_a_termination(
    ckpt: Path, tmp_path: Path, monkeypatch, capfd
) -> None:
    """Seen as "internal error: ImportError: initialization failed ... please report it",
    exit 1: it is the SIGTERM, exit 143, nothing written."""
    monkeypatch.delitem(sys.modules, "onnxruntime", raising=False)
    monkeypatch.setattr(sys, "meta_path", [_SignalledImport(), *sys.meta_path])
    code = _run([str(ckpt), "-o", str(tmp_path / "m.onnx")])
    err = capfd.readouterr().err.strip().splitlines()
    assert code == 143, err
    assert len(err) == 1 and "terminated (signal 15)" in err[0] and "internal" not in err[0]
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_output_over_its_own_checkpoint_is_refused(ckpt: Path, tmp_path: Path, capfd) -> None:
    """`msf-export x.pth -o x.pth --overwrite` replaced the checkpoint with the ONNX file."""
    own = tmp_path / "x.pth"
    own.write_bytes(ckpt.read_bytes())
    code = _run([str(own), "-o", str(own), "--overwrite"])
    assert own.read_bytes() == ckpt.read_bytes(), "the input checkpoint was replaced"
    assert "input" in _one_line_exit_2(capfd, code)


@pytest.mark.slow
@pytest.mark.parametrize(
    "option", [["--opset", "99"], ["--tolerance", "nan"], ["--tolerance", "-1"]]
)
def test_numeric_options_are_validated_up_front(
    option: list[str], ckpt: Path, tmp_path: Path, capfd
) -> None:
    """--opset 99 raised a torch traceback after loading; --tolerance nan passed any model."""
    t0 = time.perf_counter()
    _one_line_exit_2(capfd, _run([str(ckpt), "-o", str(tmp_path / "m.onnx"), *option]))
    assert time.perf_counter() - t0 < 2.0, "refused only after the export work"
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_sigterm_during_export_leaves_no_partial_file(ckpt: Path, tmp_path: Path) -> None:
    out = tmp_path / "m.onnx"
    proc = subprocess.Popen(
        [sys.executable, "-m", "msfnet.export.cli", str(ckpt), "-o", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.time() + 120
        while not any(tmp_path.iterdir()) and proc.poll() is None and time.time() < deadline:
            time.sleep(0.01)  # until the partial file appears
        os.kill(proc.pid, signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert list(tmp_path.iterdir()) == [], list(tmp_path.iterdir())
    assert proc.returncode == 143 and len(err.strip().splitlines()) == 1, err


def test_calib_without_int8_is_refused_not_ignored(ckpt: Path, tmp_path: Path, capfd) -> None:
    line = _one_line_exit_2(
        capfd,
        _run([str(ckpt), "-o", str(tmp_path / "x.onnx"), "--calib", str(tmp_path / "nowhere")]),
    )
    assert "--calib" in line and "--int8" in line
    assert not (tmp_path / "x.onnx").exists()


@pytest.mark.parametrize("ablation", [{"mfe": False}, {"mff": False}])
def test_an_ablation_checkpoint_is_read_as_its_own_network(
    ablation: dict[str, bool], tmp_path: Path, capfd
) -> None:
    """msf-train --no-mfe / --no-mff runs load (the variant from the keys); the staged graph
    cannot hold them, which is said in one line with the way out."""
    from msfnet.model.checkpoint import load_model, save_checkpoint
    from msfnet.model.network import MSFNet

    path = save_checkpoint(MSFNet(**ablation), tmp_path / "ablation.pth")
    assert load_model(path).state_dict().keys() == MSFNet(**ablation).state_dict().keys()
    line = _one_line_exit_2(capfd, _run([str(path), "-o", str(tmp_path / "a.onnx")]))
    assert "ablation checkpoint" in line and "--plain" in line
