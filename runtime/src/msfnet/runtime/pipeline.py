"""The Python API: ``Model`` (load once, run many stacks) and ``Result`` (arrays, no files).

    from msfnet import Model, load_stack
    model = Model()                        # the bundled network; Model.least_squares() for L2
    result = model(load_stack("bearPNG", select="21-96"))
    result.normals, result.metrics         # (H, W, 3) float32; NormalMetrics with ground truth
    result.save("out/bear")                # the same files as msf-run writes

The data flows stack -> estimator (normalise -> infer, tiled) -> metrics -> Result; nothing is
written until ``Result.save``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import InputError
from .estimators import (
    Estimator,
    LeastSquaresEstimator,
    NetworkEngine,
    NetworkEstimator,
    TilingOptions,
)
from .metrics import NormalMetrics, error_map, normal_metrics
from .profile import Profile, StageTimer
from .stack import LoadOptions, Stack, load_stack
from .tiling import DEFAULT_MAX_MEMORY_MB, TilePlan

WEIGHTS = Path(__file__).resolve().parent / "weights"


def default_model_path() -> Path:
    """The bundled model, shipped with the runtime (msfnet/runtime/weights/msfnet_default.onnx)."""
    return WEIGHTS / "msfnet_default.onnx"


@dataclass
class Result:
    """Everything one run produced, as arrays; serialised only by :meth:`save`."""

    stack: Stack
    normals: np.ndarray  # (H, W, 3) float32 unit normals, zeros outside the mask
    method: dict[str, object]  # what ran (estimator.describe())
    timings: Profile
    metrics: NormalMetrics | None = None  # with ground truth
    error_deg: np.ndarray | None = None  # (H, W) angular error, NaN where not scored
    plan: TilePlan | None = None
    maps: object | None = None  # inspection maps (albedo, height, curvature) when computed
    extra: dict[str, object] = field(default_factory=dict)

    def profile(self) -> dict[str, object]:
        """Latency per stage, memory, work done and what ran: profile.json's content."""
        h, w = self.stack.shape
        info: dict[str, object] = {
            **self.method, "stack": str(self.stack.source or self.stack.name),
            "lights": self.stack.num_lights, "height": h, "width": w,
            "mask_pixels": int(self.stack.mask.sum())}
        if self.plan is not None:
            p = self.plan
            info["tiles"] = {"run": len(p.tiles), "skipped": p.skipped, "tile_px": p.tile_size,
                             "halo_px": p.halo, "pixels_computed": p.pixels,
                             "overhead_vs_image": p.pixels / float(h * w)}
        return {**self.timings.summary(), **info, **self.extra}

    def save(self, folder: str | Path, *, overwrite: bool = False,
             inputs: tuple[Path, ...] = ()) -> list[Path]:
        """Write normals.npy/png, profile.json and, with ground truth, metrics.json and
        error.png into ``folder``, all at once or not at all."""
        from .files import check_output
        from .outputs import write_result

        src = tuple(p for p in (self.stack.source, *inputs) if p is not None)
        check_output(folder, src, overwrite=overwrite, folder=True)
        return write_result(self, Path(folder), overwrite=overwrite)


class Model:
    """A loaded estimator with its run options: create once, call on many stacks.

    ``Model()`` is the bundled network; ``Model("x.onnx", threads=2)`` another msfnet ONNX
    export; ``Model.least_squares()`` classical least squares. ``engine`` / ``precision``
    pick the execution engine (default: chosen for this CPU).
    """

    def __init__(self, model: str | Path | NetworkEngine | None = None, *,
                 method: str = "msf", engine: str | None = None,
                 precision: str | None = None, threads: int | None = None,
                 provider: str | None = None, tile: int | None = None,
                 max_memory_mb: float = DEFAULT_MAX_MEMORY_MB) -> None:
        self.tiling = TilingOptions(tile, max_memory_mb)
        self.estimator: Estimator
        if method == "l2":
            if model is not None:
                raise InputError("least squares (--method l2) needs no model; drop --onnx")
            self.estimator = LeastSquaresEstimator()
        elif method != "msf":
            raise InputError(f"method {method!r}: expected 'msf' (the network) or 'l2'")
        elif model is not None and not isinstance(model, (str, Path)):
            self.estimator = NetworkEstimator(model)
        else:
            path = Path(model) if model is not None else default_model_path()
            if model is None and not path.is_file():
                raise InputError(f"no model given and no bundled model at {path}; export one "
                                 "with msf-export, or use least squares (--method l2)")
            self.estimator = _open_network(path, engine, precision, threads, provider)

    @classmethod
    def least_squares(cls, *, max_memory_mb: float = DEFAULT_MAX_MEMORY_MB) -> Model:
        return cls(method="l2", max_memory_mb=max_memory_mb)

    @property
    def method(self) -> str:
        return self.estimator.method

    def describe(self) -> dict[str, object]:
        return self.estimator.describe()

    def __call__(self, stack: Stack | str | Path, load: LoadOptions | None = None, *,
                 repeat: int = 1, progress: bool = False) -> Result:
        """Normals (+ metrics with ground truth) for a Stack or a stack path; writes nothing.

        ``repeat``: run load -> metrics that many times for the latency profile.
        """
        if repeat < 1:
            raise InputError(f"--repeat must be at least 1, got {repeat}")
        prof = Profile()
        loaded: Stack | None = None
        result: Result | None = None
        for _ in range(repeat):
            timer = StageTimer()
            with timer("total"):
                with timer("load"):
                    loaded = (stack.validate() if isinstance(stack, Stack)
                              else load_stack(stack, load))
                est = self.estimator.estimate(loaded, self.tiling, timer, progress)
                metrics = err = None
                with timer("postprocess"):
                    if loaded.normals_gt is not None:
                        metrics = normal_metrics(est.normals, loaded.normals_gt, loaded.mask)
                        err = error_map(est.normals, loaded.normals_gt, loaded.mask)
            prof.add(timer)
            prof.flops = est.flops
            result = Result(loaded, est.normals, self.describe(), prof, metrics, err, est.plan)
        assert result is not None
        return result

    def predict(self, images: np.ndarray, lights: np.ndarray, mask: np.ndarray | None = None,
                intensities: np.ndarray | None = None,
                normals_gt: np.ndarray | None = None) -> Result:
        """Run on numpy arrays: images (N, H, W, 3) or (N, H, W) linear values, lights (N, 3)
        directions (x right, y up, z to the camera); mask (H, W) and intensities (N, 3)
        optional."""
        return self(Stack.from_arrays(images, lights, mask=mask, intensities=intensities,
                                      normals_gt=normals_gt, name="array"))


def _open_network(path: Path, engine: str | None, precision: str | None,
                  threads: int | None, provider: str | None) -> NetworkEstimator:
    from .session import create_session

    if engine not in (None, "onnxruntime", "ort"):
        raise InputError(f"--engine {engine!r}: this build runs onnxruntime")
    if precision not in (None, "fp32"):
        raise InputError(f"--precision {precision!r}: this build runs the model's own precision")
    session = create_session(path, threads=threads, provider=provider)
    return NetworkEstimator(session, "onnxruntime: the model's own precision")


__all__ = ["Model", "Result", "default_model_path"]
