"""Packaging: the version is written once (common.version) and read by the build; the wheel
ships the facade msfnet/__init__.py once although every source root holds a copy."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from collections import Counter
from pathlib import Path

import pytest

import msfnet

REPO = Path(__file__).resolve().parents[1]
PARTS = ("common", "runtime", "calib", "export", "model", "synth", "bench")


def _pyproject() -> dict:
    tomllib = pytest.importorskip("tomllib", reason="Python >= 3.11 reads pyproject.toml")
    with open(REPO / "pyproject.toml", "rb") as f:
        return tomllib.load(f)


def test_the_version_is_declared_once_and_read_by_the_build() -> None:
    """pyproject.toml takes it from common.version (hatch's version source), the install's
    metadata agrees with it, and no command needs importlib.metadata to know it."""
    from importlib.metadata import version

    from msfnet.common.version import __version__

    project = _pyproject()
    assert "version" not in project["project"] and "version" in project["project"]["dynamic"]
    assert project["tool"]["hatch"]["version"]["path"] == "common/src/msfnet/common/version.py"
    # a mismatch means the install is older than the source: reinstall (pip install -e .)
    assert msfnet.__version__ == __version__ == version("msfnet")


def test_commands_start_without_importlib_metadata() -> None:
    code = (
        "import sys, msfnet; from msfnet.runtime.cli.run import build_parser; build_parser(); "
        "print(msfnet.__version__, 'importlib.metadata' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == [msfnet.__version__, "False"]


def test_wheel_config_takes_the_facade_from_runtime_only() -> None:
    """hatch refuses to build a wheel with two files at one path: every root but runtime's
    must leave its facade and py.typed out."""
    excluded = set(_pyproject()["tool"]["hatch"]["build"]["targets"]["wheel"]["exclude"])
    for part in PARTS:
        for name in ("__init__.py", "py.typed"):
            pattern = f"/{part}/src/msfnet/{name}"
            assert (pattern in excluded) == (part != "runtime"), pattern


@pytest.mark.slow
def test_the_wheel_holds_each_file_once(tmp_path: Path) -> None:
    wheel_builder = pytest.importorskip("hatchling.builders.wheel", reason="needs hatchling")
    built = next(wheel_builder.WheelBuilder(str(REPO)).build(directory=str(tmp_path)))
    names = zipfile.ZipFile(built).namelist()
    assert [n for n, k in Counter(names).items() if k > 1] == []
    assert {"msfnet/__init__.py", "msfnet/py.typed"} <= set(names)
    parts = {n.split("/")[1] for n in names if n.startswith("msfnet/") and n.count("/") > 1}
    assert parts == set(PARTS)
