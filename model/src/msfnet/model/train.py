"""MSF-Net training: three stage losses through the shared regressor and the selective update.

Losses: the regressor turns each stage's max-pooled feature (m1, m2, m3) into a normal map; each
is scored by the cosine loss mean(1 - <n_pred, n_gt>) over mask pixels, weighted 0.5 : 0.5 : 1.
Selective update (SUS): the shallow loss trains extractor1 + regressor, the deep loss trains
everything, and the middle loss trains every module *except* extractor1. The middle loss is
back-propagated with ``inputs=`` restricted to the non-extractor1 parameters, which gives exactly
the gradients of detaching extractor1's output for that loss (the other parameters' gradients do
not depend on whether gradient continues into extractor1), without a second forward pass.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from msfnet.runtime.errors import InputError
from msfnet.runtime.files import write_atomic
from msfnet.runtime.least_squares import least_squares_normals
from msfnet.runtime.metrics import normal_metrics
from msfnet.synth.render import RenderOptions, render_set

from .checkpoint import save_checkpoint
from .data import BlobbySource, SynthSource
from .network import MSFNet
from .predict import autocast, predict_normals

STAGE_WEIGHTS = (0.5, 0.5, 1.0)


# ----------------------------------------------------------------------------- losses

def cosine_loss(pred: Tensor, gt: Tensor, mask: Tensor) -> Tensor:
    """mean(1 - <pred, gt>) over mask pixels; pred, gt (B, 3, H, W), mask (B, H, W)."""
    cos = (pred.float() * gt.float()).sum(dim=1)
    m = mask.to(cos.dtype)
    return ((1.0 - cos) * m).sum() / m.sum().clamp_min(1.0)


def stage_losses(model: MSFNet, images: Tensor, lights: Tensor, normals: Tensor,
                 mask: Tensor) -> list[Tensor]:
    """One cosine loss per stage output (1 without MFE, else 3), through the shared regressor."""
    return [cosine_loss(model.regressor(m), normals, mask)
            for m in model.pooled_features(images, lights)]


def later_parameters(model: MSFNet) -> list[Tensor]:
    """Every trainable parameter outside extractor1 (what the middle loss may update under SUS)."""
    return [p for n, p in model.named_parameters()
            if not n.startswith("extractor1.") and p.requires_grad]


def backward_losses(model: MSFNet, losses: Sequence[Tensor], sus: bool = True,
                    weights: Sequence[float] = STAGE_WEIGHTS) -> Tensor:
    """Accumulate gradients of the weighted stage losses; returns the weighted total (detached)."""
    if len(losses) == 1:
        losses[0].backward()
        return losses[0].detach()
    w1, w2, w3 = weights
    total = w1 * losses[0] + w2 * losses[1] + w3 * losses[2]
    if not sus:
        total.backward()
        return total.detach()
    # Middle loss first, restricted to the later modules; the graph is kept for the rest.
    torch.autograd.backward(w2 * losses[1], inputs=later_parameters(model), retain_graph=True)
    (w1 * losses[0] + w3 * losses[2]).backward()
    return total.detach()


# ----------------------------------------------------------------------------- config

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
        raise InputError(f"--curriculum {spec!r}: expected EPOCH:LMIN-LMAX:CROP[,...] "
                         "like 0:8-16:32,4:16-32:32") from exc
    phases.sort(key=lambda p: p.epoch)
    for p in phases:
        if p.lights_min < 1 or p.lights_max < p.lights_min or p.crop < 8 or p.crop % 4:
            raise InputError(f"--curriculum {spec!r}: need 1 <= LMIN <= LMAX and CROP a "
                             "multiple of 4 (>= 8)")
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
    data: str = "synth"  # "synth" or a Blobby/Sculpture root folder
    init: str | None = None  # start from these weights (fresh optimiser), e.g. the bundled model
    render_size: int = 64
    render_size_max: int | None = None  # sizes drawn from [render_size, render_size_max]
    render_max_depth: float = RenderOptions.max_depth
    render_lights: int = 40
    pool: int = 48
    refresh: int = 2
    noise: float = 0.01
    val_objects: int = 8
    val_size: int = 64
    val_lights: int = 32
    val_seed: int = 999_999
    ckpt_minutes: float = 10.0
    log_every: int = 10
    extra: dict = field(default_factory=dict)

    def phase(self, epoch: int) -> Phase:
        phases = parse_curriculum(self.curriculum)
        return [p for p in phases if p.epoch <= epoch][-1]


def bf16_available() -> bool:
    """True when bf16 autocast runs on this CPU (AVX512-BF16 / AMX); checked by a tiny conv."""
    try:
        if not torch.ops.mkldnn._is_mkldnn_bf16_supported():
            return False
        conv = torch.nn.Conv2d(3, 4, 3)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            conv(torch.zeros(1, 3, 8, 8)).sum()
        return True
    except Exception:  # any failure means: use fp32
        return False


# ----------------------------------------------------------------------------- trainer

class Trainer:
    def __init__(self, cfg: TrainConfig, resume: bool = False) -> None:
        self.cfg = cfg
        self.out = Path(cfg.out)
        torch.set_num_threads(cfg.threads)
        torch.manual_seed(cfg.seed)
        self.model = MSFNet(mfe=cfg.mfe, mff=cfg.mff)
        if cfg.init and not resume:
            from .checkpoint import check_state_dict, read_state_dict

            state = read_state_dict(cfg.init)
            check_state_dict(self.model, state, cfg.init)
            self.model.load_state_dict(state, strict=True)
        if cfg.precision == "bf16" and not bf16_available():
            raise InputError("--precision bf16: this CPU/torch cannot run bf16 autocast")
        self.bf16 = cfg.precision == "bf16" or (cfg.precision == "auto" and bf16_available())
        if cfg.channels_last:
            self.model = self.model.to(memory_format=torch.channels_last)
        self.opt = torch.optim.Adam(self.model.parameters(), lr=cfg.lr, betas=(0.9, 0.999))
        self.step = 0
        self.best = math.inf
        self.history: list[dict] = []
        if resume:
            self._load()
        if cfg.data == "synth":
            options = RenderOptions(size=cfg.render_size, lights=cfg.render_lights,
                                    max_depth=cfg.render_max_depth)
            # Training objects start far from the validation seed space: seeds differ anyway.
            self.source = SynthSource(cfg.seed, options, cfg.pool, cfg.refresh,
                                      start=self.step * cfg.refresh,
                                      max_size=cfg.render_size_max)
        else:
            self.source = BlobbySource(cfg.data)
        val_opts = RenderOptions(size=cfg.val_size, lights=cfg.val_lights)
        self.val_set = list(render_set(cfg.val_seed, cfg.val_objects, val_opts))
        self.val_ls = float(np.mean([normal_metrics(least_squares_normals(s), s.normals_gt,
                                                    s.mask).mae_deg for s in self.val_set]))

    # -- state
    def _state_paths(self) -> tuple[Path, Path]:
        return self.out / "last.pth", self.out / "last_state.pth"

    def save(self) -> None:
        weights, state = self._state_paths()
        save_checkpoint(self.model, weights, step=self.step, epoch=self.epoch)
        tmp = state.with_name(f".{state.name}.tmp")
        torch.save({"optimizer": self.opt.state_dict(), "step": self.step, "best": self.best},
                   tmp)
        tmp.replace(state)

    def _load(self) -> None:
        from .checkpoint import read_state_dict

        weights, state = self._state_paths()
        if not weights.is_file() or not state.is_file():
            raise InputError("nothing to resume: last.pth / last_state.pth missing", self.out)
        self.model.load_state_dict(read_state_dict(weights), strict=True)
        st = torch.load(state, map_location="cpu", weights_only=True)
        self.opt.load_state_dict(st["optimizer"])
        self.step, self.best = int(st["step"]), float(st["best"])
        log = self.out / "log.jsonl"
        if log.is_file():
            rows = [json.loads(x) for x in log.read_text().splitlines() if x.strip()]
            self.history = [r for r in rows if r.get("step", 0) <= self.step]

    @property
    def epoch(self) -> int:
        return self.step // self.cfg.steps_per_epoch

    def lr_at(self, epoch: int) -> float:
        return self.cfg.lr * 0.5 ** (epoch // max(self.cfg.lr_step, 1))

    # -- steps
    def train_step(self, batch) -> tuple[float, list[float]]:
        self.model.train()
        images, lights = batch.images, batch.lights
        self.opt.zero_grad(set_to_none=True)
        with autocast(self.bf16):
            losses = stage_losses(self.model, images, lights, batch.normals, batch.mask)
        total = backward_losses(self.model, losses, sus=self.cfg.sus)
        self.opt.step()
        return float(total), [float(x.detach()) for x in losses]

    def validate(self) -> float:
        maes = [normal_metrics(predict_normals(self.model, s, bf16=self.bf16), s.normals_gt,
                               s.mask).mae_deg for s in self.val_set]
        return float(np.mean(maes))

    def log(self, row: dict) -> None:
        self.history.append(row)
        with open(self.out / "log.jsonl", "a") as f:
            f.write(json.dumps(row) + "\n")

    def plot(self) -> None:
        try:
            import matplotlib

            matplotlib.use("Agg")
            import matplotlib.pyplot as plt
        except ImportError:
            return
        tr = [r for r in self.history if "loss" in r]
        va = [r for r in self.history if "val_mae" in r]
        fig, ax = plt.subplots(1, 2, figsize=(10, 3.5))
        if tr:
            ax[0].plot([r["step"] for r in tr], [r["loss"] for r in tr], lw=0.8)
        ax[0].set(xlabel="step", ylabel="weighted loss", yscale="log", title="training loss")
        if va:
            ax[1].plot([r["step"] for r in va], [r["val_mae"] for r in va], "o-", label="MSF-Net")
            ax[1].axhline(self.val_ls, color="gray", ls="--", label="least squares")
            ax[1].legend()
        ax[1].set(xlabel="step", ylabel="MAE (deg)", title="held-out synthetic MAE")
        fig.tight_layout()
        write_atomic(self.out / "curve.png", lambda t: fig.savefig(t, dpi=100, format="png"))
        plt.close(fig)

    def run(self, progress: bool = True) -> dict:
        from tqdm import tqdm

        cfg = self.cfg
        self.out.mkdir(parents=True, exist_ok=True)
        write_atomic(self.out / "config.json",
                     lambda t: t.write_text(json.dumps(asdict(cfg), indent=1)))
        total = cfg.epochs * cfg.steps_per_epoch
        last_save = time.monotonic()
        rng = np.random.default_rng([cfg.seed, self.step])
        bar = tqdm(total=total, initial=self.step, desc="train", unit="step", disable=not progress,
                   mininterval=5.0, dynamic_ncols=True)
        run_loss, t_step = None, time.perf_counter()
        while self.step < total:
            epoch, phase = self.epoch, cfg.phase(self.epoch)
            for g in self.opt.param_groups:
                g["lr"] = self.lr_at(epoch)
            lights = int(rng.integers(phase.lights_min, phase.lights_max + 1))
            batch = self.source.batch(cfg.batch, lights, phase.crop, rng, noise=cfg.noise)
            if cfg.channels_last:
                batch.normals = batch.normals.contiguous(memory_format=torch.channels_last)
            loss, parts = self.train_step(batch)
            self.step += 1
            run_loss = loss if run_loss is None else 0.95 * run_loss + 0.05 * loss
            bar.update(1)
            bar.set_postfix(loss=f"{run_loss:.4f}", ep=epoch, n=lights, crop=phase.crop)
            if self.step % cfg.log_every == 0:
                now = time.perf_counter()
                self.log({"step": self.step, "epoch": epoch, "loss": loss, "stages": parts,
                          "lights": lights, "crop": phase.crop, "lr": self.lr_at(epoch),
                          "s_per_step": (now - t_step) / cfg.log_every, "time": time.time()})
                t_step = now
            if self.step % cfg.steps_per_epoch == 0 or self.step == total:
                mae = self.validate()
                self.log({"step": self.step, "epoch": epoch + 1, "val_mae": mae,
                          "val_ls_mae": self.val_ls, "time": time.time()})
                bar.write(f"epoch {epoch + 1}: val MAE {mae:.2f} deg (least squares "
                          f"{self.val_ls:.2f}), loss {run_loss:.4f}")
                if mae < self.best:
                    self.best = mae
                    save_checkpoint(self.model, self.out / "best.pth", step=self.step,
                                    val_mae=mae)
                self.save()
                self.plot()
                last_save = time.monotonic()
            elif time.monotonic() - last_save > cfg.ckpt_minutes * 60:
                self.save()
                last_save = time.monotonic()
        bar.close()
        return {"step": self.step, "best_val_mae": self.best, "val_ls_mae": self.val_ls}
