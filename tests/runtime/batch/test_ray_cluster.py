"""msf-run --ray's worker side without Ray: what a worker builds and returns must match a
local run (Ray only moves these objects between processes)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from _runtime_helpers import sphere_stack

from msfnet.common.errors import InputError
from msfnet.common.vocabulary import speaking_as
from msfnet.runtime.api import Model
from msfnet.runtime.batch import ray_cluster
from msfnet.runtime.batch.ray_cluster import (
    ModelSpec,
    NodeWorkers,
    RayNode,
    StackWorker,
    WorkerPlan,
    cluster_nodes,
)
from msfnet.runtime.batch.ray_cluster import plan_workers as _plan_workers
from msfnet.runtime.batch.runner import BatchItem
from msfnet.runtime.infer.tiling import BASE_MEMORY_MB
from msfnet.runtime.options import ModelOptions
from msfnet.runtime.stack import LoadOptions, save_stack


def test_a_worker_builds_the_engine_and_precision_asked_for(random_onnx: Path) -> None:
    spec = ModelSpec.of(
        ModelOptions(random_onnx, engine="onnxruntime", precision="fp32", threads=1)
    )
    described = StackWorker(spec).model.describe()
    assert described.engine == "onnxruntime" and described.precision == "fp32"
    # the choice line profile.json keeps is msf-run's, as without --ray
    assert "--precision fp32 and --engine given" in str(described.choice)


def test_a_worker_returns_what_a_local_run_gives(random_onnx: Path, tmp_path: Path) -> None:
    path = save_stack(sphere_stack(n=6, h=24, w=28, seed=3), tmp_path / "s")
    worker = StackWorker(ModelSpec.of(ModelOptions(random_onnx, engine="onnxruntime", threads=1)))
    got = worker.run("s", str(path), LoadOptions())
    assert "error" not in got
    local = Model(random_onnx, engine="onnxruntime", threads=1)(path)
    np.testing.assert_allclose(got["result"].normals, local.normals, atol=1e-6, rtol=0)
    assert got["result"].method.model == str(random_onnx)  # the driver's name, not a copy
    assert got["result"].stack.images.size == 0  # no images shipped back


def test_a_worker_reports_a_bad_stack_as_text(random_onnx: Path, tmp_path: Path) -> None:
    worker = StackWorker(ModelSpec.of(ModelOptions(random_onnx, threads=1)))
    got = worker.run("missing", str(tmp_path / "nothing"), LoadOptions())
    assert "nothing" in got["error"]


@pytest.mark.parametrize("options", [{"engine": "openvino"}, {"precision": "bf16"}])
def test_least_squares_refuses_engine_options_before_any_work(options: dict[str, str]) -> None:
    with speaking_as("msf-run"), pytest.raises(InputError, match="--method l2 has no network"):
        ModelSpec.of(ModelOptions(method="l2", **options))
    with pytest.raises(InputError, match="method='l2' has no network"):  # the API's words
        Model(method="l2", **options)


def test_least_squares_refuses_a_model_file(random_onnx: Path) -> None:
    with pytest.raises(InputError, match="needs no model"):
        ModelSpec.of(ModelOptions(random_onnx, method="l2"))


# --- --max-memory with --ray: one machine's budget, split among the workers it runs at once


def _nodes(cpus: list[float]) -> list[RayNode]:
    return [RayNode(f"n{i}", c) for i, c in enumerate(cpus)]


def plan_workers(
    cpus: list[float], threads: int, stacks: int, max_memory_mb: float, workers: int | None = None
) -> WorkerPlan:
    """The plan on nodes n0, n1, ... with these CPUs, as msf-run --ray makes it (its messages
    name msf-run's flags)."""
    with speaking_as("msf-run"):
        return _plan_workers(_nodes(cpus), threads, stacks, max_memory_mb, workers)


def _counts(plan: WorkerPlan) -> dict[str | None, int]:
    return {n.node_id: n.workers for n in plan.nodes}


@pytest.mark.parametrize(
    ("nodes", "threads", "stacks", "workers", "want"),
    [
        # one 2-CPU machine (a local cluster here): two workers, half the budget each
        ([2.0], 1, 5, None, (2, 2, 2048.0)),
        # at most one worker a stack
        ([2.0], 1, 1, None, (1, 1, 4096.0)),
        # 16 CPUs but only 4096 MB: four workers of 1024 MB, not sixteen of 256
        ([16.0], 1, 40, None, (4, 4, 1024.0)),
        # --threads 4 on 16 CPUs: four fit
        ([16.0], 4, 40, None, (4, 4, 1024.0)),
        # --workers as asked, dealt over the nodes: 3 + 3
        ([8.0, 4.0], 1, 40, 6, (6, 3, 4096 / 3)),
        # 10 workers over two nodes: the small one is full at 4, the large takes 6
        ([8.0, 4.0], 1, 40, 10, (10, 6, 4096 / 6)),
    ],
)
def test_the_budget_is_shared_by_the_workers_a_node_runs_at_once(
    nodes: list[float],
    threads: int,
    stacks: int,
    workers: int | None,
    want: tuple[int, int, float],
) -> None:
    plan = plan_workers(nodes, threads, stacks, 4096.0, workers)
    assert (plan.workers, max(n.workers for n in plan.nodes)) == want[:2]
    assert plan.memory_mb == pytest.approx(want[2], rel=1e-12)
    # what runs at once on each node stays within the budget, and within its CPUs
    cpus = {n.node_id: n.cpus for n in _nodes(nodes)}
    for node in plan.nodes:
        assert node.workers * node.memory_mb <= 4096.0 * (1 + 1e-12)
        assert node.workers * threads <= cpus[node.node_id]


def test_a_cluster_of_many_nodes_runs_workers_on_every_node() -> None:
    # ten 16-CPU nodes, 4096 MB a node: four workers of 1024 MB on each, not four in all
    plan = plan_workers([16.0] * 10, 1, 200, 4096.0)
    assert plan.workers == 40
    assert plan.nodes == tuple(NodeWorkers(f"n{i}", 4, 1024.0) for i in range(10))
    # fewer stacks than room: one a stack, dealt over the nodes
    assert _counts(plan_workers([16.0] * 10, 1, 13, 4096.0)) == {
        **{f"n{i}": 2 for i in range(3)},
        **{f"n{i}": 1 for i in range(3, 10)},
    }
    # --workers 40: ten nodes hold 160 of them, four a node (1024 MB each)
    asked = plan_workers([16.0] * 10, 1, 200, 4096.0, workers=40)
    assert set(_counts(asked).values()) == {4} and asked.memory_mb == 1024.0


def test_nodes_of_different_sizes_each_get_what_they_hold() -> None:
    # 2, 4 and 32 CPUs with --threads 2: room for 1, 2 and 16; the budget allows 4 a node
    plan = plan_workers([2.0, 4.0, 32.0, 0.0], 2, 100, 4096.0)
    assert _counts(plan) == {"n0": 1, "n1": 2, "n2": 4}  # the CPU-less node gets none
    shares = {n.node_id: n.memory_mb for n in plan.nodes}
    assert shares == {"n0": 4096.0, "n1": 2048.0, "n2": 1024.0}
    assert plan.memory_mb == 1024.0 and max(n.workers for n in plan.nodes) == 4
    # --workers 12: dealt one at a time, the small nodes full first, the rest on the large one
    assert _counts(plan_workers([2.0, 4.0, 32.0], 2, 100, 8192.0, workers=12)) == {
        "n0": 1,
        "n1": 2,
        "n2": 9,
    }


def test_workers_are_refused_only_above_the_whole_clusters_room() -> None:
    assert plan_workers([4.0, 4.0], 1, 10, 8192.0, workers=8).workers == 8
    with pytest.raises(InputError, match=r"--workers 9: .* at most 8 worker.*on 2 node"):
        plan_workers([4.0, 4.0], 1, 10, 8192.0, workers=9)


def test_a_share_at_the_runtime_floor_is_refused() -> None:
    # 2 workers on a 2-CPU node: 600 MB / 2 = 300 MB, the floor itself: refused
    with pytest.raises(InputError, match=r"--max-memory 600 MB .* 300 MB each, not above"):
        plan_workers([2.0], 1, 2, 2 * BASE_MEMORY_MB, workers=2)
    assert plan_workers([2.0], 1, 2, 2 * BASE_MEMORY_MB + 1, workers=2).memory_mb > 300
    # spread over two nodes the same two workers get all 600 MB each
    assert plan_workers([2.0, 2.0], 1, 2, 2 * BASE_MEMORY_MB, workers=2).memory_mb == 600.0
    # without --workers a small budget starts one worker with all of it (one a node)
    assert plan_workers([2.0], 1, 2, 600.0) == WorkerPlan((NodeWorkers("n0", 1, 600.0),))
    assert _counts(plan_workers([2.0, 2.0], 1, 5, 600.0)) == {"n0": 1, "n1": 1}
    with pytest.raises(InputError, match="--max-memory 300 MB"):
        plan_workers([2.0], 1, 2, float(BASE_MEMORY_MB))


def test_workers_the_cluster_cannot_run_at_once_are_refused() -> None:
    # a worker that never gets its CPUs would hold its stack forever (the batch would hang)
    with pytest.raises(InputError, match=r"--workers 3: .* at most 2 worker"):
        plan_workers([2.0], 1, 5, 8192.0, workers=3)
    with pytest.raises(InputError, match=r"--workers 3: .* at most 2 worker"):
        plan_workers([3.0, 3.0], 2, 5, 8192.0, workers=3)  # 6 CPUs, but 1 + 1 fit
    with pytest.raises(InputError, match="--threads 4: no Ray node has 4 CPUs"):
        plan_workers([2.0, 3.0], 4, 5, 8192.0)


@pytest.mark.parametrize("cpus", [[0.0], [0.0, 0.0], []])
def test_a_cluster_without_cpus_says_no_node_has_joined(cpus: list[float]) -> None:
    # a head started with --num-cpus=0 before any worker joined: not a --threads problem
    with pytest.raises(InputError, match="no Ray node with CPUs has joined") as err:
        plan_workers(cpus, 1, 5, 8192.0)
    assert "--threads" not in str(err.value) and "\n" not in str(err.value)


class _FakeRef:
    def __init__(self, value: dict[str, object]) -> None:
        self.value = value


class _FakeActor:
    """Records what a worker was given; answers every stack with an error (no model run)."""

    def __init__(
        self, spec: ModelSpec, node: str | None, seen: list[tuple[ModelSpec, LoadOptions]]
    ) -> None:
        self.spec, self.node, self.seen = spec, node, seen
        self.run = self
        # its start (answered at once: a started worker)
        self.ready_ref = _FakeRef({"where": str(node)})
        self.ready = SimpleNamespace(remote=lambda: self.ready_ref)

    def remote(self, name: str, path: str, load: LoadOptions) -> _FakeRef:
        self.seen.append((self.spec, load))
        return _FakeRef({"name": name, "error": "fake worker", "where": str(self.node)})


@dataclass(frozen=True)
class _Affinity:
    node_id: str
    soft: bool


class _FakeRay:
    """The few calls run_batch_ray makes, in process: a cluster of ``cpus`` nodes (None:
    ``ray.nodes()`` fails)."""

    util = SimpleNamespace(
        scheduling_strategies=SimpleNamespace(NodeAffinitySchedulingStrategy=_Affinity)
    )

    def __init__(self, cpus: list[float] | None, total: float | None = None) -> None:
        self.cpus = cpus
        self.total = total
        self.actors: list[_FakeActor] = []
        self.seen: list[tuple[ModelSpec, LoadOptions]] = []

    def is_initialized(self) -> bool:
        return True  # the caller's session: neither started nor shut down here

    def nodes(self) -> list[dict[str, object]]:
        if self.cpus is None:
            raise RuntimeError("the GCS did not answer")
        dead = {"NodeID": "gone", "Alive": False, "Resources": {"CPU": 64.0}}
        return [dead] + [
            {"NodeID": f"n{i}", "Alive": True, "Resources": {"CPU": c} if c else {}}
            for i, c in enumerate(self.cpus)
        ]

    def cluster_resources(self) -> dict[str, float]:
        total = sum(self.cpus or []) if self.total is None else self.total
        return {"CPU": total} if total else {}  # Ray leaves out a resource it has none of

    def remote(self, num_cpus: float) -> Callable[[type], object]:
        fake = self

        class ActorClass:
            def __init__(self, node: str | None = None) -> None:
                self.node = node

            def options(self, scheduling_strategy: _Affinity) -> ActorClass:
                assert not scheduling_strategy.soft  # a worker never lands elsewhere
                return ActorClass(scheduling_strategy.node_id)

            def remote(self, spec: ModelSpec) -> _FakeActor:
                fake.actors.append(_FakeActor(spec, self.node, fake.seen))
                return fake.actors[-1]

        return lambda cls: ActorClass()

    def wait(
        self, refs: list[_FakeRef], num_returns: int, timeout: float | None = None
    ) -> tuple[list[_FakeRef], list[_FakeRef]]:
        return refs[:num_returns], refs[num_returns:]

    def get(self, ref: _FakeRef) -> dict[str, object]:
        return ref.value

    def kill(self, actor: _FakeActor) -> None:
        pass


def _items(root: Path, count: int) -> list[BatchItem]:
    return [BatchItem(root / f"s{i}") for i in range(count)]


def test_each_worker_plans_with_its_share(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    fake = _FakeRay([2.0])
    monkeypatch.setattr(ray_cluster, "import_ray", lambda: fake)
    spec = ModelSpec.of(ModelOptions(method="l2", threads=1, max_memory_mb=3000.0))
    load = LoadOptions(max_memory_mb=3000.0)
    summary = ray_cluster.run_batch_ray(
        spec, _items(tmp_path, 3), load, lambda n: None, progress=False
    )
    assert len(fake.actors) == summary.workers == 2 and len(fake.seen) == 3
    # the workers' tiles and stack-size checks both see half the budget
    assert {a.spec.options.max_memory_mb for a in fake.actors} == {1500.0}
    assert {opts.max_memory_mb for _, opts in fake.seen} == {1500.0}
    assert summary.worker_memory_mb == 1500.0
    assert summary.as_dict()["worker_memory_mb"] == 1500.0
    assert "2 Ray worker(s), 1500 MB each" in summary.totals_line()


def test_msf_run_refuses_a_budget_too_small_for_each_worker_before_any_work(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from msfnet.runtime.cli.run import main

    fake = _FakeRay([2.0])
    monkeypatch.setattr(ray_cluster, "import_ray", lambda: fake)
    stacks = [save_stack(sphere_stack(n=5, h=20, w=24, seed=i), tmp_path / f"s{i}") for i in (0, 1)]
    argv = ["--method", "l2", *map(str, stacks), "--ray", "--workers", "2"]
    out = tmp_path / "out"
    assert main([*argv, "--max-memory", "500", "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("msf-run: error: --max-memory 500 MB"), err
    assert "250 MB each" in err[0]
    assert not fake.actors and not out.exists()  # no worker started, nothing written


def test_cluster_nodes_lists_the_live_nodes_or_the_whole_cluster_as_one() -> None:
    assert cluster_nodes(_FakeRay([16.0, 0.0])) == [RayNode("n0", 16.0), RayNode("n1", 0.0)]
    # Ray cannot list its nodes: all its CPUs as one node, nothing pinned
    assert cluster_nodes(_FakeRay(None, total=12.0)) == [RayNode(None, 12.0)]
    # ... and a cluster without CPUs has none, not one (a worker would wait forever)
    assert cluster_nodes(_FakeRay(None, total=0.0)) == [RayNode(None, 0.0)]


def test_workers_are_pinned_to_their_nodes_with_their_nodes_share(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    fake = _FakeRay([2.0, 4.0])
    monkeypatch.setattr(ray_cluster, "import_ray", lambda: fake)
    spec = ModelSpec.of(ModelOptions(method="l2", threads=1, max_memory_mb=3000.0))
    load = LoadOptions(max_memory_mb=3000.0)
    summary = ray_cluster.run_batch_ray(
        spec, _items(tmp_path, 9), load, lambda n: None, progress=False, workers=5
    )
    # 5 dealt over 2 + 4 CPUs: 2 on n0 (1500 MB each), 3 on n1 (1000 MB each)
    got = sorted((a.node, a.spec.options.max_memory_mb) for a in fake.actors)
    assert got == [("n0", 1500.0)] * 2 + [("n1", 1000.0)] * 3
    # every stack ran with the share of the worker that took it
    assert len(fake.seen) == 9
    assert all(s.options.max_memory_mb == o.max_memory_mb for s, o in fake.seen)
    assert summary.workers == 5 and summary.worker_memory_mb == 1000.0  # the smallest


def test_without_a_node_list_nothing_is_pinned(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    fake = _FakeRay(None, total=2.0)
    monkeypatch.setattr(ray_cluster, "import_ray", lambda: fake)
    spec = ModelSpec.of(ModelOptions(method="l2", threads=1, max_memory_mb=3000.0))
    ray_cluster.run_batch_ray(
        spec, _items(tmp_path, 3), LoadOptions(), lambda n: None, progress=False
    )
    assert [(a.node, a.spec.options.max_memory_mb) for a in fake.actors] == [(None, 1500.0)] * 2


def test_msf_run_says_no_node_with_cpus_has_joined(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from msfnet.runtime.cli.run import main

    fake = _FakeRay([0.0])  # a head started with --num-cpus=0, no worker yet
    monkeypatch.setattr(ray_cluster, "import_ray", lambda: fake)
    stack = save_stack(sphere_stack(n=5, h=20, w=24, seed=0), tmp_path / "s0")
    out = tmp_path / "out"
    assert main(["--method", "l2", str(stack), "--ray", "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("msf-run: error: --ray: no Ray node with CPUs")
    assert not fake.actors and not out.exists()


class _FailingRay(_FakeRay):
    """Workers that die: ``start`` of them cannot start (their node died before they were
    placed), the others die on their first stack."""

    def __init__(self, cpus: list[float], start: int) -> None:
        super().__init__(cpus)
        self.cannot_start = start

    def get(self, ref: _FakeRef) -> dict[str, object]:
        if "where" in ref.value and "name" not in ref.value:  # a worker's start
            if self.cannot_start:
                self.cannot_start -= 1
                raise RuntimeError("ActorUnschedulableError: node n0 died\n(traceback ...)")
            return ref.value
        raise RuntimeError("ActorDiedError: the worker died")


@pytest.mark.parametrize("cannot_start", [0, 1, 2])
def test_stacks_left_when_every_worker_failed_are_listed_not_dropped(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, cannot_start: int
) -> None:
    fake = _FailingRay([1.0, 1.0], cannot_start)
    monkeypatch.setattr(ray_cluster, "import_ray", lambda: fake)
    spec = ModelSpec.of(ModelOptions(method="l2", threads=1))
    summary = ray_cluster.run_batch_ray(
        spec, _items(tmp_path, 6), LoadOptions(), lambda n: None, progress=False
    )
    # every stack has its row, in the given order, and each one failed
    assert [r.name for r in summary.rows] == [f"s{i}" for i in range(6)]
    errors = [r.error or "" for r in summary.rows]
    died = 2 - cannot_start  # a worker that started dies on its one stack
    assert all(e.startswith("Ray worker failed: ActorDiedError") for e in errors[:died])
    assert all(e.startswith("not run: no Ray worker left (all 2 failed") for e in errors[died:])
    if cannot_start:  # why the workers did not start, in one line
        assert "could not start: ActorUnschedulableError: node n0 died)" in errors[-1]
    assert all("\n" not in e for e in errors[died:])


class _BusyRay(_FakeRay):
    """The first worker never starts (its node's CPUs are held by another job): its start
    never answers, and waiting on it alone would never return."""

    def wait(
        self, refs: list[_FakeRef], num_returns: int, timeout: float | None = None
    ) -> tuple[list[_FakeRef], list[_FakeRef]]:
        pending = self.actors[0].ready_ref
        ready = [r for r in refs if r is not pending]
        assert ready, "the batch waits on a worker that never starts: it would hang"
        return ready[:num_returns], [r for r in refs if r not in ready[:num_returns]]


def test_a_worker_that_never_starts_is_given_no_stack(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    fake = _BusyRay([1.0, 1.0])
    monkeypatch.setattr(ray_cluster, "import_ray", lambda: fake)
    spec = ModelSpec.of(ModelOptions(method="l2", threads=1))
    summary = ray_cluster.run_batch_ray(
        spec, _items(tmp_path, 4), LoadOptions(), lambda n: None, progress=False
    )
    assert summary.workers == 2 and len(summary.rows) == 4
    # all four ran on the worker that started (n1), none waits on the one that did not
    assert {r.worker for r in summary.rows} == {"n1"}


class _SlowStartRay(_FakeRay):
    """No worker starts within the first timed wait (their CPUs are held elsewhere); then
    they do. Records the timeouts the batch waited with."""

    def __init__(self, cpus: list[float]) -> None:
        super().__init__(cpus)
        self.timeouts: list[float | None] = []

    def wait(
        self, refs: list[_FakeRef], num_returns: int, timeout: float | None = None
    ) -> tuple[list[_FakeRef], list[_FakeRef]]:
        self.timeouts.append(timeout)
        if timeout is not None and len(self.timeouts) == 1:
            return [], refs  # timed out: nothing started
        return refs[:num_returns], refs[num_returns:]


def test_a_batch_whose_workers_do_not_start_says_so_once_and_goes_on(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    fake = _SlowStartRay([2.0])
    monkeypatch.setattr(ray_cluster, "import_ray", lambda: fake)
    notes: list[str] = []
    spec = ModelSpec.of(ModelOptions(method="l2", threads=1))
    summary = ray_cluster.run_batch_ray(
        spec,
        _items(tmp_path, 3),
        LoadOptions(),
        lambda n: None,
        progress=False,
        on_note=notes.append,
    )
    assert len(summary.rows) == 3 and len(fake.seen) == 3  # every stack ran after the wait
    assert len(notes) == 1 and "\n" not in notes[0]
    assert notes[0].startswith("no Ray worker of 2 has started after 60 s")
    assert fake.timeouts[0] == ray_cluster.STALL_NOTE_S
    # once noted (or once a worker has started) the batch waits without a timeout
    assert all(t is None for t in fake.timeouts[1:])


def test_without_a_listener_the_batch_never_times_its_waits(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    fake = _SlowStartRay([2.0])
    monkeypatch.setattr(ray_cluster, "import_ray", lambda: fake)
    spec = ModelSpec.of(ModelOptions(method="l2", threads=1))
    ray_cluster.run_batch_ray(
        spec, _items(tmp_path, 2), LoadOptions(), lambda n: None, progress=False
    )
    assert fake.timeouts and all(t is None for t in fake.timeouts)


def test_rays_sigterm_handler_gives_way_to_msfnets() -> None:
    """ray.init installs its own SIGTERM handler: msf-run --ray stopped by SIGTERM exited 1
    with a native stack dump instead of 143 and its "terminated" line."""
    import signal
    from types import SimpleNamespace

    from msfnet.runtime.batch.ray_cluster import init_keeping_sigterm

    def ours(signum, frame):  # type: ignore[no-untyped-def]
        pass

    def rays(signum, frame):  # type: ignore[no-untyped-def]
        pass

    seen = {}
    fake = SimpleNamespace(init=lambda **kw: (seen.update(kw), signal.signal(signal.SIGTERM, rays)))
    previous = signal.signal(signal.SIGTERM, ours)
    try:
        init_keeping_sigterm(fake, address=None)
        assert signal.getsignal(signal.SIGTERM) is ours and seen == {"address": None}
    finally:
        signal.signal(signal.SIGTERM, previous)
