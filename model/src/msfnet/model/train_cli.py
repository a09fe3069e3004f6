"""``msf-train``: train MSF-Net on built-in synthetic data (or Blobby/Sculpture), resumably."""

from __future__ import annotations

import argparse
import json
import signal
import sys
from dataclasses import fields
from pathlib import Path

from msfnet.runtime.errors import InputError
from msfnet.synth.render import PRESETS

from .train import TrainConfig, Trainer, parse_curriculum

DEFAULTS = TrainConfig(out="")


def build_parser() -> argparse.ArgumentParser:
    d = DEFAULTS
    p = argparse.ArgumentParser(
        prog="msf-train",
        description="Train MSF-Net with three stage losses (0.5:0.5:1) and the selective update "
                    "strategy. Writes OUT/last.pth (published {'state_dict': ...} format), "
                    "OUT/best.pth (best held-out synthetic MAE), OUT/last_state.pth (optimizer), "
                    "OUT/log.jsonl, OUT/curve.png and OUT/config.json. Resume with --resume. "
                    "SIGTERM / SIGINT (Ctrl-C) finish the step, save last.pth and exit with "
                    "128 + the signal number (143 / 130), so time-boxed chunks can be chained: "
                    "`timeout 600 msf-train ... --resume` repeated.")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--resume", action="store_true",
                   help="continue from OUT/last.pth with OUT/config.json; options given "
                        "explicitly (e.g. --epochs) override the stored ones. With nothing "
                        "to resume in OUT yet, start there (so one command serves every chunk)")
    p.add_argument("--overwrite", action="store_true", help="start afresh in a non-empty OUT")
    p.add_argument("--data", default=d.data,
                   help="'synth' (built-in renderer, default) or a Blobby/Sculpture root folder")
    p.add_argument("--epochs", type=int, default=d.epochs, help=f"default {d.epochs}")
    p.add_argument("--steps-per-epoch", type=int, default=d.steps_per_epoch,
                   help=f"default {d.steps_per_epoch}")
    p.add_argument("--batch", type=int, default=d.batch, help=f"default {d.batch}")
    p.add_argument("--curriculum", default=d.curriculum,
                   help="EPOCH:LMIN-LMAX:CROP[,...]: from EPOCH on, each batch uses a random "
                        "light count in [LMIN, LMAX] and CROPxCROP crops "
                        f"(default {d.curriculum!r}; one phase = fixed setting)")
    p.add_argument("--lights", type=int, default=None,
                   help="shortcut: a fixed light count for every batch (curriculum with one "
                        "phase; the paper used 32)")
    p.add_argument("--crop", type=int, default=None, help="shortcut: fixed crop size")
    p.add_argument("--lr", type=float, default=d.lr, help=f"Adam learning rate (default {d.lr})")
    p.add_argument("--lr-step", type=int, default=d.lr_step,
                   help=f"halve the learning rate every this many epochs (default {d.lr_step})")
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--threads", type=int, default=d.threads,
                   help=f"torch threads of the training process (default {d.threads})")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default=d.device,
                   help="auto (default): cuda when torch sees a GPU, else cpu")
    p.add_argument("--workers", type=int, default=d.workers,
                   help="processes rendering batches in parallel (DataLoader workers, each with "
                        "its own object pool and seed stream); 0 = render in the training "
                        "process. Default: 0 on the CPU, min(cores - 2, 12) with cuda")
    p.add_argument("--precision", choices=("auto", "bf16", "fp32"), default=d.precision,
                   help="bf16 autocast where the device supports it natively (auto, default: "
                        "GPUs with bf16, CPUs with AVX512-BF16/AMX) or fp32")
    p.add_argument("--no-channels-last", action="store_true", help="keep NCHW weights")
    p.add_argument("--no-mfe", action="store_true",
                   help="ablation: no multi-stage extraction (extractor1 -> max -> regressor)")
    p.add_argument("--init", metavar="CKPT",
                   help="start from these weights with a fresh optimiser (e.g. the bundled "
                   "msfnet_default.pth), instead of random initialisation")
    p.add_argument("--no-mff", action="store_true",
                   help="ablation: no fusion module (a stage sees concat(raw, max))")
    p.add_argument("--no-sus", action="store_true",
                   help="ablation: no selective update (all stage losses train all modules)")
    p.add_argument("--render-size", type=int, default=d.render_size,
                   help=f"synthetic object size in pixels (default {d.render_size})")
    p.add_argument("--render-size-max", type=int, default=d.render_size_max,
                   help="draw each synthetic object's size from [--render-size, this]: larger "
                        "renders are smoother per pixel, like real full-resolution objects")
    p.add_argument("--render-max-depth", type=float, default=d.render_max_depth,
                   help="synthetic domes up to this height/radius (default "
                        f"{d.render_max_depth}; 2 gives a slant histogram like DiLiGenT ball's, "
                        "with 4x more pixels steeper than 66 deg)")
    p.add_argument("--render-preset", choices=PRESETS, default=d.render_preset,
                   help="synthetic data: 'default' renderer or 'hard' (steep rims, folds and "
                        "cups with inter-reflections, pixel-scale relief, rough / painted / "
                        "very dark materials, LED rings, mostly 8-bit); validation stays on "
                        "the default renderer so runs compare")
    p.add_argument("--val-size", type=int, default=d.val_size,
                   help=f"validation object size in pixels (default {d.val_size})")
    p.add_argument("--render-lights", type=int, default=d.render_lights,
                   help=f"lights rendered per synthetic object (default {d.render_lights})")
    p.add_argument("--pool", type=int, default=d.pool,
                   help=f"synthetic objects kept in memory (default {d.pool})")
    p.add_argument("--refresh", type=int, default=d.refresh,
                   help=f"new synthetic objects rendered per batch (default {d.refresh})")
    p.add_argument("--noise", type=float, default=d.noise,
                   help="max extra Gaussian noise, fraction of the crop's 95th percentile "
                        f"(default {d.noise})")
    p.add_argument("--val-objects", type=int, default=d.val_objects,
                   help=f"held-out synthetic validation objects (default {d.val_objects})")
    p.add_argument("--ckpt-minutes", type=float, default=d.ckpt_minutes,
                   help=f"save last.pth at least this often (default {d.ckpt_minutes})")
    p.add_argument("--log-every", type=int, default=d.log_every,
                   help=f"append a log.jsonl row every this many steps (default {d.log_every})")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


