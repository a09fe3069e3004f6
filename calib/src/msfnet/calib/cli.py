"""``msf-calib``: light directions from mirror spheres, light intensities from a matte target.

Every output of a run (the lights file, ``<output>_confidence.txt``, the diagnostic images)
appears together or not at all, never replaces a file without ``--overwrite`` and never
replaces or lands inside an input.
"""

from __future__ import annotations

import argparse
import glob
import re
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

from msfnet.calib.directions import (
    Intrinsics,
    diagnostic_image,
    estimate_directions,
    light_labels,
)
from msfnet.calib.intensities import estimate_intensities, target_normals
from msfnet.calib.sphere import fit_circles_from_images, fit_circles_from_mask
from msfnet.common.cli import (
    Parser,
    add_common_flags,
    command_main,
    finite_float,
    int_range,
    make_parser,
    path_arg,
    positive_float,
)
from msfnet.common.errors import InputError
from msfnet.common.files import check_output, same_file, staged_files, vectors_text
from msfnet.common.imageio import (
    IMAGE_SUFFIXES,
    encode_png,
    list_images,
    read_image,
    read_mask,
)
from msfnet.runtime.stack import read_vectors

PROG = "msf-calib"
EXCLUDE = ("mask", "normal", "albedo", "ambient", "dark", "diagnostic")
MAX_SPHERES = 16
IMAGE_OUT = (".png", ".tif", ".tiff", ".bmp", ".jpg")  # what the diagnostic may be saved as


def _named(folder: Path, words: tuple[str, ...]) -> Path | None:
    # every suffix list_images reads: a mask.jpg it leaves out as an image must be used here
    hits = sorted(
        p
        for p in folder.iterdir()
        if p.is_file()
        and any(w in p.stem.lower() for w in words)
        and p.suffix.lower() in IMAGE_SUFFIXES
    )
    return hits[0] if hits else None


def _as_rgb(img: np.ndarray) -> np.ndarray:
    return np.repeat(img[:, :, None], 3, axis=2) if img.ndim == 2 else img


def load_capture(
    folder: Path, ambient: Path | None, no_ambient: bool
) -> tuple[np.ndarray, list[Path], np.ndarray | None]:
    if not folder.is_dir():
        raise InputError("images folder not found", folder)
    paths = list_images(folder, exclude=EXCLUDE)
    if not paths:
        raise InputError("no images found (PNG, TIFF or TGA)", folder)
    imgs = [read_image(p) for p in paths]
    first = imgs[0]
    for p, im in zip(paths, imgs, strict=True):
        if im.shape[:2] != first.shape[:2]:
            raise InputError(
                f"image size {im.shape[1]}x{im.shape[0]} differs from {paths[0].name}", p
            )
        if im.dtype != first.dtype:
            # the white level (saturation test) comes from the bit depth: one per capture
            raise InputError(
                f"image is {im.dtype} but {paths[0].name} is {first.dtype}: one "
                "bit depth per capture",
                p,
            )
    if len({im.ndim for im in imgs}) > 1:  # grey and colour frames mixed: compare as colour
        imgs = [_as_rgb(im) for im in imgs]
    amb_path = None if no_ambient else (ambient or _named(folder, ("ambient", "dark")))
    amb = read_image(amb_path) if amb_path else None
    if amb is not None and amb_path is not None:
        if amb.shape[:2] != first.shape[:2]:
            raise InputError("ambient frame size differs from the images", amb_path)
        if amb.dtype != first.dtype:
            raise InputError(
                f"ambient frame is {amb.dtype} but the images are {first.dtype}", amb_path
            )
        if amb.ndim != imgs[0].ndim:
            amb = _as_rgb(amb)
            imgs = [_as_rgb(im) for im in imgs]
    return np.stack(imgs), paths, amb


