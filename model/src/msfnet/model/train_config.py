"""msf-train's options as typed data: the run configuration (stored as OUT/config.json) and
the light-count / crop curriculum. Kept apart from the training loop so the command line can be
parsed, and refused, without importing torch."""

from __future__ import annotations

import argparse
import functools
import json
import re
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, fields
from typing import Any, get_args, get_type_hints

from msfnet.common.cli import (
    int_range,
    nonnegative_float,
    nonnegative_int,
    path_text,
    positive_float,
    positive_int,
    thread_count,
)
from msfnet.common.errors import InputError
from msfnet.common.vocabulary import flag, opt, options_type
from msfnet.runtime.stack.types import MIN_LIGHTS
from msfnet.synth.render import PRESETS, RenderOptions

SNAPSHOT = re.compile(r"snap_\d{7}\.pth")  # what --snapshot-every writes, and nothing else
# Limits of one msf-train invocation, not settings of the run: kept out of config.json, so a
# plain --resume does not stop again after the first chunk's --time-budget.
RUN_ONLY = frozenset({"time_budget"})


@dataclass
class Phase:
    """From ``epoch`` on: light counts drawn from [lights_min, lights_max], crops of ``crop``."""

    epoch: int
    lights_min: int
    lights_max: int
    crop: int


def parse_curriculum(spec: str, source: str | None = None) -> list[Phase]:
    """``"0:8-16:32,4:16-32:32"`` -> phases (start epoch : lights range : crop size).
    ``source``: what errors name as the curriculum's origin (default: the ``curriculum``
    setting, as its reader sets it)."""
    where = opt("curriculum", spec, quote=True) if source is None else f"{source} {spec!r}"
    phases = []
    try:
        for part in spec.split(","):
            e, lights, crop = part.strip().split(":")
            lo, _, hi = lights.partition("-")
            phases.append(Phase(int(e), int(lo), int(hi or lo), int(crop)))
    except ValueError as exc:
        raise InputError(
            f"{where}: expected EPOCH:LMIN-LMAX:CROP[,...] like 0:8-16:32,4:16-32:32"
        ) from exc
    phases.sort(key=lambda p: p.epoch)
    for p in phases:
        if p.lights_min < MIN_LIGHTS or p.lights_max < p.lights_min or p.crop < 8 or p.crop % 4:
            raise InputError(
                f"{where}: need {MIN_LIGHTS} <= LMIN <= LMAX (photometric "
                "stereo's fewest lights) and CROP a multiple of 4 (>= 8)"
            )
    if not phases or phases[0].epoch != 0:
        raise InputError(f"{where}: the first phase must start at epoch 0")
    starts = [p.epoch for p in phases]
    twice = sorted({e for e in starts if starts.count(e) > 1})
    if twice:  # only the last of them would ever apply, the others silently never
        raise InputError(f"{where}: two phases start at epoch {twice[0]}; give each its own")
    return phases


def format_curriculum(phases: Sequence[Phase]) -> str:
    """The ``--curriculum`` text of ``phases`` (parse_curriculum's inverse)."""
    return ",".join(f"{p.epoch}:{p.lights_min}-{p.lights_max}:{p.crop}" for p in phases)


# Upper bounds that keep a mistyped number from asking for terabytes before anything runs.
MAX_SIZE = 4096
MAX_LIGHTS = 1024


def crop_size(text: str) -> int:
    """A --crop value: 8..MAX_SIZE and a multiple of 4, as the curriculum's CROP."""
    value = int_range(8, MAX_SIZE)(text)
    if value % 4:
        raise argparse.ArgumentTypeError(f"must be a multiple of 4, got {text!r}")
    return value


