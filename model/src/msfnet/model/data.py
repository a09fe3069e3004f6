"""Training data: random crops and light subsets of stacks, as normalised network batches.

Sources hand out ``Stack`` objects (raw images + lights + intensities + mask + normals_gt):
- ``SynthSource``: the built-in renderer behind a small pool that is refreshed a few stacks per
  batch, so rendering costs a fraction of a training step (each stack serves several crops,
  light subsets and rotations);
- ``BlobbySource``: the public Blobby / Sculpture photometric-stereo training sets.
Samples are normalised with ``msfnet.runtime.infer.normalise.normalise`` itself (crop first: the
normalisation is per pixel, so cropping commutes with it).

``StepStream`` moves all of this into DataLoader worker processes (for a GPU, which one process
cannot keep fed): worker w of W renders its own objects and builds the batches of steps
start + w, start + w + W, ..., which the DataLoader hands back round-robin, i.e. in step order.
"""

from __future__ import annotations

import signal
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Protocol

import numpy as np
import torch

from msfnet.common.errors import InputError
from msfnet.common.imageio import read_image
from msfnet.common.vocabulary import opt
from msfnet.runtime.contract import TRAIN_LIGHTS
from msfnet.runtime.infer.normalise import normalise
from msfnet.runtime.stack import MIN_LIGHTS, Stack, as_held, read_normals, unit_lights
from msfnet.synth.render import RenderOptions, render_stack


@dataclass
class Batch:
    images: torch.Tensor  # (B, N, 3, c, c) normalised network input
    lights: torch.Tensor  # (B, N, 3)
    normals: torch.Tensor  # (B, 3, c, c) ground truth
    mask: torch.Tensor  # (B, c, c) bool


# ----------------------------------------------------------------------------- augmentation


def rotate_flip(
    images: np.ndarray,
    normals: np.ndarray,
    mask: np.ndarray,
    lights: np.ndarray,
    k: int,
    flip: bool,
) -> tuple[np.ndarray, ...]:
    """Rotate the scene k x 90 deg counter-clockwise about the view axis, then mirror left-right.

    Both are symmetries of orthographic photometric stereo with isotropic materials, provided
    normals and lights turn with the image: (x, y) -> (-y, x) per quarter turn, x -> -x on flip.
    images (N, H, W, 3), normals (H, W, 3), mask (H, W), lights (N, 3).
    """
    images = np.rot90(images, k, axes=(1, 2))
    normals = np.rot90(normals, k, axes=(0, 1)).copy()
    mask = np.rot90(mask, k, axes=(0, 1))
    lights = lights.copy()
    for _ in range(k % 4):
        normals[..., 0], normals[..., 1] = -normals[..., 1], normals[..., 0].copy()
        lights[:, 0], lights[:, 1] = -lights[:, 1], lights[:, 0].copy()
    if flip:
        images, normals, mask = images[:, :, ::-1], normals[:, ::-1].copy(), mask[:, ::-1]
        normals[..., 0] *= -1
        lights[:, 0] *= -1
    return images, normals, mask, lights


def random_crop(
    stack: Stack, crop: int, rng: np.random.Generator, min_fill: float = 0.3, tries: int = 6
) -> tuple[int, int]:
    """Top-left corner of a crop holding at least ``min_fill`` object pixels (best of a few)."""
    h, w = stack.shape
    best, best_fill = (0, 0), -1.0
    for _ in range(tries):
        r, c = int(rng.integers(0, h - crop + 1)), int(rng.integers(0, w - crop + 1))
        fill = float(stack.mask[r : r + crop, c : c + crop].mean())
        if fill >= min_fill:
            return r, c
        if fill > best_fill:
            best, best_fill = (r, c), fill
    return best


