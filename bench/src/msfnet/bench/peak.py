"""Matrix-multiply peak of this machine, measured with torch in the benchmark's own run.

The size grows until one product takes long enough to time (bf16 without hardware support is
~100x slower than fp32, so a fixed 2048^3 product could take a minute there).
"""

from __future__ import annotations

import statistics
import time


def matmul_peak_gflops(dtype: str = "fp32", threads: int = 2, min_seconds: float = 0.15,
                       max_size: int = 3072, repeats: int = 5) -> dict[str, float]:
    """Median GFLOP/s of square matmuls in ``dtype`` ('fp32' or 'bf16') at ``threads``."""
    import torch

    torch.set_num_threads(threads)
    tdtype = {"fp32": torch.float32, "bf16": torch.bfloat16}[dtype]
    gen = torch.Generator().manual_seed(0)
    n = 256
    while True:
        a = torch.randn(n, n, generator=gen).to(tdtype)
        b = torch.randn(n, n, generator=gen).to(tdtype)
        a @ b  # warm-up (packing buffers, thread pool)
        t0 = time.perf_counter()
        a @ b
        dt = time.perf_counter() - t0
        if dt >= min_seconds or n >= max_size:
            break
        n = min(max_size, n * 2)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        a @ b
        times.append(time.perf_counter() - t0)
    med = statistics.median(times)
    return {"dtype": dtype, "threads": threads, "size": n,
            "gflops": 2.0 * n ** 3 / med / 1e9, "best_gflops": 2.0 * n ** 3 / min(times) / 1e9}