def _check_options(args: argparse.Namespace) -> None:
    """Option values argparse types cannot judge alone, checked before any image is read."""
    if not Path(args.output).name:
        # "." or "/": the names of the other outputs are derived from this one's
        raise InputError("-o names the output text file, not a folder", args.output)
    if args.intrinsics:
        fx, fy = args.intrinsics[:2]
        if not (fx > 0 and fy > 0):
            # fx = 0 makes every view ray NaN, and LAPACK then spins forever
            raise InputError(
                f"--intrinsics: FX and FY must be positive focal lengths in "
                f"pixels, got {fx:g} {fy:g}"
            )
        if args.focal:
            raise InputError("--focal and --intrinsics contradict each other; give one")


def _intrinsics(args: argparse.Namespace, shape: tuple[int, int]) -> Intrinsics | None:
    """The camera the options describe, checked against the images' size: finite but absurd
    values (``--focal 1e-300``, a principal point at 1e308) wrote NaN light directions."""
    if args.intrinsics:
        intr, option = Intrinsics(*args.intrinsics), "--intrinsics"
    elif args.focal:
        intr = Intrinsics(args.focal, args.focal, (shape[1] - 1) / 2, (shape[0] - 1) / 2)
        option = "--focal"
    else:
        return None
    intr.check_for(shape, option)
    return intr


def _check_result(rows: np.ndarray, what: str, unit: bool) -> None:
    """What is about to be written: finite, and unit length for directions. A failure here is
    a case the option checks missed; it must never be written with exit 0."""
    rows = np.asarray(rows, np.float64)
    bad = ~np.all(np.isfinite(rows), axis=1)
    if unit:
        with np.errstate(invalid="ignore"):
            bad |= ~(np.abs(np.linalg.norm(rows, axis=1) - 1.0) < 1e-6)
    if bad.any():
        camera = " (check --focal / --intrinsics)" if unit else ""
        raise InputError(
            f"{what} came out {'non-finite or not unit length' if unit else 'non-finite'} for "
            f"light(s) {(np.flatnonzero(bad) + 1).tolist()[:6]}{camera}; nothing was written"
        )


def _circles(folder: Path, imgs: np.ndarray, mask: Path | None, spheres: int):
    mask_path = mask or _named(folder, ("mask",))
    if mask_path is not None:
        return fit_circles_from_mask(
            read_mask(mask_path, imgs.shape[1:3]), source=mask_path
        ), mask_path
    return fit_circles_from_images(imgs, spheres, source=folder), None


def _diagnostic_paths(args: argparse.Namespace, out: Path, captures: int) -> list[Path]:
    if args.no_diagnostic:
        return []
    if args.diagnostic:
        base = Path(args.diagnostic)
        if base.suffix.lower() not in IMAGE_OUT:
            # ".png" alone is a hidden file with no suffix, hence "a name and an ending"
            raise InputError(
                f"--diagnostic: needs a file name ending in {', '.join(IMAGE_OUT)} "
                "(e.g. chrome_diagnostic.png)",
                base,
            )
        if captures == 1:
            return [base]
        return [
            base.with_name(f"{base.stem}_{k + 1}{base.suffix or '.png'}") for k in range(captures)
        ]
    suffixes = [""] if captures == 1 else [f"_{k + 1}" for k in range(captures)]
    return [out.with_name(f"{out.stem}_diagnostic{s}.png") for s in suffixes]


def _stale_diagnostics(out: Path, written: list[Path]) -> list[Path]:
    """Default-named diagnostics of ``out`` left by an earlier run that this one did not
    replace (``--overwrite --no-diagnostic``, or one capture where there were two): beside
    new lights they would describe old ones. Named, not deleted: they may be kept on purpose."""
    mine = {p.resolve() for p in written}
    default = re.compile(re.escape(out.stem) + r"_diagnostic(_[1-9][0-9]*)?\.png")
    found = out.parent.glob(glob.escape(out.stem) + "_diagnostic*.png")
    stale = {}
    for p in found:
        m = default.fullmatch(p.name)
        if m and p.is_file() and p.resolve() not in mine:
            stale[int(m[1][1:]) if m[1] else 0] = p
    return [stale[k] for k in sorted(stale)]