def make_sample(
    stack: Stack,
    lights: int,
    crop: int,
    rng: np.random.Generator,
    noise: float = 0.01,
    calib_jitter: float = 0.02,
    train_lights: int = TRAIN_LIGHTS,
) -> tuple[np.ndarray, ...]:
    """One augmented training sample: (input (N,3,c,c), lights (N,3), normals (3,c,c), mask)."""
    where = stack.source or stack.name
    if stack.normals_gt is None:
        raise InputError("training needs ground-truth normals", where)
    h, w = stack.shape
    if crop > min(h, w):
        raise InputError(f"crop {crop} is larger than the stack ({w}x{h})", where)
    if lights < MIN_LIGHTS:  # fewer lights cannot determine a normal: nothing to learn from
        raise InputError(
            f"a training sample of {lights} light(s): photometric stereo needs at least "
            f"{MIN_LIGHTS}",
            where,
        )
    if lights > stack.num_lights:
        # never fewer lights than asked: the log would report a count the network never saw,
        # and samples of different counts cannot be stacked into one batch
        raise InputError(
            f"a training sample of {lights} lights, but the stack has only {stack.num_lights}",
            where,
        )
    r, c = random_crop(stack, crop, rng)
    idx = rng.choice(stack.num_lights, size=lights, replace=False)
    imgs = stack.images[idx, r : r + crop, c : c + crop]
    imgs, normals, mask, dirs = rotate_flip(
        imgs,
        stack.normals_gt[r : r + crop, c : c + crop],
        stack.mask[r : r + crop, c : c + crop],
        stack.lights[idx],
        int(rng.integers(4)),
        bool(rng.integers(2)),
    )
    imgs = np.array(imgs, np.float32)
    if noise > 0:  # extra sensor-like noise on top of whatever the data already has
        scale = float(np.percentile(imgs, 95)) + 1e-6
        sigma = rng.uniform(0, noise) * scale
        imgs += rng.standard_normal(imgs.shape, np.float32) * np.float32(sigma)
        np.clip(imgs, 0, None, out=imgs)
    ints = stack.intensities[idx]
    if calib_jitter > 0:  # imperfect intensity calibration, as on real rigs
        ints = ints * np.exp(rng.normal(0, calib_jitter, ints.shape)).astype(np.float32)
    x = normalise(imgs, ints, mask, train_lights)
    normals = np.ascontiguousarray(normals.transpose(2, 0, 1))
    return x, dirs.astype(np.float32), normals, np.ascontiguousarray(mask)


def collate(samples: list[tuple[np.ndarray, ...]]) -> Batch:
    return Batch(*(torch.from_numpy(np.stack([s[i] for s in samples])) for i in range(4)))


# ----------------------------------------------------------------------------- sources


class SynthSource:
    """Rendered stacks from a pool; ``refresh`` new ones replace the oldest per batch.

    ``max_size`` > ``options.size`` draws each object's size from that range: the same shapes
    at more pixels are smoother per pixel, as real objects filmed at full resolution are (a
    network trained only on small renders expects too much curvature per pixel).
    """

    def __init__(
        self,
        seed: int | Sequence[int],
        options: RenderOptions,
        pool: int = 48,
        refresh: int = 2,
        start: int = 0,
        max_size: int | None = None,
    ) -> None:
        # A sequence seed gives each DataLoader worker its own stream of objects.
        self.seed = [seed] if isinstance(seed, int) else list(seed)
        self.options, self.refresh = options, refresh
        self.sizes = (options.size, max(options.size, max_size or options.size))
        # The pool after b batches holds objects b * refresh .. b * refresh + pool - 1, object k
        # in slot k % pool (each batch's new objects replace the oldest). ``start`` = b *
        # refresh rebuilds exactly that pool: a resumed run picks the objects an unbroken one
        # would have.
        self.counter = start  # index of the next object to render
        slots: list[Stack | None] = [None] * pool
        for _ in range(pool):
            slots[self.counter % pool] = self._render()
        self.pool: list[Stack] = [s for s in slots if s is not None]

    def _render(self) -> Stack:
        rng = np.random.default_rng([*self.seed, self.counter])
        options = self.options
        if self.sizes[1] > self.sizes[0]:
            options = replace(options, size=int(rng.integers(self.sizes[0], self.sizes[1] + 1)))
        stack = render_stack(rng, options, name=f"train{self.counter}")
        self.counter += 1
        return stack

    def batch(
        self, size: int, lights: int, crop: int, rng: np.random.Generator, **augment: float
    ) -> Batch:
        for _ in range(self.refresh):
            self.pool[self.counter % len(self.pool)] = self._render()
        picks = rng.choice(len(self.pool), size=size, replace=size > len(self.pool))
        stacks = [self.pool[i] for i in picks]
        return collate([make_sample(s, lights, crop, rng, **augment) for s in stacks])  # type: ignore[arg-type]


def _read_light_list(path: Path) -> tuple[list[str], np.ndarray]:
    names, dirs = [], []
    for ln in path.read_text().splitlines():
        parts = ln.split()
        if not parts or parts[0].startswith("#"):
            continue
        if len(parts) < 4:
            raise InputError(f"expected 'name lx ly lz' per line, got {ln.strip()!r}", path)
        try:
            dirs.append([float(v) for v in parts[1:4]])
        except ValueError as exc:
            raise InputError(f"bad light direction in line {ln.strip()!r}", path) from exc
        names.append(parts[0])
    if not names:
        raise InputError("image list is empty", path)
    return names, unit_lights(np.asarray(dirs), path)  # zero / NaN rows refused


