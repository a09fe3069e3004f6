"""The photometric stack: one type that every loader returns and every consumer takes.

Loaders: a DiLiGenT-layout object folder, a generic folder of images with a lights file
(txt or json), and an ``.npz`` file. One writer: the DiLiGenT layout, which every tool reads.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .errors import InputError
from .imageio import list_images, natural_key, read_image, read_mask, write_atomic, write_png

LIGHTS_NAMES = ("light_directions.txt", "lights.txt", "lights.json", "light_directions.json")
INTENSITY_NAMES = ("light_intensities.txt", "intensities.txt", "light_intensities.json")
MASK_NAMES = ("mask.png", "mask.tif", "mask.tiff", "mask.tga", "mask.bmp")
GT_NAMES = ("Normal_gt.mat", "Normal_gt.npy", "Normal_gt.png", "normal_gt.png", "normals_gt.png")


@dataclass
class Stack:
    """N images of one static object, each lit by one distant light.

    images:       (N, H, W, 3) float32, linear RGB as stored (not yet divided by intensity)
    lights:       (N, 3) float32 unit directions, camera frame: x right, y up, z to the camera
    intensities:  (N, 3) float32 RGB light intensities (ones when unknown)
    mask:         (H, W) bool object mask (all True when unknown)
    normals_gt:   (H, W, 3) float32 ground-truth unit normals, or None
    """

    name: str
    images: np.ndarray
    lights: np.ndarray
    intensities: np.ndarray
    mask: np.ndarray
    normals_gt: np.ndarray | None = None
    filenames: list[str] = field(default_factory=list)
    source: Path | None = None

    @property
    def num_lights(self) -> int:
        return int(self.images.shape[0])

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.images.shape[1]), int(self.images.shape[2])

    def subset(self, indices: Sequence[int]) -> Stack:
        idx = list(indices)
        names = [self.filenames[i] for i in idx] if self.filenames else []
        return replace(self, images=self.images[idx], lights=self.lights[idx],
                       intensities=self.intensities[idx], filenames=names)

    def validate(self) -> Stack:
        """Check shapes and values; raise InputError naming the source on any problem."""
        src = self.source if self.source is not None else self.name
        n = self.images.shape[0]
        if self.images.ndim != 4 or self.images.shape[3] != 3:
            raise InputError(f"images must be N x H x W x 3, got {self.images.shape}", src)
        if n < 3:
            raise InputError(f"photometric stereo needs at least 3 lights, got {n}", src)
        if self.lights.shape != (n, 3):
            raise InputError(f"{n} images but {self.lights.shape[0]} light directions", src)
        if self.intensities.shape != (n, 3):
            raise InputError(f"{n} images but {self.intensities.shape[0]} light intensities", src)
        if not np.all(np.isfinite(self.lights)):
            raise InputError("light directions contain NaN or infinite values", src)
        norms = np.linalg.norm(self.lights, axis=1)
        if np.any(norms < 1e-6):
            bad = np.flatnonzero(norms < 1e-6) + 1
            raise InputError(f"zero-length light direction(s) at row(s) {bad.tolist()}", src)
        if not np.all(np.isfinite(self.intensities)) or np.any(self.intensities <= 0):
            bad = np.flatnonzero(~np.all(self.intensities > 0, axis=1)) + 1
            raise InputError(f"light intensities must be positive; bad row(s) {bad.tolist()}", src)
        if self.mask.shape != self.shape:
            raise InputError(f"mask is {self.mask.shape} but images are {self.shape}", src)
        if not self.mask.any():
            raise InputError("mask is empty", src)
        if self.normals_gt is not None and self.normals_gt.shape != (*self.shape, 3):
            raise InputError(f"ground-truth normals are {self.normals_gt.shape}, images "
                             f"{self.shape}", src)
        self.lights = (self.lights / norms[:, None]).astype(np.float32)
        return self


# ----------------------------------------------------------------------------- small files

def read_vectors(path: Path, what: str) -> np.ndarray:
    """Rows of 3 numbers from txt (optional leading count line) or json (list or {key: list})."""
    if not path.is_file():
        raise InputError(f"{what} file not found", path)
    try:
        if path.suffix.lower() == ".json":
            data = json.loads(path.read_text())
            if isinstance(data, dict):
                data = next((v for k, v in data.items() if isinstance(v, list)), None)
            arr = np.asarray(data, dtype=np.float64)
        else:
            rows = [r.replace(",", " ").split() for r in path.read_text().splitlines()]
            rows = [r for r in rows if r and not r[0].startswith("#")]
            if rows and len(rows[0]) == 1 and len(rows) > 1:
                rows = rows[1:]  # a leading count line ("12")
            arr = np.asarray([[float(v) for v in r] for r in rows], dtype=np.float64)
    except (ValueError, TypeError, json.JSONDecodeError) as exc:
        raise InputError(f"cannot parse {what}: {exc}", path) from exc
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{what} must have 3 numbers per row, got shape {arr.shape}", path)
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{what} contain NaN or infinite values", path)
    return arr.astype(np.float32)


def read_normals(path: Path) -> np.ndarray:
    """Ground-truth normals (H, W, 3) from .mat (key Normal_gt), .npy or an 8/16-bit PNG."""
    suffix = path.suffix.lower()
    try:
        if suffix == ".mat":
            from scipy.io import loadmat

            mat = loadmat(str(path))
            keys = [k for k in mat if not k.startswith("_")]
            key = "Normal_gt" if "Normal_gt" in mat else keys[0]
            n = np.asarray(mat[key], dtype=np.float32)
        elif suffix == ".npy":
            n = np.load(path, allow_pickle=False).astype(np.float32)
        else:
            img = read_image(path)
            scale = 65535.0 if img.dtype == np.uint16 else 255.0
            n = img.astype(np.float32) / scale * 2.0 - 1.0
            n[np.all(img == 0, axis=-1)] = 0.0
    except InputError:
        raise
    except Exception as exc:
        raise InputError(f"cannot read ground-truth normals ({exc})", path) from exc
    if n.ndim != 3 or n.shape[2] != 3:
        raise InputError(f"ground-truth normals must be H x W x 3, got {n.shape}", path)
    norm = np.linalg.norm(n, axis=2, keepdims=True)
    return np.where(norm > 1e-6, n / np.maximum(norm, 1e-6), 0.0).astype(np.float32)


def parse_select(spec: str, n: int) -> list[int]:
    """1-based image selection like ``21-96`` or ``1,3,5-9`` -> 0-based indices."""
    out: list[int] = []
    try:
        for part in spec.split(","):
            part = part.strip()
            if not part:
                continue
            if "-" in part or ":" in part:
                a, b = part.replace(":", "-").split("-", 1)
                lo, hi = int(a) if a else 1, int(b) if b else n
                out.extend(range(lo - 1, hi))
            else:
                out.append(int(part) - 1)
    except ValueError as exc:
        raise InputError(f"--select {spec!r}: expected 1-based indices like 21-96 or 1,3,5-9")\
            from exc
    bad = [i + 1 for i in out if not 0 <= i < n]
    if bad:
        raise InputError(f"--select {spec!r}: index {bad[0]} is outside 1..{n}")
    return out


def evenly_spaced(n: int, k: int) -> list[int]:
    """k indices spread evenly over n (for --max-lights)."""
    return sorted({round(float(i)) for i in np.linspace(0, n - 1, k)})


# ----------------------------------------------------------------------------- loaders

def _first_existing(folder: Path, names: Sequence[str]) -> Path | None:
    return next((folder / n for n in names if (folder / n).is_file()), None)


def _read_images(paths: Sequence[Path], threads: int = 4) -> np.ndarray:
    """Decode in parallel (OpenCV releases the GIL) and check all sizes agree."""
    with ThreadPoolExecutor(max_workers=max(1, threads)) as pool:
        imgs = list(pool.map(read_image, paths))
    first = imgs[0]
    out = np.empty((len(imgs), first.shape[0], first.shape[1], 3), dtype=np.float32)
    for i, (p, img) in enumerate(zip(paths, imgs, strict=True)):
        if img.shape[:2] != first.shape[:2]:
            raise InputError(f"image is {img.shape[1]}x{img.shape[0]} but {paths[0].name} is "
                             f"{first.shape[1]}x{first.shape[0]}", p)
        out[i] = img[:, :, None] if img.ndim == 2 else img
    return out


def load_folder(folder: Path, lights: Path | None = None, intensities: Path | None = None,
                mask: Path | None = None, threads: int = 4,
                indices: Sequence[int] | None = None) -> Stack:
    """A DiLiGenT-layout object folder, or any folder of images plus a lights file.

    ``indices`` (0-based) picks the images to keep; only those are decoded.
    """
    if not folder.is_dir():
        raise InputError("stack folder not found", folder)
    names_file = folder / "filenames.txt"
    if names_file.is_file():
        names = [ln.strip() for ln in names_file.read_text().splitlines() if ln.strip()]
        paths = [folder / n for n in names]
    else:
        paths = list_images(folder)
    if not paths:
        raise InputError("no images found (expected PNG/TIFF/TGA files or filenames.txt)", folder)
    lights_path = lights or _first_existing(folder, LIGHTS_NAMES)
    if lights_path is None:
        raise InputError("no light directions: expected light_directions.txt or lights.txt "
                         "(or pass --lights)", folder)
    light_dirs = read_vectors(lights_path, "light directions")
    if len(light_dirs) != len(paths):
        raise InputError(f"{len(light_dirs)} light directions for {len(paths)} images in "
                         f"{folder}", lights_path)
    int_path = intensities or _first_existing(folder, INTENSITY_NAMES)
    if int_path is not None:
        ints = read_vectors(int_path, "light intensities")
        if len(ints) != len(paths):
            raise InputError(f"{len(ints)} light intensities for {len(paths)} images", int_path)
        if np.any(ints <= 0):
            raise InputError("light intensities must be positive", int_path)
    else:
        ints = np.ones((len(paths), 3), np.float32)
    if indices is not None:
        keep = list(indices)
        paths, light_dirs, ints = [paths[i] for i in keep], light_dirs[keep], ints[keep]
    images = _read_images(paths, threads)
    hw = images.shape[1:3]
    mask_path = mask or _first_existing(folder, MASK_NAMES) or next(
        (p for p in sorted(folder.iterdir()) if "mask" in p.stem.lower() and p.is_file()), None)
    mask_arr = read_mask(mask_path, hw) if mask_path else np.ones(hw, bool)
    gt_path = _first_existing(folder, GT_NAMES)
    gt = read_normals(gt_path) if gt_path else None
    if gt is not None and gt.shape[:2] != hw:
        raise InputError(f"ground truth is {gt.shape[1]}x{gt.shape[0]} but images are "
                         f"{hw[1]}x{hw[0]}", gt_path)
    return Stack(folder.name, images, light_dirs, ints, mask_arr, gt,
                 [p.name for p in paths], folder).validate()


def load_npz(path: Path) -> Stack:
    """An .npz with images (N,H,W,3) and lights (N,3); intensities, mask, normals optional."""
    try:
        data = np.load(path, allow_pickle=False)
        files = set(data.files)
        if not {"images", "lights"} <= files:
            raise InputError("npz stack needs arrays 'images' and 'lights'", path)
        images = np.asarray(data["images"], np.float32)
        if images.ndim == 3:
            images = np.repeat(images[..., None], 3, axis=3)
        n, h, w = images.shape[:3]
        lights = np.asarray(data["lights"], np.float32)
        ints = (np.asarray(data["intensities"], np.float32) if "intensities" in files
                else np.ones((n, 3), np.float32))
        mask = np.asarray(data["mask"]).astype(bool) if "mask" in files else np.ones((h, w), bool)
        gt = np.asarray(data["normals"], np.float32) if "normals" in files else None
    except InputError:
        raise
    except Exception as exc:
        raise InputError(f"cannot read npz stack ({exc})", path) from exc
    return Stack(path.stem, images, lights, ints, mask, gt, [], path).validate()


def load_stack(path: str | Path, *, lights: str | Path | None = None,
               intensities: str | Path | None = None, mask: str | Path | None = None,
               select: str | None = None, max_lights: int | None = None,
               threads: int = 4) -> Stack:
    """Load any supported stack with --select and --max-lights applied (only kept images are
    decoded)."""
    path = Path(path)
    opt = {k: Path(v) if v is not None else None
           for k, v in (("lights", lights), ("intensities", intensities), ("mask", mask))}
    if path.suffix.lower() == ".npz":
        if not path.is_file():
            raise InputError("stack file not found", path)
        stack = load_npz(path)
        if opt["lights"] is not None:
            stack.lights = read_vectors(opt["lights"], "light directions")
        if opt["intensities"] is not None:
            stack.intensities = read_vectors(opt["intensities"], "light intensities")
        if opt["mask"] is not None:
            stack.mask = read_mask(opt["mask"], stack.shape)
        stack.validate()
        return stack.subset(_selection(stack.num_lights, select, max_lights)).validate()
    count = _count_images(path)
    return load_folder(path, opt["lights"], opt["intensities"], opt["mask"], threads,
                       _selection(count, select, max_lights) if count else None)


def _count_images(folder: Path) -> int:
    """How many images a folder stack holds, without decoding any (0 if unknown)."""
    if not folder.is_dir():
        return 0
    names_file = folder / "filenames.txt"
    if names_file.is_file():
        return sum(1 for ln in names_file.read_text().splitlines() if ln.strip())
    return len(list_images(folder))


def _selection(n: int, select: str | None, max_lights: int | None) -> list[int]:
    """--select (1-based spec), then --max-lights evenly spread over what is left."""
    keep = parse_select(select, n) if select else list(range(n))
    if max_lights is not None and max_lights < len(keep):
        if max_lights < 3:
            raise InputError(f"--max-lights {max_lights}: at least 3 lights are needed")
        keep = [keep[i] for i in evenly_spaced(len(keep), max_lights)]
    return keep


# ----------------------------------------------------------------------------- writer

def _write_rows(path: Path, rows: np.ndarray) -> None:
    text = "".join(" ".join(f"{v:.8f}" for v in r) + "\n" for r in rows)
    write_atomic(path, lambda tmp: tmp.write_text(text))


def save_stack(stack: Stack, folder: str | Path, bit_depth: int = 16) -> Path:
    """Write a stack in the DiLiGenT layout (16-bit PNGs, text lights, mask, Normal_gt.mat)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    top = 65535 if bit_depth == 16 else 255
    dtype = np.uint16 if bit_depth == 16 else np.uint8
    names = stack.filenames or [f"{i + 1:03d}.png" for i in range(stack.num_lights)]
    names = [Path(n).with_suffix(".png").name for n in names]
    for name, img in zip(names, stack.images, strict=True):
        write_png(folder / name, np.clip(np.rint(img), 0, top).astype(dtype))
    write_atomic(folder / "filenames.txt", lambda t: t.write_text("\n".join(names) + "\n"))
    _write_rows(folder / "light_directions.txt", stack.lights)
    _write_rows(folder / "light_intensities.txt", stack.intensities)
    write_png(folder / "mask.png", stack.mask.astype(np.uint8) * 255)
    if stack.normals_gt is not None:
        from scipy.io import savemat

        write_atomic(folder / "Normal_gt.mat",
                     lambda t: savemat(str(t), {"Normal_gt": stack.normals_gt.astype(np.float64)}))
    return folder


__all__ = ["Stack", "load_stack", "natural_key", "parse_select", "read_normals", "read_vectors",
           "save_stack"]
