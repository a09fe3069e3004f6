"""One time-boxed training run on a lent accelerator, prepared so its first minute trains.

    python -m msfnet.model.device_run --out $OUT --limit 600 [--margin 60] [-- msf-train options]

``scripts/device_train.sh`` wraps this for the device tool (docs/training.md gives the exact
call). What it does:

- trains with ``msf-train`` in a private scratch folder made inside ``--work`` (and removed
  after the copy; nothing else in ``--work`` is touched), from the bundled weights
  (``--init``), on batches rendered on the device itself (``--render-on device``), until
  ``--margin`` seconds before ``--limit`` (counted from this process's start);
- keeps ``--snapshots`` fp16 snapshots (~4.5 MB each) spread over the run and copies them, with
  ``log.jsonl``, ``config.json`` and ``summary.json`` (steps, samples/s, GPU utilisation, the
  share of the wall time spent training), into ``--out``: at most 8 files, each well under the
  16 MiB that comes back from the device tool. An ``--out`` holding an earlier run's results
  is refused unless ``--overwrite`` (which then replaces them all: no snapshots of two runs
  side by side);
- exits for sure: the renderer runs in this process (no workers to get stuck), a watchdog
  thread copies what exists and calls ``os._exit`` if training has not returned ``--margin / 2``
  seconds before the limit, and the normal path ends in ``os._exit`` too (after flushing), so
  no CUDA or thread teardown can hold the command past its limit.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import statistics
import sys
import threading
import time
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path

from msfnet.common.cli import path_arg
from msfnet.common.files import scratch_folder, write_atomic
from msfnet.model.train_config import SNAPSHOT

STARTED = time.monotonic()  # the command's clock starts with this process
BUNDLED = Path(__file__).parent / "weights" / "msfnet_default.pth"
MAX_FILES = 8  # what the device tool brings back from $OUT
# What deliver() writes into --out besides the snapshots: with those, an earlier run's results.
# (Anything else, such as the console log the documented call tees into $OUT, is not ours.)
RESULTS = ("log.jsonl", "config.json", "summary.json")
TRAIN_DEFAULTS = (
    # a fine-tune of the bundled weights on the hard cases; one "epoch" = 1,000 steps between
    # synthetic validations (6 objects at 96 px, seconds on a GPU)
    "--lr=1e-4",  # 2e-4 knocked the bundled weights back on the CPU (docs/training.md)
    "--lr-step=5",  # halved every 5,000 steps (1e-4 ... 6.25e-6 over 20,000)
    "--epochs=1000",
    "--steps-per-epoch=1000",
    "--curriculum=0:8-32:32",
    "--render-preset=hard",
    "--val-objects=6",
    "--val-size=96",
    "--log-every=50",
    "--ckpt-minutes=2",
)


@dataclass(frozen=True)
class Summary:
    device: str
    torch: str
    steps: int
    samples: int
    train_seconds: float  # from the first logged window to the last row (the stop)
    wall_seconds: float  # the whole command so far
    train_fraction: float  # train_seconds / wall_seconds
    samples_per_s_median: float | None
    gpu_util_median: float | None  # NVML samples taken once a second while training
    gpu_util_mean: float | None
    exit: str  # "time budget", "done" (every epoch), "watchdog" or "error: ..."
    snapshots: tuple[str, ...]


class UtilSampler(threading.Thread):
    """GPU utilisation (NVML through torch) once a second, while the run lasts."""

    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.samples: list[float] = []
        self.stop = threading.Event()

    def run(self) -> None:
        import torch

        if not torch.cuda.is_available():
            return
        while not self.stop.wait(1.0):
            try:
                self.samples.append(float(torch.cuda.utilization()))
            except Exception:  # no NVML: the log's data-wait share has to do
                return


def _rows(work: Path) -> list[dict]:
    log = work / "log.jsonl"
    rows = []
    if log.is_file():
        for line in log.read_text().splitlines():
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError:
                continue  # a line torn by a hard exit
    return rows


def _run_batch(work: Path, batch: int) -> int:
    """The batch the run trained with: its config.json's (a --batch given to msf-train after
    ``--`` wins over device_run's own), ``batch`` if it wrote none."""
    try:
        stored = json.loads((work / "config.json").read_text()).get("batch")
    except (OSError, ValueError, AttributeError):
        return batch
    return stored if isinstance(stored, int) and not isinstance(stored, bool) else batch


