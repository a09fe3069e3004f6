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
import multiprocessing
import signal
import threading
import time
from collections.abc import Collection, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from msfnet.common.cpu import usable_cores
from msfnet.common.errors import InputError
from msfnet.common.files import STAGING_TAG, folder_lock, staged_files, to_jsonable, write_atomic
from msfnet.common.files.locks import LOCK_NAME
from msfnet.common.vocabulary import opt, verbatim
from msfnet.model.checkpoint import (
    check_state_dict,
    checkpoint_content,
    read_checkpoint,
    read_torch_file,
    save_checkpoint,
    torch_save,
)
from msfnet.model.data import (
    Batch,
    BlobbySource,
    SourceSpec,
    StepPlan,
    SynthSource,
    batch_from_dict,
    check_blobby_samples,
    find_blobby_samples,
    make_loader,
    raise_worker_error,
)
from msfnet.model.network import MSFNet
from msfnet.model.predict import autocast, predict_normals
from msfnet.model.train_config import SNAPSHOT, TrainConfig, parse_curriculum
from msfnet.runtime.evaluate.metrics import normal_metrics
from msfnet.runtime.infer.least_squares import least_squares_normals
from msfnet.runtime.stack import Stack
from msfnet.synth.render import RenderOptions, render_set

STAGE_WEIGHTS = (0.5, 0.5, 1.0)


# ----------------------------------------------------------------------------- losses


def cosine_loss(pred: Tensor, gt: Tensor, mask: Tensor) -> Tensor:
    """mean(1 - <pred, gt>) over mask pixels; pred, gt (B, 3, H, W), mask (B, H, W)."""
    cos = (pred.float() * gt.float()).sum(dim=1)
    m = mask.to(cos.dtype)
    return ((1.0 - cos) * m).sum() / m.sum().clamp_min(1.0)


def gradient_loss(pred: Tensor, gt: Tensor, mask: Tensor) -> Tensor:
    """Mean over horizontal and vertical neighbour pairs inside the mask of |d pred - d gt|_1
    (summed over the three components).

    The cosine loss barely notices a 1-3 px groove smoothed away (few pixels, small angles);
    this term scores the change from pixel to pixel, which is what such relief is made of."""
    p, g, m = pred.float(), gt.float(), mask.float()
    total = pred.new_zeros((), dtype=torch.float32)
    count = pred.new_zeros((), dtype=torch.float32)
    for dim in (2, 3):  # rows, columns of (B, 3, H, W); the mask is (B, H, W)
        n = p.shape[dim] - 1
        dp = p.narrow(dim, 1, n) - p.narrow(dim, 0, n)
        dg = g.narrow(dim, 1, n) - g.narrow(dim, 0, n)
        both = m.narrow(dim - 1, 1, n) * m.narrow(dim - 1, 0, n)
        total = total + ((dp - dg).abs().sum(dim=1) * both).sum()
        count = count + both.sum()
    return total / count.clamp_min(1.0)


def stage_losses(
    model: MSFNet,
    images: Tensor,
    lights: Tensor,
    normals: Tensor,
    mask: Tensor,
    grad_weight: float = 0.0,
    preds: list[Tensor] | None = None,
) -> list[Tensor]:
    """One loss per stage output (1 without MFE, else 3), through the shared regressor: the
    cosine loss, plus ``grad_weight`` x ``gradient_loss`` when that is above 0. ``preds``:
    a list that receives each stage's normal map."""
    out = []
    for m in model.pooled_features(images, lights):
        pred = model.regressor(m)
        if preds is not None:
            preds.append(pred)
        loss = cosine_loss(pred, normals, mask)
        if grad_weight > 0:
            loss = loss + grad_weight * gradient_loss(pred, normals, mask)
        out.append(loss)
    return out


def later_parameters(model: MSFNet) -> list[Tensor]:
    """Every trainable parameter outside extractor1 (what the middle loss may update under SUS)."""
    named = model.named_parameters()
    return [p for n, p in named if not n.startswith("extractor1.") and p.requires_grad]


def backward_losses(
    model: MSFNet,
    losses: Sequence[Tensor],
    sus: bool = True,
    weights: Sequence[float] = STAGE_WEIGHTS,
) -> Tensor:
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


