"""Loaders: a DiLiGenT-layout object folder, a folder of images with a lights file, an .npz.

Each returns a validated :class:`Stack` with unit light directions; only the selected images
are decoded. Real-camera options (:mod:`.transforms`) are applied while loading, in the order
ROI -> downscale -> linearise -> auto-mask; images, mask and ground truth stay aligned.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from msfnet.common.cli import path_arg, positive_float, positive_int
from msfnet.common.errors import InputError, first_line
from msfnet.common.files.locations import same_file
from msfnet.common.imageio import (
    IMAGE_SUFFIXES,
    MAX_PIXELS,
    ImageHeader,
    image_header,
    list_images,
    mask_threshold,
    npy_header,
    read_image,
    read_mask,
)
from msfnet.common.vocabulary import declare, flag, opt, options_type
from msfnet.runtime.contract import INPUT_MULTIPLE
from msfnet.runtime.stack.readers import (
    check_gt_header,
    companion_intensities,
    read_normals,
    read_vectors,
    unit_normals,
)
from msfnet.runtime.stack.select import selection
from msfnet.runtime.stack.transforms import (
    Roi,
    Transforms,
    auto_mask,
    check_roi,
    halo_roi,
    parse_roi,
)
from msfnet.runtime.stack.types import (
    Stack,
    as_held,
    as_mask,
    check_intensities,
    check_lights,
    held_dtype,
    unit_lights,
)

# ModelOptions' --max-memory, which LoadOptions holds too (the loader refuses by it)
declare("max_memory_mb", "--max-memory")

if TYPE_CHECKING:
    from os import PathLike

LIGHTS_NAMES = ("light_directions.txt", "lights.txt", "lights.json", "light_directions.json")
# what an .npz stack may hold: images and lights, optionally intensities, mask and normals
NPZ_MEMBERS = ("images", "lights", "intensities", "mask", "normals")
INTENSITY_NAMES = ("light_intensities.txt", "intensities.txt", "light_intensities.json")
MASK_NAMES = ("mask.png", "mask.tif", "mask.tiff", "mask.tga", "mask.bmp")
GT_NAMES = ("Normal_gt.mat", "Normal_gt.npy", "Normal_gt.png", "normal_gt.png", "normals_gt.png")
# what a STACK argument may be, for the message when it is something else
STACK_KINDS = (
    "a folder of images with a lights file (DiLiGenT layout), or an .npz with "
    "arrays 'images' and 'lights'"
)


@options_type
@dataclass(frozen=True)
class LoadOptions:
    """How to read a stack: files that override the stack's own, and which images to keep."""

    # Each user-set field carries its command-line spelling (common.vocabulary), by category:
    # "stack" (files that override the stack's own, which images), "camera" (real-camera
    # inputs, applied while loading in this order: ROI -> downscale -> linearise -> auto-mask)
    # and "linearise" (one of two encodings).
    lights: Path | None = flag(
        None,
        "light directions file (txt or json), overrides the stack's",
        type=path_arg,
        category="stack",
    )
    intensities: Path | None = flag(
        None, "light intensities file (txt or json)", type=path_arg, category="stack"
    )
    mask: Path | None = flag(None, "mask image (> 127 is object)", type=path_arg, category="stack")
    select: str | None = flag(
        None,
        "1-based image subset, e.g. 21-96 or 1,3,5-9 (default: all images, or the "
        "benchmark's own selection, e.g. DiLiGenT bear 21-96, which a line reports and "
        "--select overrides)",
        metavar="SPEC",
        category="stack",
    )
    max_lights: int | None = flag(
        None, "use K evenly spaced lights", type=positive_int, metavar="K", category="stack"
    )
    threads: int = 4  # decoding threads
    roi: Roi | None = flag(
        None,
        "crop images, mask and ground truth to this rectangle (pixels of the stored images, "
        "origin top-left); the network also sees a halo of the image around it, the outputs "
        "are the rectangle's",
        type=parse_roi,
        metavar="X,Y,W,H",
        category="camera",
    )
    downscale: int = flag(
        1,
        "average each K x K block (integer K; mask: majority of the block)",
        type=positive_int,
        metavar="K",
        category="camera",
    )
    srgb: bool = flag(
        False,
        "images are sRGB-encoded (8-bit camera output): linearise them",
        action="store_true",
        category="linearise",
    )
    gamma: float | None = flag(
        None,
        "images are power-law encoded: linear = (value / white) ** G",
        type=positive_float,
        metavar="G",
        category="linearise",
    )
    white_level: float | None = flag(
        None,
        "full-scale value for --srgb / --gamma (default 255 / 65535 by bit depth; needed for "
        "floating-point images above 1)",
        type=positive_float,
        metavar="V",
        category="camera",
    )
    auto_mask: bool = flag(
        False,
        "compute the object mask from the stack (object on a dark background); written beside "
        "the outputs as mask.png",
        action="store_true",
        category="camera",
    )
    # refuse, before decoding, a stack whose images alone (as held) exceed this (the model's
    # memory budget, declared there)
    max_memory_mb: float | None = None
    # grow the ROI by this many held pixels on every side (clipped to the image) and record
    # the ROI's box on the stack (Stack.roi_box): the network then sees the real image around
    # the ROI instead of zeros. Model sets it for the network path with edge context and
    # crops every output back to the ROI; 0: the plain crop.
    roi_halo: int = 0

    if TYPE_CHECKING:
        # What the generated __init__ accepts: the files as str or any os.PathLike, held as
        # Path once made (__post_init__); the other fields as declared (tests/runtime/stack/
        # test_load.py checks that this stays the fields' list).
        def __init__(
            self,
            lights: str | PathLike[str] | None = None,
            intensities: str | PathLike[str] | None = None,
            mask: str | PathLike[str] | None = None,
            select: str | None = None,
            max_lights: int | None = None,
            threads: int = 4,
            roi: Roi | None = None,
            downscale: int = 1,
            srgb: bool = False,
            gamma: float | None = None,
            white_level: float | None = None,
            auto_mask: bool = False,
            max_memory_mb: float | None = None,
            roi_halo: int = 0,
        ) -> None: ...

    def __post_init__(self) -> None:
        for name in ("lights", "intensities", "mask"):  # LoadOptions(lights="x.txt") works
            value = getattr(self, name)
            if value is not None and not isinstance(value, Path):
                object.__setattr__(self, name, Path(value))
        self.transforms()  # refuse contradictory options before any decoding
        if self.auto_mask and self.mask is not None:
            raise InputError(
                f"{opt('auto_mask')} and {opt('mask')} both give the mask: choose one",
                option="auto_mask",
            )
        if self.white_level is not None and not self.white_level > 0:
            raise InputError(f"white level {self.white_level}: must be positive")
        if self.roi_halo < 0:
            raise InputError(f"ROI halo {self.roi_halo}: must be 0 or more pixels")

    def inputs(self) -> list[Path]:
        """The files these options read (never to be written over)."""
        return [p for p in (self.lights, self.intensities, self.mask) if p is not None]

    def transforms(self) -> Transforms:
        return Transforms(self.roi, self.downscale, self.srgb, self.gamma, self.white_level)

    def describe(self) -> dict[str, object]:
        """The real-camera options in effect, the image selection when there is one, and the
        files given in place of the stack's own (lights, intensities, mask: as given), for
        profile.json: a saved result names the light file it was computed with."""
        chosen: dict[str, object] = {
            k: v
            for k, v in (("select", self.select), ("max_lights", self.max_lights))
            if v is not None
        }
        for name in ("lights", "intensities", "mask"):
            given = getattr(self, name)
            if given is not None:
                chosen[name] = str(given)
        if self.roi is not None and self.roi_halo:
            chosen["roi_halo"] = self.roi_halo
        return {**self.transforms().describe(), "auto_mask": self.auto_mask, **chosen}

    def grown(
        self, shape: tuple[int, int], src: str | Path | None = None
    ) -> tuple[Transforms, tuple[int, int, int, int] | None]:
        """The per-image transforms for images of stored ``shape``, with the ROI grown by
        ``roi_halo`` (see :func:`~.transforms.halo_roi`), and the requested ROI's box inside
        the grown crop (None without a halo)."""
        t = self.transforms()
        if self.roi is None or self.roi_halo <= 0:
            return t, None
        check_roi(self.roi, shape, src)  # the plain ROI's message, naming the file
        roi, box = halo_roi(self.roi, shape, self.roi_halo, t.downscale, INPUT_MULTIPLE)
        return replace(t, roi=roi), box


