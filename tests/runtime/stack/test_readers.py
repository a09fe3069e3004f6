"""Light and intensity files as editors write them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from msfnet.runtime.stack.readers import read_vectors

ROWS = [[-0.0629, 0.1, 0.99], [0.2, -0.3, 0.93], [0.0, 0.5, 0.86]]


@pytest.mark.parametrize("suffix", [".txt", ".json"])
def test_a_utf8_byte_order_mark_is_read(tmp_path: Path, suffix: str) -> None:
    """Windows Notepad's "UTF-8" starts the file with a BOM; it was refused as
    "could not convert string to float: '\\ufeff-0.0629'"."""
    text = (
        "\n".join(" ".join(map(str, r)) for r in ROWS) + "\r\n" if suffix == ".txt" else str(ROWS)
    )
    path = tmp_path / f"light_directions{suffix}"
    path.write_bytes(b"\xef\xbb\xbf" + text.encode())
    np.testing.assert_allclose(read_vectors(path, "light directions"), ROWS, rtol=1e-6)
