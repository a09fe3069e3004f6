"""msf-export's ``main`` goes through common.cli.command_main like every command: --list-variants
needs no checkpoint, a missing checkpoint is a usage error, and the body runs as "msf-export"
(the writer its outputs' manifests and provenance name). Torch-free: the exporter is faked."""

from __future__ import annotations

import sys
import types
from pathlib import Path

import pytest

from msfnet.common.cli import current_command
from msfnet.common.files import current_writer
from msfnet.export.cli import main as export_main
from msfnet.export.variants import VARIANTS


def test_list_variants_prints_the_table_without_a_checkpoint(capsys) -> None:
    assert export_main(["--list-variants"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("variants:\n")
    for variant in VARIANTS:
        assert f"  {variant.name} " in out


def test_a_missing_checkpoint_is_a_usage_error(capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        export_main(["-o", "x.onnx"])
    assert exc.value.code == 2
    assert capsys.readouterr().err == (
        "msf-export: error: the following arguments are required: checkpoint\n"
    )


@pytest.fixture
def fake_exporter(monkeypatch) -> dict[str, object]:
    """msfnet.export.pipeline replaced (no torch needed): what the body hands the exporter."""
    seen: dict[str, object] = {}

    def export_variant(checkpoint: Path, variant: object, output: Path, **kwargs: object):
        seen.update(writer=current_writer(), command=current_command(), output=output)
        if kwargs.get("calib"):  # the int8 variants: what the quantiser will be told
            seen["options"] = kwargs["options"]
        return types.SimpleNamespace(lines=lambda: ["fake export"])

    fake = types.ModuleType("msfnet.export.pipeline")
    fake.export_variant = export_variant  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "msfnet.export.pipeline", fake)
    return seen


def test_the_export_runs_as_msf_export(tmp_path: Path, fake_exporter, capsys) -> None:
    argv = [str(tmp_path / "m.pth"), "--plain"]
    assert export_main(argv) == 0
    assert fake_exporter == {
        "writer": "msf-export",
        "command": ("msf-export", *argv),
        "output": tmp_path / "m.onnx",
    }
    assert capsys.readouterr().out == "fake export\n"


@pytest.mark.parametrize(
    ("name", "default"),
    [
        ("checkp_30.pth.tar", "checkp_30.onnx"),
        ("model.pth", "model.onnx"),
        ("model.pt", "model.onnx"),
        ("run.v2.ckpt", "run.v2.onnx"),
        ("weights.tar", "weights.onnx"),
        ("weights", "weights.onnx"),
        ("same.onnx", "same.onnx"),  # then refused as its own input, by the exporter
    ],
)
def test_the_default_output_drops_both_suffixes(
    tmp_path: Path, fake_exporter, name: str, default: str
) -> None:
    """`msf-export checkp_30.pth.tar` wrote checkp_30.pth.onnx."""
    assert export_main([str(tmp_path / name), "-q"]) == 0
    assert fake_exporter["output"] == tmp_path / default


def test_an_input_error_in_the_body_is_one_line_exit_2(
    tmp_path: Path, fake_exporter, capsys
) -> None:
    # --calib on a variant that is not calibrated: refused in the body, before the exporter
    argv = [str(tmp_path / "m.pth"), "--plain", "--calib", str(tmp_path)]
    assert export_main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("msf-export: error: --calib: only the int8 variants"), err
    assert err.count("\n") == 1 and fake_exporter == {}


@pytest.mark.parametrize(("flags", "bits"), [(["--weight-bits", "7"], 7), ([], None)])
def test_weight_bits_reach_the_export_options(
    tmp_path: Path, fake_exporter, flags: list[str], bits: int | None
) -> None:
    argv = [str(tmp_path / "m.pth"), "--variant", "staged-int8", "--calib", str(tmp_path), *flags]
    assert export_main(argv) == 0
    options = fake_exporter["options"]
    assert options.weight_bits == bits  # type: ignore[attr-defined]
    assert options.reduce_range is (None if bits is None else True)  # type: ignore[attr-defined]
