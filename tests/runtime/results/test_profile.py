"""The memory figures a run sizes its work by and reports."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from msfnet.runtime.instrument import memory_in_use_mb, peak_rss_mb


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/self/status is Linux's")
def test_memory_in_use_is_the_resident_size_psutil_reports() -> None:
    psutil = pytest.importorskip("psutil")
    before = memory_in_use_mb()
    block = np.ones(64 * 2**20 // 8)  # 64 MB, touched
    now = memory_in_use_mb()
    assert before is not None and now is not None
    assert now == pytest.approx(psutil.Process().memory_info().rss / 2**20, abs=4.0)
    assert now - before == pytest.approx(64.0, abs=8.0)
    assert peak_rss_mb() >= now - 1.0
    del block
