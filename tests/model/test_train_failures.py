"""msf-train when a run goes wrong: a fresh run failing before its first last.pth keeps the
weights it wrote, a diverging run stops without saving NaN weights, a second msf-train into a
busy OUT is refused, and --time-budget is one invocation's limit, reported as such."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from _runtime_helpers import QUICK_VALIDATION, folder_held

torch = pytest.importorskip("torch")

from msfnet.common.errors import InputError  # noqa: E402
from msfnet.common.files.locks import LOCK_NAME  # noqa: E402
from msfnet.model.train import Trainer  # noqa: E402
from msfnet.model.train_cli import main as train_main  # noqa: E402
from msfnet.model.train_config import TrainConfig  # noqa: E402

# the review's tiny setting: a step and a validation take well under a second
TINY = [
    "--batch",
    "1",
    "--lights",
    "4",
    "--crop",
    "8",
    "--render-size",
    "16",
    "--render-lights",
    "4",
    "--pool",
    "2",
    "--refresh",
    "1",
    *QUICK_VALIDATION,
    "--log-every",
    "1",
    "--precision",
    "fp32",
    "--no-progress",
]


def _cfg(out: Path, **kw) -> TrainConfig:
    base = dict(
        out=str(out),
        epochs=1,
        steps_per_epoch=3,
        batch=1,
        curriculum="0:4-4:8",
        render_size=16,
        render_lights=4,
        pool=2,
        refresh=1,
        val_objects=1,
        val_size=16,
        threads=1,
        device="cpu",
        log_every=1,
        precision="fp32",
    )
    base.update(kw)
    return TrainConfig(**base)


def _strict_rows(log: Path) -> list[dict]:
    """log.jsonl read as strict JSON: a bare NaN / Infinity fails."""

    def refuse(token: str) -> None:
        raise ValueError(f"not JSON: {token}")

    return [json.loads(line, parse_constant=refuse) for line in log.read_text().splitlines()]


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}


# ----------------------------------------------------------------------------- finding 2


def test_a_fresh_run_failing_before_last_pth_keeps_its_snapshots(
    tmp_path: Path, monkeypatch, capsys
) -> None:
    """A late error (a bad Blobby file, a full disk, out of memory) before the first last.pth
    removed the whole folder, --snapshot-seconds snapshots included."""
    out = tmp_path / "run"
    t = Trainer(_cfg(out, snapshot_seconds=1e-6))  # a snapshot after every step

    def bad_object() -> float:
        raise InputError("image file not found", "blob/obj/005.png")

    monkeypatch.setattr(t, "validate", bad_object)  # at the end of the epoch, before any save
    with pytest.raises(InputError):
        t.run(progress=False, report=True)
    names = sorted(p.name for p in out.iterdir())
    snaps = ["snap_0000001.pth", "snap_0000002.pth", "snap_0000003.pth"]
    assert names == ["config.json", "log.jsonl", *snaps]  # how they were trained, too
    assert "kept in" in capsys.readouterr().out


def test_a_fresh_run_failing_without_weights_leaves_nothing(tmp_path: Path, monkeypatch) -> None:
    out = tmp_path / "runs" / "run"
    t = Trainer(_cfg(out))

    def bad_object() -> float:
        raise InputError("image file not found", "blob/obj/005.png")

    monkeypatch.setattr(t, "validate", bad_object)
    with pytest.raises(InputError):
        t.run(progress=False, report=False)
    assert not (tmp_path / "runs").exists()


# ----------------------------------------------------------------------------- finding 3


def test_a_diverging_run_stops_without_saving_nan_weights(tmp_path: Path, capfd) -> None:
    """--lr 1e30 sent the weights to NaN: last.pth and best.pth were saved with them, exit 0,
    log.jsonl held bare NaN, and --resume then refused the folder."""
    out = tmp_path / "run"
    common = ["--out", str(out), *TINY, "-q"]
    assert train_main([*common, "--epochs", "1", "--steps-per-epoch", "2"]) == 0
    before = {n: (out / n).read_bytes() for n in ("last.pth", "last_state.pth", "best.pth")}
    capfd.readouterr()
    # step 3 sends the weights to ~1e30, the loss of step 4 is NaN
    assert train_main([*common, "--resume", "--epochs", "3", "--lr", "1e30"]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("msf-train: error: "), err
    assert "training diverged" in err[0] and "at step 4" in err[0], err
    assert "last.pth is left at step 2" in err[0], err
    assert {n: (out / n).read_bytes() for n in before} == before
    _strict_rows(out / "log.jsonl")
    # and the run can go on from there with a sane learning rate
    assert train_main([*common, "--resume", "--epochs", "2", "--lr", "1e-3"]) == 0
    state = torch.load(out / "last.pth", weights_only=True)
    assert state["step"] == 4
    assert all(torch.isfinite(v).all() for v in state["state_dict"].values())


def test_diverged_weights_are_never_ranked_best(tmp_path: Path, capfd) -> None:
    """A validation right after the weights blew up: NaN normals scored 180 deg, which beat
    best = inf, so best.pth held the diverged weights."""
    out = tmp_path / "run"
    argv = ["--out", str(out), *TINY, "-q", "--epochs", "1", "--steps-per-epoch", "1"]
    assert train_main([*argv, "--lr", "1e30"]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "training diverged" in err[0] and "nothing was saved" in err[0]
    assert not out.exists()  # a fresh run with no weights to keep


def test_a_non_finite_validation_is_logged_as_null_and_not_best(
    tmp_path: Path, monkeypatch
) -> None:
    out = tmp_path / "run"
    t = Trainer(_cfg(out, steps_per_epoch=1))
    monkeypatch.setattr(t, "validate", lambda: float("nan"))
    t.run(progress=False, report=False)
    assert not (out / "best.pth").exists() and (out / "last.pth").is_file()
    rows = _strict_rows(out / "log.jsonl")
    assert [r["val_mae"] for r in rows if "val_mae" in r] == [None]


# ----------------------------------------------------------------------------- finding 4


def test_a_second_msf_train_into_a_busy_folder_is_refused(tmp_path: Path, capfd) -> None:
    """Two msf-train in one OUT both ran: last.pth replaced in turn, the log interleaved."""
    out = tmp_path / "run"
    out.mkdir()
    (out / "config.json").write_text(
        json.dumps(
            {"epochs": 1, "steps_per_epoch": 2, "batch": 1, "curriculum": "0:4-4:8"}
            | {"lr": 1e-3, "seed": 0}
        )
    )
    for name in ("last.pth", "last_state.pth", "log.jsonl"):
        (out / name).write_text("x")
    before = _files(out)
    with folder_held(out, "msf-train") as holder:
        for extra in (["--resume"], ["--overwrite"]):
            assert train_main(["--out", str(out), *extra, "--no-progress"]) == 2
            err = capfd.readouterr().err.strip().splitlines()
            assert len(err) == 1 and "another msf-train is working in this folder" in err[0]
            now = _files(out)
            now.pop(LOCK_NAME)  # the holder's
            assert now == before
        holder.kill()  # like kill -9: the lock file stays, and holds nothing any more
    # a lock left by a killed run neither blocks nor counts as a file in OUT
    assert train_main(["--out", str(out), "--resume", "--no-progress"]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "another msf-train" not in err[0] and "last.pth" in err[0], err


# ----------------------------------------------------------------------------- finding 7


def test_time_budget_is_this_invocations_and_reported_as_a_stop(tmp_path: Path, capsys) -> None:
    """--time-budget was stored in config.json, so a plain --resume stopped again after the
    same seconds; and a budget stop said "done" like a finished run."""
    out = tmp_path / "run"
    common = ["--out", str(out), *TINY]
    # spent before the first step (it counts from msf-train's start)
    assert (
        train_main([*common, "--epochs", "2", "--steps-per-epoch", "2", "--time-budget", "1e-3"])
        == 0
    )
    said = capsys.readouterr().out
    assert "stopped by --time-budget at step 0 of 4" in said and "--resume" in said
    assert "done" not in said
    stored = json.loads((out / "config.json").read_text())
    assert "time_budget" not in stored
    # runs of earlier versions stored it: a plain --resume must not stop on it again
    (out / "config.json").write_text(json.dumps({**stored, "time_budget": 1e-3}))
    assert train_main(["--out", str(out), "--resume", "--no-progress"]) == 0
    assert "done at step 4" in capsys.readouterr().out
    assert torch.load(out / "last.pth", weights_only=True)["step"] == 4
