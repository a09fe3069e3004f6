"""``msf-run --ray``: the same batch spread over a Ray cluster (optional extra ``msfnet[ray]``).

Each worker is a Ray actor that loads the model once and then takes stacks one at a time
(a new stack goes to whichever worker finished first). Workers read the stacks themselves, so
the stack paths must be visible to them (the same machine, or a shared filesystem); the model
file travels with the job, so ``--onnx`` needs to exist on the driver only. Results (normals,
metrics, profile; no images) come back to the driver, which writes every output folder.

Ray is imported only here, only when asked for: the edge runtime does not depend on it.
"""

from __future__ import annotations

import importlib.util
import os
import socket
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from msfnet.common.errors import InputError
from msfnet.common.files import writing_as
from msfnet.runtime.batch.runner import BatchItem, BatchSummary, OnResult, StackRow, row_for
from msfnet.runtime.options import ModelOptions
from msfnet.runtime.results.profile import BatchStats
from msfnet.runtime.stack import LoadOptions, load_stack

if TYPE_CHECKING:
    from msfnet.runtime.api import Model, Result


def import_ray() -> Any:
    try:
        import ray
    except ImportError as exc:
        raise InputError(
            "--ray needs Ray, which is not installed: pip install "
            "'msfnet[ray]' (on the driver and on every cluster node)"
        ) from exc
    return ray


def _check_client() -> None:
    """A ray:// address goes through Ray's client, which needs gRPC (Ray's ``client`` extra):
    without it Ray fails with an import error deep inside ``ray.init``."""
    if importlib.util.find_spec("grpc") is None:
        raise InputError(
            "--ray ray://...: a ray:// address needs Ray's client (gRPC), which is not "
            "installed: pip install 'msfnet[ray]' (it brings ray[client])"
        )


@dataclass(frozen=True)
class ModelSpec:
    """What a worker needs to build the same Model: the options, and the model file's bytes
    (None: the bundled model of the worker's own msfnet install)."""

    options: ModelOptions
    onnx_bytes: bytes | None = None

    @property
    def onnx_name(self) -> str | None:
        return None if self.options.model is None else str(self.options.model)

    @classmethod
    def of(cls, options: ModelOptions) -> ModelSpec:
        """The spec of ``options`` (already checked on creation), the model file read here:
        the workers may not see the driver's files."""
        onnx = options.model
        if onnx is not None and not onnx.is_file():
            raise InputError("ONNX model not found", onnx)
        return cls(options, None if onnx is None else onnx.read_bytes())

    def build(self, folder: Path) -> Model:
        from msfnet.runtime.api import Model

        path = None
        if self.onnx_bytes is not None:
            path = folder / Path(self.onnx_name or "model.onnx").name
            path.write_bytes(self.onnx_bytes)
        return Model(options=self.options.replace(model=path))


class StackWorker:
    """The body of a Ray actor: one model, many stacks."""

    def __init__(self, spec: ModelSpec) -> None:
        self._tmp = tempfile.TemporaryDirectory(prefix="msfnet-worker-")
        self.spec = spec
        self.model = spec.build(Path(self._tmp.name))
        self.where = f"{socket.gethostname()}:{os.getpid()}"

    def run(self, name: str, path: str, load: LoadOptions) -> dict[str, Any]:
        """Load and run one stack; errors come back as text (exception types with custom
        constructors do not always survive pickling)."""
        start = time.perf_counter()
        try:
            # the driver is msf-run: its errors keep the command's words (flags), not the
            # Python API's keywords
            with writing_as("msf-run"):
                load = self.model._loading(load)  # an ROI grown by the halo
                stack = load_stack(Path(path), load)
                decode_s = time.perf_counter() - start
                t0 = time.perf_counter()
                result = self.model(stack)
                compute_s = time.perf_counter() - t0
        except InputError as exc:
            return {"name": name, "error": str(exc), "where": self.where}
        if self.spec.onnx_name is not None:
            result.method["model"] = self.spec.onnx_name  # the driver's name, not our copy
        runs = result.timings.runs
        runs[-1]["load"] = decode_s
        runs[-1]["total"] = runs[-1].get("total", 0.0) + decode_s
        result.input = load.describe()  # as model(path, load) records it
        result.batch = BatchStats(decode_s, worker=self.where)
        return {
            "name": name,
            "result": result.without_images(),
            "decode_s": decode_s,
            "compute_s": compute_s,
            "where": self.where,
        }


def _absolute(load: LoadOptions) -> LoadOptions:
    """Workers do not share the driver's working directory."""

    def fix(p: Path | None) -> Path | None:
        return None if p is None else p.resolve()

    return replace(
        load, lights=fix(load.lights), intensities=fix(load.intensities), mask=fix(load.mask)
    )