def resolve_device(name: str) -> torch.device:
    """``auto`` = cuda when torch sees a GPU, else cpu; ``cuda`` without one is an error."""
    if name not in ("auto", "cpu", "cuda"):
        raise InputError(
            f"{opt('device', name, quote=True)}: choose auto, cpu or cuda", option="device"
        )
    if name == "cuda" and not torch.cuda.is_available():
        raise InputError(
            f"{opt('device', 'cuda')}: torch sees no CUDA GPU (a CPU-only torch build, or no "
            "driver)",
            option="device",
        )
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    return torch.device(name)


def default_workers(device: torch.device, cores: int | None = None) -> int:
    """Render workers: none on the CPU (the cores train; today's in-process source), and on a
    GPU all cores but two (the main process and the GPU feeder), at most 12."""
    if device.type != "cuda":
        return 0
    return max(0, min((usable_cores() if cores is None else cores) - 2, 12))


def stop_workers(timeout: float = 10.0, spare: Collection[object] = ()) -> int:
    """Stop the child processes still alive (DataLoader workers) after ``timeout`` seconds;
    returns how many had to be killed.

    Workers ignore SIGTERM (``data.worker_init``), so the terminate() that torch's and
    multiprocessing's shutdown fall back on cannot stop one that is stuck, and a stuck worker
    keeps the process alive long after it has saved. SIGKILL can."""
    deadline = time.monotonic() + timeout
    killed = 0
    for child in multiprocessing.active_children():
        if child in spare:
            continue
        child.join(max(0.0, deadline - time.monotonic()))
        if child.is_alive():
            child.kill()
            child.join(2.0)
            killed += 1
    return killed


def gpu_utilisation() -> float | None:
    """GPU busy percentage over the driver's last sample window, if NVML can tell."""
    try:
        return float(torch.cuda.utilization())
    except Exception:  # no pynvml / NVML: the data-wait fraction has to do
        return None


# ----------------------------------------------------------------------------- trainer


def snapshot_name(step: int) -> str:
    return f"snap_{step:07d}.pth"


# What a run writes besides weights: all a fresh run that failed before its first last.pth
# leaves that cannot be used (last_state.pth without last.pth cannot be resumed from).
RUN_FILES = ("config.json", "log.jsonl", "curve.png", "last_state.pth")


def trained_weights(out: Path) -> list[str]:
    """The weight files in ``out`` a run wrote (last.pth, best.pth, snapshots)."""
    return sorted(
        p.name
        for p in out.glob("*.pth")
        if p.is_file() and (p.name in ("last.pth", "best.pth") or SNAPSHOT.fullmatch(p.name))
    )


def json_row(row: dict) -> str:
    """One log.jsonl line: non-finite numbers as null (bare NaN is not JSON)."""
    return json.dumps(to_jsonable(row), allow_nan=False)


def _gt(stack: Stack) -> np.ndarray:
    """Validation objects are rendered: they always carry ground truth."""
    assert stack.normals_gt is not None
    return stack.normals_gt


@dataclass(frozen=True)
class TrainOutcome:
    """Where a training run ended."""

    step: int
    best_val_mae: float  # best held-out synthetic MAE so far (deg)
    val_ls_mae: float  # least squares on the same held-out set (deg)
    stopped: int | None = None  # the signal that stopped it early, if one did
    budget_spent: bool = False  # stopped early by --time-budget (last.pth saved)


@dataclass
class _Throughput:
    """Since ``start`` (perf_counter): time blocked on data and samples trained, over a log
    row's or an epoch's steps."""

    start: float
    wait: float = 0.0
    samples: int = 0


@dataclass
class _RunState:
    """What the training loop carries from step to step."""

    total: int  # the step the run ends at
    deadline: float | None  # --time-budget's end (time.monotonic), if any
    last_save: float  # time.monotonic() of the last save of last.pth
    last_snap: float  # time.monotonic() of the last --snapshot-seconds snapshot
    loss: float | None = None  # the running (exponentially smoothed) loss
    budget_spent: bool = False
    win: _Throughput = field(init=False)  # since the last log row
    ep: _Throughput = field(init=False)  # since the epoch began

    def __post_init__(self) -> None:
        self.win = _Throughput(time.perf_counter())
        self.ep = _Throughput(self.win.start)


