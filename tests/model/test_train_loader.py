"""Training on the available device: device choice, the worker DataLoader path, throughput
logging, the hard render preset, and a clean stop on SIGTERM that --resume continues."""

from __future__ import annotations

import json
import multiprocessing
import os
import signal

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="needs torch: the [train] extra")

from msfnet.common.errors import InputError  # noqa: E402
from msfnet.model import train as train_mod  # noqa: E402
from msfnet.model.data import SourceSpec, StepPlan, StepStream, make_loader, worker_init  # noqa: E402
from msfnet.model.train import TrainConfig, Trainer, default_workers, resolve_device  # noqa: E402
from msfnet.model.train_cli import main as train_main  # noqa: E402
from msfnet.synth import RenderOptions  # noqa: E402

torch.set_num_threads(2)

TINY = [
    "--batch",
    "1",
    "--lights",
    "3",
    "--crop",
    "8",
    "--pool",
    "2",
    "--render-size",
    "24",
    "--val-objects",
    "1",
    "--val-size",
    "32",
    "--log-every",
    "1",
    "--no-progress",
    "--precision",
    "fp32",
    "--device",
    "cpu",
]


def test_device_choice_without_cuda(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == torch.device("cpu")
    assert resolve_device("cpu") == torch.device("cpu")
    with pytest.raises(InputError, match="no CUDA"):
        resolve_device("cuda")
    with pytest.raises(InputError, match="choose"):
        resolve_device("tpu")
    assert default_workers(torch.device("cpu"), cores=16) == 0  # CPU: the cores train
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("auto") == torch.device("cuda")
    cuda = torch.device("cuda")
    assert [default_workers(cuda, cores=c) for c in (2, 8, 16, 64)] == [0, 6, 12, 12]


def test_trainer_on_cpu_when_cuda_is_unavailable(monkeypatch, tmp_path):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    cfg = TrainConfig(
        out=str(tmp_path),
        batch=1,
        curriculum="0:3-3:16",
        render_size=24,
        pool=1,
        val_objects=1,
        val_size=32,
        render_preset="hard",
    )
    t = Trainer(cfg)
    assert t.device.type == "cpu" and t.workers == 0
    assert t.bf16 == train_mod.bf16_available()
    assert next(t.model.parameters()).device.type == "cpu"
    assert t.render_options == RenderOptions.hard(
        size=24, lights=cfg.render_lights, max_depth=cfg.render_max_depth
    )
    assert t.source is not None and t.source.options.steep > 0  # the hard preset reaches data


def _stream(start=0, total=4):
    opts = RenderOptions(size=24, lights=6)
    spec = SourceSpec("synth", 3, opts, pool=2, refresh=1)
    plan = StepPlan(3, 2, 2, ((0, 3, 5, 16), (1, 4, 4, 8)), noise=0.01)
    return spec, plan, StepStream(spec, plan, start, total)


def test_step_stream_is_deterministic_and_follows_the_curriculum():
    _spec, _plan, stream = _stream()
    a, b = list(stream), list(stream)
    assert [d["step"] for d in a] == [0, 1, 2, 3]
    for x, y in zip(a, b, strict=True):
        torch.testing.assert_close(x["images"], y["images"], rtol=0, atol=0)
    # epochs of 2 steps: phase 0 (3-5 lights, 16 px) then phase 1 (4 lights, 8 px)
    assert all(3 <= d["n_lights"] <= 5 and d["crop"] == 16 for d in a[:2])
    assert all(d["n_lights"] == 4 and d["crop"] == 8 for d in a[2:])
    assert tuple(a[3]["images"].shape) == (2, 4, 3, 8, 8)
    resumed = list(_stream(start=2)[2])
    assert [d["step"] for d in resumed] == [2, 3]


def test_two_workers_deliver_steps_in_order():
    spec, plan, _ = _stream()
    got = [(int(d["step"]), tuple(d["images"].shape)) for d in make_loader(spec, plan, 1, 5, 2)]
    assert [s for s, _ in got] == [1, 2, 3, 4]
    assert got[-1][1][1] == 4  # phase 1 from epoch 1 on


@pytest.mark.slow
def test_cli_trains_through_worker_processes_and_logs_throughput(tmp_path):
    out = tmp_path / "run"
    assert (
        train_main(
            ["--out", str(out), "--epochs", "1", "--steps-per-epoch", "2", "--workers", "1", *TINY]
        )
        == 0
    )
    rows = [json.loads(r) for r in (out / "log.jsonl").read_text().splitlines()]
    steps = [r for r in rows if "loss" in r]
    assert [r["step"] for r in steps] == [1, 2]
    for r in steps + [r for r in rows if "val_mae" in r]:
        assert r["samples_per_s"] > 0 and 0.0 <= r["data_wait"] <= 1.0
    assert "gpu_util" not in steps[0]  # CPU run
    assert torch.load(out / "last.pth", weights_only=True)["step"] == 2
    assert json.loads((out / "config.json").read_text())["workers"] == 1


@pytest.mark.slow
def test_sigterm_saves_last_and_resume_finishes(tmp_path, monkeypatch):
    out = tmp_path / "run"
    real_step = Trainer.train_step

    def step_then_signal(self, batch):
        result = real_step(self, batch)
        if self.step == 0:  # during the first step: as `timeout` would send it
            os.kill(os.getpid(), signal.SIGTERM)
        return result

    monkeypatch.setattr(Trainer, "train_step", step_then_signal)
    cmd = [
        "--out",
        str(out),
        "--epochs",
        "1",
        "--steps-per-epoch",
        "3",
        "--workers",
        "1",
        *TINY,
    ]
    # the first chunk starts the run; the next ones add --resume
    assert train_main(cmd) == 128 + signal.SIGTERM
    assert torch.load(out / "last.pth", weights_only=True)["step"] == 1
    assert torch.load(out / "last_state.pth", weights_only=True)["step"] == 1
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # handlers restored
    monkeypatch.setattr(Trainer, "train_step", real_step)
    assert train_main([*cmd, "--resume"]) == 0
    rows = [json.loads(r) for r in (out / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows if "loss" in r] == [1, 2, 3]
    assert [r["stopped"] for r in rows if "stopped" in r] == ["SIGTERM"]
    assert torch.load(out / "last.pth", weights_only=True)["step"] == 3


def test_in_process_path_is_unchanged_by_the_worker_option(tmp_path):
    # workers=0 keeps the original in-process source and random stream: the first batch equals
    # what SynthSource.batch gives with rng [seed, 0].
    from msfnet.model.data import SynthSource

    cfg = TrainConfig(
        out=str(tmp_path),
        batch=2,
        curriculum="0:4-4:16",
        render_size=24,
        pool=2,
        refresh=1,
        val_objects=1,
        val_size=32,
        device="cpu",
        workers=0,
    )
    t = Trainer(cfg)
    batch, lights, crop = next(t._local_batches(10))
    ref_src = SynthSource(
        cfg.seed,
        RenderOptions(size=24, lights=cfg.render_lights, max_depth=cfg.render_max_depth),
        2,
        1,
    )
    rng = np.random.default_rng([cfg.seed, 0])
    rng.integers(4, 5)
    ref = ref_src.batch(2, 4, 16, rng, noise=cfg.noise)
    assert (lights, crop) == (4, 16)
    torch.testing.assert_close(batch.images, ref.images, rtol=0, atol=0)


def _signal_self_after_init() -> None:
    worker_init(0)
    os.kill(os.getpid(), signal.SIGTERM)
    os.kill(os.getpid(), signal.SIGINT)


def test_workers_leave_signals_to_the_main_process():
    # `timeout` signals the whole process group: a worker dying of it would make torch raise in
    # the main process mid-step (or mid-save) instead of the clean stop.
    p = multiprocessing.get_context("fork").Process(target=_signal_self_after_init)
    p.start()
    p.join(30)
    assert p.exitcode == 0


def _ignore_term_and_sleep(ready) -> None:
    worker_init(0)
    ready.set()
    import time

    time.sleep(60)


def test_stuck_workers_that_ignore_sigterm_are_killed():
    # A worker ignoring SIGTERM survives terminate(); left alone it keeps the run from exiting
    # (seen on a GPU run: over 100 s after the save, until the outer timeout's SIGKILL).
    ctx = multiprocessing.get_context("fork")
    ready = ctx.Event()
    p = ctx.Process(target=_ignore_term_and_sleep, args=(ready,), daemon=True)
    p.start()
    try:
        assert ready.wait(30)
        p.terminate()
        p.join(0.5)
        assert p.is_alive()  # terminate() alone does not stop it
        assert train_mod.stop_workers(timeout=0.2, spare={p}) == 0  # a caller's own child
        assert p.is_alive()
        assert train_mod.stop_workers(timeout=0.2) >= 1
        assert not p.is_alive() and p.exitcode == -signal.SIGKILL
    finally:
        if p.is_alive():
            p.kill()


@pytest.mark.slow
def test_snapshots_are_kept_every_k_epochs(tmp_path):
    out = tmp_path / "run"
    assert (
        train_main(
            [
                "--out",
                str(out),
                "--epochs",
                "4",
                "--steps-per-epoch",
                "1",
                "--snapshot-every",
                "2",
                *TINY,
            ]
        )
        == 0
    )
    assert sorted(p.name for p in out.glob("snap_*.pth")) == [
        "snap_0000002.pth",
        "snap_0000004.pth",
    ]
    snap = torch.load(out / "snap_0000004.pth", weights_only=True)
    last = torch.load(out / "last.pth", weights_only=True)
    assert snap["step"] == 4 and all(
        torch.equal(snap["state_dict"][k], v) for k, v in last["state_dict"].items()
    )
    # --overwrite counts snapshots as msf-train's own files, and only those it names
    (out / "snap_final.pth").write_bytes(b"the user's")
    assert (
        train_main(
            ["--out", str(out), "--overwrite", "--epochs", "1", "--steps-per-epoch", "1", *TINY]
        )
        == 2
    )
    (out / "snap_final.pth").unlink()
    assert (
        train_main(
            ["--out", str(out), "--overwrite", "--epochs", "1", "--steps-per-epoch", "1", *TINY]
        )
        == 0
    )
    assert not list(out.glob("snap_*.pth"))


def test_resume_refuses_weights_and_optimiser_of_different_steps(tmp_path):
    """A kill between the two files of a save must not resume from mismatched halves."""
    from msfnet.model.checkpoint import save_checkpoint

    cfg = TrainConfig(
        out=str(tmp_path),
        batch=1,
        curriculum="0:3-3:16",
        render_size=24,
        pool=1,
        val_objects=1,
        val_size=32,
        precision="fp32",
    )
    t = Trainer(cfg)
    t.step = 5
    t.save()
    assert Trainer(cfg, resume=True).step == 5  # a consistent pair resumes
    save_checkpoint(t.model, tmp_path / "last.pth", step=6)
    with pytest.raises(
        InputError,
        match=r"last\.pth is from step 6 but last_state\.pth "
        r"from step 5",
    ):
        Trainer(cfg, resume=True)
    for odd in ({"step": 6}, {"optimizer": {}, "step": "six", "best": None}):
        torch.save(odd, tmp_path / "last_state.pth")  # no optimiser / not numbers
        with pytest.raises(InputError, match="not an msf-train optimiser state"):
            Trainer(cfg, resume=True)
