"""``run_stack``: the importable API behind ``msf-run`` (stack -> normals, metrics, profile)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import InputError
from .flops import inference_flops
from .infer import choose_plan, infer_normals
from .least_squares import least_squares_normals
from .metrics import error_map, normal_metrics
from .outputs import check_outdir, default_outdir, write_outputs
from .profile import Profile, StageTimer
from .session import ModelSession, create_session
from .stack import Stack, load_stack
from .tiling import TilePlan

METHODS = ("msf", "l2")


def default_model_path() -> Path:
    """The bundled model, shipped with the runtime (msfnet/runtime/weights/msfnet_default.onnx)."""
    return Path(__file__).resolve().parent / "weights" / "msfnet_default.onnx"


@dataclass
class RunResult:
    normals: np.ndarray  # (H, W, 3) float32, zeros outside the mask
    stack: Stack
    metrics: dict | None
    profile: dict
    table: str
    outdir: Path | None
    files: list[Path] = field(default_factory=list)
    plan: TilePlan | None = None


def _resolve_model(onnx: str | Path | None, method: str) -> Path | None:
    if method not in METHODS:
        raise InputError(f"--method {method!r}: expected one of {', '.join(METHODS)}")
    if method == "l2":
        if onnx is not None:
            raise InputError("--method l2 needs no model; drop --onnx")
        return None
    if onnx is not None:
        return Path(onnx)
    bundled = default_model_path()
    if not bundled.is_file():
        raise InputError(f"no --onnx MODEL given and no bundled model at {bundled}; export one "
                         "with msf-export, or use --method l2")
    return bundled


def run_stack(stack: str | Path | Stack, *, onnx: str | Path | None = None,
              method: str = "msf", outdir: str | Path | None = None, write: bool = True,
              overwrite: bool = False, lights: str | Path | None = None,
              intensities: str | Path | None = None, mask: str | Path | None = None,
              select: str | None = None, max_lights: int | None = None,
              threads: int | None = None, provider: str | None = None, tile: int | None = None,
              max_memory_mb: float | None = None, repeat: int = 1, progress: bool = False,
              session: ModelSession | None = None) -> RunResult:
    """Load a stack (path or Stack), estimate normals, score against ground truth, write outputs.

    ``method``: "msf" (ONNX model ``onnx``, default the bundled one) or "l2" (least squares).
    ``tile``: window edge in px, 0 = untiled, None = sized from ``max_memory_mb`` (default 4096).
    ``repeat``: run load -> postprocess that many times for the latency profile.
    Nothing is written when ``write`` is False; otherwise all files land in ``outdir`` at once.
    """
    if repeat < 1:
        raise InputError(f"--repeat must be at least 1, got {repeat}")
    model_path = _resolve_model(onnx, method) if session is None else session.info.path
    source = stack.source if isinstance(stack, Stack) else Path(stack)
    out = None
    if write:
        name = stack.name if isinstance(stack, Stack) else Path(stack).stem
        out = Path(outdir) if outdir is not None else default_outdir(name)
        inputs = [p for p in (source, lights, intensities, mask) if p is not None]
        check_outdir(out, overwrite, [Path(p) for p in inputs])
    prof = Profile()
    init = StageTimer()
    if model_path is not None and session is None:
        with init("session"):
            session = create_session(model_path, threads=threads, provider=provider)
    result_normals = None
    loaded: Stack | None = None
    plan = None
    for _ in range(repeat):
        timer = StageTimer()
        with timer("total"):
            with timer("load"):
                if isinstance(stack, Stack):
                    loaded = stack.validate()
                else:
                    loaded = load_stack(stack, lights=lights, intensities=intensities, mask=mask,
                                        select=select, max_lights=max_lights)
            if session is not None:
                plan = choose_plan(loaded, session, tile, max_memory_mb)
                res = infer_normals(session, loaded, plan, timer, progress=progress)
                result_normals = res.normals
            else:
                with timer("inference"):
                    result_normals = least_squares_normals(loaded)
            metrics = err = None
            with timer("postprocess"):
                if loaded.normals_gt is not None:
                    metrics = normal_metrics(result_normals, loaded.normals_gt, loaded.mask)
                    err = error_map(result_normals, loaded.normals_gt, loaded.mask)
        prof.add(timer)
    assert loaded is not None and result_normals is not None
    if plan is not None and session is not None:
        prof.flops = inference_flops(loaded.num_lights, plan.pixels)
    h, w = loaded.shape
    prof.info = {
        "method": method, "model": str(model_path) if model_path else None,
        "stack": str(source) if source else loaded.name, "lights": loaded.num_lights,
        "height": h, "width": w, "mask_pixels": int(loaded.mask.sum()),
        "session_init_s": init.seconds.get("session"),
        "threads": session.threads if session else None,
        "provider": session.provider if session else None,
        "tiles": None if plan is None else {
            "run": len(plan.tiles), "skipped": plan.skipped, "tile_px": plan.tile_size,
            "halo_px": plan.halo, "pixels_computed": plan.pixels,
            "overhead_vs_image": plan.pixels / float(h * w)},
    }
    summary = prof.summary()
    files: list[Path] = []
    if write and out is not None:
        files = write_outputs(out, result_normals, loaded.mask, profile=summary, metrics=metrics,
                              error_deg=err, overwrite=overwrite)
    return RunResult(result_normals, loaded, metrics, summary, prof.table(), out, files, plan)


__all__ = ["METHODS", "RunResult", "default_model_path", "run_stack"]
