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

from msfnet.calib.directions import Intrinsics, diagnostic_image, estimate_directions, light_labels
from msfnet.calib.intensities import estimate_intensities, target_normals
from msfnet.calib.options import SHARED, CalibOptions, DirectionsOptions, IntensitiesOptions
from msfnet.calib.sphere import fit_circles_from_images, fit_circles_from_mask
from msfnet.common.cli import (
    Parser,
    add_common_flags,
    add_flags,
    command_main,
    flag_names,
    make_parser,
    options_from_args,
    path_arg,
)
from msfnet.common.errors import InputError
from msfnet.common.files import check_output, same_file, staged_files, vectors_text
from msfnet.common.imageio import IMAGE_SUFFIXES, encode_png, list_images, read_image, read_mask
from msfnet.runtime.stack import read_vectors

PROG = "msf-calib"
EXCLUDE = ("mask", "normal", "albedo", "ambient", "dark", "diagnostic")
IMAGE_OUT = (".png", ".tif", ".tiff", ".bmp", ".jpg")  # what the diagnostic may be saved as


def _named(folder: Path, words: tuple[str, ...]) -> Path | None:
    # every suffix list_images reads: a mask.jpg it leaves out as an image must be used here
    named = [p for p in folder.iterdir() if any(w in p.stem.lower() for w in words)]
    hits = sorted(p for p in named if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
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


def _check_options(options: CalibOptions) -> None:
    """Option values argparse types cannot judge alone, checked before any image is read."""
    if not options.output.name:
        # "." or "/": the names of the other outputs are derived from this one's
        raise InputError("-o names the output text file, not a folder", options.output)
    if options.intrinsics:
        fx, fy = options.intrinsics[:2]
        if not (fx > 0 and fy > 0):
            # fx = 0 makes every view ray NaN, and LAPACK then spins forever
            raise InputError(
                f"--intrinsics: FX and FY must be positive focal lengths in "
                f"pixels, got {fx:g} {fy:g}"
            )
        if options.focal:
            raise InputError("--focal and --intrinsics contradict each other; give one")


def _intrinsics(options: CalibOptions, shape: tuple[int, int]) -> Intrinsics | None:
    """The camera the options describe, checked against the images' size: finite but absurd
    values (``--focal 1e-300``, a principal point at 1e308) wrote NaN light directions."""
    if options.intrinsics:
        intr, option = Intrinsics(*options.intrinsics), "--intrinsics"
    elif options.focal:
        intr = Intrinsics(options.focal, options.focal, (shape[1] - 1) / 2, (shape[0] - 1) / 2)
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


def _diagnostic_paths(options: DirectionsOptions, captures: int) -> list[Path]:
    out = options.output
    if options.no_diagnostic:
        return []
    if options.diagnostic:
        base = options.diagnostic
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


def _say(options: CalibOptions, text: str) -> None:
    if not options.quiet:
        print(text)


def _warn(options: CalibOptions, text: str) -> None:
    """``msf-calib: warning: <image>: ...`` on stderr; not with -q (errors only)."""
    if not options.quiet:
        print(f"{PROG}: warning: {text}", file=sys.stderr)


def cmd_directions(options: DirectionsOptions) -> int:
    _check_options(options)
    out = options.output
    folders = list(options.images_dir)
    for k, folder in enumerate(folders):  # one capture twice would weigh double in the mean
        twin = next((f for f in folders[:k] if same_file(f, folder)), None)
        if twin is not None:
            raise InputError(f"given twice (also as {twin}): give each capture once", folder)
    diag_paths = _diagnostic_paths(options, len(folders))
    conf_path = out.with_name(out.stem + "_confidence.txt")
    inputs: list[Path | None] = [*folders, options.mask, options.ambient]
    _check_outputs([out, conf_path, *diag_paths], inputs, options.overwrite)
    captures: list[np.ndarray] = []
    circles, names, diag = [], None, []
    ambients, fitted = [], []
    for k, folder in enumerate(folders):
        imgs, paths, amb = load_capture(folder, options.ambient, options.no_ambient)
        if captures and len(imgs) != len(captures[0]):
            raise InputError(
                f"{len(imgs)} images but {folders[0]} has {len(captures[0])}: every capture "
                "holds one image per light",
                folder,
            )
        circ, mpath = _circles(folder, imgs, options.mask, options.spheres)
        how = f"mask {mpath.name}" if mpath else "fitted from the images (no mask)"
        for c in circ:
            _say(
                options,
                f"capture {k + 1}: sphere at ({c.cx:.2f}, {c.cy:.2f}) r={c.r:.2f} px, {how}",
            )
        captures.append(imgs)
        circles.append(circ)
        fitted.append(mpath is None)
        ambients.append(amb)
        names = names or [p.name for p in paths]
        diag.append((imgs, circ))
    intr = _intrinsics(options, captures[0].shape[1:3])
    names = names or []
    res = estimate_directions(
        captures, circles, intr, ambients, names=names, source=folders[0], fitted=fitted
    )
    _check_result(res.directions, "light directions", unit=True)
    for w in res.warnings:
        _warn(options, w)
    pairs = zip(res.confidence, res.spread_deg, strict=True)
    confidence = "".join(f"{c:.4f} {s:.3f}\n" for c, s in pairs)
    writers: list[tuple[Path, Callable[[Path], None]]] = [
        (out, _text_writer(vectors_text(res.directions))),
        (conf_path, _text_writer(confidence)),
    ]
    labels = light_labels(names)
    for k, ((imgs, circ), dpath) in enumerate(zip(diag, diag_paths, strict=False)):
        picture = diagnostic_image(imgs, circ, res.estimates, capture=k, labels=labels)
        writers.append((dpath, _png_writer(picture, dpath)))
    _commit(writers, options.overwrite)
    for stale in _stale_diagnostics(out, diag_paths):
        _warn(options, f"{stale}: from an earlier run (this run wrote no image of that name)")
    _say(options, f"{len(res.directions)} light directions -> {out} (x right, y up, z to camera)")
    for i, (d, c) in enumerate(zip(res.directions, res.confidence, strict=True)):
        _say(options, f"  {names[i]:>20s}: {d[0]:+.4f} {d[1]:+.4f} {d[2]:+.4f}  confidence {c:.2f}")
    _say(options, f"confidence -> {conf_path}")
    for dpath in diag_paths:
        _say(options, f"diagnostic image -> {dpath}")
    return 0


def cmd_intensities(options: IntensitiesOptions) -> int:
    _check_options(options)
    out = options.output
    folder = options.images_dir
    lights_path = options.lights
    _check_outputs([out], [folder, lights_path, options.mask, options.ambient], options.overwrite)
    if options.normal is not None and options.target != "plane":
        raise InputError("--normal is the plane target's: add --target plane, or leave it out")
    normal = np.asarray(options.normal or (0.0, 0.0, 1.0), np.float64)
    if options.target == "plane" and not (np.linalg.norm(normal) > 0 and normal[2] > 0):
        raise InputError(
            f"--normal {' '.join(f'{v:g}' for v in normal)}: the plane normal must "
            "be non-zero and face the camera (z > 0)"
        )
    imgs, paths, amb = load_capture(folder, options.ambient, options.no_ambient)
    lights = read_vectors(lights_path, "light directions").astype(np.float64)
    if len(lights) != len(imgs):
        raise InputError(
            f"{len(lights)} light directions for {len(imgs)} images in {folder}", lights_path
        )
    if np.any(np.linalg.norm(lights, axis=1) < 1e-6):
        raise InputError("zero-length light direction", lights_path)
    mask_path = options.mask or _named(folder, ("mask",))
    mask = read_mask(mask_path, imgs.shape[1:3]) if mask_path else None
    intr = _intrinsics(options, imgs.shape[1:3])
    if options.target == "sphere":
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
        accept_poor_fit=options.accept_poor_fit,
        plane=options.target == "plane",
    )
    _check_result(ints, "light intensities", unit=False)
    for w in warnings:
        _warn(options, w)
    _commit([(out, _text_writer(vectors_text(ints)))], options.overwrite)
    _say(
        options,
        f"{len(ints)} RGB light intensities (mean 1) -> {out}"
        + ("" if amb is not None else " (no ambient frame subtracted)"),
    )
    return 0


