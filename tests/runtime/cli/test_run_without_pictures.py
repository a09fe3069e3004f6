"""msf-run and msf-eval on an install without matplotlib: the pictures are drawn with numpy,
OpenCV and Pillow, so every output, pictures included, is written and nothing warns.
matplotlib is installed here, so a meta-path finder blocks it in a fresh interpreter, as on a
headless box without it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
from _runtime_helpers import sphere_stack

from msfnet.runtime.stack import save_stack

# Runs a command's main in a child where importing matplotlib (or any submodule) fails.
CHILD = """
import sys

class NoMatplotlib:
    def find_spec(self, name, path=None, target=None):
        if name == "matplotlib" or name.startswith("matplotlib."):
            raise ImportError(f"No module named {name!r} (blocked by the test)")
        return None

sys.meta_path.insert(0, NoMatplotlib())
from importlib import import_module
main = import_module(sys.argv[1]).main
code = main(sys.argv[2:])
assert "matplotlib" not in sys.modules
sys.exit(code)
"""

FIGURES = {"normals_view.png", "error.png"}  # drawn by results.maps.pictures
NON_PICTURES = {
    "normals.npy",
    "metrics.json",
    "profile.json",
    "maps.json",
    "albedo.png",
    "height.png",
    "height.tif",
    "curvature.png",
    "albedo.tif",
    "mesh.ply",
    "report.html",
}


def _msf_run(
    args: list[str], cwd: Path, module: str = "msfnet.runtime.cli.run"
) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", CHILD, module, *args],
        capture_output=True,
        text=True,
        check=False,
        timeout=300,
        cwd=cwd,
    )


def test_without_matplotlib_every_output_and_picture_is_written(tmp_path: Path) -> None:
    stack = save_stack(sphere_stack(n=6, h=24, w=28), tmp_path / "part")
    out = tmp_path / "out"
    done = _msf_run([str(stack), "--method", "l2", "-o", str(out)], tmp_path)
    assert done.returncode == 0, done.stderr
    assert not [line for line in done.stderr.splitlines() if "warning" in line], done.stderr
    written = {p.name for p in out.iterdir() if not p.name.startswith(".")}
    assert written >= NON_PICTURES | FIGURES, sorted((NON_PICTURES | FIGURES) - written)
    for name in FIGURES:
        img = cv2.imread(str(out / name), cv2.IMREAD_UNCHANGED)
        assert img is not None and img.ndim == 3 and img.shape[1] >= 400, name
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["error_png_max_deg"] > 0 and metrics["mae_deg"] >= 0
    report = (out / "report.html").read_text()
    assert "msfnet[pictures]" not in report and "not drawn" not in report
    assert report.count("data:image/png;base64") >= 5  # inputs, normals, albedo, height, ...


def test_a_batch_without_matplotlib_draws_every_stack(tmp_path: Path) -> None:
    for name in ("a", "b"):
        save_stack(sphere_stack(n=6, h=24, w=28), tmp_path / "stacks" / name)
    out = tmp_path / "out"
    done = _msf_run([str(tmp_path / "stacks"), "--method", "l2", "-o", str(out)], tmp_path)
    assert done.returncode == 0, done.stderr
    assert "warning" not in done.stderr, done.stderr
    for name in ("a", "b"):
        assert (out / name / "mesh.ply").is_file() and (out / name / "normals.npy").is_file()
        assert (out / name / "normals_view.png").is_file()


def test_msf_eval_without_matplotlib_scores_and_draws(tmp_path: Path) -> None:
    for name in ("a", "b"):
        save_stack(sphere_stack(n=6, h=24, w=28), tmp_path / "bench" / name)
    out = tmp_path / "eval"
    args = [str(tmp_path / "bench"), "--l2-only", "-o", str(out)]
    done = _msf_run(args, tmp_path, "msfnet.runtime.cli.eval")
    assert done.returncode == 0, done.stderr
    assert "figures not drawn" not in done.stderr, done.stderr
    rows = json.loads((out / "results.json").read_text())["results"]
    assert [r["object"] for r in rows] == ["a", "b"]
    assert all(r["results"]["l2"]["mae_deg"] >= 0 for r in rows)
    assert (out / "a" / "l2_normals.png").is_file()
    assert sorted(p.name for p in out.rglob("*_error.png")) == ["l2_error.png", "l2_error.png"]
