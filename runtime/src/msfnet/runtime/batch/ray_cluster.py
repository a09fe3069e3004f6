"""``msf-run --ray``: the same batch spread over a Ray cluster (optional extra ``msfnet[ray]``).

Each worker is a Ray actor that loads the model once and then takes stacks one at a time
(a new stack goes to whichever worker finished first). Workers read the stacks themselves, so
the stack paths must be visible to them (the same machine, or a shared filesystem); the model
file travels with the job, so ``--onnx`` needs to exist on the driver only. Results (normals,
metrics, profile; no images) come back to the driver, which writes every output folder.

Memory: ``--max-memory`` is the budget of one machine (Ray node), not of each worker. Each
worker holds ``--threads`` CPUs, so a node runs at most its CPUs / ``--threads`` workers. The
workers are pinned to nodes (Ray's node-affinity scheduling), spread round-robin over the live
nodes up to what each holds, so the driver knows how many share each node's budget: each gets
``--max-memory`` / (the workers on its node) and plans its tiles (and refuses stacks) with that
share (:func:`plan_workers`). Without ``--workers``, a node takes only as many as get
WORKER_MEMORY_MB each (one at least); a share no larger than the runtime's own floor
(tiling's BASE_MEMORY_MB) is refused before any worker starts. When Ray cannot list its nodes
the cluster is planned as one node and nothing is pinned (the safe side: every worker shares
one budget). Ray's own processes (GCS, raylet, object store) and the driver are outside the
budget; a worker's own overhead stays under that floor.

Ray is imported only here, only when asked for: the edge runtime does not depend on it.
"""

from __future__ import annotations

import importlib.util
import os
import re
import signal
import socket
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from msfnet.common.errors import InputError
from msfnet.common.files import writing_as
from msfnet.common.vocabulary import declare, opt, speaking_as
from msfnet.runtime.batch.runner import BatchItem, BatchSummary, OnResult, StackRow, row_for
from msfnet.runtime.engines.method import RunMethod
from msfnet.runtime.infer.tiling import BASE_MEMORY_MB
from msfnet.runtime.options import ModelOptions
from msfnet.runtime.results.profile import BatchStats
from msfnet.runtime.results.result import SaveOptions
from msfnet.runtime.stack import LoadOptions, load_stack

if TYPE_CHECKING:
    from msfnet.runtime.api import Model, Result

# msf-run's --ray ADDRESS and --workers K (Ray's batch; no options type holds them)
declare("ray", "--ray")
declare("workers", "--workers")

# The least share of --max-memory a worker is started with when --workers is not given: a full
# DiLiGenT object still runs within it, in smaller tiles (docs/benchmark.md).
WORKER_MEMORY_MB = 1024
# Seconds without any worker started before the batch says why it waits: a worker starts once
# Ray has its CPUs, which another job may hold for as long as it runs.
STALL_NOTE_S = 60.0


# Seconds the driver waits for a TCP answer from a cluster address before giving up: Ray's own
# connect retried a closed HOST:PORT forever, and a ray:// address for ~34 s.
CONNECT_TIMEOUT_S = 5.0
RAY_CLIENT_PORT = 10001  # a ray://HOST address without a port: the Ray client's own
# a host name as resolvers take it: "_" too (Docker service names), a trailing dot (absolute)
_LABEL = r"[A-Za-z0-9_](?:[A-Za-z0-9_-]{0,61}[A-Za-z0-9_])?"
_HOST = re.compile(rf"(?=.{{1,254}}$){_LABEL}(?:\.{_LABEL})*\.?")