@options_type
@dataclass
class TrainConfig:
    """One training run's settings. The fields with a ``flag`` are msf-train's options: the
    command line is generated from them (common.cli.add_flags), so the two cannot drift apart.
    ``%(default)s`` in a help text is argparse's: it prints the field's default."""

    out: str  # -o/--output/--out: written by hand in train_cli (a required Path)
    epochs: int = flag(20, "default %(default)s", type=positive_int)
    steps_per_epoch: int = flag(300, "default %(default)s", type=positive_int)
    batch: int = flag(8, "default %(default)s", type=positive_int)
    curriculum: str = flag(
        "0:16-32:32",
        "EPOCH:LMIN-LMAX:CROP[,...]: from EPOCH on, each batch uses a random light count in "
        "[LMIN, LMAX] and CROPxCROP crops (default %(default)r; one phase = fixed setting)",
    )
    lr: float = flag(1e-3, "Adam learning rate (default %(default)s)", type=positive_float)
    lr_step: int = flag(
        5, "halve the learning rate every this many epochs (default %(default)s)", type=positive_int
    )
    seed: int = flag(
        0,
        "seed of the synthetic data and the initial weights (default %(default)s)",
        type=nonnegative_int,
    )
    threads: int = flag(
        2, "torch threads of the training process (default %(default)s)", type=thread_count
    )
    precision: str = flag(
        "auto",
        "bf16 autocast where the device supports it natively (auto, default: GPUs with bf16, "
        "CPUs with AVX512-BF16/AMX) or fp32",
        choices=("auto", "bf16", "fp32"),
    )
    channels_last: bool = flag(
        True, "keep NCHW weights", name="--no-channels-last", action="store_false"
    )
    mfe: bool = flag(
        True,
        "ablation: no multi-stage extraction (extractor1 -> max -> regressor)",
        name="--no-mfe",
        action="store_false",
    )
    mff: bool = flag(
        True,
        "ablation: no fusion module (a stage sees concat(raw, max))",
        name="--no-mff",
        action="store_false",
    )
    sus: bool = flag(
        True,
        "ablation: no selective update (all stage losses train all modules)",
        name="--no-sus",
        action="store_false",
    )
    grad_loss: float = flag(
        0.0,
        "add W x the L1 distance between predicted and true normal changes from pixel to pixel "
        "to each stage loss (default 0: the paper's loss). Experimental: meant to keep 1-3 px "
        "relief, it lowered detail in a short CPU fine-tune (docs/training.md)",
        type=nonnegative_float,
        metavar="W",
    )
    consistency: float = flag(
        0.0,
        "also train each batch turned / mirrored one of 7 ways and add W x the disagreement of "
        "the two predictions mapped back (rotation consistency; about 2x the step time; "
        "default 0: off)",
        type=nonnegative_float,
        metavar="W",
    )
    data: str = flag(
        "synth",
        "'synth' (built-in renderer, default) or a Blobby/Sculpture root folder",
        type=path_text,
    )
    init: str | None = flag(
        None,
        "start from these weights with a fresh optimiser (e.g. the bundled msfnet_default.pth), "
        "instead of random initialisation",
        metavar="CKPT",
        type=path_text,
    )
    render_size: int = flag(
        64,
        "synthetic object size in pixels (default %(default)s; --render-on cpu only)",
        type=int_range(8, MAX_SIZE),
    )
    render_size_max: int | None = flag(
        None,
        "draw each synthetic object's size from [--render-size, this]: larger renders are "
        "smoother per pixel, like real full-resolution objects (--render-on cpu only)",
        type=int_range(8, MAX_SIZE),
    )
    render_max_depth: float = flag(
        RenderOptions.max_depth,
        "synthetic domes up to this height/radius (default %(default)s; 2 gives a slant "
        "histogram like DiLiGenT ball's, with 4x more pixels steeper than 66 deg; "
        "--render-on cpu only)",
        type=positive_float,
    )
    render_preset: str = flag(
        "default",
        "synthetic data: 'default' renderer or 'hard' (steep rims, folds and cups with "
        "inter-reflections, pixel-scale relief, rough / painted / very dark materials, LED "
        "rings, mostly 8-bit); validation stays on the default renderer so runs compare",
        choices=PRESETS,
    )
    render_lights: int = flag(
        40,
        "lights rendered per synthetic object (default %(default)s; --render-on cpu only)",
        type=int_range(3, MAX_LIGHTS),
    )
    pool: int = flag(
        48,
        "synthetic objects kept in memory (default %(default)s; --render-on cpu only)",
        type=positive_int,
    )
    refresh: int = flag(
        2,
        "new synthetic objects rendered per batch (default %(default)s; --render-on cpu only)",
        type=nonnegative_int,
    )
    noise: float = flag(
        0.01,
        "max extra Gaussian noise, fraction of the crop's 95th percentile (default "
        "%(default)s; --render-on cpu only: the device renderer draws its own sensor noise)",
        type=nonnegative_float,
    )
    val_objects: int = flag(
        8, "held-out synthetic validation objects (default %(default)s)", type=positive_int
    )
    val_size: int = flag(
        64, "validation object size in pixels (default %(default)s)", type=int_range(8, MAX_SIZE)
    )
    val_lights: int = 32
    val_seed: int = 999_999
    ckpt_minutes: float = flag(
        10.0, "save last.pth at least this often (default %(default)s)", type=positive_float
    )
    snapshot_every: int = flag(
        0,
        "also keep snap_<step>.pth every this many epochs, to select a model on real objects "
        "later (default 0: only last.pth and best.pth)",
        type=nonnegative_int,
        metavar="EPOCHS",
    )
    log_every: int = flag(
        10, "append a log.jsonl row every this many steps (default %(default)s)", type=positive_int
    )
    device: str = flag(
        "auto",
        "auto (default): cuda when torch sees a GPU, else cpu",
        choices=("auto", "cpu", "cuda"),
    )
    workers: int | None = flag(
        None,
        "processes rendering batches in parallel (DataLoader workers, each with its own object "
        "pool and seed stream); 0 = render in the training process. Default: 0 on the CPU, "
        "min(cores - 2, 12) with cuda (--render-on cpu only)",
        type=nonnegative_int,
    )
    render_on: str = flag(
        "cpu",
        "where synthetic batches are rendered: cpu (default: the numpy renderer, in the "
        "training process or --workers) or device (the torch renderer on the training device "
        "itself, as batched tensor operations: each batch at the curriculum's crop and light "
        "count, --render-preset applies; --noise, --render-size, --render-size-max, "
        "--render-max-depth, --render-lights, --pool, --refresh and --workers are for cpu "
        "only and refused with device)",
        choices=("cpu", "device"),
    )
    time_budget: float | None = flag(
        None,
        "stop this many seconds after msf-train starts (imports and set-up included), "
        "finishing the step and saving last.pth (exit 0, reported as 'stopped by "
        "--time-budget'): e.g. a minute short of a time-boxed session. Applies to this "
        "invocation only: it is not stored, so --resume runs on without it unless given again",
        type=positive_float,
        metavar="SECONDS",
    )
    snapshot_seconds: float = flag(
        0.0,
        "also keep snap_<step>.pth (fp16, ~4.5 MB) every this many seconds (default 0: none)",
        type=nonnegative_float,
        metavar="SECONDS",
    )
    extra: dict = field(default_factory=dict)

    def stored(self) -> dict:
        """What config.json records: every field but the limits of one invocation."""
        return {k: v for k, v in asdict(self).items() if k not in RUN_ONLY}

    def phase(self, epoch: int) -> Phase:
        phases = parse_curriculum(self.curriculum)
        return [p for p in phases if p.epoch <= epoch][-1]