# CLI option -> TrainConfig field (where the names differ)
RENAME = {"no_channels_last": "channels_last", "no_mfe": "mfe", "no_mff": "mff", "no_sus": "sus"}


def _explicit(argv: list[str] | None) -> dict:
    """Only the options the user typed (for overriding a stored config on --resume)."""
    p = build_parser()
    for action in p._actions:
        action.default = argparse.SUPPRESS
        action.required = False
    return vars(p.parse_args(argv))


def config_from(args: dict, base: dict) -> TrainConfig:
    cfg = dict(base)
    names = {f.name for f in fields(TrainConfig)}
    for key, value in args.items():
        if key in RENAME:
            cfg[RENAME[key]] = not value
        elif key in names:
            cfg[key] = str(value) if key == "out" else value
    if args.get("lights") is not None or args.get("crop") is not None:
        phase = parse_curriculum(cfg["curriculum"])[0]
        lights = args.get("lights") or phase.lights_max
        crop = args.get("crop") or phase.crop
        cfg["curriculum"] = f"0:{lights}-{lights}:{crop}"
    out = TrainConfig(**cfg)
    parse_curriculum(out.curriculum)  # validate early
    if out.epochs < 1 or out.steps_per_epoch < 1 or out.batch < 1:
        raise InputError("--epochs, --steps-per-epoch and --batch must be >= 1")
    if out.workers is not None and out.workers < 0:
        raise InputError("--workers must be >= 0")
    if out.data == "synth":
        crop = max(p.crop for p in parse_curriculum(out.curriculum))
        if crop > out.render_size:
            raise InputError(f"crop {crop} exceeds --render-size {out.render_size}")
        if out.render_size_max is not None and out.render_size_max < out.render_size:
            raise InputError(f"--render-size-max {out.render_size_max} is below --render-size "
                             f"{out.render_size}")
    elif not Path(out.data).is_dir():
        raise InputError("--data: not 'synth' and not a folder", out.data)
    return out


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        out: Path = args.out
        stored = out / "config.json"
        resume = args.resume and (out / "last.pth").is_file() and (
            out / "last_state.pth").is_file()
        if args.resume and not resume:
            # Nothing saved yet (first chunk, or killed before the first save): start here,
            # from the stored settings if a config.json was written.
            print(f"msf-train: nothing to resume in {out}: starting there", flush=True)
            base = json.loads(stored.read_text()) if stored.is_file() else {}
            explicit = _explicit(argv) if base else vars(args)
            cfg = config_from(explicit, base)
            for name in ("log.jsonl", "best.pth", "last.pth", "last_state.pth"):
                (out / name).unlink(missing_ok=True)
        elif resume:
            if not stored.is_file():
                raise InputError("--resume: no config.json in the output folder", out)
            cfg = config_from(_explicit(argv), json.loads(stored.read_text()))
        else:
            if out.exists() and any(out.iterdir()) and not args.overwrite:
                raise InputError("output folder is not empty (use --resume to continue or "
                                 "--overwrite to start afresh)", out)
            if args.overwrite:
                for name in ("log.jsonl", "last.pth", "last_state.pth", "best.pth"):
                    (out / name).unlink(missing_ok=True)
            cfg = config_from(vars(args), {})
        trainer = Trainer(cfg, resume=resume)
        data = cfg.data if cfg.data != "synth" else f"synth ({cfg.render_preset})"
        print(f"msf-train: {trainer.device.type}, "
              f"{'bf16 autocast' if trainer.bf16 else 'fp32'}, "
              f"{'channels_last' if cfg.channels_last else 'NCHW'}, {cfg.threads} threads, "
              f"{trainer.workers} data workers, data {data}, curriculum {cfg.curriculum}, "
              f"from step {trainer.step}; validation: {len(trainer.val_set)} objects, "
              f"least squares MAE {trainer.val_ls:.2f} deg", flush=True)
        result = trainer.run(progress=not args.no_progress)
    except InputError as exc:
        print(f"msf-train: error: {exc}", file=sys.stderr)
        return 2
    if "stopped" in result:
        sig = int(result["stopped"])
        print(f"msf-train: stopped by {signal.Signals(sig).name} at step {result['step']}; "
              "last.pth saved, continue with --resume")
        return 128 + sig
    print(f"msf-train: done at step {result['step']}: best held-out MAE "
          f"{result['best_val_mae']:.2f} deg (least squares {result['val_ls_mae']:.2f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