def cluster_endpoint(address: str) -> tuple[str, int] | None:
    """(host, port) of a --ray address, None for one Ray resolves itself (a local instance,
    'auto', 'local'); InputError for an address that cannot be valid (a port beyond 65535,
    ``256.1.1.1``, ``ray://:::::``), before any connection is tried."""
    if address in ("", "auto", "local"):
        return None
    client = address.startswith("ray://")
    rest = address.removeprefix("ray://")
    if rest.startswith("["):  # [IPv6]:port
        host, _, port_text = rest[1:].partition("]")
        port_text = port_text.removeprefix(":")
        valid = _is_ip(host, 6)
    else:
        host, _, port_text = rest.rpartition(":") if ":" in rest else (rest, "", "")
        valid = _is_ip(host, 4) if re.fullmatch(r"[\d.]+", host) else bool(_HOST.fullmatch(host))
    if not port_text and client:
        port_text = str(RAY_CLIENT_PORT)
    if not valid or not port_text.isdigit() or not 1 <= int(port_text) <= 65535:
        raise InputError(
            f"{opt('ray', address)}: not a cluster address (expected HOST:PORT, ray://HOST[:PORT] "
            "or auto; a port in 1..65535)",
            option="ray",
        )
    return host, int(port_text)


def _is_ip(text: str, version: int) -> bool:
    import ipaddress

    try:
        return ipaddress.ip_address(text).version == version
    except ValueError:
        return False


def check_reachable(address: str, timeout_s: float = CONNECT_TIMEOUT_S) -> None:
    """One TCP connection to the address, within ``timeout_s``: InputError naming why none
    came (nothing listening, an unknown host, no answer)."""
    endpoint = cluster_endpoint(address)
    if endpoint is None:
        return
    try:
        socket.create_connection(endpoint, timeout=timeout_s).close()
    except socket.gaierror as exc:
        why = f"unknown host {endpoint[0]!r} ({exc.strerror})"
    except ConnectionRefusedError:
        why = "nothing listens there (is the Ray head running? ray start --head)"
    except TimeoutError:
        why = f"no answer within {timeout_s:g} s"
    except OSError as exc:
        why = exc.strerror or type(exc).__name__
    else:
        return
    raise InputError(f"{opt('ray', address)}: cannot connect: {why}", option="ray")


def import_ray() -> Any:
    try:
        import ray
    except ImportError as exc:
        raise InputError(
            f"{opt('ray')} needs Ray, which is not installed: pip install "
            "'msfnet[ray]' (on the driver and on every cluster node)",
            option="ray",
        ) from exc
    return ray


