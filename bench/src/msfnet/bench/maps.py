"""Timing of the inspection maps on a full-frame object: ``python -m msfnet.bench.maps``.

The object is synthetic so the benchmark runs anywhere: a 612 x 512 frame (DiLiGenT's size)
holding an elliptical dome with three Gaussian bumps that fills ~64 % of it (~200k mask
pixels, 12x the DiLiGenT ball's mask), with exact normals. For each integration method it
reports the median and spread of the wall time over ``--repeat`` runs, the process CPU time
(on a machine shared with other jobs the two differ), the height RMS error against the rendered
surface, and the CPU model and core count, as a table and optionally as JSON.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import numpy as np

from msfnet.common import cpu
from msfnet.common.cli import command_main, make_parser, path_arg, positive_int
from msfnet.common.files import check_output, write_json
from msfnet.runtime.results.maps.curvature import curvature_maps
from msfnet.runtime.results.maps.integrate import METHODS, integrate_normals

PROG = "python -m msfnet.bench.maps"

HEIGHT, WIDTH = 512, 612


def bench_object(h: int = HEIGHT, w: int = WIDTH) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(height (H, W) px, mask (H, W) bool, unit normals (H, W, 3)): an elliptical dome
    (80 px high at 612 px wide, scaled with the width) with bumps, filling an ellipse with
    semi-axes 0.45 W and 0.45 H."""
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    au, av = 0.45 * w, 0.45 * h
    u, v = (cols - w / 2) / au, (rows - h / 2) / av
    mask = u**2 + v**2 < 0.98  # off the vertical rim, where a dome's slope is unbounded
    scale = w / WIDTH  # the same shape at any frame size
    amp = 80.0 * scale
    root = np.sqrt(np.clip(1 - u**2 - v**2, 1e-3, None))
    z = amp * root
    d_col, d_row = -amp * u / (au * root), -amp * v / (av * root)
    for fr, fc, a, fs in (
        (0.39, 0.41, 20.0, 0.05),
        (0.59, 0.65, -15.0, 0.065),
        (0.29, 0.69, 10.0, 0.033),
    ):
        r0, c0, s = fr * h, fc * w, fs * w  # bumps placed and sized relative to the frame
        e = a * scale * np.exp(-((rows - r0) ** 2 + (cols - c0) ** 2) / (2 * s * s))
        z += e
        d_col += -e * (cols - c0) / s**2
        d_row += -e * (rows - r0) / s**2
    n = np.stack([-d_col, d_row, np.ones_like(z)], axis=-1)  # y up: dz/dy = -dz/drow
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n[~mask] = 0
    return np.where(mask, z, np.nan), mask, n


def _times(walls: list[float], cpus: list[float]) -> dict[str, float]:
    """Median, fastest and slowest wall time, and the median CPU time, in seconds."""
    return {
        "median_s": statistics.median(walls),
        "min_s": min(walls),
        "max_s": max(walls),
        "cpu_s": statistics.median(cpus),
    }


def time_call(fn, repeat: int) -> tuple[list[float], list[float], object]:
    walls, cpus, out = [], [], None
    for _ in range(repeat):
        w0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        walls.append(time.perf_counter() - w0)
        cpus.append(time.process_time() - c0)
    return walls, cpus, out


def run(
    methods: tuple[str, ...], repeat: int, size: tuple[int, int] = (HEIGHT, WIDTH)
) -> dict[str, object]:
    z, mask, n = bench_object(*size)
    results: dict[str, object] = {
        "cpu": cpu.detect_cpu().model,
        "cores": cpu.usable_cores(),
        "frame": f"{size[1]}x{size[0]}",
        "mask_pixels": int(mask.sum()),
        "load_average": os.getloadavg(),
        "methods": {},
    }
    table = results["methods"]
    assert isinstance(table, dict)
    for method in methods:
        walls, cpus, res = time_call(lambda m=method: integrate_normals(n, mask, m), repeat)
        hgt = res.height  # type: ignore[attr-defined]
        d = (hgt - z)[mask]
        d -= d.mean()
        rms = float(np.sqrt(np.mean(d * d)))
        table[method] = {
            **_times(walls, cpus),
            "iterations": res.iterations,  # type: ignore[attr-defined]
            "rms_px": rms,
            "rms_pct_of_range": float(100 * rms / (np.nanmax(z) - np.nanmin(z))),
        }
    walls, cpus, _ = time_call(lambda: curvature_maps(n, mask), repeat)
    table["curvature"] = _times(walls, cpus)
    return results


def format_table(results: dict[str, object]) -> str:
    lines = [
        f"CPU: {results['cpu']} ({results['cores']} usable cores, load average "
        f"{', '.join(f'{x:.1f}' for x in results['load_average'])})",  # type: ignore
        f"object: {results['frame']} frame, {results['mask_pixels']} mask pixels",
        f"{'map':<10} {'median s':>9} {'min s':>7} {'max s':>7} {'cpu s':>7} "
        f"{'iters':>6} {'RMS px':>8} {'% range':>8}",
    ]
    for name, r in results["methods"].items():  # type: ignore[attr-defined]
        extra = (
            f"{r['iterations']:>6} {r['rms_px']:>8.3f} {r['rms_pct_of_range']:>8.3f}"
            if "rms_px" in r
            else f"{'':>6} {'':>8} {'':>8}"
        )
        lines.append(
            f"{name:<10} {r['median_s']:>9.3f} {r['min_s']:>7.3f} {r['max_s']:>7.3f} "
            f"{r['cpu_s']:>7.3f} {extra}"
        )
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    p = make_parser(
        PROG,
        f"Time normal integration (and curvature) on a {WIDTH}x{HEIGHT} masked object.",
        (f"{PROG} --repeat 5 --json maps.json",),
    )
    p.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS))
    p.add_argument(
        "--repeat", type=positive_int, default=3, help="runs per method (median reported)"
    )
    p.add_argument(
        "--size",
        type=positive_int,
        nargs=2,
        default=(HEIGHT, WIDTH),
        metavar=("H", "W"),
        help=f"frame size (default {HEIGHT} {WIDTH})",
    )
    p.add_argument("--json", type=path_arg, default=None, help="also write the results here")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --json file")
    return p


def _run(args: argparse.Namespace) -> int:
    if args.json is not None:  # before the timing, which takes a while
        check_output(args.json, overwrite=args.overwrite)
    results = run(tuple(args.methods), args.repeat, tuple(args.size))
    if args.json is not None:
        write_json(args.json, results, overwrite=args.overwrite)
    if not args.quiet:
        print(format_table(results))
    return 0


def main(argv: list[str] | None = None) -> int:
    return command_main(PROG, build_parser(), _run, argv)


if __name__ == "__main__":
    sys.exit(main())