def _intensities_file(options: LoadOptions) -> Path | None:
    """--intensities, else the intensities a --lights JSON holds (as the file overrides the
    stack's directions, it brings its intensities too)."""
    if options.intensities is not None or options.lights is None:
        return options.intensities
    return companion_intensities(options.lights)


def _first_existing(folder: Path, names: Sequence[str]) -> Path | None:
    """The first of ``names`` present in ``folder``. One that is there but no readable file (a
    dangling link, a folder, a pipe) is refused, never taken as absent."""
    for name in names:
        path = folder / name
        if os.path.lexists(path):
            _regular_file(path)
            return path
    return None


def _regular_file(path: Path) -> None:
    if path.is_symlink() and not path.exists():
        raise InputError(f"dangling link (to {os.readlink(path)})", path)
    if not path.is_file():
        what = "a folder" if path.is_dir() else "not a regular file (a pipe or a device?)"
        raise InputError(f"is {what}; expected a file", path)


def _listed_images(folder: Path, names_file: Path) -> list[Path]:
    """The images filenames.txt lists, which must lie in the stack folder: an entry reaching
    outside it (``../x.png``, an absolute path) would be an input no output check knows of."""
    names = _names(names_file)
    for name in names:
        if "\0" in name:  # no file system takes it; os.stat raised a bare ValueError
            raise InputError(f"entry {name[:80]!r} holds a NUL byte: no file name does", names_file)
        part = Path(os.path.normpath(name))  # sub/../002.png is 002.png
        if part.is_absolute() or part.parts[:1] == ("..",):
            raise InputError(
                f"entry {name[:80]!r} lies outside the stack folder; list the images by "
                "their names in the folder",
                names_file,
            )
    return [folder / n for n in names]