def find_blobby_samples(root: str | Path) -> list[tuple[Path, Path]]:
    """(normal map, image list) pairs: every folder holding ``<shape>_normal.png`` and, below
    it, material folders each with a text file listing ``name lx ly lz`` per image."""
    root = Path(root)
    if not root.is_dir():
        raise InputError("Blobby/Sculpture root folder not found", root)
    pairs = []
    for normal in sorted(root.rglob("*_normal.png")):
        for mat in sorted(p for p in normal.parent.iterdir() if p.is_dir()):
            lists = sorted(mat.glob("*.txt"))
            if lists:
                pairs.append((normal, lists[0]))
    if not pairs:
        raise InputError(
            "no '<shape>_normal.png' with material folders (holding an image list "
            "'name lx ly lz') found",
            root,
        )
    return pairs


def check_blobby_samples(pairs: Sequence[tuple[Path, Path]], lights: int) -> None:
    """Refuse, before training starts, what can be found without decoding an image: an image
    list that is malformed, names a file that is not there, or lists fewer images than
    ``lights`` (the curriculum's largest light count). Reads each list once and each material
    folder's listing once (no stat per image: the sets hold ~10^6 images). What only decoding
    finds (a damaged PNG, a size mismatch) is reported when a batch reads it."""
    for _normal, image_list in pairs:
        names, _dirs = _read_light_list(image_list)
        folder = image_list.parent
        if len(names) < lights:
            fix = (
                f"lower {opt('lights')} or the curriculum's LMAX to {len(names)}, or "
                if len(names) >= MIN_LIGHTS
                else ""
            )
            raise InputError(
                f"{image_list.name} lists {len(names)} images but the curriculum asks for up "
                f"to {lights} lights ({fix}leave this object out)",
                folder,
            )
        present = {p.name for p in folder.iterdir() if not p.is_dir()}
        for name in names:
            # a name with a folder part is not in the listing: looked up on its own
            found = name in present if Path(name).name == name else (folder / name).is_file()
            if not found:
                raise InputError(
                    f"image file not found (listed in {image_list.name})", folder / name
                )


def load_blobby_sample(normal_png: Path, image_list: Path) -> Stack:
    """One shape under one material: images from the list, mask where the normal is non-zero."""
    normals = read_normals(normal_png)
    names, dirs = _read_light_list(image_list)
    imgs = []
    for name in names:
        img = read_image(image_list.parent / name)  # as stored: make_sample casts the crop
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, axis=2)
        if img.shape[:2] != normals.shape[:2]:
            raise InputError(
                f"image is {img.shape[1]}x{img.shape[0]} but the normal map is "
                f"{normals.shape[1]}x{normals.shape[0]}",
                image_list.parent / name,
            )
        imgs.append(img)
    mask = np.linalg.norm(normals, axis=2) > 0.5
    return Stack(
        f"{normal_png.parent.name}/{image_list.parent.name}",
        as_held(np.stack(imgs)),
        dirs,
        np.ones((len(names), 3), np.float32),
        mask,
        normals,
        names,
        image_list.parent,
    ).validate()


class BlobbySource:
    """Samples from the Blobby / Sculpture sets, decoded lazily with a small LRU cache."""

    def __init__(
        self, root: str | Path, cache: int = 64, pairs: Sequence[tuple[Path, Path]] | None = None
    ) -> None:
        # ``pairs``: an index made (and checked) already, e.g. by the main process for its
        # DataLoader workers, which then need not search the root again
        self.pairs = list(pairs) if pairs is not None else find_blobby_samples(root)
        self.cache: OrderedDict[int, Stack] = OrderedDict()
        self.cache_size = cache

    def get(self, i: int) -> Stack:
        if i in self.cache:
            self.cache.move_to_end(i)
            return self.cache[i]
        stack = load_blobby_sample(*self.pairs[i])
        self.cache[i] = stack
        if len(self.cache) > self.cache_size:
            self.cache.popitem(last=False)
        return stack

    def batch(
        self, size: int, lights: int, crop: int, rng: np.random.Generator, **augment: float
    ) -> Batch:
        picks = rng.choice(len(self.pairs), size=size, replace=size > len(self.pairs))
        stacks = [self.get(int(i)) for i in picks]
        return collate([make_sample(s, lights, crop, rng, **augment) for s in stacks])  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- worker stream


class Source(Protocol):
    def batch(
        self, size: int, lights: int, crop: int, rng: np.random.Generator, **augment: float
    ) -> Batch: ...