# the fields without a flag, checked as their flag would (val_* are fixed for runs to compare)
_UNFLAGGED: dict[str, Callable[[str], object]] = {
    "out": path_text,
    "val_lights": int_range(MIN_LIGHTS, MAX_LIGHTS),
    "val_seed": nonnegative_int,
}
_KINDS = {
    bool: "true or false",
    int: "an integer",
    float: "a number",
    str: "text",
    dict: "an object",
}


def stored_value_problem(name: str, value: object) -> str | None:
    """What is wrong with ``value`` as config.json's ``name`` (a TrainConfig field), by the
    rules of the field's flag; None when nothing is. config.json is the run's editable record,
    so a hand-edited value must be refused like a typed one, not reach torch or numpy."""
    hint = _field_types()[name]
    args = get_args(hint)  # (int, NoneType) for "int | None"; () for a plain type
    kind = next((t for t in args if t is not type(None)), hint)
    if value is None:
        return None if type(None) in args else _expected(kind, value)
    # JSON numbers: an integer is a float's value too, but true / false is no number
    number = isinstance(value, (int, float) if kind is float else kind)
    if not (isinstance(value, bool) if kind is bool else number and not isinstance(value, bool)):
        return _expected(kind, value)
    spec = next(f.metadata.get("flag") for f in fields(TrainConfig) if f.name == name)
    if spec is not None and spec.choices is not None and value not in spec.choices:
        return f"must be one of {', '.join(spec.choices)}, got {json.dumps(value)}"
    check = _UNFLAGGED.get(name) if spec is None else spec.type
    if check is not None:
        try:
            check(str(value))
        except argparse.ArgumentTypeError as exc:
            # the flag's own words, with the JSON value in place of the quoted text
            return str(exc).replace(repr(str(value)), json.dumps(value))
    if name == "curriculum":
        try:
            parse_curriculum(str(value), source="")
        except InputError as exc:
            return exc.message.strip()
    return None


@functools.cache
def _field_types() -> dict[str, Any]:
    """TrainConfig's field types (its annotations are text: ``from __future__``)."""
    return get_type_hints(TrainConfig)


def _expected(kind: type, value: object) -> str:
    return f"must be {_KINDS.get(kind, kind.__name__)}, got {json.dumps(value)}"
