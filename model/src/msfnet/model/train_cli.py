"""``msf-train``: train MSF-Net on built-in synthetic data (or Blobby/Sculpture), resumably."""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import time
from collections.abc import Collection
from dataclasses import fields
from pathlib import Path
from typing import Any

from msfnet.common.cli import Command, add_flags, command_main, int_range, make_parser, path_arg
from msfnet.common.errors import InputError, first_line
from msfnet.common.files import STAGING_TAG, check_not_input, folder_lock
from msfnet.common.files.locks import LOCK_NAME
from msfnet.model.train_config import (
    MAX_LIGHTS,
    RUN_ONLY,
    SNAPSHOT,
    Phase,
    TrainConfig,
    crop_size,
    format_curriculum,
    parse_curriculum,
    stored_value_problem,
)
from msfnet.runtime.stack.types import MIN_LIGHTS

PROG = "msf-train"
COMMAND = Command(PROG, extra="train")
# What msf-train writes into OUT: --overwrite deletes these and nothing else (with the
# ".*.pth.tmp" temporaries an msf-train killed with kill -9 may have left).
_WEIGHTS = ("last.pth", "last_state.pth", "best.pth")
TRAIN_FILES = ("config.json", "log.jsonl", "curve.png", *_WEIGHTS, *(f".{w}.tmp" for w in _WEIGHTS))


