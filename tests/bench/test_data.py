"""msf-bench's data root: --data, $MSFNET_DATA, ./shared/data, ../shared/data; clear errors."""

from __future__ import annotations

from pathlib import Path

import pytest

from msfnet.bench.cli import build_parser, options, resolve_paths
from msfnet.bench.data import data_root
from msfnet.bench.options import BenchOptions
from msfnet.common.errors import InputError
from msfnet.common.vocabulary import speaking_as


def _tree(tmp_path: Path) -> tuple[Path, Path]:
    """tmp/work/checkout (the current folder) and tmp/work/shared/data beside it."""
    cwd = tmp_path / "work" / "checkout"
    cwd.mkdir(parents=True)
    data = tmp_path / "work" / "shared" / "data"
    (data / "DiLiGenT" / "ballPNG").mkdir(parents=True)
    return cwd, data


def _options(*argv: str) -> BenchOptions:
    return options(build_parser().parse_args(argv))


def test_order_explicit_env_then_relative(tmp_path: Path) -> None:
    cwd, data = _tree(tmp_path)
    other = tmp_path / "elsewhere"
    other.mkdir()
    assert data_root(None, cwd=cwd, env={}) == data.resolve()  # ../shared/data
    (cwd / "shared" / "data").mkdir(parents=True)
    assert data_root(None, cwd=cwd, env={}) == (cwd / "shared" / "data").resolve()  # ./ first
    assert data_root(None, cwd=cwd, env={"MSFNET_DATA": str(other)}) == other
    assert data_root(data, cwd=cwd, env={"MSFNET_DATA": str(other)}) == data


def test_missing_folders_are_errors_naming_what_was_tried(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="MSFNET_DATA") as exc:
        data_root(None, cwd=tmp_path, env={})
    assert str(tmp_path / "shared" / "data") in str(exc.value)
    # a typo in an explicit setting is an error, not a fallback to ./shared/data
    (tmp_path / "shared" / "data").mkdir(parents=True)
    with pytest.raises(InputError, match="MSFNET_DATA"):
        data_root(None, cwd=tmp_path, env={"MSFNET_DATA": str(tmp_path / "typo")})
    with speaking_as("msf-bench"), pytest.raises(InputError, match="--data"):
        data_root(tmp_path / "typo", cwd=tmp_path, env={})


def test_default_stack_does_not_depend_on_the_install_location(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    cwd, data = _tree(tmp_path)
    (data / "psmImages" / "cat").mkdir(parents=True)
    monkeypatch.chdir(cwd)
    monkeypatch.delenv("MSFNET_DATA", raising=False)
    stack, calib, _ = resolve_paths(_options())
    assert stack == data.resolve() / "DiLiGenT" / "ballPNG"
    assert calib == (stack, data.resolve() / "psmImages" / "cat")
    with speaking_as("msf-bench"), pytest.raises(InputError, match="--data"):
        resolve_paths(_options("--data", str(tmp_path / "nowhere")))


def test_a_named_data_root_that_is_missing_is_an_error_beside_a_stack(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With --stack given, a mistyped --data or $MSFNET_DATA was dropped in silence and int8
    calibrated on the one stack instead of four."""
    stack = tmp_path / "ballPNG"
    stack.mkdir()
    monkeypatch.chdir(tmp_path)  # no data root beside it either
    monkeypatch.delenv("MSFNET_DATA", raising=False)
    opts = _options("--stack", str(stack), "--data", str(tmp_path / "dta"))
    with speaking_as("msf-bench"), pytest.raises(InputError, match="--data: folder not found"):
        resolve_paths(opts)
    monkeypatch.setenv("MSFNET_DATA", str(tmp_path / "dta"))
    with pytest.raises(InputError, match="MSFNET_DATA"):
        resolve_paths(_options("--stack", str(stack)))
    monkeypatch.delenv("MSFNET_DATA")
    # nothing named, none found: the stack alone
    assert resolve_paths(_options("--stack", str(stack)))[1] == (stack,)