def _check_outputs(outputs: list[Path], inputs: list[Path | None], overwrite: bool) -> None:
    """Before any work: every output is new (or --overwrite), none is an input or lies inside
    an input folder, and no two outputs are the same file."""
    seen: dict[Path, Path] = {}
    for path in outputs:
        key = path.resolve()
        if key in seen:
            raise InputError(
                f"two outputs of this run are the same file ({seen[key]}); choose "
                "another --diagnostic or -o",
                path,
            )
        seen[key] = path
        check_output(path, inputs, overwrite=overwrite)


def _commit(writers: list[tuple[Path, Callable[[Path], None]]], overwrite: bool) -> None:
    """Write every output or none (staged, renamed together)."""
    with staged_files([p for p, _ in writers], overwrite=overwrite) as temps:
        for tmp, (target, write) in zip(temps, writers, strict=True):
            try:
                write(tmp)
            except OSError as exc:  # a full disk: name the output, not its hidden temporary
                if exc.filename is not None or exc.errno is None:
                    raise
                raise OSError(exc.errno, exc.strerror, str(target)) from exc


def _text_writer(text: str) -> Callable[[Path], None]:
    def write(tmp: Path) -> None:
        tmp.write_text(text)

    return write


def _png_writer(rgb: np.ndarray, target: Path) -> Callable[[Path], None]:
    def write(tmp: Path) -> None:
        # the staging name ends in the target's suffix, so OpenCV picks the encoder from it
        encode_png(tmp, rgb, name=target)

    return write


def _say(args: argparse.Namespace, text: str) -> None:
    if not args.quiet:
        print(text)


def _warn(args: argparse.Namespace, text: str) -> None:
    """``msf-calib: warning: <image>: ...`` on stderr; not with -q (errors only)."""
    if not args.quiet:
        print(f"{PROG}: warning: {text}", file=sys.stderr)


def cmd_directions(args: argparse.Namespace) -> int:
    _check_options(args)
    out = Path(args.output)
    folders = [Path(f) for f in args.images_dir]
    for k, folder in enumerate(folders):  # one capture twice would weigh double in the mean
        twin = next((f for f in folders[:k] if same_file(f, folder)), None)
        if twin is not None:
            raise InputError(f"given twice (also as {twin}): give each capture once", folder)
    diag_paths = _diagnostic_paths(args, out, len(folders))
    conf_path = out.with_name(out.stem + "_confidence.txt")
    inputs: list[Path | None] = [*folders, args.mask, args.ambient]
    _check_outputs([out, conf_path, *diag_paths], inputs, args.overwrite)
    captures: list[np.ndarray] = []
    circles, names, diag = [], None, []
    ambients, fitted = [], []
    for k, folder in enumerate(folders):
        imgs, paths, amb = load_capture(folder, args.ambient, args.no_ambient)
        if captures and len(imgs) != len(captures[0]):
            raise InputError(
                f"{len(imgs)} images but {folders[0]} has {len(captures[0])}: every capture "
                "holds one image per light",
                folder,
            )
        circ, mpath = _circles(folder, imgs, args.mask, args.spheres)
        how = f"mask {mpath.name}" if mpath else "fitted from the images (no mask)"
        for c in circ:
            _say(args, f"capture {k + 1}: sphere at ({c.cx:.2f}, {c.cy:.2f}) r={c.r:.2f} px, {how}")
        captures.append(imgs)
        circles.append(circ)
        fitted.append(mpath is None)
        ambients.append(amb)
        names = names or [p.name for p in paths]
        diag.append((imgs, circ))
    intr = _intrinsics(args, captures[0].shape[1:3])
    names = names or []
    res = estimate_directions(
        captures, circles, intr, ambients, names=names, source=folders[0], fitted=fitted
    )
    _check_result(res.directions, "light directions", unit=True)
    for w in res.warnings:
        _warn(args, w)
    writers: list[tuple[Path, Callable[[Path], None]]] = [
        (out, _text_writer(vectors_text(res.directions))),
        (
            conf_path,
            _text_writer(
                "".join(
                    f"{c:.4f} {s:.3f}\n"
                    for c, s in zip(res.confidence, res.spread_deg, strict=True)
                )
            ),
        ),
    ]
    for k, ((imgs, circ), dpath) in enumerate(zip(diag, diag_paths, strict=False)):
        writers.append(
            (
                dpath,
                _png_writer(
                    diagnostic_image(
                        imgs, circ, res.estimates, capture=k, labels=light_labels(names)
                    ),
                    dpath,
                ),
            )
        )
    _commit(writers, args.overwrite)
    for stale in _stale_diagnostics(out, diag_paths):
        _warn(args, f"{stale}: from an earlier run (this run wrote no image of that name)")
    _say(args, f"{len(res.directions)} light directions -> {out} (x right, y up, z to camera)")
    for i, (d, c) in enumerate(zip(res.directions, res.confidence, strict=True)):
        _say(args, f"  {names[i]:>20s}: {d[0]:+.4f} {d[1]:+.4f} {d[2]:+.4f}  confidence {c:.2f}")
    _say(args, f"confidence -> {conf_path}")
    for dpath in diag_paths:
        _say(args, f"diagnostic image -> {dpath}")
    return 0


