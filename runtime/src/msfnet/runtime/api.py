"""The Python API: ``Model`` (load once, run many stacks) and ``Result`` (arrays, no files).

Example (tests/runtime/test_api_example.py runs exactly this; ``obj/`` is any stack folder)::

    from msfnet import Model, load_stack

    model = Model()                          # the bundled network, loaded once
    stack = load_stack("obj/", max_lights=8) # DiLiGenT-layout folder, images + lights, .npz
    result = model(stack)                    # arrays only: nothing is written
    print(result.normals.shape)              # (H, W, 3) float32 unit normals, x right, y up
    print(result.metrics)                    # MAE / median / err15 / err30 with ground truth
    result.save("out/obj")                   # the files msf-run writes (normals.npy, ...)

    # many stacks, one Result at a time, the next one decoded while this one runs
    for r in model.stream("stacks/"):        # a folder of stacks, a list, or a capture loop
        print(r.summary())                   # one line: stack, method, score, seconds
        view = r.plot()                      # (h, w, 3) uint8 RGB picture of the normals

    baseline = Model.least_squares()         # classical least squares, same API
    l2 = baseline(stack)                     # the stack's own intensities, mask, ground truth

The data flows stack -> estimator (normalise -> infer, tiled) -> metrics -> maps -> Result;
nothing is written until ``Result.save``. README's "Python API" has the rest.
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Generator, Iterable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from msfnet.common.errors import InputError
from msfnet.common.vocabulary import declare, opt
from msfnet.runtime.engines.base import Engine
from msfnet.runtime.engines.bundled import bundled_model_path, default_model_path, open_network
from msfnet.runtime.engines.interrupt import time_limit
from msfnet.runtime.engines.method import RunMethod
from msfnet.runtime.evaluate.metrics import error_map, normal_metrics
from msfnet.runtime.infer.compose import build_estimator
from msfnet.runtime.infer.estimators import (
    Estimator,
    LeastSquaresEstimator,
    NetworkEstimator,
    TilingOptions,
    for_light_count,
)
from msfnet.runtime.infer.ladder import RUNGS
from msfnet.runtime.infer.tiling import BASE_MEMORY_MB, DEFAULT_MAX_MEMORY_MB, HALO
from msfnet.runtime.instrument import StageTimer
from msfnet.runtime.options import DEFAULT_MAPS, ModelOptions, map_options
from msfnet.runtime.results.maps import MapOptions, stack_maps
from msfnet.runtime.results.maps.registered import Frame
from msfnet.runtime.results.profile import Profile
from msfnet.runtime.results.result import Result
from msfnet.runtime.sources import (
    BatchItem,
    Decoded,
    Leftovers,
    StackSource,
    decode_ahead,
    path_item,
    record_decode,
    stream_items,
)
from msfnet.runtime.stack import LoadOptions, Stack, prepare_stack
from msfnet.runtime.stack import load_stack as read_stack
from msfnet.runtime.stream import Skipped, Stream, given_source

# msf-run --repeat: Model.__call__'s repeat (a timing, not a setting of the model)
declare("repeat", "--repeat")


def load_stack(
    path: str | os.PathLike[str], options: LoadOptions | None = None, **overrides: Any
) -> Stack:
    """Read a stack (folder, .npz, ...): ``load_stack("obj/", max_lights=8)``, ``load_stack(p,
    LoadOptions(lights="lights.txt"))``. A folder named for a benchmark object is read with
    the benchmark's selection (``bearPNG``: 21-96, with a UserWarning) unless ``select`` given."""
    given = options if options is not None else LoadOptions()
    if overrides:
        given = replace(given, **overrides)
    path = Path(path)
    return read_stack(path, _protocol(path, given, stacklevel=3)[0])


