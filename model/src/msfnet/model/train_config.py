"""msf-train's options as typed data: the run configuration (stored as OUT/config.json) and
the light-count / crop curriculum. Kept apart from the training loop so the command line can be
parsed, and refused, without importing torch."""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from msfnet.common.errors import InputError
from msfnet.runtime.stack.types import MIN_LIGHTS
from msfnet.synth.render import RenderOptions

SNAPSHOT = re.compile(r"snap_\d{7}\.pth")  # what --snapshot-every writes, and nothing else


@dataclass
class Phase:
    """From ``epoch`` on: light counts drawn from [lights_min, lights_max], crops of ``crop``."""

    epoch: int
    lights_min: int
    lights_max: int
    crop: int


def parse_curriculum(spec: str) -> list[Phase]:
    """``"0:8-16:32,4:16-32:32"`` -> phases (start epoch : lights range : crop size)."""
    phases = []
    try:
        for part in spec.split(","):
            e, lights, crop = part.strip().split(":")
            lo, _, hi = lights.partition("-")
            phases.append(Phase(int(e), int(lo), int(hi or lo), int(crop)))
    except ValueError as exc:
        raise InputError(
            f"--curriculum {spec!r}: expected EPOCH:LMIN-LMAX:CROP[,...] like 0:8-16:32,4:16-32:32"
        ) from exc
    phases.sort(key=lambda p: p.epoch)
    for p in phases:
        if p.lights_min < MIN_LIGHTS or p.lights_max < p.lights_min or p.crop < 8 or p.crop % 4:
            raise InputError(
                f"--curriculum {spec!r}: need {MIN_LIGHTS} <= LMIN <= LMAX (photometric "
                "stereo's fewest lights) and CROP a multiple of 4 (>= 8)"
            )
    if not phases or phases[0].epoch != 0:
        raise InputError(f"--curriculum {spec!r}: the first phase must start at epoch 0")
    return phases


@dataclass
class TrainConfig:
    out: str
    epochs: int = 20
    steps_per_epoch: int = 300
    batch: int = 8
    curriculum: str = "0:16-32:32"
    lr: float = 1e-3
    lr_step: int = 5  # halve the learning rate every lr_step epochs
    seed: int = 0
    threads: int = 2
    precision: str = "auto"  # auto | bf16 | fp32
    channels_last: bool = True
    mfe: bool = True
    mff: bool = True
    sus: bool = True
    grad_loss: float = 0.0  # weight of gradient_loss beside the cosine loss (0: the paper's)
    consistency: float = 0.0  # weight of the rotation-consistency term (model.equivariance)
    data: str = "synth"  # "synth" or a Blobby/Sculpture root folder
    init: str | None = None  # start from these weights (fresh optimiser), e.g. the bundled model
    render_size: int = 64
    render_size_max: int | None = None  # sizes drawn from [render_size, render_size_max]
    render_max_depth: float = RenderOptions.max_depth
    render_preset: str = "default"  # "default" or "hard" (msfnet.synth RenderOptions.preset)
    render_lights: int = 40
    pool: int = 48
    refresh: int = 2
    noise: float = 0.01
    val_objects: int = 8
    val_size: int = 64
    val_lights: int = 32
    val_seed: int = 999_999
    ckpt_minutes: float = 10.0
    snapshot_every: int = 0  # keep snap_<step>.pth every this many epochs (0: none)
    log_every: int = 10
    device: str = "auto"  # auto | cpu | cuda
    workers: int | None = None  # DataLoader worker processes; None = default_workers(device)
    # "cpu": the numpy renderer (in process or in workers); "device": the torch renderer
    # (msfnet.synth.torch_render) on the training device itself
    render_on: str = "cpu"
    time_budget: float | None = None  # stop (and save) this many seconds after the Trainer was made
    snapshot_seconds: float = 0.0  # also keep snap_<step>.pth (fp16) this often (0: never)
    extra: dict = field(default_factory=dict)

    def phase(self, epoch: int) -> Phase:
        phases = parse_curriculum(self.curriculum)
        return [p for p in phases if p.epoch <= epoch][-1]
