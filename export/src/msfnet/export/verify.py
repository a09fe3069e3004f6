"""Verification: a candidate model against a reference on object pixels, and the pass/fail rule.

A *runner* maps network inputs ``images (1, N, 3, H, W), lights (1, N, 3)`` to normals
``(1, 3, H, W)``: PyTorch, an in-memory ONNX graph, or the written file as the runtime loads it.
Angles are atan2(|a x b|, a . b) in float64 (``runtime.evaluate.metrics.angular_error_deg``),
over the object pixels only (in the background a trained network's raw output is a near-zero
vector whose direction is ill-conditioned, and the runtime zeroes those pixels anyway).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from msfnet.common.errors import InputError
from msfnet.export.variants import VerificationRow, VerifyRule
from msfnet.runtime.evaluate.metrics import angular_error_deg

if TYPE_CHECKING:
    import torch

    from msfnet.runtime.stack import Stack

Runner = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class Case:
    """One check: network inputs (batch B), object masks (B, H, W), and where they came from."""

    images: np.ndarray
    lights: np.ndarray
    mask: np.ndarray
    source: str = "rendered"


def rendered_cases(
    checks: Iterable[tuple[int, int, int]], batch: int = 1, seed: int = 100
) -> Iterator[Case]:
    """Rendered non-Lambertian objects at each (N, H, W), normalised as the runtime does."""
    from msfnet.export.onnx_export import rendered_inputs

    for i, (n, h, w) in enumerate(checks):
        images, lights, masks = rendered_inputs(batch, n, h, w, seed=seed + i)
        yield Case(images, lights, masks)


def tile_cases(stacks: Sequence[Stack], *, seed: int = 1000, **options: int) -> Iterator[Case]:
    """Calibration-like tiles (``quantize.calibration_tiles``, same options: inside the stacks'
    masks, at up to three light counts), taken at other places than the calibration's own
    (another seed)."""
    from msfnet.export.quantize import calibration_tiles

    for feeds, mask, name in calibration_tiles(stacks, seed=seed, **options):
        yield Case(feeds["images"], feeds["lights"], mask[None], source=f"tile of {name}")


def torch_runner(model: torch.nn.Module) -> Runner:
    import torch

    def run(images: np.ndarray, lights: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return model(torch.from_numpy(images), torch.from_numpy(lights)).numpy()

    return run


def session_runner(session: object, staged_chunk: int | None = None) -> Runner:
    """An onnxruntime.InferenceSession; ``staged_chunk``: a staged graph, run by the runtime's
    light-chunked loop with that many lights per call (one stack at a time)."""
    from msfnet.runtime.engines.staged_loop import run_staged

    def run(images: np.ndarray, lights: np.ndarray) -> np.ndarray:
        if staged_chunk:
            return np.concatenate(
                [
                    run_staged(session, images[b : b + 1], lights[b : b + 1], staged_chunk)
                    for b in range(len(images))
                ]
            )
        return session.run(["normals"], {"images": images, "lights": lights})[0]  # type: ignore[attr-defined]

    return run


def cpu_session(data: bytes, threads: int | None = None):  # type: ignore[no-untyped-def]
    """An ONNX Runtime CPU session on a serialised graph, quiet (warnings off)."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    if threads:
        opts.intra_op_num_threads = threads
    opts.log_severity_level = 3
    return ort.InferenceSession(data, opts, providers=["CPUExecutionProvider"])


def proto_runner(data: bytes, staged_chunk: int | None, threads: int | None = None) -> Runner:
    """An in-memory ONNX graph (serialised) on ONNX Runtime's CPU provider."""
    return session_runner(cpu_session(data, threads), staged_chunk)


def file_runner(path: Path, staged_chunk: int | None, threads: int | None = None) -> Runner:
    """The written file exactly as the runtime loads it (metadata and I/O names checked)."""
    import onnx

    from msfnet.runtime.engines.ort_session import create_session

    try:
        onnx.checker.check_model(str(path), full_check=True)
    except onnx.checker.ValidationError as exc:
        raise InputError(f"exported graph fails onnx.checker: {str(exc).splitlines()[0]}") from exc
    model = create_session(path, threads=threads)
    if model.info.staged and staged_chunk:
        model = replace(model, lights_per_call=staged_chunk)
    return model.run


def compare(candidate: Runner, reference: Runner, cases: Iterable[Case]) -> list[VerificationRow]:
    """One row per case (and batch item): angles and the candidate's norm error on the mask."""
    rows = []
    for case in cases:
        n, h, w = case.images.shape[1], case.images.shape[3], case.images.shape[4]
        try:
            got = candidate(case.images, case.lights)
        except Exception as exc:  # ORT raises its own Fail/InvalidArgument types
            raise InputError(
                f"verification failed: ONNX Runtime cannot run N={n} {w}x{h} "
                f"({str(exc).splitlines()[0][:200]})"
            ) from exc
        want = reference(case.images, case.lights)
        for b in range(len(case.images)):
            a = got[b].transpose(1, 2, 0)[case.mask[b]]
            r = want[b].transpose(1, 2, 0)[case.mask[b]]
            if not len(a):
                continue
            diff = angular_error_deg(a, r)
            norm_error = np.abs(np.linalg.norm(a.astype(np.float64), axis=-1) - 1.0)
            rows.append(
                VerificationRow(
                    lights=n,
                    size=(h, w),
                    max_deg=float(diff.max()),
                    mean_deg=float(diff.mean()),
                    pixels=int(diff.size),
                    norm_error=float(norm_error.max()),
                    source=case.source,
                )
            )
    return rows


def judge(
    rows: Sequence[VerificationRow],
    rule: VerifyRule,
    limit_deg: float,
    what: str = "the exported model",
    source: Path | None = None,
) -> None:
    """Raise InputError unless every row has unit normals and the rule's statistic is within
    ``limit_deg``. NaN fails every comparison here. ``source``: the checkpoint, named in the
    message."""
    if not rows:
        raise InputError(f"verification failed: no object pixels to compare {what} on", source)
    for r in rows:
        if not r.norm_error <= rule.unit_norm_tol:
            h, w = r.size
            raise InputError(
                f"verification failed: {what} gives no unit normals on object pixels "
                f"(| |n| - 1 | up to {r.norm_error:.3g} at N={r.lights} {w}x{h}, "
                f"{r.source}); degenerate weights (e.g. an all-zero checkpoint)?",
                source,
            )
    if rule.statistic == "max":
        stat = max(r.max_deg for r in rows)
    else:
        px = sum(r.pixels for r in rows)
        stat = sum(r.mean_deg * r.pixels for r in rows) / px
    if not (math.isfinite(stat) and stat <= limit_deg):
        worst = max(r.max_deg for r in rows)
        raise InputError(
            f"verification failed: {what} differs from the reference by "
            f"{stat:.4g} deg {rule.statistic} (> {limit_deg:g} deg; max "
            f"{worst:.4g} deg): {rule.describe(limit_deg)}",
            source,
        )


__all__ = [
    "Case",
    "Runner",
    "compare",
    "file_runner",
    "judge",
    "proto_runner",
    "rendered_cases",
    "session_runner",
    "tile_cases",
    "torch_runner",
]
