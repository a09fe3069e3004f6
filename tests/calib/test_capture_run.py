"""msf-capture --run: capture (simulated rig) then msf-run, in one command."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from msfnet.calib.capture_cli import main as capture_main


def test_capture_then_run_with_the_simulated_rig(tmp_path: Path, capsys) -> None:
    stack_dir, out = tmp_path / "captured", tmp_path / "out"
    args = [
        str(stack_dir),
        "--camera",
        "sim",
        "--light-rig",
        "sim",
        "--count",
        "8",
        "--run",
        "--method",
        "l2",
        "-o",
        str(out),
    ]
    assert capture_main(args) == 0, capsys.readouterr().err
    assert (stack_dir / "light_directions.txt").is_file()
    normals = np.load(out / "normals.npy", allow_pickle=False)
    assert normals.shape[2] == 3 and np.isfinite(normals).all()
    lit = np.linalg.norm(normals, axis=2) > 0.5
    assert lit.sum() > 1000  # the sphere was reconstructed, not an empty map
    # A second run resumes the finished session (captures nothing) and refuses the old output.
    assert capture_main(args) == 2
    assert "--overwrite" in capsys.readouterr().err