@dataclass(frozen=True)
class SourceSpec:
    """How a worker builds its own source (picklable, unlike a filled pool)."""

    data: str  # "synth" or a Blobby/Sculpture root
    seed: int
    options: RenderOptions
    pool: int = 48
    refresh: int = 2
    max_size: int | None = None
    # Blobby/Sculpture: the (normal map, image list) pairs the main process indexed and checked
    pairs: tuple[tuple[Path, Path], ...] | None = None

    def build(self, worker: int, workers: int, start_step: int) -> Source:
        """The source of DataLoader worker ``worker`` of ``workers`` for steps ``start_step +
        worker``, ``+ workers``, ...: those an unbroken run gives its worker ``(start_step +
        worker) % workers``, whose object stream and pool it takes over as they are after its
        earlier steps, so a resumed run renders what an unbroken one would (same worker
        count)."""
        if self.data != "synth":
            return BlobbySource(self.data, pairs=self.pairs)
        owner = (start_step + worker) % workers
        done = max(0, -(-(start_step - owner) // workers))  # its steps before start_step
        # Tag 1 keeps worker streams apart from the in-process stream [seed, counter]
        return SynthSource(
            [self.seed, 1, owner, workers],
            self.options,
            self.pool,
            self.refresh,
            start=done * self.refresh,
            max_size=self.max_size,
        )


@dataclass(frozen=True)
class StepPlan:
    """What the batch of a given global step looks like (the curriculum, resolved per step)."""

    seed: int
    batch: int
    steps_per_epoch: int
    phases: tuple[tuple[int, int, int, int], ...]  # (epoch, lights_min, lights_max, crop)
    noise: float = 0.01

    def lights_and_crop(self, step: int, rng: np.random.Generator) -> tuple[int, int]:
        epoch = step // self.steps_per_epoch
        _e, lo, hi, crop = [p for p in self.phases if p[0] <= epoch][-1]
        return int(rng.integers(lo, hi + 1)), crop


ERROR_KEY = "input_error"  # a worker's InputError, sent in place of a batch (StepStream)


def raise_worker_error(d: dict) -> None:
    """Raise the InputError a DataLoader worker sent in place of a batch, if it sent one."""
    if ERROR_KEY in d:
        raise InputError(str(d[ERROR_KEY]), d.get("error_path"))


class StepStream(torch.utils.data.IterableDataset):
    """Batches of steps ``start .. total-1`` as dicts of tensors, built in DataLoader workers.

    Worker w of W yields steps start + w, start + w + W, ... (the DataLoader takes one batch from
    each worker in turn, so they arrive in step order). Each batch's light count, crops and
    augmentation come from ``default_rng([seed, 2, step])``: with a given worker count, the same
    command resumed at the same step gives the same batches."""

    def __init__(self, spec: SourceSpec, plan: StepPlan, start: int, total: int) -> None:
        super().__init__()
        self.spec, self.plan, self.start, self.total = spec, plan, start, total

    def __iter__(self) -> Iterator[dict]:
        info = torch.utils.data.get_worker_info()
        worker, workers = (0, 1) if info is None else (info.id, info.num_workers)
        if self.start + worker >= self.total:
            return
        step = self.start + worker
        try:
            source = self.spec.build(worker, workers, self.start)
            for step in range(self.start + worker, self.total, workers):
                rng = np.random.default_rng([self.plan.seed, 2, step])
                lights, crop = self.plan.lights_and_crop(step, rng)
                b = source.batch(self.plan.batch, lights, crop, rng, noise=self.plan.noise)
                yield {**vars(b), "step": step, "n_lights": lights, "crop": crop}
        except InputError as exc:
            if info is None:  # iterated in the calling process: nothing to carry across
                raise
            # Bad data (a damaged image, a size mismatch) found by a worker. Raised here,
            # torch would hand the main process an InputError whose message is the worker's
            # whole traceback; sent as data in the step's turn, the main process raises the
            # same one-line error (raise_worker_error).
            yield {
                ERROR_KEY: exc.message,
                "error_path": None if exc.path is None else str(exc.path),
                "step": step,
            }


def worker_init(_worker_id: int) -> None:
    """Workers render with numpy on one thread each, and ignore SIGINT and SIGTERM.

    Ctrl-C, and `timeout` (which signals its whole process group), reach the workers too. A
    worker killed by them makes torch raise "DataLoader worker killed" in the main process at
    an arbitrary point, possibly while it saves. Only the main process should react: it
    finishes the step, saves last.pth and shuts the workers down through the DataLoader (which
    does not need signals); a worker whose parent has died exits by itself."""
    torch.set_num_threads(1)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)


def make_loader(
    spec: SourceSpec,
    plan: StepPlan,
    start: int,
    total: int,
    workers: int,
    pin_memory: bool = False,
    prefetch: int = 4,
) -> torch.utils.data.DataLoader:
    """A DataLoader over ``StepStream`` with ``workers`` persistent worker processes (>= 1)."""
    if workers < 1:
        raise ValueError("make_loader needs at least one worker (0 = the in-process source)")
    return torch.utils.data.DataLoader(
        StepStream(spec, plan, start, total),
        batch_size=None,
        num_workers=workers,
        persistent_workers=True,
        pin_memory=pin_memory,
        prefetch_factor=prefetch,
        worker_init_fn=worker_init,
    )


def batch_from_dict(d: dict) -> Batch:
    return Batch(d["images"], d["lights"], d["normals"], d["mask"])
