"""Shared fixtures: paths to the real data beside the checkout, skipped cleanly when absent."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
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


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)