def summarise(work: Path, sampler: UtilSampler, exit_: str, batch: int) -> Summary:
    import torch

    every = _rows(work)
    rows = [r for r in every if "loss" in r]
    speeds = [r["samples_per_s"] for r in rows[1:]]  # the first window holds cuDNN's tuning
    # the steps done: the last row that names one (the stop's row comes after the last loss
    # row, which is up to --log-every steps behind; a short run may have no loss row at all)
    steps = max((r["step"] for r in every if type(r.get("step")) is int), default=0)
    stopped = next((r.get("stopped") for r in reversed(every) if "stopped" in r), None)
    if exit_ == "done" and stopped == "time_budget":
        exit_ = "time budget"  # the planned end of a device run: msf-train's --time-budget
    # from the first logged window to the last row (the stop's): the span the steps reach
    times = [r["time"] for r in every if isinstance(r.get("time"), (int, float))]
    span = times[-1] - rows[0]["time"] if rows and times else 0.0
    wall = time.monotonic() - STARTED
    util = sampler.samples[2:]  # the first seconds are start-up
    device = torch.cuda.get_device_name() if torch.cuda.is_available() else "cpu"
    return Summary(
        device=device,
        torch=torch.__version__,
        steps=steps,
        samples=steps * _run_batch(work, batch),
        train_seconds=round(span, 1),
        wall_seconds=round(wall, 1),
        train_fraction=round(span / wall, 3) if wall > 0 else 0.0,
        samples_per_s_median=round(statistics.median(speeds), 1) if speeds else None,
        gpu_util_median=statistics.median(util) if util else None,
        gpu_util_mean=round(statistics.fmean(util), 1) if util else None,
        exit=exit_,
        snapshots=tuple(p.name for p in _snapshots(work)),
    )


def _snapshots(work: Path, keep: int = MAX_FILES - 3) -> list[Path]:
    snaps = sorted(p for p in work.glob("snap_*.pth") if SNAPSHOT.fullmatch(p.name))
    return snaps[-keep:]


def _final_snapshot(work: Path) -> None:
    """The last saved weights as an fp16 snapshot, unless the newest snapshot is that step."""
    import torch

    from msfnet.model.checkpoint import read_checkpoint, save_checkpoint
    from msfnet.model.network import MSFNet
    from msfnet.model.train import snapshot_name

    last = work / "last.pth"
    if not last.is_file():
        return
    tensors, step = read_checkpoint(last)
    if step is None or (work / snapshot_name(step)).is_file():
        return
    model = MSFNet()
    model.load_state_dict(tensors, strict=True)
    with torch.no_grad():
        save_checkpoint(model, work / snapshot_name(step), fp16=True, step=step)


def earlier_results(out: Path) -> list[str]:
    """What an earlier run delivered into ``out`` (snapshots, log, config, summary)."""
    if not out.is_dir():
        return []
    return sorted(p.name for p in out.iterdir() if p.name in RESULTS or SNAPSHOT.fullmatch(p.name))


def deliver(work: Path, out: Path, summary: Summary, keep: int) -> None:
    """Copy the newest ``keep`` snapshots, the log, the config and the summary into ``out``;
    then remove the rest of an earlier run's results (main lets them be there only with
    --overwrite), so the folder never mixes two runs' snapshots."""
    out.mkdir(parents=True, exist_ok=True)
    stale = set(earlier_results(out))
    files = [*_snapshots(work, keep), work / "log.jsonl", work / "config.json"]
    for src in files:
        if src.is_file():
            write_atomic(out / src.name, partial(shutil.copyfile, src))
            stale.discard(src.name)
    text = json.dumps(asdict(summary), indent=1) + "\n"
    write_atomic(out / "summary.json", lambda tmp: tmp.write_text(text))
    stale.discard("summary.json")
    for name in sorted(stale):
        (out / name).unlink(missing_ok=True)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m msfnet.model.device_run",
        description="A time-boxed msf-train run for a lent GPU (see docs/training.md).",
    )
    p.add_argument("--out", type=path_arg, required=True, help="what comes back ($OUT)")
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the results of an earlier run in --out (refused otherwise)",
    )
    p.add_argument(
        "--work",
        type=path_arg,
        default=Path("/tmp/msf_device_run"),
        help="folder to train in: a private scratch folder is made inside it and removed "
        "afterwards; nothing else in it is touched (default %(default)s)",
    )
    p.add_argument("--limit", type=float, default=600.0, help="the command's limit, seconds")
    p.add_argument("--margin", type=float, default=60.0, help="stop training this much earlier")
    p.add_argument("--init", type=path_arg, default=BUNDLED, help="weights to start from")
    p.add_argument("--snapshots", type=int, default=4, help="snapshots to bring back (<= 5)")
    p.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"))
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("train", nargs=argparse.REMAINDER, help="-- further msf-train options")
    return p


