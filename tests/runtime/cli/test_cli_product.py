"""msf-run's real-camera flags and the --json outputs of msf-run and msf-eval."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from _runtime_helpers import sphere_stack

from msfnet.common.imageio import read_mask
from msfnet.runtime.cli.eval import main as eval_main
from msfnet.runtime.cli.run import main as run_main
from msfnet.runtime.stack import save_stack


def _json_objects(text: str) -> list[dict]:
    """Concatenated JSON objects (msf-run --json prints one per stack)."""
    decoder, out, i = json.JSONDecoder(), [], 0
    while i < len(text):
        if text[i].isspace():
            i += 1
            continue
        obj, i = decoder.raw_decode(text, i)
        out.append(obj)
    return out


@pytest.mark.slow
def test_auto_mask_roi_and_downscale_flags(tmp_path: Path) -> None:
    stack = sphere_stack(n=8, h=48, w=64)
    # a folder without a usable mask (all ones), the object on a black background
    folder = save_stack(replace(stack, mask=np.ones(stack.shape, bool)), tmp_path / "cam")
    out = tmp_path / "out"
    assert (
        run_main(
            [
                "--method",
                "l2",
                str(folder),
                "-o",
                str(out),
                "--auto-mask",
                "--roi",
                "4,2,56,44",
                "--downscale",
                "2",
                "-q",
            ]
        )
        == 0
    )
    mask = read_mask(out / "mask.png")  # the computed mask, beside the outputs
    assert mask.shape == (22, 28) and np.load(out / "normals.npy").shape == (22, 28, 3)
    truth = stack.mask[2:46, 4:60].reshape(22, 2, 28, 2).mean(axis=(1, 3)) >= 0.5
    assert (mask & truth).sum() / (mask | truth).sum() > 0.9
    profile = json.loads((out / "profile.json").read_text())
    assert profile["input"] == {
        "roi": [4, 2, 56, 44],
        "downscale": 2,
        "linearise": None,
        "auto_mask": True,
    }
    # the same in a batch (two stacks)
    other = save_stack(
        replace(sphere_stack(n=8, h=48, w=64, seed=3), mask=np.ones(stack.shape, bool)),
        tmp_path / "cam2",
    )
    assert (
        run_main(
            [
                "--method",
                "l2",
                str(folder),
                str(other),
                "-o",
                str(tmp_path / "b"),
                "--auto-mask",
                "-q",
            ]
        )
        == 0
    )
    assert read_mask(tmp_path / "b" / "cam2" / "mask.png").sum() < 0.6 * 48 * 64
    # without --auto-mask no mask.png is written
    assert run_main(["--method", "l2", str(folder), "-o", str(tmp_path / "o2"), "-q"]) == 0
    assert not (tmp_path / "o2" / "mask.png").exists()


def test_linearisation_flags_exclude_each_other(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = save_stack(sphere_stack(n=4), tmp_path / "s")
    with pytest.raises(SystemExit) as exc:
        run_main(["--method", "l2", str(folder), "--srgb", "--gamma", "2.2"])
    assert exc.value.code == 2 and "not allowed with" in capsys.readouterr().err
    assert (
        run_main(["--method", "l2", str(folder), "--roi", "0,0,999,10", "-o", str(tmp_path / "o")])
        == 2
    )
    assert "reaches past the 44x36 image" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_json_outputs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = tmp_path / "set"
    for i in range(2):
        save_stack(sphere_stack(n=5, seed=i), root / f"o{i}")
    assert run_main(["--method", "l2", str(root), "-o", str(tmp_path / "run"), "--json"]) == 0
    objects = _json_objects(capsys.readouterr().out)
    assert [o.get("stack", "").split("/")[-1] for o in objects[:2]] == ["o0", "o1"]
    assert objects[-1]["summary"]["totals"]["stacks"] == 2
    assert eval_main([str(root), "--l2-only", "-o", str(tmp_path / "ev"), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["methods"] == ["l2"] and len(result["objects"]) == 2
    assert result["output"] == str(tmp_path / "ev") and "table" not in result
