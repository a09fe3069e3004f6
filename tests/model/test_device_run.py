"""Training on batches rendered on the training device (``--render-on device``), the time
budget, and the prepared GPU run (``scripts/device_train.sh`` / ``msfnet.model.device_run``)
rehearsed on the CPU."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from msfnet.model.checkpoint import check_state_dict, read_state_dict  # noqa: E402
from msfnet.model.network import MSFNet  # noqa: E402
from msfnet.model.train import Trainer  # noqa: E402
from msfnet.model.train_cli import main as train_main  # noqa: E402
from msfnet.model.train_config import TrainConfig  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
SMALL = ("--curriculum", "0:4-4:16", "--val-objects", "1", "--val-size", "16", "--threads", "1")


def _cfg(out: Path, **kw) -> TrainConfig:
    base = dict(
        out=str(out),
        epochs=1,
        steps_per_epoch=2,
        batch=2,
        curriculum="0:4-4:16",
        val_objects=1,
        val_size=16,
        threads=1,
        device="cpu",
        render_on="device",
        log_every=1,
        precision="fp32",
    )
    base.update(kw)
    return TrainConfig(**base)


@pytest.mark.slow
def test_device_batches_are_reproducible(tmp_path) -> None:
    a = Trainer(_cfg(tmp_path / "a"))
    b = Trainer(_cfg(tmp_path / "b"))
    first = next(a._device_batches(2))[0]
    again = next(b._device_batches(2))[0]
    assert torch.equal(first.images, again.images) and torch.equal(first.normals, again.normals)
    assert first.images.shape == (2, 4, 3, 16, 16) and a.workers == 0


@pytest.mark.slow
def test_render_on_device_trains(tmp_path) -> None:
    out = tmp_path / "run"
    t = Trainer(_cfg(out))
    result = t.run(progress=False, report=False)
    assert result.step == 2
    rows = [json.loads(x) for x in (out / "log.jsonl").read_text().splitlines()]
    assert all(r["loss"] == r["loss"] for r in rows if "loss" in r)  # no NaN
    MSFNet().load_state_dict(torch.load(out / "last.pth", weights_only=True)["state_dict"])


def test_time_budget_stops_and_saves(tmp_path) -> None:
    out = tmp_path / "run"
    t = Trainer(_cfg(out, epochs=50, time_budget=0.001))
    result = t.run(progress=False, report=False)
    assert result.step == 0 and result.stopped is None
    assert (out / "last.pth").is_file()
    last = json.loads((out / "log.jsonl").read_text().splitlines()[-1])
    assert last["stopped"] == "time_budget"


def test_time_budget_counts_from_the_commands_start(tmp_path) -> None:
    """msf-train's start, not the Trainer's: a budget the imports already spent stops at once
    (with the Trainer's clock, 60 s would have trained on)."""
    out = tmp_path / "run"
    t = Trainer(_cfg(out, epochs=50, time_budget=60.0), started=time.monotonic() - 61.0)
    result = t.run(progress=False, report=False)
    assert result.step == 0 and (out / "last.pth").is_file()


def test_cli_refuses_device_rendering_of_a_folder(tmp_path, capsys) -> None:
    (tmp_path / "blobby").mkdir()
    out = str(tmp_path / "r")
    rc = train_main(["--out", out, "--render-on", "device", "--data", str(tmp_path / "blobby")])
    assert rc == 2
    assert "--render-on device renders synthetic data" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


def _env() -> dict[str, str]:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env.pop("OUT", None)
    return env


@pytest.mark.slow
def test_prepared_run_rehearsed_on_the_cpu(tmp_path) -> None:
    """The script as the device tool runs it, with a 45 s limit: it trains, stops 20 s before
    the limit, and leaves at most 8 files of at most 16 MiB; the snapshots load strictly."""
    out = tmp_path / "out"
    env = dict(_env(), LIMIT="45", MARGIN="20", OUT=str(out))
    t0 = time.monotonic()
    proc = subprocess.run(
        [
            "bash",
            str(ROOT / "scripts" / "device_train.sh"),
            "--device",
            "cpu",
            "--batch",
            "2",
            "--work",
            str(tmp_path / "work"),
            "--",
            *SMALL,
            "--steps-per-epoch",
            "5",
            "--log-every",
            "1",
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=90,
        cwd=tmp_path,
    )
    wall = time.monotonic() - t0
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert wall < 45
    files = sorted(out.iterdir())
    assert 4 <= len(files) <= 8
    assert all(f.stat().st_size < 16 * 2**20 for f in files)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["exit"] == "time budget" and summary["steps"] > 0
    assert summary["samples_per_s_median"] > 0 and 0 < summary["train_fraction"] <= 1
    snaps = [f for f in files if f.name.startswith("snap_")]
    assert snaps and [s.name for s in snaps] == summary["snapshots"]
    for snap in snaps:
        state = read_state_dict(snap)
        check_state_dict(MSFNet(), state, snap)
        assert all(v.dtype == torch.float16 for v in state.values() if v.is_floating_point())


@pytest.mark.slow
def test_watchdog_exits_when_training_hangs(tmp_path) -> None:
    """Training that never returns: the watchdog brings back what exists and ends the
    process with 124 half a margin before the limit."""
    code = (
        "import sys, time\n"
        "import msfnet.model.train_cli as cli\n"
        "cli.main = lambda argv: time.sleep(600)\n"
        "from msfnet.model import device_run\n"
        "device_run.main(sys.argv[1:])\n"
    )
    out = tmp_path / "out"
    t0 = time.monotonic()
    proc = subprocess.run(
        [
            sys.executable,
            "-c",
            code,
            "--out",
            str(out),
            "--work",
            str(tmp_path / "w"),
            "--limit",
            "14",
            "--margin",
            "6",
            "--device",
            "cpu",
        ],
        env=_env(),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 124, proc.stdout + proc.stderr
    assert time.monotonic() - t0 < 14
    assert json.loads((out / "summary.json").read_text())["exit"] == "watchdog"


def _device_run(monkeypatch, out: Path, work: Path, *extra: str) -> int:
    """device_run in this process, trained for 2 steps (its clock restarted: it counts from
    the module's import)."""
    from msfnet.model import device_run

    monkeypatch.setattr(device_run, "STARTED", time.monotonic())
    argv = ["--out", str(out), "--work", str(work), "--limit", "60", "--margin", "5"]
    argv += ["--device", "cpu", *extra, "--", *SMALL, "--epochs", "1", "--steps-per-epoch", "2"]
    return device_run.main([*argv, "--log-every", "1"])


def _tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}


def test_device_run_never_deletes_the_work_folder(tmp_path, monkeypatch) -> None:
    """--work DIR was removed with everything in it (rmtree) before msf-train even started."""
    work = tmp_path / "precious"
    work.mkdir()
    (work / "notes.txt").write_text("my results")
    (work / "last.pth").write_bytes(b"my weights")
    before = _tree(work)
    assert _device_run(monkeypatch, tmp_path / "out", work, "--batch", "1") == 0
    assert _tree(work) == before
    assert sorted(p.name for p in work.iterdir()) == sorted(before)  # no scratch left either
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["steps"] == 2


def test_device_run_counts_samples_with_the_batch_msf_train_used(tmp_path, monkeypatch) -> None:
    """A --batch after -- wins in msf-train; summary.json multiplied by device_run's own."""
    out = tmp_path / "out"
    rc = _device_run(monkeypatch, out, tmp_path / "w", "--batch", "3", "--", "--batch", "1")
    assert rc == 0
    assert json.loads((out / "config.json").read_text())["batch"] == 1
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == 2 and summary["samples"] == 2


def test_device_run_refuses_an_out_of_an_earlier_run(tmp_path, monkeypatch, capfd) -> None:
    """A second run into one OUT replaced the first's log, config and summary and left both
    runs' snapshots side by side; now it is refused, and --overwrite replaces them all."""
    out = tmp_path / "out"
    out.mkdir()
    for name in ("snap_0000999.pth", "summary.json", "log.jsonl", "config.json"):
        (out / name).write_text("earlier run")
    (out / "device_run.txt").write_text("the console log the documented call tees here")
    before = _tree(out)
    assert _device_run(monkeypatch, out, tmp_path / "w", "--batch", "1") == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("device_run: error: "), err
    assert "earlier run" in err[0] and "--overwrite" in err[0]
    assert _tree(out) == before and not (tmp_path / "w").exists()
    assert _device_run(monkeypatch, out, tmp_path / "w", "--batch", "1", "--overwrite") == 0
    summary = json.loads((out / "summary.json").read_text())
    snaps = sorted(p.name for p in out.glob("snap_*.pth"))
    assert snaps == list(summary["snapshots"]) and "snap_0000999.pth" not in snaps
    assert (out / "device_run.txt").read_text() == before["device_run.txt"].decode()


def test_the_summary_counts_the_steps_after_the_last_logged_loss(tmp_path: Path) -> None:
    """A run stopped by its budget at step 20 with --log-every 50 reported 0 steps, 0 samples
    and "done" (a CPU rehearsal of scripts/device_train.sh); on a GPU the count was up to a
    log window short."""
    from msfnet.model import device_run

    rows = [{"step": s, "loss": 0.1, "samples_per_s": 50.0, "time": 100.0 + s} for s in (50, 100)]
    rows.append({"step": 137, "stopped": "time_budget", "time": 240.0})
    (tmp_path / "log.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    (tmp_path / "config.json").write_text(json.dumps({"batch": 4}))
    sampler = device_run.UtilSampler()
    summary = device_run.summarise(tmp_path, sampler, "done", batch=64)
    assert (summary.steps, summary.samples, summary.exit) == (137, 137 * 4, "time budget")
    assert summary.train_seconds == 90.0  # from the first logged window to the stop

    (tmp_path / "log.jsonl").write_text(json.dumps(rows[-1] | {"step": 20}) + "\n")
    summary = device_run.summarise(tmp_path, sampler, "done", batch=64)
    assert (summary.steps, summary.samples, summary.exit) == (20, 80, "time budget")
    assert summary.samples_per_s_median is None

    (tmp_path / "log.jsonl").write_text(json.dumps(rows[0]) + "\n")  # every epoch ran
    assert device_run.summarise(tmp_path, sampler, "done", batch=64).exit == "done"
    assert device_run.summarise(tmp_path, sampler, "watchdog", batch=64).exit == "watchdog"
