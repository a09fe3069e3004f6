"""The install as the README gives it: CI runs the README's command, torch comes from the CPU
index, and what the README's commands write into the clone is ignored by git."""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
CPU_INDEX = "https://download.pytorch.org/whl/cpu"


def _readme_command(number: int) -> str:
    """The command under ``# <number>. ...`` in the README's install block."""
    text = (REPO / "README.md").read_text()
    match = re.search(rf"^# {number}\. .*\n(.+)$", text, re.MULTILINE)
    assert match, f"README: no install command {number}"
    return match.group(1).strip()


def _ci_command() -> str:
    lines = (REPO / ".ci" / "run").read_text().splitlines()
    marker = next(i for i, ln in enumerate(lines) if "keep the two in sync" in ln)
    return lines[marker + 1].strip()


def test_ci_runs_the_readme_test_command() -> None:
    assert _ci_command() == _readme_command(2)


def test_torch_is_installed_first_from_the_cpu_index() -> None:
    """A bare ``pip install torch`` takes the CUDA build (GBs) on an ordinary machine; the
    CPU build, pinned by its local version (which PyPI cannot offer), must come first, from
    PyTorch's CPU index, before any extra needs torch."""
    first, *rest = _readme_command(2).split(" && ")
    words = shlex.split(first)
    assert words[:3] == ["pip", "install", "torch==2.13.0+cpu"], first
    assert words[words.index("--extra-index-url") + 1] == CPU_INDEX
    assert any("[export" in step for step in rest)  # the extras that need torch come after
    assert "torch" not in _readme_command(1)  # the edge install stays torch-free


def _readme_outputs() -> list[str]:
    """Paths, relative to the clone root, that the README's shell examples write there."""
    text = (REPO / "README.md").read_text()
    blocks = re.findall(r"```(?:sh|bash)\n(.*?)```", text, re.DOTALL)
    out = ["msf-out/ballPNG/normals.npy", "msf-eval/DiLiGenT/results.json"]  # defaults
    out += ["msf-bench-out/index.html", ".mypy_cache/x", ".hypothesis/x", ".ci-venv/bin/python"]
    for block in blocks:
        for line in block.replace("\\\n", " ").splitlines():
            words = shlex.split(line, comments=True)
            for i, word in enumerate(words[:-1]):
                if word in ("-o", "--out", "--report-dir"):
                    target = words[i + 1].rstrip("/")
                    out.append(target if "." in Path(target).name else f"{target}/x")
            if words[:1] == ["msf-capture"]:
                out.append(words[1].rstrip("/") + "/session.json")
            if words[:2] == ["msf-calib", "directions"] and "-o" in words:
                stem = Path(words[words.index("-o") + 1]).stem
                out += [f"{stem}_confidence.txt", f"{stem}_diagnostic.png"]
    return [p for p in out if not p.startswith(("/", ".."))]  # outside the clone: not ours


def test_gitignore_covers_what_the_readme_commands_write() -> None:
    if shutil.which("git") is None or not (REPO / ".git").exists():
        pytest.skip("not a git checkout")
    paths = _readme_outputs()
    assert "light_directions_diagnostic.png" in paths and "avg.pth" in paths  # parsed
    assert "msfnet.onnx" in paths and "out/bear/x" in paths and "obj/session.json" in paths
    done = subprocess.run(
        ["git", "check-ignore", "--no-index", "--verbose", "--non-matching", *paths],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=False,
    )
    missed = [ln.split("\t")[-1] for ln in done.stdout.splitlines() if ln.startswith("::")]
    assert missed == [], f"not ignored: {missed}"
    # the tracked sources stay visible (an over-broad pattern would hide them)
    kept = subprocess.run(
        ["git", "check-ignore", "--no-index", "README.md", "runtime/src/msfnet/runtime/api.py"]
        + [str(p.relative_to(REPO)) for p in REPO.glob("*/src/msfnet/*/**/*.onnx")],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=False,
    )
    assert kept.stdout == ""
