"""Shared fixtures: paths to the real data beside the checkout, skipped cleanly when absent."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np
import pytest
from _runtime_helpers import build_random_onnx

# A background job (`pytest &` in a script, CI runners that start one) begins with SIGINT ignored,
# and so would every child it starts: a test that sends Ctrl-C would see nothing happen. Python's
# own handler back here means in-process tests get KeyboardInterrupt and children start with the
# default disposition (exec resets handled signals; ignored ones it keeps).
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

REPO = Path(__file__).resolve().parents[1]
# $MSFNET_DATA, else ../shared/data beside the checkout (as in CI)
SHARED_DATA = Path(os.environ.get("MSFNET_DATA") or REPO.parent / "shared" / "data")
BALL = SHARED_DATA / "DiLiGenT" / "ballPNG"
PSM = SHARED_DATA / "psmImages"


def _require(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"real data not found at {path} (CI keeps ../shared/data beside the checkout)")
    return path


@pytest.fixture(scope="session")
def ball_dir() -> Path:
    return _require(BALL)


@pytest.fixture(scope="session")
def psm_dir() -> Path:
    return _require(PSM)


@pytest.fixture(autouse=True, scope="session")
def _private_cache_home(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Tests keep the CPU probe (msfnet.common.cpu) in a folder of their own, not the user's
    ~/.cache."""
    os.environ["XDG_CACHE_HOME"] = str(tmp_path_factory.mktemp("cache"))


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


@pytest.fixture(scope="session")
def random_onnx(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Built once per session (the file is reused if another module asks again)."""
    folder = tmp_path_factory.getbasetemp() / "runtime_model"
    folder.mkdir(exist_ok=True)
    return build_random_onnx(folder)


@pytest.fixture(scope="session")
def sensitive_onnx(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.getbasetemp() / "runtime_model"
    folder.mkdir(exist_ok=True)
    return build_random_onnx(folder, sensitive=True)


@pytest.fixture(scope="session")
def staged_onnx(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``sensitive_onnx``'s weights as a staged export (msf-export --staged)."""
    folder = tmp_path_factory.getbasetemp() / "runtime_model"
    folder.mkdir(exist_ok=True)
    return build_random_onnx(folder, sensitive=True, staged=True)


@pytest.fixture
def mat_parses(monkeypatch: pytest.MonkeyPatch) -> list[Path]:
    """Every parse of a .mat file's element headers during the test, by path (the helper
    common.matfile._variables counted)."""
    from collections.abc import Iterator
    from typing import BinaryIO

    from msfnet.common import matfile

    parses: list[Path] = []
    real = matfile._variables

    def counted(f: BinaryIO, order: str, path: Path) -> Iterator[object]:
        parses.append(path)
        return real(f, order, path)

    monkeypatch.setattr(matfile, "_variables", counted)
    return parses
