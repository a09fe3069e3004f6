"""The Python API: ``Model`` (load once, run many stacks) and ``Result`` (arrays, no files).

Example (tests/runtime/test_api_example.py runs exactly this; ``obj/`` is any stack folder)::

    from msfnet import Model, load_stack

    model = Model()                          # the bundled network, loaded once
    stack = load_stack("obj/", max_lights=8) # DiLiGenT-layout folder, images + lights, .npz
    result = model(stack)                    # arrays only: nothing is written
    print(result.normals.shape)              # (H, W, 3) float32 unit normals, x right, y up
    print(result.metrics)                    # MAE / median / err15 / err30 with ground truth
    result.save("out/obj")                   # the files msf-run writes (normals.npy/.png, ...)

    baseline = Model.least_squares()         # classical least squares, same API
    l2 = baseline.predict(stack.images, stack.lights, mask=stack.mask)  # plain numpy arrays

``Model("x.onnx", threads=2)`` loads another msfnet export. The data flows stack -> estimator
(normalise -> infer, tiled) -> metrics -> Result; nothing is written until ``Result.save``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from msfnet.common.errors import InputError
from msfnet.runtime.engines.base import Engine
from msfnet.runtime.evaluate.metrics import NormalMetrics, error_map, normal_metrics
from msfnet.runtime.infer.estimators import (
    Estimator,
    LeastSquaresEstimator,
    NetworkEstimator,
    TilingOptions,
)
from msfnet.runtime.infer.fine_detail import FineDetailEstimator
from msfnet.runtime.infer.tiling import DEFAULT_MAX_MEMORY_MB, TilePlan
from msfnet.runtime.options import DEFAULT_MAPS, ModelOptions
from msfnet.runtime.results.maps import InspectionMaps, MapOptions, stack_maps
from msfnet.runtime.results.profile import BatchStats, Profile, StageTimer
from msfnet.runtime.stack import LoadOptions, Stack, load_stack, prepare_stack

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
    maps: InspectionMaps | None = None  # albedo, height, curvature, ... (Model(maps=...))
    input: dict[str, object] | None = None  # how the stack was read (LoadOptions.describe())
    batch: BatchStats | None = None  # set by a batch run

    def profile(self) -> dict[str, object]:
        """Latency per stage, memory, work done and what ran: profile.json's content."""
        h, w = self.stack.shape
        info: dict[str, object] = {
            **self.method,
            "stack": str(self.stack.source or self.stack.name),
            "lights": self.stack.num_lights,
            "height": h,
            "width": w,
            "mask_pixels": int(self.stack.mask.sum()),
        }
        if self.plan is not None:
            p = self.plan
            info["tiles"] = {
                "run": len(p.tiles),
                "skipped": p.skipped,
                "tile_px": p.tile_size,
                "halo_px": p.halo,
                "pixels_computed": p.pixels,
                "overhead_vs_image": p.pixels / float(h * w),
            }
        if self.input is not None:
            info["input"] = self.input
        if self.stack.warnings:  # a stack that loads but looks wrong: kept with the result
            info["warnings"] = list(self.stack.warnings)
        if self.batch is not None:
            info["batch"] = self.batch.as_dict()
        return {**self.timings.summary(), **info}

    @property
    def auto_mask(self) -> bool:
        """Whether the mask was computed from the images (``--auto-mask``)."""
        return self.input is not None and bool(self.input.get("auto_mask"))

    def save(
        self,
        folder: str | Path,
        *,
        overwrite: bool = False,
        inputs: tuple[Path, ...] = (),
        write_mask: bool | None = None,
        report: bool = True,
    ) -> list[Path]:
        """Write normals.npy/png, profile.json and, with ground truth, metrics.json and
        error.png into ``folder``, all at once or not at all; mask.png too when the mask was
        computed (``write_mask``: None = only then). Returns the files written."""
        from msfnet.common.files import check_output
        from msfnet.runtime.results.outputs import write_result

        folder = Path(folder)
        src = tuple(p for p in (self.stack.source, *inputs) if p is not None)
        check_output(folder, src, overwrite=overwrite, folder=True)
        # an automatic mask is a result the user should be able to inspect and reuse
        return write_result(
            self,
            folder,
            overwrite=overwrite,
            report=report,
            write_mask=self.auto_mask if write_mask is None else write_mask,
        )

    def without_images(self) -> Result:
        """A copy whose stack no longer holds the images (N x H x W x 0: shape and light count
        kept), to keep or ship many results (a batch, a Ray task) without their inputs."""
        n, h, w = self.stack.images.shape[:3]
        stack = replace(self.stack, images=np.empty((n, h, w, 0), np.float32))
        return replace(self, stack=stack)


