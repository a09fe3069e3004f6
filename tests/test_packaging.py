"""Packaging: the version is written once (pyproject.toml) and read from the install; the wheel
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


def test_version_is_pyprojects() -> None:
    # A mismatch means the install is older than pyproject.toml: reinstall (pip install -e .)
    assert msfnet.__version__ == _pyproject()["project"]["version"]


def test_version_without_an_install_is_unknown() -> None:
    # -S: no site-packages, so the source roots are on sys.path but no metadata names msfnet
    roots = [str(REPO / part / "src") for part in PARTS]
    code = f"import sys; sys.path[:0] = {roots!r}; import msfnet; print(msfnet.__version__)"
    out = subprocess.run(
        [sys.executable, "-S", "-c", code], capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "0+unknown"


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