def run_batch_ray(
    spec: ModelSpec,
    items: Sequence[BatchItem],
    load: LoadOptions,
    out_for: Callable[[str], Path | None],
    *,
    address: str | None = None,
    workers: int | None = None,
    overwrite: bool = False,
    summary_dir: Path | None = None,
    on_result: OnResult | None = None,
    progress: bool | None = None,
    inputs: tuple[Path, ...] = (),
) -> BatchSummary:
    """Run the batch on Ray: ``address`` as ``ray.init`` takes it (None: $RAY_ADDRESS, else a
    local instance; "auto": a running cluster; "ray://head:10001": a remote one). A Ray
    session already initialised by the caller is used as it is and left running."""
    from tqdm import tqdm

    ray = import_ray()
    if (address or os.environ.get("RAY_ADDRESS") or "").startswith("ray://"):
        _check_client()
    started = not ray.is_initialized()
    if started:
        try:
            ray.init(address=address, include_dashboard=False, logging_level="WARNING")
        except (ConnectionError, ValueError, RuntimeError) as exc:
            raise InputError(
                f"--ray {address or os.environ.get('RAY_ADDRESS') or ''}: cannot "
                f"connect to Ray ({exc})".replace(":  ", ": ")
            ) from exc
    try:
        cpus = float(ray.cluster_resources().get("CPU", 1.0))
        per_worker = float(spec.options.threads or 1)
        count = workers or max(1, min(len(items), int(cpus // per_worker)))
        actor_class = ray.remote(num_cpus=per_worker)(StackWorker)
        actors = [actor_class.remote(spec) for _ in range(count)]
        summary = BatchSummary("ray", {}, workers=count, prefetch=False)
        opts = _absolute(load)
        todo = [(item, item.options(opts)) for item in items]
        todo.reverse()  # pop() from the end keeps the given order
        in_flight: dict[Any, tuple[Any, BatchItem]] = {}

        def submit(actor: Any) -> None:
            if todo:
                item, options = todo.pop()
                ref = actor.run.remote(item.name, str(item.path.resolve()), options)
                in_flight[ref] = (actor, item)

        start = time.perf_counter()
        for actor in actors:
            submit(actor)
        bar = tqdm(
            total=len(items),
            unit="stack",
            desc="ray batch",
            leave=False,
            disable=True if progress is False else None,
        )
        try:
            while in_flight:
                done, _ = ray.wait(list(in_flight), num_returns=1)
                actor, item = in_flight.pop(done[0])
                try:
                    payload = ray.get(done[0])
                except Exception as exc:  # the worker died (RayActorError, OOM kill, ...)
                    payload = {"name": item.name, "error": f"Ray worker failed: {exc}"}
                else:
                    submit(actor)  # a live worker takes the next stack at once
                if "result" in payload:  # where the selection and lights came from, as locally
                    payload["result"].input = item.describe_input(opts)
                method = _record(payload, item, out_for, overwrite, inputs, summary, on_result)
                if method and not summary.model:
                    summary.model = method
                summary.wall_s = time.perf_counter() - start
                if summary_dir is not None:
                    summary.write(summary_dir)
                bar.update(1)
            summary.wall_s = time.perf_counter() - start
        finally:
            bar.close()
        # the summary lists stacks in the given order, however they finished
        order = {item.name: i for i, item in enumerate(items)}
        summary.rows.sort(key=lambda r: order.get(r.name, len(order)))
        if summary_dir is not None:
            summary.write(summary_dir)
        for actor in actors:
            ray.kill(actor)
        return summary
    finally:
        if started:
            ray.shutdown()


def _record(
    payload: dict[str, Any],
    item: BatchItem,
    out_for: Callable[[str], Path | None],
    overwrite: bool,
    inputs: tuple[Path, ...],
    summary: BatchSummary,
    on_result: OnResult | None,
) -> dict[str, object]:
    """Write one stack's outputs and add its row; returns what ran ({} on an error)."""
    if "error" in payload:
        row = StackRow(
            item.name, str(item.path), error=payload["error"], worker=payload.get("where")
        )
        summary.rows.append(row)
        if on_result:
            on_result(row, None)
        return {}
    result: Result = payload["result"]
    out = out_for(item.name)
    t0 = time.perf_counter()
    if out is not None:
        result.save(out, overwrite=overwrite, inputs=inputs)
    row = row_for(result, out)
    row.decode_s, row.compute_s = payload["decode_s"], payload["compute_s"]
    row.save_s, row.worker = time.perf_counter() - t0, payload["where"]
    summary.rows.append(row)
    if on_result:
        on_result(row, result)
    return result.method


__all__ = ["ModelSpec", "StackWorker", "import_ray", "run_batch_ray"]