def _names(names_file: Path) -> list[str]:
    """The non-blank lines of filenames.txt, stripped."""
    lines = names_file.read_text(encoding="utf-8-sig").splitlines()
    return [ln.strip() for ln in lines if ln.strip()]


def check_stack_size(
    n: int,
    h: int,
    w: int,
    max_memory_mb: float | None,
    src: str | Path | None = None,
    dtype: np.dtype | type = np.float32,
) -> None:
    """The loaded stack is N x H x W x 3 values of ``dtype`` (as held: see
    :func:`~.types.held_dtype`): refuse it up front if that alone is over the memory budget (a
    96-image full-resolution stack otherwise fills the memory while decoding, before any later
    check can speak)."""
    need = n * h * w * 3 * np.dtype(dtype).itemsize / 2**20
    if max_memory_mb is not None and need > max_memory_mb:
        size = f"{need:.0f}" if need >= 1 else f"{need:.2g}"  # "1536", "2", "0.14"
        raise InputError(
            f"{n} images of {w}x{h} take {size} MB loaded, above "
            f"{opt('max_memory_mb', max_memory_mb)} MB (use "
            f"{opt('select')}/{opt('max_lights')} or a larger budget)",
            src,
        )


def _held_size(shape: tuple[int, int], transforms: Transforms, src: Path) -> tuple[int, int]:
    """(H, W) an image of stored size ``shape`` has once ROI and downscale are applied."""
    h, w = shape
    if transforms.roi is not None:
        check_roi(transforms.roi, shape, src)
        w, h = transforms.roi[2], transforms.roi[3]
    k = transforms.downscale
    return h // k, w // k


_BITS_DTYPE: dict[int, np.dtype] = {8: np.dtype(np.uint8), 16: np.dtype(np.uint16)}


def check_headers(
    paths: Sequence[Path], transforms: Transforms, max_memory_mb: float | None
) -> tuple[int, int] | None:
    """Every frame's header, before any frame is decoded: sizes (and bit depths, where the
    headers tell) must agree, the ROI must fit and the stack as held must fit the budget. A
    frame whose format has no readable header is checked once decoded. Returns the stored size
    the headers agree on (None if no header was readable)."""
    headers = [(p, image_header(p)) for p in paths]
    known = [(p, h) for p, h in headers if h is not None]
    if not known:
        return None
    p0, h0 = known[0]
    for p, h in known[1:]:
        if h.shape != h0.shape:
            raise _unlike(p, p0, f"{h.width}x{h.height}", f"{h0.width}x{h0.height}")
        if h.bits in _BITS_DTYPE and h0.bits in _BITS_DTYPE and h.bits != h0.bits:
            raise _unlike(p, p0, _BITS_DTYPE[h.bits], _BITS_DTYPE[h0.bits], "one bit depth")
    hh, ww = _held_size(h0.shape, transforms, p0)
    check_stack_size(
        len(paths), hh, ww, max_memory_mb, p0.parent, _held_from_header(h0, transforms)
    )
    return h0.shape


def _unlike(path: Path, first: Path, this: object, that: object, rule: str = "") -> InputError:
    """An image unlike the stack's first one: ``rule`` names the stack's rule it breaks."""
    tail = f": {rule} per stack" if rule else ""
    return InputError(f"image is {this} but {first.name} is {that}{tail}", path)


def _held_from_header(header: ImageHeader, transforms: Transforms) -> np.dtype:
    """The type the stack will hold, as far as the header tells: float32 where loading changes
    values; where the header is silent on depth, uint8 (the smallest: the exact check follows
    the first decode, so a stack that fits is never refused on a guess)."""
    if transforms.changes_values:
        return np.dtype(np.float32)
    if header.bits is None:
        return np.dtype(np.uint8)
    return held_dtype(_BITS_DTYPE.get(header.bits, np.dtype(np.float32)))