def _add_shared(sp: argparse.ArgumentParser, options: type[CalibOptions]) -> None:
    """The options both sub-commands take, after their own: output, mask, ambient frame,
    camera model, --overwrite."""
    add_common_flags(sp, sub_command=True)  # before or after the sub-command's name
    sp.add_argument("-o", "--output", type=path_arg, required=True, help="output text file")
    add_flags(sp, options, only=flag_names(options, SHARED))


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
    add_flags(d, DirectionsOptions, only=flag_names(DirectionsOptions, ""))
    _add_shared(d, DirectionsOptions)


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
    add_flags(i, IntensitiesOptions, only=flag_names(IntensitiesOptions, ""))
    _add_shared(i, IntensitiesOptions)


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


def _main(args: argparse.Namespace) -> int:
    """The sub-command's options, built once from the flags, and its run."""
    given = {"output": args.output, "quiet": args.quiet}
    if args.command == "directions":
        given["images_dir"] = tuple(args.images_dir)
        return cmd_directions(options_from_args(DirectionsOptions, args, overrides=given))
    given["images_dir"] = args.images_dir
    return cmd_intensities(options_from_args(IntensitiesOptions, args, overrides=given))


def main(argv: list[str] | None = None) -> int:
    return command_main(PROG, build_parser(), _main, argv)


if __name__ == "__main__":
    sys.exit(main())