def _protocol(
    path: Path, load: LoadOptions, *, stacklevel: int
) -> tuple[LoadOptions, BatchItem | None]:
    """``load`` with the benchmark protocol's selection for the stack folder ``path``
    (:func:`~msfnet.runtime.sources.path_item`: DiLiGenT bear, 21-96) where ``load`` selects
    no images itself, and the item that chose it (None: no protocol selection applies). The
    line msf-run prints then is a UserWarning here: the selection changes the result."""
    item = path_item(path)
    note = item.note(load)
    if note is None:
        return load, None
    warnings.warn(note, UserWarning, stacklevel=stacklevel)
    return item.options(load), item


class Model:
    """A loaded estimator with its run options: create once, call on many stacks.

    ``model``: None for the bundled network, an msfnet ONNX export's path (loaded once, here)
    or an Engine; ``Model.least_squares()`` is classical least squares. The keyword settings
    are the fields of :class:`~msfnet.runtime.options.ModelOptions` (``method``, ``engine``,
    ``precision``, ``threads``, ``tile``, ``max_memory_mb``, ``fine_detail``, ...), checked
    here; ``options=`` passes a whole ModelOptions instead. ``maps``: a
    :class:`msfnet.MapOptions`, map names as ``--maps`` takes them, or None for normals only.
    Calling it (``model(stack)``, :meth:`predict`) returns a :class:`Result`, writes nothing.
    """

    def __init__(
        self,
        model: str | Path | Engine | None = None,
        *,
        options: ModelOptions | None = None,
        **settings: Any,
    ) -> None:
        self._open(model, options, settings)

    def _open(
        self, model: str | Path | Engine | None, options: ModelOptions | None, settings: Any
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
            with time_limit(opts.timeout_s):  # the engine's compile
                # None: the bundled pair's file for this CPU
                engine, why = open_network(opts.model, opts.engine_request())
                self.estimator = NetworkEstimator(engine, why)
        self.estimator = build_estimator(self.estimator, opts.layers())

    @classmethod
    def least_squares(
        cls,
        *,
        max_memory_mb: float = DEFAULT_MAX_MEMORY_MB,
        maps: MapOptions | str | Iterable[str] | None = DEFAULT_MAPS,
    ) -> Model:
        """Per-pixel least squares (Woodham 1980): no network, the same inputs and outputs."""
        opts = ModelOptions(method="l2", max_memory_mb=max_memory_mb, maps=map_options(maps))
        return cls(options=opts)

    @property
    def method(self) -> str:
        return self.estimator.method

    def describe(self) -> RunMethod:
        return self.estimator.describe()

    def __repr__(self) -> str:
        d = self.describe()
        what = "least squares" if self.method == "l2" else d.model
        return f"Model({what}, engine={d.engine}, precision={d.precision}, threads={d.threads})"

    def __call__(
        self,
        stack: Stack | str | Path,
        load: LoadOptions | None = None,
        *,
        repeat: int = 1,
        progress: bool = False,
    ) -> Result:
        """Normals (+ metrics with ground truth) for a Stack or a stack path; writes nothing.

        ``load``: how to read a path (on a Stack in memory, applied to a copy); a folder named
        for a benchmark object is read with its selection unless ``load`` selects images.
        ``repeat``: run load -> metrics that many times for the latency profile. For many
        stacks see :meth:`stream`.
        """
        if isinstance(stack, (list, tuple)) or not isinstance(stack, (Stack, str, Path)):
            raise InputError(
                f"model(...) runs one stack (a Stack or a path), got "
                f"{type(stack).__name__}; for several use model.stream(...), which "
                "yields one Result at a time"
            )
        return self._run(stack, load, repeat, progress)

    def stream(
        self,
        source: str | os.PathLike[str] | Stack | Iterable[str | os.PathLike[str] | Stack],
        load: LoadOptions | None = None,
        *,
        prefetch: bool = True,
        on_error: str = "raise",
    ) -> Stream[Result]:
        """Run many stacks, yielding one :class:`Result` at a time; writes nothing, and holds
        at most two stacks (the current one and the next being decoded).

        ``source``: a folder of stacks (as msf-run reads it), a stack path, a Stack, or any
        iterable of paths and Stacks (a list, a capture loop). ``load`` applies to every stack.
        ``prefetch``: decode the next stack in a background thread (a generator source is
        then advanced from it); False does everything in the calling thread. ``on_error``:
        "raise" (a stack that cannot be read or run raises InputError at its turn and ends the
        stream) or "skip" (warn, record it in ``stream.skipped``, go on). Stopping early never
        drops a stack taken from the source: ``stream.stop()`` returns those not run.
        """
        if on_error not in ("raise", "skip"):
            raise InputError(f"on_error must be 'raise' or 'skip', got {on_error!r}")
        opts = self._loading(load if load is not None else LoadOptions())
        items, total = stream_items(source, select_given=opts.select is not None)

        def results(taken: Leftovers, skipped: list[Skipped]) -> Generator[Result, None, None]:
            def skip(error: InputError, item: StackSource) -> None:
                source = given_source(item)
                skipped.append(Skipped(source, error))
                where = "" if error.path is not None else f"{source.name}: "
                warnings.warn(f"{where}{error}; skipped", RuntimeWarning, stacklevel=4)

            for decoded in decode_ahead(
                items, opts, prefetch=prefetch, total=total, unprocessed=taken
            ):
                if decoded.error is not None:
                    if on_error == "raise":
                        raise decoded.error
                    skip(decoded.error, decoded.item)
                    continue
                item = decoded.item
                note = item.note(opts) if isinstance(item, BatchItem) else None
                if note is not None:  # a benchmark's selection, as model(path) says it
                    warnings.warn(note, UserWarning, stacklevel=3)
                try:
                    result = self._run_decoded(decoded, opts)
                except InputError as exc:  # e.g. intrinsics its normals cannot use
                    if on_error == "raise":
                        taken.items.append(decoded.item)
                        raise
                    skip(exc, decoded.item)
                    continue
                except BaseException:  # interrupted or failed: the caller gets it back
                    taken.items.append(decoded.item)
                    raise
                yield result

        return Stream(results, warn_unprocessed=total is None)

    def _loading(self, load: LoadOptions) -> LoadOptions:
        """``load`` with an ROI grown by the network's halo where the network runs with edge
        context: it then sees the real image around the ROI, not zeros, and draws no rim at
        the crop's edges. ``edge_context=False`` keeps the published protocol's zeros."""
        if load.roi is None or load.roi_halo or not self.options.is_network:
            return load
        if not self.options.edge_context:
            return load
        # --speed balanced / fast run the network on a shrunk stack: its receptive field
        # spans that many more held pixels
        return replace(load, roi_halo=math.ceil(HALO * RUNGS[self.options.speed].scale))

    def _run_decoded(self, decoded: Decoded, load: LoadOptions) -> Result:
        """Run a stack that :func:`~msfnet.runtime.sources.decode_ahead` decoded, recording
        its decoding as ``model(path, load)`` would (streams and batches)."""
        assert decoded.stack is not None
        budget = self.tiling
        if decoded.beside:
            # the next stack is being decoded beside this one: leave its memory out of the
            # tile budget (estimated by this stack's size; sequences are rarely mixed). A
            # budget for this call only: the Model may be shared by other threads.
            spare = budget.max_memory_mb - decoded.stack.images.nbytes / 2**20
            # a floor above the runtime's own base (tiling.BASE_MEMORY_MB), never below it
            budget = replace(budget, max_memory_mb=max(spare, BASE_MEMORY_MB + 256.0))
        result = self._run(decoded.stack, None, 1, False, budget, placed=load)
        record_decode(result, decoded, load)
        return result

    def _run(
        self,
        stack: Stack | str | Path,
        load: LoadOptions | None,
        repeat: int,
        progress: bool,
        tiling: TilingOptions | None = None,
        placed: LoadOptions | None = None,
    ) -> Result:
        """``placed``: how an already decoded ``stack`` was cut (ROI, downscale), for the maps'
        frame when ``load`` is None."""
        tiling = self.tiling if tiling is None else tiling
        if repeat < 1:
            raise InputError(f"{opt('repeat')} must be at least 1, got {repeat}", option="repeat")
        if load is not None:
            load = self._loading(load)
        recorded = None if load is None else load.describe()  # Result.input
        if not isinstance(stack, Stack):
            given = load if load is not None else LoadOptions()
            protocol, item = _protocol(Path(stack), given, stacklevel=4)
            if item is not None:  # recorded as a stream and msf-run record it
                load, recorded = protocol, item.describe_input(given)
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
                        loaded = read_stack(stack, load)
                if self.maps is not None:  # settings the maps refuse: before the estimate
                    _placed(self.maps, load or placed).check_shape(loaded.inner().shape)
                estimator, loaded = for_light_count(self.estimator, loaded)
                with time_limit(self.options.timeout_s):
                    est = estimator.estimate(loaded, tiling, timer, progress)
                normals = est.normals
                if loaded.roi_box is not None:
                    # grown by a halo for context: every output is the requested ROI's
                    y0, y1, x0, x1 = loaded.roi_box
                    normals = np.ascontiguousarray(normals[y0:y1, x0:x1])
                    loaded = loaded.inner()
                metrics = err = None
                with timer("postprocess"):
                    if loaded.normals_gt is not None:
                        metrics = normal_metrics(normals, loaded.normals_gt, loaded.mask)
                        err = error_map(normals, loaded.normals_gt, loaded.mask)
                maps = None
                if self.maps is not None:
                    with timer("maps"):
                        maps = stack_maps(
                            loaded,
                            normals,
                            _placed(self.maps, load or placed),
                            max_memory_mb=tiling.max_memory_mb,
                        )
                        if maps.warning:  # a map that did not fit in --max-memory
                            loaded.warnings.append(maps.warning)
            prof.add(timer)
            prof.flops = est.flops
            result = Result(
                loaded,
                normals,
                estimator.describe(),
                prof,
                metrics,
                err,
                est.plan,
                maps,
                input=recorded,
            )
        assert result is not None
        return result

    def predict(
        self,
        images: npt.ArrayLike,
        lights: npt.ArrayLike,
        mask: npt.ArrayLike | None = None,
        intensities: npt.ArrayLike | None = None,
        normals_gt: npt.ArrayLike | None = None,
    ) -> Result:
        """Run on numpy arrays (or nested lists): images (N, H, W, 3) or (N, H, W) linear
        values, lights (N, 3) directions (x right, y up, z to the camera); mask (H, W) and
        intensities (N, 3) optional. Writes nothing.

        ``intensities``: the lights' RGB intensities the images are divided by (ones when
        omitted): pass ``intensities=stack.intensities`` for a Stack's images, which are not
        divided yet, or the normals bend toward the brighter lights."""
        stack = Stack.from_arrays(
            images, lights, mask=mask, intensities=intensities, normals_gt=normals_gt, name="array"
        )
        return self(stack)


def _placed(maps: MapOptions, load: LoadOptions | None) -> MapOptions:
    """``maps`` with the frame the loading gave (ROI corner, downscale), unless the caller set
    one: maps.json and the TIFF tags then place the maps as msf-run's do. ``pixel_size_mm``
    stays a map pixel (the API's meaning); the stored image's is derived again."""
    if load is None or not maps.frame.is_identity:
        return maps
    frame = Frame.of_cut(load.roi, load.downscale)
    if frame.is_identity:
        return maps
    return replace(maps, frame=frame, image_pixel_size_mm=None)


__all__ = [
    "DEFAULT_MAPS",
    "Model",
    "ModelOptions",
    "Result",
    "bundled_model_path",
    "default_model_path",
    "load_stack",
]