def _read_images(
    paths: Sequence[Path],
    threads: int = 4,
    transforms: Transforms | None = None,
    max_memory_mb: float | None = None,
) -> tuple[np.ndarray, tuple[int, int]]:
    """Decode in parallel (OpenCV releases the GIL), each image reduced by ``transforms`` in
    its thread and copied straight into the stack, so no second stack-sized array is ever
    held; sizes and bit depths must all agree (checked from the headers before any decoding,
    and again once decoded). Returns the images and the stored size.

    The stack takes the type of the first image as transformed: uint8/uint16 when no value
    changes, else float32 (see ``Transforms.image``)."""
    transforms = transforms or Transforms()
    stored = check_headers(paths, transforms, max_memory_mb)

    def read(path: Path) -> tuple[np.ndarray, np.dtype, tuple[int, int], int]:
        # the size the headers agreed on, checked again from the handle that is decoded: a
        # frame replaced since its header was read is refused before its pixels are decoded
        img = read_image(path, stored)
        if img.ndim == 2:
            img = img[:, :, None]
        _check_float_scale(img, transforms, path)
        return transforms.image(img, path), img.dtype, img.shape[:2], img.shape[2]

    first, dtype0, shape0, channels0 = read(paths[0])
    check_stack_size(
        len(paths), first.shape[0], first.shape[1], max_memory_mb, paths[0].parent, first.dtype
    )
    out = np.empty((len(paths), first.shape[0], first.shape[1], 3), dtype=first.dtype)
    out[0] = first

    def read_into(i: int) -> None:
        img, dtype, shape, channels = read(paths[i])
        if shape != shape0:
            raise _unlike(paths[i], paths[0], f"{shape[1]}x{shape[0]}", f"{shape0[1]}x{shape0[0]}")
        if dtype != dtype0:
            # an 8-bit image among 16-bit ones is 257x too dark: silently wrong normals
            raise _unlike(paths[i], paths[0], dtype, dtype0, "one bit depth")
        if channels != channels0:
            # a grey frame among colour ones would stand for all three colours of its light
            kind = {1: "grey", 3: "colour (RGB)"}
            this, that = (kind.get(c, f"{c}-channel") for c in (channels, channels0))
            raise _unlike(paths[i], paths[0], this, that, "one kind of image")
        out[i] = img  # grey (H, W, 1) broadcasts to RGB

    with ThreadPoolExecutor(max_workers=max(1, threads)) as pool:
        for _ in pool.map(read_into, range(1, len(paths))):  # raises the first error in order
            pass
    return out, shape0


def _check_float_scale(img: np.ndarray, transforms: Transforms, src: str | Path | None) -> None:
    """Linearising needs the full-scale value; float images carry none."""
    linear = not (transforms.srgb or transforms.gamma is not None)
    if linear or transforms.white is not None or not np.issubdtype(img.dtype, np.floating):
        return
    if float(np.max(img)) > 1.0:
        raise InputError(
            "floating-point images with values above 1: give the full-scale "
            f"value ({opt('white_level')}) to linearise them",
            src,
        )


# below this overlap the automatic mask and the stack's own are different objects, not two
# traces of one outline (psmImages and DiLiGenT: 0.91-0.99)
MASK_AGREEMENT_IOU = 0.9


def _finish(stack: Stack, options: LoadOptions, own_mask: str = "mask") -> Stack:
    """The stack-wide last step: the automatic mask. It replaces the stack's own mask
    (``own_mask`` names it) with a warning when the two disagree: never silently."""
    if not options.auto_mask:
        return _check_box(stack).validate()
    found = auto_mask(stack.images)
    notes = stack.load_warnings
    if not stack.mask.all():  # an all-ones mask is no mask: nothing to compare with
        iou = float((found & stack.mask).sum() / max(1, (found | stack.mask).sum()))
        if iou < MASK_AGREEMENT_IOU:
            notes = (
                *notes,
                f"{stack.source or stack.name}: {opt('auto_mask')} finds "
                f"{int(found.sum()):,} px, the stack's {own_mask} {int(stack.mask.sum()):,} px "
                f"(IoU {iou:.2f}): the automatic one is used; leave out {opt('auto_mask')} to "
                "use the stack's own",
            )
    # never alter a caller's stack
    return _check_box(replace(stack, mask=found, load_warnings=notes)).validate()


def _check_box(stack: Stack) -> Stack:
    """A halo-grown crop keeps its own mask around the ROI: the network sees the object there
    as a full-image run does (shadowed parts included, which the lit rule of infer.tiled's
    edge context would drop). The ROI itself must hold some of the object, as a plain crop
    must."""
    if stack.roi_box is not None:
        y0, y1, x0, x1 = stack.roi_box
        if not stack.mask[y0:y1, x0:x1].any():
            raise InputError("mask is empty", stack.source or stack.name)
    return stack


def prepare_stack(stack: Stack, options: LoadOptions) -> Stack:
    """Apply the loading options to a stack already in memory: selection, ROI, downscale,
    linearisation, auto-mask (what :func:`load_stack` does while decoding). Lights, mask and
    intensity files in ``options`` are for loaders and are refused here."""
    if options.inputs():
        raise InputError(
            "lights, intensities and mask files apply when a stack is loaded "
            "from disk; this stack is already in memory"
        )
    keep = selection(stack.num_lights, options.select, options.max_lights)
    if keep != list(range(stack.num_lights)):
        stack = stack.subset(keep)
    if options.transforms().active:
        stack = stack.inner()  # a stack grown for an earlier ROI: only its ROI is kept
    t, box = options.grown(stack.shape, stack.source or stack.name)
    if t.active:
        _check_float_scale(stack.images, t, stack.source or stack.name)
        images = np.stack([t.image(img, stack.source or stack.name) for img in stack.images])
        gt = None if stack.normals_gt is None else t.normals(stack.normals_gt)
        stack = replace(stack, images=images, mask=t.mask(stack.mask), normals_gt=gt, roi_box=box)
    return _finish(stack, options)