def _check_client() -> None:
    """A ray:// address goes through Ray's client, which needs gRPC (Ray's ``client`` extra):
    without it Ray fails with an import error deep inside ``ray.init``."""
    if importlib.util.find_spec("grpc") is None:
        raise InputError(
            f"{opt('ray', 'ray://...')}: a ray:// address needs Ray's client (gRPC), which is not "
            "installed: pip install 'msfnet[ray]' (it brings ray[client])",
            option="ray",
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
        with speaking_as("msf-run"):  # the engine-choice line profile.json keeps: its words
            self.model = spec.build(Path(self._tmp.name))
        self.where = f"{socket.gethostname()}:{os.getpid()}"

    def ready(self) -> str:
        """Answers once the worker has started (its model loaded): where it runs."""
        return self.where

    def run(self, name: str, path: str, load: LoadOptions) -> dict[str, Any]:
        """Load and run one stack; errors come back as text (exception types with custom
        constructors do not always survive pickling)."""
        start = time.perf_counter()
        try:
            # the driver is msf-run: its errors keep the command's words (flags), not the
            # Python API's keywords
            with writing_as("msf-run"), speaking_as("msf-run"):
                load = self.model._loading(load)  # an ROI grown by the halo
                stack = load_stack(Path(path), load)
                decode_s = time.perf_counter() - start
                t0 = time.perf_counter()
                result = self.model(stack)
                compute_s = time.perf_counter() - t0
        except InputError as exc:
            return {"name": name, "error": str(exc), "where": self.where}
        if self.spec.onnx_name is not None:
            result.method = replace(result.method, model=self.spec.onnx_name)  # the driver's name
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


@dataclass(frozen=True)
class RayNode:
    """A live node of the cluster, as the plan sees it."""

    node_id: str | None  # Ray's NodeID; None: Ray could not list its nodes (not pinned)
    cpus: float


@dataclass(frozen=True)
class NodeWorkers:
    """The workers pinned to one node, and the part of --max-memory each one may use."""

    node_id: str | None  # None: not pinned (the whole cluster planned as one node)
    workers: int  # actors started there, each holding --threads CPUs for the whole batch
    memory_mb: float  # each one's budget: --max-memory / workers


@dataclass(frozen=True)
class WorkerPlan:
    """Where the Ray workers start: the nodes given at least one, in the order Ray lists them."""

    nodes: tuple[NodeWorkers, ...]

    @property
    def workers(self) -> int:
        return sum(n.workers for n in self.nodes)

    @property
    def memory_mb(self) -> float:
        """The smallest share (a worker on the busiest node)."""
        return min(n.memory_mb for n in self.nodes)


def cluster_nodes(ray: Any) -> list[RayNode]:
    """The live nodes of the cluster with their CPUs; when Ray cannot list them, the whole
    cluster's CPUs as one node without an id (every worker then shares one budget)."""
    try:
        listed = ray.nodes()
    except Exception:  # a developer API: its failure must not stop the batch
        listed = []
    nodes = [
        RayNode(str(n["NodeID"]), float(n.get("Resources", {}).get("CPU", 0.0)))
        for n in listed
        if n.get("Alive") and n.get("NodeID")
    ]
    # a cluster without CPUs lists no "CPU" at all: 0, so the plan says so instead of
    # starting a worker that would wait forever
    return nodes or [RayNode(None, float(ray.cluster_resources().get("CPU", 0.0)))]


def _spread(count: int, limits: Sequence[int]) -> list[int]:
    """``count`` workers dealt one at a time over the nodes, each up to its limit (evenly
    spread, so the busiest node's share of the budget is as large as it can be)."""
    counts = [0] * len(limits)
    left = min(count, sum(limits))
    while left:
        for i, limit in enumerate(limits):
            if left and counts[i] < limit:
                counts[i] += 1
                left -= 1
    return counts


def plan_workers(
    nodes: Sequence[RayNode],
    threads: int,
    stacks: int,
    max_memory_mb: float,
    workers: int | None = None,
) -> WorkerPlan:
    """Workers for ``stacks`` stacks on ``nodes``, each worker holding ``threads`` CPUs, and
    each worker's share of ``max_memory_mb``, the budget of one node. A node holds at most
    ``cpus // threads`` workers. ``workers``: as asked, spread round-robin over the nodes up
    to what each holds; None: on each node as many as it holds and as get WORKER_MEMORY_MB of
    the budget (one at least), at most one a stack in all.

    Ray places a worker only where its CPUs are free and keeps them until the batch ends;
    more workers than the cluster holds would wait for CPUs that never free (the batch would
    hang), so they are refused. Raises InputError when no node fits one worker, or when a
    share would not exceed the runtime's own floor (tiling.BASE_MEMORY_MB)."""
    if not any(n.cpus > 0 for n in nodes):
        raise InputError(
            f"{opt('ray')}: no Ray node with CPUs has joined the cluster yet (the head may have "
            "been started as ray start --num-cpus=0, or the autoscaler is at zero nodes): start a "
            "worker node (ray start --address=HEAD:PORT) or wait for one, then run again",
            option="ray",
        )
    room = [int(n.cpus // threads) for n in nodes]
    capacity = sum(room)
    if capacity == 0:
        raise InputError(
            f"{opt('threads', threads)}: no Ray node has {threads} CPUs for a worker (the "
            f"largest has {max(n.cpus for n in nodes):g}); use fewer {opt('threads')}",
            option="threads",
        )
    if workers is None:
        most = max(1, int(max_memory_mb // WORKER_MEMORY_MB))
        limits = [min(r, most) for r in room]
        count = max(1, min(stacks, sum(limits)))
    elif workers > capacity:
        raise InputError(
            f"{opt('workers', workers)}: the Ray cluster runs at most {capacity} worker(s) of "
            f"{threads} thread(s) at once ({sum(n.cpus for n in nodes):g} CPUs on "
            f"{len(nodes)} node(s)); more would wait for CPUs forever. Use fewer "
            f"{opt('workers')} or {opt('threads')}",
            option="workers",
        )
    else:
        limits, count = room, workers
    counts = _spread(count, limits)
    busiest = max(counts)
    share = max_memory_mb / busiest
    if share <= BASE_MEMORY_MB:
        raise InputError(
            f"{opt('max_memory_mb', max_memory_mb)} MB is one node's budget, shared by the "
            f"{busiest} Ray workers that run at once on a node: {share:.0f} MB each, not "
            f"above the {BASE_MEMORY_MB} MB a worker takes before any stack (use a larger "
            f"{opt('max_memory_mb')}, or fewer {opt('workers')} or more {opt('threads')})",
            option="max_memory_mb",
        )
    return WorkerPlan(
        tuple(
            NodeWorkers(n.node_id, c, max_memory_mb / c)
            for n, c in zip(nodes, counts, strict=True)
            if c
        )
    )


def _absolute(load: LoadOptions) -> LoadOptions:
    """Workers do not share the driver's working directory."""

    def fix(p: Path | None) -> Path | None:
        return None if p is None else p.resolve()

    return replace(
        load, lights=fix(load.lights), intensities=fix(load.intensities), mask=fix(load.mask)
    )


def init_keeping_sigterm(ray: Any, **kwargs: Any) -> None:
    """``ray.init``, with msfnet's SIGTERM handler put back afterwards: Ray installs its own
    (a native stack dump, exit 1), and a batch stopped by SIGTERM must exit 143 with its
    "terminated" line and the finished stacks kept, as without --ray."""
    main = threading.current_thread() is threading.main_thread()
    previous = signal.getsignal(signal.SIGTERM) if main else None
    ray.init(**kwargs)
    if main and previous is not None:
        signal.signal(signal.SIGTERM, previous)


# a Ray actor handle and the load options it runs its stacks with (its share of the budget)
_Worker = tuple[Any, LoadOptions]


def _connect(ray: Any, address: str | None) -> bool:
    """Start Ray's session at ``address`` (True), or use the one the caller already started
    as it is (False); InputError where no connection comes."""
    given = address or os.environ.get("RAY_ADDRESS") or ""
    if given.startswith("ray://"):
        _check_client()
    started = not ray.is_initialized()
    if started:
        check_reachable(given)
        try:
            init_keeping_sigterm(
                ray, address=address, include_dashboard=False, logging_level="WARNING"
            )
        except (ConnectionError, ValueError, RuntimeError) as exc:
            raise InputError(
                f"{opt('ray', address or os.environ.get('RAY_ADDRESS') or '')}: cannot "
                f"connect to Ray ({exc})".replace(":  ", ": ")
            ) from exc
    return started


def _start_actors(
    ray: Any, spec: ModelSpec, plan: WorkerPlan, base: LoadOptions, threads: int
) -> list[_Worker]:
    """One actor for each planned worker, pinned to its node, each with the load options it
    runs with (its share of the budget)."""
    actor_class = ray.remote(num_cpus=threads)(StackWorker)
    actors: list[_Worker] = []
    for node in plan.nodes:
        # every worker plans its tiles and checks stack sizes with its share, not the whole
        node_spec = replace(spec, options=spec.options.replace(max_memory_mb=node.memory_mb))
        opts = base
        if opts.max_memory_mb is not None:
            opts = replace(opts, max_memory_mb=node.memory_mb)
        where = actor_class
        if node.node_id is not None:  # pinned: the share assumes exactly these on the node
            strategies = ray.util.scheduling_strategies
            where = actor_class.options(
                scheduling_strategy=strategies.NodeAffinitySchedulingStrategy(
                    node_id=node.node_id, soft=False
                )
            )
        actors += [(where.remote(node_spec), opts) for _ in range(node.workers)]
    return actors


@dataclass
class _Outputs:
    """Where each stack's answer goes (as :func:`_record` takes it): its output folder and its
    row of the summary."""

    out_for: Callable[[str], Path | None]
    overwrite: bool
    inputs: tuple[Path, ...]
    summary: BatchSummary
    on_result: OnResult | None
    save: SaveOptions | None = None

    def record(self, payload: dict[str, Any], item: BatchItem) -> RunMethod | None:
        return _record(payload, item, self)


@dataclass
class _Flight:
    """The batch as it runs on the workers: the stacks not yet sent (the next last), and what
    each ref in flight answers: a stack, or (None) a worker that has started. A stack goes only
    to a started worker: one still waiting for CPUs (taken by another job on its node) would
    hold its stack, and the batch, forever."""

    actors: list[_Worker]
    todo: list[BatchItem]
    in_flight: dict[Any, tuple[_Worker, BatchItem | None]] = field(default_factory=dict)
    failed_starts: list[str] = field(default_factory=list)
    worker_up: bool = False
    noted: bool = False

    def submit(self, worker: _Worker) -> None:
        """The next stack, if any is left, to ``worker``."""
        if self.todo:
            item = self.todo.pop()
            actor, worker_load = worker
            options = item.options(worker_load)
            ref = actor.run.remote(item.name, str(item.path.resolve()), options)
            self.in_flight[ref] = (worker, item)

    def stacks_in_flight(self) -> bool:
        return any(item is not None for _, item in self.in_flight.values())

    def collect(self, ray: Any, ref: Any) -> tuple[BatchItem, dict[str, Any], LoadOptions] | None:
        """The answer of a finished ref, its worker given the next stack if it lives: the
        stack, its payload (an error where the worker died) and the worker's load options;
        None where the ref was a worker's start (or a failed one)."""
        worker, maybe_item = self.in_flight.pop(ref)
        try:
            payload = ray.get(ref)
        except Exception as exc:  # the worker died (RayActorError, OOM kill, ...)
            if maybe_item is None:  # it never started (no stack lost)
                self.failed_starts.append((str(exc).strip().splitlines() or [""])[0])
                return None
            payload = {"name": maybe_item.name, "error": f"Ray worker failed: {exc}"}
        else:
            self.worker_up = self.worker_up or maybe_item is None
            self.submit(worker)  # a live worker takes the next stack at once
        if maybe_item is None:
            return None
        return maybe_item, payload, worker[1]


def _run_stacks(
    ray: Any,
    flight: _Flight,
    outputs: _Outputs,
    bar: Any,
    start: float,
    threads: int,
    summary_dir: Path | None,
    on_note: Callable[[str], None] | None,
) -> None:
    """Record each stack's answer as it comes, until no stack is left or running (workers
    that never started are not waited on); ``on_note`` once when no worker has started after
    STALL_NOTE_S seconds."""
    summary = outputs.summary
    while flight.in_flight and (flight.todo or flight.stacks_in_flight()):
        quiet = flight.worker_up or flight.noted or on_note is None
        done, _ = ray.wait(
            list(flight.in_flight), num_returns=1, timeout=None if quiet else STALL_NOTE_S
        )
        if not done:  # only with a timeout: no worker has started yet
            flight.noted = True
            if on_note is not None:
                on_note(
                    f"no Ray worker of {len(flight.actors)} has started after "
                    f"{STALL_NOTE_S:.0f} s: the CPUs they need ({threads} each) may be "
                    "held by other jobs; still waiting (Ctrl-C stops)"
                )
            continue
        answer = flight.collect(ray, done[0])
        if answer is None:
            continue
        item, payload, worker_load = answer
        if "result" in payload:  # where the selection and lights came from, as locally
            payload["result"].input = item.describe_input(worker_load)
        method = outputs.record(payload, item)
        if method:
            summary.note_model(method)
        summary.wall_s = time.perf_counter() - start
        if summary_dir is not None:
            summary.write(summary_dir)
        bar.update(1)


def _record_not_run(flight: _Flight, outputs: _Outputs, bar: Any) -> None:
    """Every worker failed (dead nodes, model load errors): the stacks left are listed as not
    run, not dropped from the summary."""
    failed = flight.failed_starts
    last = f"; the last that could not start: {failed[-1]}" if failed else ""
    why = f" (all {len(flight.actors)} failed{last})"
    while flight.todo:
        item = flight.todo.pop()
        left = {"name": item.name, "error": f"not run: no Ray worker left{why}"}
        outputs.record(left, item)
        bar.update(1)


def run_batch_ray(
    spec: ModelSpec,
    items: Sequence[BatchItem],
    load: LoadOptions,
    out_for: Callable[[str], Path | None],
    *,
    address: str | None = None,
    workers: int | None = None,
    overwrite: bool = False,
    save: SaveOptions | None = None,
    summary_dir: Path | None = None,
    on_result: OnResult | None = None,
    progress: bool | None = None,
    inputs: tuple[Path, ...] = (),
    on_note: Callable[[str], None] | None = None,
) -> BatchSummary:
    """Run the batch on Ray: ``address`` as ``ray.init`` takes it (None: $RAY_ADDRESS, else a
    local instance; "auto": a running cluster; "ray://head:10001": a remote one). A Ray
    session already initialised by the caller is used as it is and left running.
    ``on_note``: called with one line, once, when no worker has started after STALL_NOTE_S
    seconds (the batch goes on waiting)."""
    from tqdm import tqdm

    ray = import_ray()
    started = _connect(ray, address)
    try:
        threads = spec.options.threads or 1
        plan = plan_workers(
            cluster_nodes(ray), threads, len(items), spec.options.max_memory_mb, workers
        )
        summary = BatchSummary(
            "ray", None, workers=plan.workers, prefetch=False, worker_memory_mb=plan.memory_mb
        )
        actors = _start_actors(ray, spec, plan, _absolute(load), threads)
        outputs = _Outputs(out_for, overwrite, inputs, summary, on_result, save)
        flight = _Flight(actors, list(reversed(items)))  # pop() from the end: the given order
        start = time.perf_counter()
        for worker in actors:
            flight.in_flight[worker[0].ready.remote()] = (worker, None)
        bar = tqdm(
            total=len(items),
            unit="stack",
            desc="ray batch",
            leave=False,
            disable=True if progress is False else None,
        )
        try:
            _run_stacks(ray, flight, outputs, bar, start, threads, summary_dir, on_note)
            _record_not_run(flight, outputs, bar)
            summary.wall_s = time.perf_counter() - start
        finally:
            bar.close()
        # the summary lists stacks in the given order, however they finished
        order = {item.name: i for i, item in enumerate(items)}
        summary.rows.sort(key=lambda r: order.get(r.name, len(order)))
        if summary_dir is not None:
            summary.write(summary_dir)
        for actor, _ in actors:
            ray.kill(actor)
        return summary
    finally:
        if started:
            ray.shutdown()


def _record(payload: dict[str, Any], item: BatchItem, outputs: _Outputs) -> RunMethod | None:
    """Write one stack's outputs and add its row; returns what ran (None on an error)."""
    summary, on_result = outputs.summary, outputs.on_result
    if "error" in payload:
        row = StackRow(
            item.name, str(item.path), error=payload["error"], worker=payload.get("where")
        )
        summary.rows.append(row)
        if on_result:
            on_result(row, None)
        return None
    result: Result = payload["result"]
    out = outputs.out_for(item.name)
    t0 = time.perf_counter()
    if out is not None:
        result.save(out, overwrite=outputs.overwrite, inputs=outputs.inputs, options=outputs.save)
    row = row_for(result, out)
    row.decode_s, row.compute_s = payload["decode_s"], payload["compute_s"]
    row.save_s, row.worker = time.perf_counter() - t0, payload["where"]
    summary.rows.append(row)
    if on_result:
        on_result(row, result)
    return result.method


__all__ = [
    "WORKER_MEMORY_MB",
    "ModelSpec",
    "NodeWorkers",
    "RayNode",
    "StackWorker",
    "WorkerPlan",
    "cluster_nodes",
    "import_ray",
    "plan_workers",
    "run_batch_ray",
]