def cmd_intensities(args: argparse.Namespace) -> int:
    _check_options(args)
    out = Path(args.output)
    folder = Path(args.images_dir)
    lights_path = Path(args.lights)
    _check_outputs([out], [folder, lights_path, args.mask, args.ambient], args.overwrite)
    if args.normal is not None and args.target != "plane":
        raise InputError("--normal is the plane target's: add --target plane, or leave it out")
    normal = np.asarray(args.normal or (0.0, 0.0, 1.0), np.float64)
    if args.target == "plane" and not (np.linalg.norm(normal) > 0 and normal[2] > 0):
        raise InputError(
            f"--normal {' '.join(f'{v:g}' for v in normal)}: the plane normal must "
            "be non-zero and face the camera (z > 0)"
        )
    imgs, paths, amb = load_capture(folder, args.ambient, args.no_ambient)
    lights = read_vectors(lights_path, "light directions").astype(np.float64)
    if len(lights) != len(imgs):
        raise InputError(
            f"{len(lights)} light directions for {len(imgs)} images in {folder}", lights_path
        )
    if np.any(np.linalg.norm(lights, axis=1) < 1e-6):
        raise InputError("zero-length light direction", lights_path)
    mask_path = args.mask or _named(folder, ("mask",))
    mask = read_mask(mask_path, imgs.shape[1:3]) if mask_path else None
    intr = _intrinsics(args, imgs.shape[1:3])
    if args.target == "sphere":
        circ = (
            fit_circles_from_mask(mask, source=mask_path)
            if mask is not None
            else fit_circles_from_images(imgs, source=folder)
        )[0]
        normals, valid = target_normals(imgs.shape[1:3], circle=circ, mask=mask, intrinsics=intr)
    else:
        normals, valid = target_normals(imgs.shape[1:3], plane_normal=normal, mask=mask)
    ints, warnings = estimate_intensities(
        imgs,
        lights,
        normals,
        valid,
        amb,
        names=[p.name for p in paths],
        source=folder,
        accept_poor_fit=args.accept_poor_fit,
        plane=args.target == "plane",
    )
    _check_result(ints, "light intensities", unit=False)
    for w in warnings:
        _warn(args, w)
    _commit([(out, _text_writer(vectors_text(ints)))], args.overwrite)
    _say(
        args,
        f"{len(ints)} RGB light intensities (mean 1) -> {out}"
        + ("" if amb is not None else " (no ambient frame subtracted)"),
    )
    return 0