@dataclass(frozen=True)
class _FolderFiles:
    """A folder stack's files and light table, read and checked, no image decoded."""

    paths: list[Path]
    lights_path: Path
    light_dirs: np.ndarray
    intensities: np.ndarray


def _folder_files(folder: Path, options: LoadOptions) -> _FolderFiles:
    if not folder.is_dir():
        if folder.exists():  # an image, a .npy, ...: it is there, just not a stack
            raise InputError(f"not a supported stack: expected {STACK_KINDS}", folder)
        raise InputError("stack folder not found", folder)
    names_file = folder / "filenames.txt"
    if os.path.lexists(names_file):
        _regular_file(names_file)
        paths = _listed_images(folder, names_file)
        _refuse_repeats(paths, names_file)
    else:
        paths = list_images(folder)
        _refuse_repeats(paths)
    if not paths:
        raise InputError("no images found (expected PNG/TIFF/TGA files or filenames.txt)", folder)
    lights_path = options.lights or _first_existing(folder, LIGHTS_NAMES)
    if lights_path is None:
        raise InputError(
            "no light directions: expected light_directions.txt or lights.txt (or pass "
            f"{opt('lights')})",
            folder,
        )
    light_dirs = read_vectors(lights_path, "light directions")
    if len(light_dirs) != len(paths):
        raise InputError(
            f"{len(light_dirs)} light directions for {len(paths)} images in {folder}", lights_path
        )
    int_path = _intensities_file(options) or _intensity_file(folder, lights_path)
    if int_path is not None:
        ints = read_vectors(int_path, "light intensities")
        if len(ints) != len(paths):
            raise InputError(f"{len(ints)} light intensities for {len(paths)} images", int_path)
        check_intensities(ints, int_path)
    else:
        ints = np.ones((len(paths), 3), np.float32)
    return _FolderFiles(paths, lights_path, light_dirs, ints)


def folder_name(path: str | Path) -> str:
    """The name a stack folder goes by, also when it is given as ``.`` or ``sub/..`` (whose
    ``Path.name`` is empty or ``..``)."""
    return Path(os.path.abspath(path)).name or "stack"


def _intensity_file(folder: Path, lights_path: Path) -> Path | None:
    """The stack's intensities: its JSON light file's own, or a file of INTENSITY_NAMES; both
    is refused (which one the rig's is cannot be guessed)."""
    own = companion_intensities(lights_path)
    beside = _first_existing(folder, INTENSITY_NAMES)
    if own is not None and beside is not None and not same_file(own, beside):
        raise InputError(
            f"light intensities are given twice: in {own.name} and in this file; keep one "
            f"(or name the one to use with {opt('intensities')})",
            beside,
        )
    return own or beside


def linked_reads(path: str | Path) -> list[Path]:
    """The files a stack folder reads that live elsewhere: a symlink or a hard-linked file
    among its images (as filenames.txt lists them, or the folder's), light, intensity, mask
    and ground-truth files, or a file reached through a linked sub-folder. Output checks take
    them as inputs (an --overwrite must not delete one). Only these: a link the loader never
    reads (a ``results`` link to the output) is no input. Lenient: a stack the loader will
    refuse lists what it can."""
    folder = Path(path)
    if not folder.is_dir():
        return []
    names_file = folder / "filenames.txt"
    try:
        if names_file.is_file():
            images = _listed_images(folder, names_file)
        else:
            images = list_images(folder, strict=False)
        other = _other_mask(folder)
    except (OSError, UnicodeDecodeError, InputError):
        return []  # the loader says what is wrong
    own = [folder / n for n in (*LIGHTS_NAMES, *INTENSITY_NAMES, *MASK_NAMES, *GT_NAMES)]
    found = []
    for file in dict.fromkeys([*images, *own, *([other] if other is not None else [])]):
        try:
            st = os.lstat(file)
        except OSError:  # missing: nothing there to replace
            continue
        # one lstat a file (a batch of linked stacks makes many); a name through a sub-folder
        # (filenames.txt's sub/x.png) may pass a link on its way
        if stat.S_ISLNK(st.st_mode) or st.st_nlink > 1 or file.parent != folder:
            found.append(file)
    return found


def check_stack_files(path: str | Path, options: LoadOptions | None = None) -> None:
    """What :func:`load_stack` checks before decoding an image (the folder, its image list,
    light and intensity files and their counts, --select / --max-lights, and the first
    kept image's header against the memory budget), in milliseconds: a command over many
    stacks finds a mismatch before its first stack runs, not after."""
    opts = options or LoadOptions()
    path = Path(path)
    if path.suffix.lower() == ".npz":
        return  # one file, read whole: load_npz checks it as it opens it
    files = _folder_files(path, opts)
    keep = selection(len(files.paths), opts.select, opts.max_lights)
    header = image_header(files.paths[keep[0]])
    if header is not None:  # the ROI without its halo: the exact check comes with the load
        t = opts.transforms()
        hh, ww = _held_size(header.shape, t, files.paths[keep[0]])
        check_stack_size(len(keep), hh, ww, opts.max_memory_mb, path, _held_from_header(header, t))


