"""msf-inspect's command line (cli/inspect.py): every file it reads is an input that no output
may contain or replace. The defect step itself is tested in tests/runtime/results."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
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


def _run_folder(tmp_path: Path, name: str, *extra: str) -> tuple[Path, Path]:
    from msfnet.runtime.cli.run import main as run_main

    stack = png_stack(tmp_path / f"{name}-stack", 16)
    out = tmp_path / name
    assert run_main([str(stack), "--method", "l2", "-o", str(out), "-q", *extra]) == 0
    return stack, out


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("msf-inspect: error:"), err
    return err[0]


def test_stack_flags_on_a_run_folder_are_refused_not_ignored(tmp_path: Path, capsys) -> None:
    """--pixel-size 0.05 --depth 0.005 on a px run folder inspected at 0.005 px, silently;
    --onnx of a missing file passed too."""
    _, run = _run_folder(tmp_path, "run")
    out = tmp_path / "v"
    for extra in (["--pixel-size", "0.05"], ["--onnx", "none.onnx"], ["--local-size", "30"]):
        assert _code([str(run), "--depth", "0.005", "-o", str(out), *extra]) == 2
        line = _one_line(capsys)
        assert f"{extra[0]} applies only when INPUT is a stack" in line and "(px)" in line
    # given at its default it is ignored just the same: refused too
    assert _code([str(run), "--depth", "0.005", "-o", str(out), "--local-size", "12"]) == 2
    assert "--local-size applies only" in _one_line(capsys)
    # how a stack would be run, not what the maps mean: accepted (a wrapper always caps them)
    for extra in (["--threads", "1"], ["--max-memory", "2000"], ["--engine", "onnxruntime"]):
        argv = [str(run), "--depth", "0.005", "-o", str(out), *extra, "-q", "--overwrite"]
        assert _code(argv) in (0, 1), capsys.readouterr().err
        capsys.readouterr()
    import shutil

    shutil.rmtree(out)
    # --maps none (no map: parsed to an empty tuple) is an output choice too, not "not given"
    for extra in (["--no-tiff"], ["--maps", "height"], ["--maps", "none"], ["--no-report"]):
        assert _code([str(run), "--depth", "0.005", "-o", str(out), *extra]) == 2
        assert "msf-inspect writes only its verdict" in _one_line(capsys)
    assert not out.exists()
    assert "--no-tiff" not in capsys.readouterr().out + _help()


def _help() -> str:
    from msfnet.runtime.cli.inspect import build_parser

    return build_parser().format_help()


def _code(argv: list[str]) -> int:
    try:
        return inspect_main(argv)
    except SystemExit as exc:
        return int(exc.code or 0)


def test_folders_msfnet_wrote_without_maps_are_named(tmp_path: Path, capsys) -> None:
    """They were read as stacks: "no light directions" for a --no-maps run, "no images found"
    for a batch."""
    from msfnet.runtime.cli.run import main as run_main

    stack, bare = _run_folder(tmp_path, "bare", "--no-maps")
    other = png_stack(tmp_path / "other", 16, seed=1)
    batch = tmp_path / "batch"
    assert run_main([str(stack), str(other), "--method", "l2", "-q", "-o", str(batch)]) == 0
    out = tmp_path / "v"
    assert _code([str(bare), "--depth", "0.1", "-o", str(out)]) == 2
    assert "an msf-run output without maps" in _one_line(capsys)
    assert _code([str(batch), "--depth", "0.1", "-o", str(out)]) == 2
    assert "batch output" in _one_line(capsys)
    assert not out.exists()


def test_a_missing_reference_is_refused_before_the_part_runs(
    tmp_path: Path, capsys, monkeypatch
) -> None:
    from msfnet.runtime.cli import inspect as cli

    stack = png_stack(tmp_path / "part", 16)
    monkeypatch.setattr(cli, "_prepare", lambda *a: (_ for _ in ()).throw(AssertionError("ran")))
    out = tmp_path / "v"
    argv = [str(stack), "--method", "l2", "--reference", str(tmp_path / "gone"), "--depth", "1"]
    assert _code([*argv, "-o", str(out)]) == 2
    assert "gone: no such file or folder" in _one_line(capsys)


@pytest.mark.parametrize(
    ("edit", "words"),
    [
        (lambda text: "{broken", "maps.json: not valid JSON"),
        (lambda text: text.replace('"local_shape": "px"', '"local_shape": "furlong"'), "units"),
    ],
)
def test_a_damaged_maps_json_says_what_is_wrong(tmp_path: Path, capsys, edit, words) -> None:
    import json
    import shutil

    _, run = _run_folder(tmp_path, "run")
    copy = tmp_path / "copy"
    shutil.copytree(run, copy)
    (copy / ".msfnet-output.json").unlink()
    text = json.dumps(json.loads((copy / "maps.json").read_text()))
    (copy / "maps.json").write_text(edit(text))
    assert _code([str(copy), "--depth", "0.1", "-o", str(tmp_path / "v")]) == 2
    assert words in _one_line(capsys)


def test_the_verdict_says_where_and_what_made_the_maps(tmp_path: Path, capsys) -> None:
    """With --roi, coordinates were the ROI's with nothing to say so; verdict.json had no
    provenance, unlike every other output."""
    import json

    stack = png_stack(tmp_path / "part", 16, h=48, w=64)
    out = tmp_path / "v"
    argv = [str(stack), "--method", "l2", "--roi", "8,4,40,36", "--depth", "1e-4", "-o", str(out)]
    assert inspect_main(argv) == 1  # a sphere's relief is far above 1e-4 px
    line = capsys.readouterr().out
    assert "at image x=" in line
    verdict = json.loads((out / "verdict.json").read_text())
    assert verdict["frame"] == {"origin_xy": [8, 4], "downscale": 1}
    region = verdict["regions"][0]
    assert region["image_peak"] == [region["peak"][0] + 8, region["peak"][1] + 4]
    prov = verdict["provenance"]
    assert prov["input"] == str(stack) and prov["model"] is None and prov["version"]


def test_auto_mask_is_a_load_option_msf_inspect_keeps(tmp_path: Path, capsys) -> None:
    """--auto-mask was refused as an output choice: without it a stack with no mask file is
    inspected background and all."""
    import numpy as np

    from msfnet.runtime.stack import load_stack

    stack = png_stack(tmp_path / "part", 16, h=40, w=48)
    (stack / "mask.png").unlink()
    out = tmp_path / "v"
    argv = [str(stack), "--method", "l2", "--auto-mask", "--depth", "50", "-o", str(out)]
    assert inspect_main([*argv, "-q"]) == 0
    inspected = json.loads((out / "verdict.json").read_text())["pixels_inspected"]
    assert 0 < inspected < 40 * 48 == int(np.prod(load_stack(stack).shape))


def test_a_reference_stack_reading_a_file_in_the_output_through_a_link_is_refused(
    tmp_path: Path, capsys
) -> None:
    """review-links23.md 1: the reference's linked mask.png was replaced by --overwrite."""
    part = png_stack(tmp_path / "part", 16)
    ref = png_stack(tmp_path / "ref", 16, seed=1)
    out = tmp_path / "verdict"
    base = [str(part), "--method", "l2", "--depth", "0.01", "-q"]
    assert inspect_main([*base, "-o", str(out)]) in (0, 1)
    (ref / "mask.png").unlink()
    (ref / "mask.png").symlink_to(out / "overlay.png")
    before = (out / "overlay.png").read_bytes()
    capsys.readouterr()
    code = inspect_main([*base, "--reference", str(ref), "-o", str(out), "--overwrite"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and "ref/mask.png (reached through a link)" in err[0], err
    assert (out / "overlay.png").read_bytes() == before