def _add_common(sp: argparse.ArgumentParser) -> None:
    """The options both sub-commands take, after their own: output, mask, ambient frame,
    camera model, --overwrite."""
    add_common_flags(sp, sub_command=True)  # before or after the sub-command's name
    sp.add_argument("-o", "--output", type=path_arg, required=True, help="output text file")
    sp.add_argument(
        "--mask",
        type=path_arg,
        help="target mask image (default: a file in the "
        "folder with 'mask' in its name; else the sphere is fitted from images)",
    )
    sp.add_argument(
        "--ambient",
        type=path_arg,
        help="dark/ambient frame to subtract (default: a "
        "file with 'ambient' or 'dark' in its name)",
    )
    sp.add_argument("--no-ambient", action="store_true", help="do not subtract any frame")
    sp.add_argument(
        "--focal",
        type=positive_float,
        help="perspective: focal length in "
        "pixels, principal point at the image centre (default: orthographic)",
    )
    sp.add_argument(
        "--intrinsics",
        type=finite_float,
        nargs=4,
        metavar=("FX", "FY", "CX", "CY"),
        help="perspective: full pinhole intrinsics in pixels (FX, FY > 0)",
    )
    sp.add_argument(
        "--overwrite",
        action="store_true",
        help="replace existing outputs (lights, confidence, diagnostic files)",
    )


def _add_directions(sub: argparse._SubParsersAction[Parser]) -> None:
    """The ``directions`` sub-command: mirror-sphere folders, spheres, diagnostic image."""
    d = sub.add_parser(
        "directions",
        help="light directions from mirror-sphere images",
        description="One x y z row per image (natural file order), DiLiGenT "
        "frame, plus <output>_confidence.txt and a diagnostic image. Several "
        "folders = several captures of the same lights, averaged. Several blobs "
        "in the mask = several spheres, averaged.",
    )
    d.add_argument("images_dir", nargs="+", type=path_arg, help="folder(s) of mirror-sphere images")
    d.add_argument(
        "--spheres",
        type=int_range(1, MAX_SPHERES),
        default=1,
        help="spheres to find when there is no mask (default 1)",
    )
    d.add_argument(
        "--diagnostic",
        type=path_arg,
        help="diagnostic PNG path (default "
        "<output>_diagnostic.png; with several captures, _1, _2, ... are appended)",
    )
    d.add_argument("--no-diagnostic", action="store_true", help="write no diagnostic image")
    _add_common(d)
    d.set_defaults(func=cmd_directions)


def _add_intensities(sub: argparse._SubParsersAction[Parser]) -> None:
    """The ``intensities`` sub-command: white-target folder, lights file, target shape."""
    i = sub.add_parser(
        "intensities",
        help="RGB light intensities from a matte white target",
        description="One r g b row per image, scaled to mean 1.",
    )
    i.add_argument(
        "images_dir", type=path_arg, help="folder of images of a matte white sphere or plane"
    )
    i.add_argument(
        "--lights", type=path_arg, required=True, help="light_directions.txt for these images"
    )
    i.add_argument(
        "--target",
        choices=("sphere", "plane"),
        default="sphere",
        help="the white target's shape (default sphere; plane: see --normal)",
    )
    i.add_argument(
        "--normal",
        type=finite_float,
        nargs=3,
        default=None,
        metavar=("X", "Y", "Z"),
        help="plane normal, with --target plane (default 0 0 1, facing the camera)",
    )
    i.add_argument(
        "--accept-poor-fit",
        action="store_true",
        help="write the intensities even when the target fits matte shading poorly (fit "
        "residual above 20%%: usually wrong light directions or a glossy target); a warning "
        "says so",
    )
    _add_common(i)
    i.set_defaults(func=cmd_intensities)


def build_parser() -> argparse.ArgumentParser:
    p = make_parser(
        PROG,
        "Light directions from mirror-sphere images; RGB light intensities from a matte "
        "white target. All outputs of a run are written together or not at all.",
        (
            "msf-calib directions chrome/ -o light_directions.txt",
            "msf-calib intensities white/ --lights light_directions.txt -o light_intensities.txt",
        ),
    )
    sub = p.add_subparsers(dest="command", required=True, metavar="{directions,intensities}")
    _add_directions(sub)
    _add_intensities(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    return command_main(PROG, build_parser(), lambda args: args.func(args), argv)


if __name__ == "__main__":
    sys.exit(main())