def load_folder(
    folder: Path, options: LoadOptions = LoadOptions(), indices: Sequence[int] | None = None
) -> Stack:
    """A DiLiGenT-layout object folder, or any folder of images plus a lights file.

    ``indices`` (0-based) picks the images to keep; only those are decoded.
    """
    files = _folder_files(folder, options)
    paths, lights_path = files.paths, files.lights_path
    light_dirs, ints = files.light_dirs, files.intensities
    if indices is not None:
        keep = list(indices)
        paths, light_dirs, ints = [paths[i] for i in keep], light_dirs[keep], ints[keep]
    light_dirs = unit_lights(light_dirs, lights_path)
    check_lights(light_dirs, lights_path)
    t, box = (
        options.grown(_stored_shape(paths[0]), paths[0])
        if options.roi_halo
        else (options.transforms(), None)
    )
    images, hw = _read_images(paths, options.threads, t, options.max_memory_mb)
    # read with --auto-mask too: the automatic mask is compared with it (see _finish)
    mask_path = options.mask or _first_existing(folder, MASK_NAMES) or _other_mask(folder)
    mask_arr = t.mask(read_mask(mask_path, hw)) if mask_path else np.ones(images.shape[1:3], bool)
    if mask_path is not None and not mask_arr.any():  # the file's fault, not the stack's
        raise InputError(
            f"mask is empty (no pixel above {mask_threshold(mask_path)} inside the image read)",
            mask_path,
        )
    gt_path = _first_existing(folder, GT_NAMES)
    gt = None
    if gt_path is not None:
        # one parse of a .mat; an .npy or image checked from the handle read
        gt = t.normals(read_normals(gt_path, check_gt_header(gt_path, hw), shape=hw))
    stack = Stack(
        folder_name(folder), images, light_dirs, ints, mask_arr, gt, [p.name for p in paths], folder
    )
    return _finish(replace(stack, roi_box=box), options, mask_path.name if mask_path else "mask")


def _stored_shape(path: Path) -> tuple[int, int]:
    """(H, W) of an image as stored: from its header, else decoded (formats without one)."""
    header = image_header(path)
    return header.shape if header is not None else read_image(path).shape[:2]


def _refuse_repeats(paths: Sequence[Path], listing: Path | None = None) -> None:
    """One photo listed twice would count as two lights (one of them with the wrong
    direction): refused, naming both. Names are compared as the files they reach
    (``./001.png``, ``sub/../001.png`` and a link to it are the same photo). ``listing``:
    filenames.txt (its lines are named), None for a folder's images in name order."""
    seen: dict[Path, int] = {}
    for line, path in enumerate(paths, 1):
        key = Path(os.path.realpath(path))  # a link loop: its own name, refused when read
        if key in seen:
            first = paths[seen[key] - 1]
            if listing is None:
                raise InputError(
                    f"is the same file as {first.name} (through a link): one photo cannot "
                    "stand for two lights",
                    path,
                )
            same = (
                f"{path.name} is listed twice"
                if first.name == path.name
                else f"{first.name} and {path.name} are the same photo"
            )
            raise InputError(
                f"{same} (lines {seen[key]} and {line}): one photo cannot stand for two lights",
                listing,
            )
        seen[key] = line


def _other_mask(folder: Path) -> Path | None:
    """An image named like a mask (``cat.mask.tga``); not a text file or a macOS ``._`` one."""
    return next(
        (
            p
            for p in sorted(folder.iterdir())
            if "mask" in p.stem.lower()
            and p.suffix.lower() in IMAGE_SUFFIXES
            and not p.name.startswith(".")
            and p.is_file()
        ),
        None,
    )


def _npz_array(data: np.lib.npyio.NpzFile, key: str, path: Path) -> np.ndarray:
    arr = np.asarray(data[key])
    _check_numbers(arr.dtype, key, path)
    return arr


def _check_numbers(dtype: np.dtype, key: str, path: Path) -> None:
    if dtype.kind not in "biuf":  # complex, strings, objects: not pixel values
        raise InputError(f"npz array {key!r} has dtype {dtype}; expected numbers", path)


def _check_float32_range(values: np.ndarray, what: str, path: Path) -> None:
    """float64 values beyond float32's range would become inf once held: refused."""
    if values.dtype.kind == "f" and values.dtype.itemsize > 4:
        finite = np.isfinite(values)
        top = np.abs(values, where=finite, out=np.zeros(values.shape)).max(initial=0.0)
        if top > np.finfo(np.float32).max:
            raise InputError(f"npz {what} hold values beyond the float32 range", path)