class Trainer:
    def __init__(
        self, cfg: TrainConfig, resume: bool = False, started: float | None = None
    ) -> None:
        # --time-budget counts from ``started`` (msf-train's start: torch's import and the
        # set-up included, ~2.5 s a user's clock sees), else from here
        self.created = time.monotonic() if started is None else started
        self.cfg = cfg
        self.out = Path(cfg.out)
        self.device = resolve_device(cfg.device)
        self.workers = default_workers(self.device) if cfg.workers is None else cfg.workers
        if self.workers < 0:
            raise InputError(f"{opt('workers')} must be >= 0", option="workers")
        if cfg.render_on not in ("cpu", "device"):
            raise InputError(
                f"{opt('render_on', cfg.render_on, quote=True)}: choose cpu or device",
                option="render_on",
            )
        self.on_device = cfg.render_on == "device"
        if self.on_device:
            if cfg.data != "synth":
                raise InputError(
                    f"{opt('render_on', 'device')} renders synthetic data; drop {opt('data')}",
                    option="render_on",
                )
            self.workers = 0  # nothing to render on the CPU
        torch.set_num_threads(cfg.threads)
        torch.manual_seed(cfg.seed)
        self.model = MSFNet(mfe=cfg.mfe, mff=cfg.mff)
        if cfg.init and not resume:
            from msfnet.model.checkpoint import check_state_dict, read_state_dict

            state = read_state_dict(cfg.init)
            check_state_dict(self.model, state, cfg.init)
            self.model.load_state_dict(state, strict=True)
        cuda = self.device.type == "cuda"
        can_bf16 = torch.cuda.is_bf16_supported() if cuda else bf16_available()
        if cfg.precision == "bf16" and not can_bf16:
            raise InputError(
                f"{opt('precision', 'bf16')}: this {self.device.type.upper()}/torch cannot run "
                "bf16 autocast",
                option="precision",
            )
        self.bf16 = cfg.precision == "bf16" or (cfg.precision == "auto" and can_bf16)
        if cuda:
            # Input shapes repeat (a few light counts x crop sizes): let cuDNN pick kernels;
            # TF32 for whatever autocast leaves in fp32.
            torch.backends.cudnn.benchmark = True
            torch.backends.cuda.matmul.allow_tf32 = True
            torch.backends.cudnn.allow_tf32 = True
        self.model = self.model.to(self.device)
        if cfg.channels_last:
            self.model = self.model.to(memory_format=torch.channels_last)  # type: ignore[call-overload]
        self.opt = torch.optim.Adam(self.model.parameters(), lr=cfg.lr, betas=(0.9, 0.999))
        self.step = 0
        self.saved_step: int | None = None  # the step last.pth holds, once there is one
        self.best = math.inf
        self.history: list[dict] = []
        self.stop_signal: int | None = None  # set by SIGTERM / SIGINT during run()
        if resume:
            self._load()
        self.render_options = RenderOptions.preset(
            cfg.render_preset,
            size=cfg.render_size,
            lights=cfg.render_lights,
            max_depth=cfg.render_max_depth,
        )
        self.blobby_pairs: tuple[tuple[Path, Path], ...] | None = None
        if cfg.data != "synth":
            # indexed and checked here, before anything is written or trained: a list naming
            # a missing image, or fewer images than the curriculum's most lights, is refused
            # in one line instead of failing (or quietly training on fewer lights) mid-run
            pairs = find_blobby_samples(cfg.data)
            most = max(p.lights_max for p in parse_curriculum(cfg.curriculum))
            check_blobby_samples(pairs, most)
            self.blobby_pairs = tuple(pairs)
        self.source: SynthSource | BlobbySource | None = None
        if self.workers == 0 and not self.on_device:  # in-process; workers build their own
            if cfg.data == "synth":
                # Training objects start far from the validation seed space: seeds differ.
                self.source = SynthSource(
                    cfg.seed,
                    self.render_options,
                    cfg.pool,
                    cfg.refresh,
                    start=self.step * cfg.refresh,
                    max_size=cfg.render_size_max,
                )
            else:
                self.source = BlobbySource(cfg.data, pairs=self.blobby_pairs)
        val_opts = RenderOptions(size=cfg.val_size, lights=cfg.val_lights)
        self.val_set = list(render_set(cfg.val_seed, cfg.val_objects, val_opts))
        ls = [normal_metrics(least_squares_normals(s), _gt(s), s.mask) for s in self.val_set]
        self.val_ls = float(np.mean([m.mae_deg for m in ls]))

    # -- state
    def _state_paths(self) -> tuple[Path, Path]:
        return self.out / "last.pth", self.out / "last_state.pth"

    def save(self) -> None:
        """last.pth and last_state.pth, replaced together: a resume needs both of one step."""
        self._check_finite()
        weights, state = self._state_paths()
        content = checkpoint_content(self.model, step=self.step, epoch=self.epoch)
        optimiser = {"optimizer": self.opt.state_dict(), "step": self.step, "best": self.best}
        with staged_files([weights, state], overwrite=True) as (tmp_weights, tmp_state):
            torch_save(content, tmp_weights)
            torch_save(optimiser, tmp_state)
        self.saved_step = self.step

    def _diverged(self, what: str, step: int) -> InputError:
        """The error that ends a diverged run; nothing is saved over last.pth or best.pth."""
        kept = f"last.pth is left at step {self.saved_step}"
        if self.saved_step is None:
            kept = "nothing was saved"
        return InputError(
            f"training diverged: {what} at step {step} (a learning rate too high? "
            f"{opt('lr', verbatim(f'{self.cfg.lr:g}'))}); {kept}",
            self.out,
        )

    def _check_finite(self) -> None:
        """Refuse to write weights holding NaN / inf: they would replace a usable last.pth,
        best.pth or snapshot, and --resume refuses them anyway (one sync, at saves only)."""
        values = [v.detach() for v in self.model.state_dict().values() if v.is_floating_point()]
        peaks = torch.stack([v.abs().amax().float() for v in values if v.numel()])
        if not bool(torch.isfinite(peaks).all()):
            raise self._diverged("the weights are not finite", self.step)

    def _load(self) -> None:
        weights, state = self._state_paths()
        if not weights.is_file() or not state.is_file():
            raise InputError("nothing to resume: last.pth / last_state.pth missing", self.out)
        tensors, saved = read_checkpoint(weights)
        check_state_dict(self.model, tensors, weights)
        self.model.load_state_dict(tensors, strict=True)
        st = read_torch_file(state)
        if (
            not isinstance(st, dict)
            or not {"optimizer", "step", "best"} <= set(st)
            or not isinstance(st["step"], int)
            or not isinstance(st["best"], (int, float))
        ):
            raise InputError(
                "not an msf-train optimiser state (expected optimizer, step, best)", state
            )
        if saved is not None and saved != int(st["step"]):
            raise InputError(
                f"last.pth is from step {saved} but last_state.pth from step "
                f"{st['step']} (the run was stopped while saving); start a new "
                f"run with {opt('init')} on last.pth",
                self.out,
            )
        try:
            self.opt.load_state_dict(st["optimizer"])
        except (ValueError, KeyError, TypeError) as exc:
            raise InputError(
                f"the optimiser state does not fit this network ({exc})", state
            ) from exc
        # load_state_dict does not compare the moments' shapes with the parameters': a
        # damaged state would fail at the first step as an internal error
        for param in (p for group in self.opt.param_groups for p in group["params"]):
            for name, value in self.opt.state.get(param, {}).items():
                if isinstance(value, Tensor) and value.dim() > 0 and value.shape != param.shape:
                    raise InputError(
                        f"the optimiser state does not fit this network ({name} "
                        f"{tuple(value.shape)} for a parameter {tuple(param.shape)})",
                        state,
                    )
        self.step, self.best = int(st["step"]), float(st["best"])
        self.saved_step = self.step
        self.history = self._history_until(self.step)

    def _history_until(self, step: int) -> list[dict]:
        """log.jsonl's rows up to ``step`` (the saved state), the file rewritten to match: rows
        logged after the last save would come again after resuming, and a kill in mid-append
        leaves a torn last line."""
        log = self.out / "log.jsonl"
        if not log.is_file():
            return []
        rows = []
        for line in log.read_text().splitlines():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(row, dict) and row.get("step", 0) <= step:
                rows.append(row)
        write_atomic(log, lambda t: t.write_text("".join(json_row(r) + "\n" for r in rows)))
        return rows

    @property
    def epoch(self) -> int:
        return self.step // self.cfg.steps_per_epoch

    def lr_at(self, epoch: int) -> float:
        return self.cfg.lr * 0.5 ** (epoch // max(self.cfg.lr_step, 1))

    # -- data
    def _loader_batches(self, total: int):
        spec = SourceSpec(
            self.cfg.data,
            self.cfg.seed,
            self.render_options,
            self.cfg.pool,
            self.cfg.refresh,
            self.cfg.render_size_max,
            self.blobby_pairs,
        )
        phases = tuple(
            (p.epoch, p.lights_min, p.lights_max, p.crop)
            for p in parse_curriculum(self.cfg.curriculum)
        )
        plan = StepPlan(
            self.cfg.seed, self.cfg.batch, self.cfg.steps_per_epoch, phases, self.cfg.noise
        )
        loader = make_loader(
            spec, plan, self.step, total, self.workers, pin_memory=self.device.type == "cuda"
        )
        batches = iter(loader)
        try:
            for d in batches:
                raise_worker_error(d)  # a worker's bad data: the same one-line error
                if d["step"] != self.step:  # the round-robin order is what makes this hold
                    raise RuntimeError(f"data loader sent step {d['step']}, expected {self.step}")
                yield batch_from_dict(d), int(d["n_lights"]), int(d["crop"])
        finally:
            # Shut the workers down here, through torch. An exception leaving this generator
            # keeps its frame (and so the loader) alive in its traceback, so the loader would
            # not shut them down; stop_workers would then kill them, and torch's SIGCHLD
            # handler, still watching their pids, would replace the real error with "worker
            # killed". _shutdown_workers (private, in torch since 1.x) lets them exit, then
            # stops watching their pids before it terminates any that are left.
            shutdown = getattr(batches, "_shutdown_workers", None)
            if shutdown is not None:
                shutdown()

    def _local_batches(self, total: int):
        """Batches rendered in this process; step s's light count, picks, crops and
        augmentation come from a generator seeded with (seed, s), so a resumed run gets the
        batches an unbroken one would (with SynthSource's pool rebuilt for the step)."""
        cfg = self.cfg
        assert self.source is not None
        for step in range(self.step, total):
            rng = np.random.default_rng([cfg.seed, step])
            phase = cfg.phase(step // cfg.steps_per_epoch)
            lights = int(rng.integers(phase.lights_min, phase.lights_max + 1))
            yield (
                self.source.batch(cfg.batch, lights, phase.crop, rng, noise=cfg.noise),
                lights,
                phase.crop,
            )

    def _device_batches(self, total: int):
        """Batches rendered by the torch renderer on the training device: the batch of step
        s comes from a generator seeded with (seed, s), so a resumed run gets the same data."""
        from msfnet.synth import torch_render as tr

        cfg = self.cfg
        options = tr.TorchRenderOptions.preset(cfg.render_preset)
        gen = torch.Generator(device=self.device)
        while self.step < total:
            gen.manual_seed(tr.step_seed(cfg.seed, self.step))
            rng = np.random.default_rng([cfg.seed, 2, self.step])
            phase = cfg.phase(self.epoch)
            lights = int(rng.integers(phase.lights_min, phase.lights_max + 1))
            with torch.no_grad():  # (closed before the yield: grad mode is thread state)
                rendered = tr.render_batch(cfg.batch, lights, phase.crop, gen, options, self.device)
                batch = Batch(*tr.training_tensors(rendered, gen))
            yield batch, lights, phase.crop

    def to_device(self, batch: Batch) -> Batch:
        nb = self.device.type == "cuda"  # from pinned memory, the copy overlaps compute
        normals = batch.normals.to(self.device, non_blocking=nb)
        if self.cfg.channels_last:
            normals = normals.contiguous(memory_format=torch.channels_last)
        return Batch(
            batch.images.to(self.device, non_blocking=nb),
            batch.lights.to(self.device, non_blocking=nb),
            normals,
            batch.mask.to(self.device, non_blocking=nb),
        )

    # -- steps
    def train_step(self, batch) -> tuple[float, list[float]]:
        self.model.train()
        images, lights = batch.images, batch.lights
        self.opt.zero_grad(set_to_none=True)
        preds: list[Tensor] = []
        with autocast(self.bf16, self.device.type):
            losses = stage_losses(
                self.model, images, lights, batch.normals, batch.mask, self.cfg.grad_loss, preds
            )
            if self.cfg.consistency > 0:
                losses = self._with_consistency(batch, losses, preds)
        total = backward_losses(self.model, losses, sus=self.cfg.sus)
        loss = float(total)  # (the sync the log needs anyway)
        if not math.isfinite(loss):
            # before opt.step: a NaN/inf gradient would turn every weight into NaN
            raise self._diverged(f"the loss is not finite ({loss})", self.step + 1)
        self.opt.step()
        return loss, [float(x.detach()) for x in losses]

    def _with_consistency(
        self, batch: Batch, losses: list[Tensor], preds: list[Tensor]
    ) -> list[Tensor]:
        """--consistency: the batch turned one of 7 ways trains too (losses averaged), and the
        deep loss gains W x the disagreement of the two deep predictions (model.equivariance)."""
        from msfnet.model.equivariance import consistency_turn, turn_back, turn_batch

        k, flip = consistency_turn(self.cfg.seed, self.step)
        t = turn_batch(batch, k, flip)
        turned: list[Tensor] = []
        t_losses = stage_losses(
            self.model, t.images, t.lights, t.normals, t.mask, self.cfg.grad_loss, turned
        )
        agree = cosine_loss(turn_back(turned[-1], k, flip), preds[-1], batch.mask)
        out = [(a + b) / 2 for a, b in zip(losses, t_losses, strict=True)]
        out[-1] = out[-1] + self.cfg.consistency * agree
        return out

    def validate(self) -> float:
        maes = []
        for s in self.val_set:
            normals = predict_normals(self.model, s, bf16=self.bf16)
            if not np.isfinite(normals[s.mask]).all():
                # NaN normals score 180 deg, which would beat best = inf as a "best" model
                raise self._diverged("the validation normals are not finite", self.step)
            maes.append(normal_metrics(normals, _gt(s), s.mask).mae_deg)
        return float(np.mean(maes))

    def log(self, row: dict) -> None:
        self.history.append(row)
        path = self.out / "log.jsonl"
        try:
            with open(path, "a") as f:
                f.write(json_row(row) + "\n")
        except OSError as exc:  # a full disk: one line naming the file, not a bare errno
            if exc.filename is not None or exc.errno is None:
                raise
            raise OSError(exc.errno, exc.strerror, str(path)) from exc

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

    # -- stopping on a signal
    def _on_signal(self, signum: int, _frame: object) -> None:
        if self.stop_signal is not None:  # a second signal: stop now, without saving
            raise KeyboardInterrupt
        self.stop_signal = signum

    def _install_handlers(self) -> dict[int, Any]:
        """SIGTERM / SIGINT finish the current step, save last.pth and return (a GPU session
        cut into 10-minute chunks then resumes with --resume). Main thread only."""
        self.stop_signal = None
        if threading.current_thread() is not threading.main_thread():
            return {}
        return {sig: signal.signal(sig, self._on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}

    def run(self, progress: bool = True, report: bool = True) -> TrainOutcome:
        """Train to the configured end or a SIGTERM / SIGINT. ``progress``: the progress bar;
        ``report``: a line per epoch.

        OUT is held for the whole run (common.files.folder_lock): a second msf-train into it
        is refused instead of both replacing last.pth in turn and mixing their logs.

        A new run that fails before its first save (a full disk, say) leaves nothing that
        cannot be used: its config, log and optimiser state go, but trained weights
        (--snapshot-seconds / --snapshot-every snapshots, best.pth) are kept, with the config
        and log that tell how they were trained."""
        with folder_lock(self.out, "msf-train"):
            fresh = not any(p.name != LOCK_NAME for p in self.out.iterdir())
            try:
                return self._train(progress, report)
            except Exception:
                if fresh and not self._state_paths()[0].exists():
                    self._discard_unusable(report)
                raise

    def _discard_unusable(self, report: bool) -> None:
        """After a fresh run failed before its first last.pth: remove what it wrote, unless it
        wrote weights (then say what is left). The folder itself goes with the lock, which
        removes it if it created it and it is empty."""
        weights = trained_weights(self.out)
        if weights:
            if report:
                print(
                    f"msf-train: the run ended before its first last.pth; kept in {self.out}: "
                    f"{', '.join(weights)} (start a new run from one with {opt('init')})",
                    flush=True,
                )
            return
        for path in self.out.iterdir():
            if path.name in RUN_FILES or STAGING_TAG in path.name:
                path.unlink(missing_ok=True)

    def _train(self, progress: bool, report: bool) -> TrainOutcome:
        self._write_config()
        total = self.cfg.epochs * self.cfg.steps_per_epoch
        last_save = time.monotonic()
        bar = self._progress_bar(total, progress)
        old_handlers = self._install_handlers()
        before = set(multiprocessing.active_children())  # not ours to stop afterwards
        batches = self._batches(total)
        # --time-budget: stop like a signal would (save, return) once it is spent
        budget = self.cfg.time_budget
        deadline = None if budget is None else self.created + budget
        run = _RunState(total, deadline, last_save, last_snap=time.monotonic())
        try:
            self._run_steps(run, batches, bar, report)
            if self.stop_signal is not None:
                self.save()
                name = signal.Signals(self.stop_signal).name
                self.log({"step": self.step, "stopped": name, "time": time.time()})
        finally:
            self._end_run(batches, before, old_handlers, bar)
        return TrainOutcome(self.step, self.best, self.val_ls, self.stop_signal, run.budget_spent)

    def _write_config(self) -> None:
        """Create OUT and write config.json (the configuration this run trains with)."""
        cfg = self.cfg
        self.out.mkdir(parents=True, exist_ok=True)
        write_atomic(
            self.out / "config.json", lambda t: t.write_text(json.dumps(cfg.stored(), indent=1))
        )

    def _progress_bar(self, total: int, progress: bool) -> Any:
        """The tqdm progress bar over the run's steps (disabled unless ``progress``)."""
        from tqdm import tqdm

        bar = {"desc": "train", "unit": "step", "mininterval": 5.0, "dynamic_ncols": True}
        return tqdm(total=total, initial=self.step, disable=not progress, **bar)

    def _batches(self, total: int) -> Iterator[tuple[Batch, int, int]]:
        """(batch, lights, crop) per step up to ``total``: rendered on the device, by loader
        workers or in this process."""
        if self.on_device:
            return self._device_batches(total)
        if self.workers > 0:
            return self._loader_batches(total)
        return self._local_batches(total)

    def _run_steps(
        self, run: _RunState, batches: Iterator[tuple[Batch, int, int]], bar: Any, report: bool
    ) -> None:
        """The training loop: steps until the end, a signal, the time budget or the end of
        the batches, with logging, epoch ends and periodic saves along the way."""
        cfg = self.cfg
        while self.step < run.total and self.stop_signal is None:
            if run.deadline is not None and time.monotonic() >= run.deadline:
                self.log({"step": self.step, "stopped": "time_budget", "time": time.time()})
                self.save()
                run.budget_spent = True
                break
            epoch = self.epoch
            for g in self.opt.param_groups:
                g["lr"] = self.lr_at(epoch)
            t0 = time.perf_counter()
            got = self._next_batch(batches)
            if got is None:
                break
            batch, lights, crop = got
            batch = self.to_device(batch)
            waited = time.perf_counter() - t0
            for acc in (run.win, run.ep):
                acc.wait += waited
                acc.samples += cfg.batch
            loss, parts = self.train_step(batch)
            self.step += 1
            self._timed_snapshot(run)
            run.loss = loss if run.loss is None else 0.95 * run.loss + 0.05 * loss
            bar.update(1)
            bar.set_postfix(loss=f"{run.loss:.4f}", ep=epoch, n=lights, crop=crop)
            if self.step % cfg.log_every == 0:
                self._log_steps(run, epoch, loss, parts, lights, crop)
            if self.step % cfg.steps_per_epoch == 0 or self.step == run.total:
                self._end_epoch(run, epoch, bar, report)
            elif time.monotonic() - run.last_save > cfg.ckpt_minutes * 60:
                self.save()
                run.last_save = time.monotonic()

    def _next_batch(
        self, batches: Iterator[tuple[Batch, int, int]]
    ) -> tuple[Batch, int, int] | None:
        """The next (batch, lights, crop); None when the batches ran out, or when fetching
        failed after a signal (the workers were killed along with us)."""
        try:
            return next(batches)
        except StopIteration:
            return None
        except Exception:
            if self.stop_signal is None:
                raise
            return None  # workers killed along with us (a signal to the process group)

    def _timed_snapshot(self, run: _RunState) -> None:
        """--snapshot-seconds: an fp16 snapshot once that many seconds passed since the last."""
        cfg = self.cfg
        if cfg.snapshot_seconds and time.monotonic() - run.last_snap >= cfg.snapshot_seconds:
            # fp16: small enough to copy out of a time-boxed GPU session
            self._check_finite()
            save_checkpoint(
                self.model, self.out / snapshot_name(self.step), fp16=True, step=self.step
            )
            run.last_snap = time.monotonic()

    def _log_steps(
        self, run: _RunState, epoch: int, loss: float, parts: list[float], lights: int, crop: int
    ) -> None:
        """Every --log-every steps: a log row with the loss and the throughput since the last."""
        cfg = self.cfg
        now = time.perf_counter()
        win = run.win
        span = now - win.start
        row = {
            "step": self.step,
            "epoch": epoch,
            "loss": loss,
            "stages": parts,
            "lights": lights,
            "crop": crop,
            "lr": self.lr_at(epoch),
            "s_per_step": span / cfg.log_every,
            "samples_per_s": win.samples / span,
            "data_wait": win.wait / span,
            "time": time.time(),
        }
        if self.device.type == "cuda":
            row["gpu_util"] = gpu_utilisation()
        self.log(row)
        run.win = _Throughput(now)

    def _end_epoch(self, run: _RunState, epoch: int, bar: Any, report: bool) -> None:
        """At an epoch's end: validate, log (and with ``report`` print) the epoch's row, keep
        the snapshot / best.pth it earns, then save last.pth and the curve."""
        ep = run.ep
        span = time.perf_counter() - ep.start
        mae = self.validate()
        speed = {"samples_per_s": ep.samples / span, "data_wait": ep.wait / span}
        util = gpu_utilisation() if self.device.type == "cuda" else None
        if util is not None:
            speed["gpu_util"] = util
        row = {"step": self.step, "epoch": epoch + 1, "val_mae": mae, "val_ls_mae": self.val_ls}
        self.log({**row, **speed, "time": time.time()})
        gpu = f", GPU {util:.0f} %" if util is not None else ""
        if report:
            bar.write(
                f"epoch {epoch + 1}: val MAE {mae:.2f} deg (least "
                f"squares {self.val_ls:.2f}), loss {run.loss:.4f}, "
                f"{speed['samples_per_s']:.1f} samples/s, data wait "
                f"{100 * speed['data_wait']:.0f} %{gpu}"
            )
        self._keep_epoch_weights(epoch, mae)
        self.save()
        self.plot()
        run.last_save = time.monotonic()
        run.ep = _Throughput(time.perf_counter())

    def _keep_epoch_weights(self, epoch: int, mae: float) -> None:
        """The epoch's --snapshot-every snapshot, and best.pth when ``mae`` is the best yet."""
        cfg = self.cfg
        if cfg.snapshot_every and (epoch + 1) % cfg.snapshot_every == 0:
            # Synthetic validation does not rank real objects reliably: keep
            # snapshots to select on real validation objects afterwards.
            self._check_finite()
            snap = self.out / snapshot_name(self.step)
            save_checkpoint(self.model, snap, step=self.step, val_mae=mae)
        if math.isfinite(mae) and mae < self.best:  # NaN is never "best"
            self.best = mae
            self._check_finite()
            save_checkpoint(self.model, self.out / "best.pth", step=self.step, val_mae=mae)

    def _end_run(
        self,
        batches: Iterator[tuple[Batch, int, int]],
        before: set[multiprocessing.process.BaseProcess],
        old_handlers: dict[int, Any],
        bar: Any,
    ) -> None:
        """However the run ended: stop the batch source and its workers, put the signal
        handlers back and close the progress bar."""
        close = getattr(batches, "close", None)
        if close is not None:
            close()  # shuts the DataLoader's workers down
        if self.workers > 0:
            stop_workers(spare=before)
        for sig, handler in old_handlers.items():
            signal.signal(sig, handler)
        bar.close()