class Model:
    """A loaded estimator with its run options: create once, call on many stacks.

    ``Model()`` is the bundled network; ``Model("x.onnx", threads=2)`` another msfnet ONNX
    export (loaded once, here); ``Model.least_squares()`` classical least squares. The keyword
    settings are the fields of :class:`~msfnet.runtime.options.ModelOptions` (``method``,
    ``engine``, ``precision``, ``threads``, ``provider``, ``tile``, ``max_memory_mb``,
    ``maps``, ``fine_detail``, ...); ``options=`` passes a whole ModelOptions instead.
    ``fine_detail`` also runs the network at 2x for relief of a few pixels
    (:mod:`msfnet.runtime.infer.fine_detail`).
    Calling it (``model(stack)``, :meth:`predict`) returns a :class:`Result` and writes
    nothing; a model may be called any number of times.
    """

    def __init__(
        self,
        model: str | Path | Engine | None = None,
        *,
        options: ModelOptions | None = None,
        **settings: Any,
    ) -> None:
        engine_given = model is not None and not isinstance(model, (str, Path))
        if model is not None and not engine_given:
            settings["model"] = Path(model)  # type: ignore[arg-type]
        opts = ModelOptions.of(options, **settings)
        if engine_given and not opts.is_network:
            raise InputError("least squares (method='l2') runs no engine; drop the model")
        self.options = opts
        self.tiling = TilingOptions(opts.tile, opts.max_memory_mb)
        self.maps = opts.maps  # inspection maps computed after the normals (None: normals only)
        self.estimator: Estimator
        if not opts.is_network:
            self.estimator = LeastSquaresEstimator()
        elif engine_given:
            self.estimator = NetworkEstimator(model)  # type: ignore[arg-type]
        else:
            path = opts.model if opts.model is not None else default_model_path()
            if opts.model is None and not path.is_file():
                raise InputError(
                    f"no model given and no bundled model at {path}; export one "
                    "with msf-export, or use least squares (--method l2)"
                )
            self.estimator = _open_network(path, opts)
        if opts.fine_detail and isinstance(self.estimator, NetworkEstimator):
            self.estimator = FineDetailEstimator(self.estimator)

    @classmethod
    def least_squares(
        cls, *, max_memory_mb: float = DEFAULT_MAX_MEMORY_MB, maps: MapOptions | None = DEFAULT_MAPS
    ) -> Model:
        """Per-pixel least squares (Woodham 1980): no network, the same inputs and outputs."""
        return cls(options=ModelOptions(method="l2", max_memory_mb=max_memory_mb, maps=maps))

    @property
    def method(self) -> str:
        return self.estimator.method

    def describe(self) -> dict[str, object]:
        return self.estimator.describe()

    def __repr__(self) -> str:
        d = self.describe()
        what = "least squares" if self.method == "l2" else f"{d.get('model')}"
        return (
            f"Model({what}, engine={d.get('engine')}, precision={d.get('precision')}, "
            f"threads={d.get('threads')})"
        )

    def __call__(
        self,
        stack: Stack | str | Path,
        load: LoadOptions | None = None,
        *,
        repeat: int = 1,
        progress: bool = False,
    ) -> Result:
        """Normals (+ metrics with ground truth) for a Stack or a stack path; writes nothing.

        ``load``: how to read a path (selection, files, ROI, downscale, linearisation,
        auto-mask); on a Stack already in memory its selection and real-camera options are
        applied to a copy. ``repeat``: run load -> metrics that many times for the latency
        profile.
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
                    if isinstance(stack, Stack):
                        loaded = (
                            prepare_stack(stack, load) if load is not None else stack.validate()
                        )
                    else:
                        loaded = load_stack(stack, load)
                est = self.estimator.estimate(loaded, self.tiling, timer, progress)
                metrics = err = None
                with timer("postprocess"):
                    if loaded.normals_gt is not None:
                        metrics = normal_metrics(est.normals, loaded.normals_gt, loaded.mask)
                        err = error_map(est.normals, loaded.normals_gt, loaded.mask)
                maps = None
                if self.maps is not None:
                    with timer("maps"):
                        maps = stack_maps(loaded, est.normals, self.maps)
            prof.add(timer)
            prof.flops = est.flops
            result = Result(
                loaded,
                est.normals,
                self.describe(),
                prof,
                metrics,
                err,
                est.plan,
                maps,
                input=load.describe() if load is not None else None,
            )
        assert result is not None
        return result

    def predict(
        self,
        images: np.ndarray,
        lights: np.ndarray,
        mask: np.ndarray | None = None,
        intensities: np.ndarray | None = None,
        normals_gt: np.ndarray | None = None,
    ) -> Result:
        """Run on numpy arrays: images (N, H, W, 3) or (N, H, W) linear values, lights (N, 3)
        directions (x right, y up, z to the camera); mask (H, W) and intensities (N, 3)
        optional. Writes nothing."""
        return self(
            Stack.from_arrays(
                images,
                lights,
                mask=mask,
                intensities=intensities,
                normals_gt=normals_gt,
                name="array",
            )
        )


def _open_network(path: Path, opts: ModelOptions) -> NetworkEstimator:
    """Pick the engine and precision for this CPU and model (or honour the overrides)."""
    from msfnet.common.cpu import detect_cpu
    from msfnet.runtime.engines import installed_engines
    from msfnet.runtime.engines.dispatch import choose_engine, open_engine

    engine = opts.engine
    if opts.provider is not None and engine is None:
        engine = "onnxruntime"  # execution providers are ONNX Runtime's
    choice = choose_engine(path, detect_cpu(), installed_engines(), engine, opts.precision)
    return NetworkEstimator(
        open_engine(choice, opts.threads, provider=opts.provider), choice.reason
    )


__all__ = ["DEFAULT_MAPS", "Model", "ModelOptions", "Result", "default_model_path"]