def _npz_header(data: np.lib.npyio.NpzFile, key: str) -> tuple[tuple[int, ...], np.dtype]:
    """An array's shape and type from its .npy header, without reading (or inflating) the
    data."""
    assert data.zip is not None  # np.load of a zip file
    with data.zip.open(f"{key}.npy") as f:
        return npy_header(f)  # type: ignore[arg-type]


def _held_npz_images(images: np.ndarray, path: Path) -> np.ndarray:
    """Stored images in their held type, converted an image at a time so that only the
    stored array and the held one exist together (no whole-stack temporaries); float64
    values beyond float32's range (they would become inf) are refused."""
    held = held_dtype(images.dtype)
    if images.dtype == held or images.ndim < 3:
        return images
    out = np.empty(images.shape, held)
    for i in range(images.shape[0]):
        _check_float32_range(images[i], "images", path)
        out[i] = images[i]
    return out


def _check_npz_headers(data: np.lib.npyio.NpzFile, path: Path, max_memory_mb: float | None) -> None:
    """Every member that will be read, sized from its header before any is inflated: the
    images against the budget and the pixel limit, the others against what the images allow
    (a zip member may inflate to any size, whatever its name)."""
    shape, dtype = _npz_header(data, "images")
    _check_numbers(dtype, "images", path)
    if len(shape) not in (3, 4):
        raise InputError(f"npz images must be N x H x W (x 3), got {shape}", path)
    n, h, w = shape[:3]
    if h * w > MAX_PIXELS:
        raise InputError(
            f"npz images are {w}x{h} ({h * w / 1e6:.0f} MP), above the "
            f"{MAX_PIXELS / 1e6:.0f} MP limit: refusing to read them",
            path,
        )
    check_stack_size(n, h, w, max_memory_mb, path, held_dtype(dtype))
    held = held_dtype(dtype)
    if max_memory_mb is not None and dtype != held:
        # reading holds the stored array (8 B a float64 value) and the held copy beside it
        stored = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
        need = (stored + n * h * w * 3 * held.itemsize) / 2**20
        if need > max_memory_mb:
            raise InputError(
                f"npz images are {dtype} {shape}: reading them holds {need:.0f} MB (the "
                f"stored array and its {held} copy), above "
                f"{opt('max_memory_mb', max_memory_mb)} MB "
                "(save them as float32 or uint16, or use a larger budget)",
                path,
            )
    most = {"lights": n * 3, "intensities": n * 3, "mask": h * w, "normals": h * w * 3}
    for key, limit in most.items():
        if key not in data.files:
            continue
        found, _ = _npz_header(data, key)
        if key in ("lights", "intensities") and len(found) == 2 and found[1] != 3:
            raise InputError(
                f"npz array {key!r} is {found}: 3 numbers per row expected (x y z / r g b)", path
            )
        if int(np.prod(found, dtype=np.int64)) > limit:
            raise InputError(
                f"npz array {key!r} is {found}: larger than the {key} of {n} images of "
                f"{w}x{h} can be; refusing to read it",
                path,
            )


@dataclass(frozen=True)
class _NpzArrays:
    """What an .npz stack file holds, read and checked (the optional members defaulted)."""

    images: np.ndarray  # N x H x W x 3, in their held type
    lights: np.ndarray
    intensities: np.ndarray
    mask: np.ndarray
    normals: np.ndarray | None


def _check_npz_file(path: Path) -> None:
    """An existing regular file starting with a zip header: np.load would try unpickling
    anything else."""
    if not path.exists():
        raise InputError("stack file not found", path)
    if not path.is_file():
        raise InputError("not a regular file (expected an .npz stack)", path)
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic != b"PK\x03\x04":  # np.load would try unpickling anything else
        raise InputError(
            "not an .npz file (no zip header); expected arrays 'images' and "
            "'lights' saved with numpy.savez",
            path,
        )


def _check_npz_members(files: set[str], path: Path) -> None:
    """The members an .npz stack must hold, and none it may not."""
    if not {"images", "lights"} <= files:
        raise InputError(
            "npz stack needs arrays 'images' and 'lights' (it has "
            f"{', '.join(sorted(files)) or 'none'})",
            path,
        )
    # an unknown member is refused, never skipped ("light_intensities" for "intensities")
    unknown = sorted(files - set(NPZ_MEMBERS))
    if unknown:
        raise InputError(
            f"npz array {unknown[0]!r} is not one of a stack's "
            f"({', '.join(repr(m) for m in NPZ_MEMBERS)})",
            path,
        )


def _npz_images(data: np.lib.npyio.NpzFile, path: Path) -> np.ndarray:
    """The stored images in their held type as N x H x W x 3 (grey ones repeated)."""
    images = _held_npz_images(_npz_array(data, "images", path), path)
    if images.ndim == 4 and images.shape[3] == 1:
        images = images[..., 0]
    if images.ndim == 3:  # grey: repeated once held (float64 would triple 8 B a value)
        images = np.repeat(images[..., None], 3, axis=3)
    if images.ndim != 4 or images.shape[3] != 3 or 0 in images.shape:
        raise InputError(f"npz images must be N x H x W (x 3), got {images.shape}", path)
    return images