def build_parser() -> argparse.ArgumentParser:
    p = make_parser(
        PROG,
        "Train MSF-Net with three stage losses (0.5:0.5:1) and the selective update "
        "strategy. Writes OUT/last.pth (published {'state_dict': ...} format), "
        "OUT/best.pth (best held-out synthetic MAE), OUT/last_state.pth (optimizer), "
        "OUT/log.jsonl, OUT/curve.png and OUT/config.json (best.pth and curve.png from the first "
        "validation, at the end of the first epoch, on). Resume with --resume. "
        "SIGTERM / SIGINT (Ctrl-C) finish the step, save last.pth and exit with "
        "128 + the signal number (143 / 130), so time-boxed chunks can be chained: "
        "`timeout 600 msf-train ... --resume` repeated.",
        (
            "msf-train --out runs/a --epochs 2 --steps-per-epoch 50",
            "msf-train --out runs/a --resume --epochs 4",
            "msf-train --out runs/gpu --device cuda --render-preset hard --resume   # chunks",
        ),
    )
    p.add_argument(
        "-o",
        "--output",
        "--out",
        dest="out",
        type=path_arg,
        required=True,
        help="output (run) folder",
    )
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue from OUT/last.pth with OUT/config.json; options given "
        "explicitly (e.g. --epochs) override the stored ones. A run stopped before its "
        "first save starts again from its config.json; a missing or empty OUT is refused "
        "(a mistyped folder would start a new run of hours)",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="start afresh in an OUT of an earlier msf-train run (only its files are deleted)",
    )
    add_flags(p, TrainConfig)  # the run's settings: one flag per TrainConfig field
    # shortcuts that rewrite --curriculum (config_from), so no field of their own
    p.add_argument(
        "--lights",
        metavar="K",
        type=int_range(MIN_LIGHTS, MAX_LIGHTS),  # photometric stereo's fewest lights
        default=None,
        help="shortcut: a fixed light count for every batch (every phase of the curriculum "
        "uses K lights, its crops kept; the paper used 32)",
    )
    p.add_argument(
        "--crop",
        type=crop_size,
        default=None,
        help="shortcut: a fixed crop size, a multiple of 4 (every phase of the curriculum "
        "crops S x S, its light counts kept)",
        metavar="S",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def _explicit(argv: list[str] | None) -> dict:
    """Only the options the user typed (for overriding a stored config on --resume)."""
    p = build_parser()
    for action in p._actions:
        action.default = argparse.SUPPRESS
        action.required = False
    return vars(p.parse_args(argv))


# What --render-on device does not use: its renderer draws each batch at the step's crop and
# light count (the curriculum), with its own sensor noise and object sizes, in the training
# process. Given with it, these would be stored in config.json yet change nothing.
CPU_RENDER_ONLY: tuple[str, ...] = ("noise", "render_size", "render_size_max", "render_max_depth")
CPU_RENDER_ONLY += ("render_lights", "pool", "refresh", "workers")


def _flag(name: str) -> str:
    """The option spelling of a TrainConfig field."""
    return "--" + name.replace("_", "-")


def config_from(args: dict, base: dict, typed: Collection[str] | None = None) -> TrainConfig:
    """The run's settings: ``base`` (a stored config.json, or nothing) with ``args`` over it.
    ``typed``: the options the user typed (their field names; default: every key of
    ``args``): errors name these, and options --render-on device would ignore are refused
    only when typed (the defaults are stored either way)."""
    typed = set(args) if typed is None else set(typed)
    cfg = dict(base)
    names = {f.name for f in fields(TrainConfig)}
    for key, value in args.items():
        if key in names:  # the flags store under the field names (--no-mfe: mfe=False)
            cfg[key] = str(value) if key == "out" else value
    # where the curriculum came from, for errors that name what the user typed
    spec = str(cfg.get("curriculum", TrainConfig.curriculum))
    if "curriculum" in typed:
        source = "--curriculum"
    elif "curriculum" in base:
        source = "config.json's curriculum"
    else:
        source = "the default --curriculum"
    origin = f"{source} {spec!r}"
    phases = parse_curriculum(spec, source)
    lights, crop = args.get("lights"), args.get("crop")
    if lights is not None or crop is not None:
        # the shortcuts replace only their part of every phase: --crop alone keeps the light
        # range (the default's 16-32 lights), --lights alone the crops and the phases
        phases = [
            Phase(p.epoch, lights or p.lights_min, lights or p.lights_max, crop or p.crop)
            for p in phases
        ]
        same = [(p.lights_min, p.lights_max, p.crop) for p in phases]
        phases = [p for i, p in enumerate(phases) if i == 0 or same[i] != same[i - 1]]
        cfg["curriculum"] = format_curriculum(phases)
    out = TrainConfig(**cfg)
    if out.epochs < 1 or out.steps_per_epoch < 1 or out.batch < 1:
        raise InputError("--epochs, --steps-per-epoch and --batch must be >= 1")
    if out.workers is not None and out.workers < 0:
        raise InputError("--workers must be >= 0")
    if out.render_on == "device" and out.data != "synth":
        raise InputError("--render-on device renders synthetic data; drop --data")
    most = max(p.lights_max for p in phases)
    widest = max(p.crop for p in phases)
    lights_from = f"--lights {lights}" if lights is not None else origin
    crop_from = f"--crop {crop}" if crop is not None else origin
    if out.data == "synth" and out.render_on == "device":
        ignored = [_flag(name) for name in CPU_RENDER_ONLY if name in typed]
        if ignored:
            raise InputError(
                f"{', '.join(ignored)}: not used by --render-on device (it renders each "
                "batch's crop and lights, as the curriculum asks, with its own noise and "
                "object sizes, in the training process); drop "
                f"{'it' if len(ignored) == 1 else 'them'} or use --render-on cpu"
            )
    elif out.data == "synth":
        if most > out.render_lights:  # the sampler would quietly use fewer lights
            raise InputError(
                f"{lights_from} asks for up to {most} lights but "
                f"--render-lights renders {out.render_lights}"
            )
        if widest > out.render_size:
            raise InputError(
                f"{crop_from} asks for {widest} px crops but --render-size is {out.render_size}"
            )
        if out.render_size_max is not None and out.render_size_max < out.render_size:
            raise InputError(
                f"--render-size-max {out.render_size_max} is below --render-size {out.render_size}"
            )
    elif not Path(out.data).is_dir():
        raise InputError("--data: not 'synth' and not a folder", out.data)
    return out


# keys every msf-train config.json has had: older runs may lack newer options, never these
CORE_KEYS = frozenset({"epochs", "steps_per_epoch", "batch", "curriculum", "lr", "seed"})


def _stored_config(out: Path, flag: str = "--resume", values: bool = True) -> dict:
    """OUT/config.json of an earlier run, refused in one line if missing, damaged or not
    msf-train's. ``values``: also check each value by its option's rules (what --resume will
    use; --overwrite only needs to know the run is msf-train's)."""
    stored = out / "config.json"
    if not stored.is_file():
        raise InputError(f"{flag}: no config.json in the output folder (not an msf-train run)", out)
    try:
        data = json.loads(stored.read_text())
    except (ValueError, UnicodeDecodeError, RecursionError) as exc:
        raise InputError(f"{flag}: config.json is damaged ({exc})", stored) from exc
    known = {f.name for f in fields(TrainConfig)}
    if not isinstance(data, dict) or not CORE_KEYS <= set(data) <= known:
        unknown = sorted(set(data) - known) if isinstance(data, dict) else []
        raise InputError(
            f"{flag}: config.json is not an msf-train configuration"
            + (f" (unknown keys {unknown[:3]})" if unknown else ""),
            stored,
        )
    # runs of earlier versions stored --time-budget: one chunk's limit, not the run's
    kept = {k: v for k, v in data.items() if k not in RUN_ONLY}
    for key, value in kept.items() if values else ():
        # a hand-edited value ("batch": 1.5, "pool": 0, "noise": null) is refused as the
        # option would be, not left to fail in torch or numpy as an internal error
        problem = stored_value_problem(key, value)
        if problem is not None:
            raise InputError(f'"{key}": {problem}', stored)
    return kept


def _entries(out: Path) -> list[Path]:
    """What OUT holds, leaving out the lock msf-train holds it with (or a killed one left)."""
    return [p for p in out.iterdir() if p.name != LOCK_NAME]


def _ours(path: Path) -> bool:
    """A file msf-train writes in OUT (by name; a folder is never ours)."""
    name = path.name
    return (
        path.is_file()
        and not path.is_symlink()
        and (name in TRAIN_FILES or STAGING_TAG in name or SNAPSHOT.fullmatch(name) is not None)
    )


def _weights_in(out: Path) -> list[str]:
    """Trained weights in OUT: never deleted to make room for a fresh start by --resume."""
    return sorted(p.name for p in out.glob("*.pth") if _ours(p) and STAGING_TAG not in p.name)


def _prepare_out(args: argparse.Namespace) -> list[Path]:
    """OUT is never an input nor holds one; an existing OUT is continued (--resume) or, with
    --overwrite, cleared of msf-train's own files only (returned: the caller deletes them once
    every option has been checked)."""
    out: Path = args.out
    inputs = [args.init] + ([args.data] if args.data != "synth" else [])
    check_not_input(out, inputs, folder=True)
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a folder", out)
    if args.resume and args.overwrite:
        raise InputError("--resume and --overwrite contradict each other")
    if args.resume and (not out.exists() or not _entries(out)):
        state = "does not exist" if not out.exists() else "is empty"
        raise InputError(
            f"--resume: nothing to resume, the folder {state} (a new run: leave out --resume)", out
        )
    if args.resume or not out.exists() or not _entries(out):
        return []
    if not args.overwrite:
        raise InputError(
            "output folder is not empty (use --resume to continue or --overwrite to start afresh)",
            out,
        )
    foreign = sorted(p.name for p in _entries(out) if not _ours(p))
    if foreign:
        raise InputError(
            f"--overwrite: the folder holds files msf-train did not write (e.g. "
            f"{foreign[0]}); refusing to delete them",
            out,
        )
    _stored_config(out, "--overwrite", values=False)  # names alone do not make it ours
    return sorted(_entries(out))  # deleted by the caller once every option has been checked


def _run(args: argparse.Namespace, argv: list[str] | None, started: float | None = None) -> int:
    # torch now, after the options were checked and before OUT is touched: a missing torch
    # must not cost an earlier run's files (--overwrite, --resume clean up first)
    import msfnet.model.train  # noqa: F401

    _prepare_out(args)  # the refusals first: the lock would create a missing OUT
    # held from before OUT is read to the end of training: a second msf-train into it is
    # refused at once, not left to swap last.pth with this one and interleave the log
    with folder_lock(args.out, PROG):
        return _run_locked(args, argv, started)


def _run_locked(args: argparse.Namespace, argv: list[str] | None, started: float | None) -> int:
    from msfnet.model.checkpoint import read_state_dict
    from msfnet.model.train import Trainer

    def say(line: str) -> None:
        if not args.quiet:
            print(line, flush=True)

    out: Path = args.out
    earlier = _prepare_out(args)  # again: what it checked may have changed before the lock
    explicit = _explicit(argv)  # what the user typed: errors name it, --resume keeps the rest
    resume = args.resume and (out / "last.pth").is_file() and (out / "last_state.pth").is_file()
    if args.resume and not resume:
        # Nothing saved yet (first chunk, or killed before the first save): start here, from
        # the stored settings if a config.json was written; but never in someone else's folder.
        foreign = sorted(p.name for p in _entries(out) if not _ours(p)) if out.is_dir() else []
        if foreign:
            raise InputError(
                f"--resume: no msf-train run here (no config.json / last.pth) but "
                f"other files (e.g. {foreign[0]})",
                out,
            )
        weights = _weights_in(out) if out.is_dir() else []
        if weights:  # e.g. last_state.pth lost: starting over would delete trained weights
            raise InputError(
                f"--resume: {', '.join(weights)} but no complete last.pth + "
                "last_state.pth pair to continue from; start a new run from "
                "those weights with --init in another folder",
                out,
            )
        say(f"msf-train: nothing to resume in {out}: starting there")
        base = _stored_config(out) if (out / "config.json").is_file() else {}
        cfg = config_from(explicit if base else vars(args), base, set(explicit))
        (out / "log.jsonl").unlink(missing_ok=True)  # rows of a run that never saved
    elif resume:
        stored = _stored_config(out)
        for flag, key in (("--no-mfe", "mfe"), ("--no-mff", "mff")):
            if key in explicit and stored.get(key, True):
                raise InputError(
                    f"--resume: {flag} changes the network of the run being "
                    "resumed; start a new run instead",
                    out,
                )
        cfg = config_from(explicit, stored, set(explicit))
    else:
        cfg = config_from(vars(args), {}, set(explicit))
        if cfg.init is not None:
            read_state_dict(cfg.init)  # a bad --init is refused while the earlier run exists
    try:  # device, data, precision checked: writes nothing
        trainer = Trainer(cfg, resume=resume, started=started)
    except (ValueError, TypeError, KeyError, RuntimeError) as exc:
        if not resume or isinstance(exc, InputError):
            raise
        # what --resume read (config.json's values, last_state.pth's optimiser) does not fit
        raise InputError(
            f"--resume: the run's config.json or last_state.pth cannot be used "
            f"({type(exc).__name__}: {first_line(exc)}); start a new run",
            out,
        ) from exc
    for path in earlier:  # --overwrite: only now, with every option and the set-up checked
        path.unlink()
    data = cfg.data if cfg.data != "synth" else f"synth ({cfg.render_preset})"
    say(
        f"msf-train: {trainer.device.type}, "
        f"{'bf16 autocast' if trainer.bf16 else 'fp32'}, "
        f"{'channels_last' if cfg.channels_last else 'NCHW'}, {cfg.threads} threads, "
        f"{trainer.workers} data workers, data {data}, curriculum {cfg.curriculum}, "
        f"from step {trainer.step}; validation: {len(trainer.val_set)} objects, "
        f"least squares MAE {trainer.val_ls:.2f} deg"
    )
    if not args.quiet:
        _announce_duration(trainer, cfg)
    result = trainer.run(progress=not (args.no_progress or args.quiet), report=not args.quiet)
    if result.stopped is not None:
        say(
            f"msf-train: stopped by {signal.Signals(result.stopped).name} at step "
            f"{result.step}; last.pth saved, continue with --resume"
        )
        return 128 + result.stopped
    best = (
        f"best held-out MAE {result.best_val_mae:.2f} deg (least squares {result.val_ls_mae:.2f})"
        if math.isfinite(result.best_val_mae)
        else "before the first validation (end of an epoch): no best.pth or curve.png yet"
    )
    if result.budget_spent:  # exit 0 as documented, but never read as a finished run
        total = cfg.epochs * cfg.steps_per_epoch
        say(
            f"msf-train: stopped by --time-budget at step {result.step:,} of {total:,}, {best}; "
            "last.pth saved, continue with --resume"
        )
    else:
        say(f"msf-train: done at step {result.step}: {best}")
    return 0


# steps timed for the duration estimate, after the first (set-up, first renders, warm caches)
ESTIMATE_STEPS = 4


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def _announce_duration(trainer: Any, cfg: TrainConfig) -> None:
    """Say what the run asks for, and once a few steps are timed, how long it will take here:
    the defaults are hours on a small CPU (docs/training.md), which no one should learn from
    the clock."""
    from tqdm import tqdm  # its write() keeps the progress bar intact

    total = cfg.epochs * cfg.steps_per_epoch
    left = total - trainer.step
    if left <= 0:
        return
    print(
        f"msf-train: {left:,} steps to go ({cfg.epochs} epochs x {cfg.steps_per_epoch} "
        f"steps of batch {cfg.batch}); the time it takes here follows after "
        f"{ESTIMATE_STEPS + 1} steps. Ctrl-C or --time-budget stop with last.pth saved, "
        "--resume continues",
        flush=True,
    )
    step = trainer.train_step
    times: list[float] = []

    def timed(batch: Any) -> Any:
        times.append(time.perf_counter())  # a step is the time between starts: data included
        if len(times) == ESTIMATE_STEPS + 2:
            per_step = (times[-1] - times[1]) / ESTIMATE_STEPS
            remaining = per_step * max(0, total - trainer.step)
            tqdm.write(
                f"msf-train: {per_step:.2g} s a step on this {trainer.device.type}: "
                f"about {_duration(remaining)} for the remaining "
                f"{total - trainer.step:,} steps (validation each epoch not included)"
            )
        return step(batch)

    trainer.train_step = timed


def main(argv: list[str] | None = None) -> int:
    started = time.monotonic()  # --time-budget's zero: before torch is imported
    return command_main(COMMAND, build_parser(), lambda args: _run(args, argv, started), argv)


if __name__ == "__main__":
    sys.exit(main())