def _error(message: str) -> int:
    print(f"device_run: error: {message}", file=sys.stderr, flush=True)
    return 2


def main(argv: list[str] | None = None) -> int:
    # options device_run does not know are msf-train's (as are those after --)
    args, unknown = build_parser().parse_known_args(argv)
    keep = max(1, min(args.snapshots, MAX_FILES - 3))
    if args.out.exists() and not args.out.is_dir():
        return _error(f"{args.out}: exists and is not a folder")
    earlier = earlier_results(args.out)
    if earlier and not args.overwrite:
        return _error(
            f"{args.out}: holds an earlier run's results ({', '.join(earlier[:3])}"
            f"{', ...' if len(earlier) > 3 else ''}); use another folder, or --overwrite to "
            "replace them"
        )
    if args.work.exists() and not args.work.is_dir():
        return _error(f"{args.work}: --work exists and is not a folder")
    budget = args.limit - args.margin - (time.monotonic() - STARTED)
    if budget < 5:
        return _error("no time left to train (--limit minus --margin)")
    # Never delete --work itself: it is the user's (the default is shared by every run on the
    # machine); train in a private folder inside it, which only this process removes (one a
    # killed run left is removed by the next run, as staging of a dead process).
    with contextlib.ExitStack() as scratch:
        try:
            work = scratch.enter_context(scratch_folder(args.work / "train"))
        except OSError as exc:
            return _error(f"{args.work}: cannot make a scratch folder in --work ({exc.strerror})")
        return _train_and_deliver(args, unknown, work, budget, keep)


def _train_and_deliver(
    args: argparse.Namespace, unknown: list[str], work: Path, budget: float, keep: int
) -> int:
    sampler = UtilSampler()
    done = threading.Event()

    def watchdog() -> None:
        # Last resort: whatever holds the process, bring back what exists and exit.
        if done.wait(max(1.0, args.limit - args.margin / 2 - (time.monotonic() - STARTED))):
            return
        try:
            deliver(work, args.out, summarise(work, sampler, "watchdog", args.batch), keep)
        finally:
            print("device_run: watchdog: training did not return in time; exiting", flush=True)
            sys.stderr.flush()
            os._exit(124)

    threading.Thread(target=watchdog, daemon=True).start()
    sampler.start()
    extra = unknown + [a for a in args.train if a != "--"]
    train_argv = ["--out", str(work), "--device", args.device, "--render-on", "device"]
    train_argv += ["--init", str(args.init), f"--batch={args.batch}", *TRAIN_DEFAULTS]
    train_argv += [f"--time-budget={budget:.1f}", f"--snapshot-seconds={budget / keep:.1f}"]
    train_argv += ["--no-progress", *extra]  # later options win (argparse keeps the last)
    print(f"device_run: training for {budget:.0f} s: msf-train {' '.join(train_argv)}", flush=True)
    from msfnet.model.train_cli import main as train_main

    exit_ = "done"
    try:
        rc = train_main(train_argv)
        if rc != 0:
            exit_ = f"error: msf-train exited {rc}"
        _final_snapshot(work)
    except BaseException as exc:  # still bring back what exists
        exit_, rc = f"error: {exc!r}", 1
    sampler.stop.set()
    summary = summarise(work, sampler, exit_, args.batch)
    deliver(work, args.out, summary, keep)
    done.set()
    print("device_run: " + json.dumps(asdict(summary)), flush=True)
    return rc


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)  # no interpreter teardown (CUDA, threads) between us and the limit