def _read_npz(path: Path, max_memory_mb: float | None) -> _NpzArrays:
    """Every member of an .npz stack, sized from its header before any is inflated; a file
    numpy cannot read is an InputError."""
    try:
        data = np.load(path, allow_pickle=False)
        files = set(data.files)
        _check_npz_members(files, path)
        _check_npz_headers(data, path, max_memory_mb)  # before anything inflates
        images = _npz_images(data, path)
        n, h, w = images.shape[:3]
        lights = _npz_array(data, "lights", path)
        ints = (
            _npz_array(data, "intensities", path)
            if "intensities" in files
            else np.ones((n, 3), np.float32)
        )
        mask = _npz_array(data, "mask", path) if "mask" in files else np.ones((h, w), bool)
        gt = _npz_array(data, "normals", path) if "normals" in files else None
        _check_float32_range(lights, "lights", path)
        _check_float32_range(ints, "intensities", path)
        images = as_held(images)  # uint8/uint16 kept: values exact, 2-4x smaller than float32
    except InputError:
        raise
    except Exception as exc:  # zip errors, bad headers, truncated members
        raise InputError(f"cannot read npz stack ({first_line(exc)})", path) from exc
    return _NpzArrays(images, lights, ints, mask, gt)


def _npz_lights(
    arrays: _NpzArrays, path: Path, options: LoadOptions
) -> tuple[np.ndarray, np.ndarray, Path]:
    """The light directions and intensities (the file's, or --lights / --intensities), checked
    against the image count, and the file the directions came from."""
    lights, ints = arrays.lights, arrays.intensities
    n = arrays.images.shape[0]
    if options.lights is not None:
        lights = read_vectors(options.lights, "light directions")
    int_src = _intensities_file(options)
    if int_src is not None:
        ints = read_vectors(int_src, "light intensities")
    lights_src = options.lights or path
    if lights.ndim != 2 or lights.shape[1] != 3:
        raise InputError(
            f"light directions must have 3 numbers per row, got shape {lights.shape}", lights_src
        )
    if len(lights) != n:
        raise InputError(f"{n} images but {len(lights)} light directions", lights_src)
    ints = np.asarray(ints, np.float32)
    if ints.shape != (n, 3):
        raise InputError(
            f"{n} images but light intensities of shape {ints.shape} (expected {n} x 3)",
            int_src or path,
        )
    return lights, ints, lights_src


def _npz_mask_normals(
    arrays: _NpzArrays, path: Path, options: LoadOptions
) -> tuple[np.ndarray, np.ndarray | None]:
    """The mask (the file's, or --mask) and the unit ground-truth normals, checked against the
    image size."""
    h, w = arrays.images.shape[1:3]
    mask, gt = arrays.mask, arrays.normals
    if options.mask is not None:
        mask = read_mask(options.mask, (h, w))
    elif mask.shape != (h, w):
        raise InputError(f"npz mask is {mask.shape} but images are {(h, w)}", path)
    if gt is not None:
        if gt.shape != (h, w, 3):
            raise InputError(f"npz normals are {gt.shape}, expected {(h, w, 3)}", path)
        gt = unit_normals(gt)
    return mask, gt


def load_npz(path: Path, options: LoadOptions = LoadOptions()) -> Stack:
    """An .npz with images (N,H,W,3) and lights (N,3); intensities, mask, normals optional."""
    _check_npz_file(path)
    arrays = _read_npz(path, options.max_memory_mb)
    lights, ints, lights_src = _npz_lights(arrays, path, options)
    mask, gt = _npz_mask_normals(arrays, path, options)
    lights = unit_lights(lights, lights_src)
    stack = Stack(path.stem, arrays.images, lights, ints, as_mask(mask, path), gt, [], path)
    # the files are read: the rest is what prepare_stack does to any in-memory stack
    files_read = replace(options, lights=None, intensities=None, mask=None)
    return prepare_stack(stack.validate(), files_read)


def count_images(folder: Path) -> int:
    """How many images a folder stack holds, without decoding any (0 if unknown)."""
    if not folder.is_dir():
        return 0
    names_file = folder / "filenames.txt"
    if names_file.is_file():
        return len(_names(names_file))
    return len(list_images(folder, strict=False))


def load_stack(path: str | Path, options: LoadOptions | None = None, **overrides: object) -> Stack:
    """Load any supported stack with --select and --max-lights applied (only kept images are
    decoded). Keyword overrides build the options: ``load_stack(p, select="21-96")``."""
    opts = options or LoadOptions()
    if overrides:
        fields = {
            k: Path(str(v)) if k in ("lights", "intensities", "mask") and v is not None else v
            for k, v in overrides.items()
        }
        opts = LoadOptions(**{**opts.__dict__, **fields})
    path = Path(path)
    if path.suffix.lower() == ".npz":
        return load_npz(path, opts)
    count = count_images(path)
    return load_folder(
        path, opts, selection(count, opts.select, opts.max_lights) if count else None
    )
