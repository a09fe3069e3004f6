"""Result files (runtime/results/outputs.py): PNGs through imageio's one encoder."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from msfnet.common.imageio import encode_png
from msfnet.runtime.results import outputs


@pytest.mark.parametrize("shape", [(7, 5, 3), (7, 5)])
def test_write_rgb_png_is_the_shared_encoder(
    shape: tuple[int, ...], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    img = np.random.default_rng(2).integers(0, 65536, shape, np.uint16)
    encode_png(tmp_path / "a.png", img)
    calls: list[Path] = []

    def spy(path: Path, arr: np.ndarray, name: Path | None = None) -> None:
        calls.append(path)
        encode_png(path, arr, name=name)

    monkeypatch.setattr(outputs, "encode_png", spy)
    outputs.write_rgb_png(tmp_path / "b.png", img)
    assert calls == [tmp_path / "b.png"]
    assert (tmp_path / "a.png").read_bytes() == (tmp_path / "b.png").read_bytes()
