"""msf-inspect's command line (cli/inspect.py): every file it reads is an input that no output
may contain or replace. The defect step itself is tested in tests/runtime/results."""

from __future__ import annotations

from pathlib import Path

from _runtime_helpers import png_stack

from msfnet.runtime.cli.inspect import main as inspect_main


def test_an_output_holding_a_file_the_load_flags_read_is_refused(tmp_path: Path, capsys) -> None:
    """Only the part and --reference were inputs: -o on a folder holding the --mask (or
    --lights, --intensities, --onnx) file read, with --overwrite, deleted it."""
    stack = png_stack(tmp_path / "part", 16)
    out = tmp_path / "verdict"
    base = [str(stack), "--method", "l2", "--depth", "0.01", "-q"]
    assert inspect_main([*base, "-o", str(out)]) in (0, 1)
    lights = out / "lights.txt"  # a file inside the output, as a user might keep one
    capsys.readouterr()
    for flag, path in (("--mask", out / "overlay.png"), ("--lights", lights)):
        if flag == "--lights":
            lights.write_text((stack / "light_directions.txt").read_text())
        code = inspect_main([*base, flag, str(path), "-o", str(out), "--overwrite"])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1, err
        assert err[0].startswith("msf-inspect: error:") and "contains the input" in err[0]
        assert path.is_file()
