"""``msf-calib``: light directions from mirror spheres, light intensities from a matte target."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from msfnet.runtime.errors import InputError
from msfnet.runtime.files import write_atomic
from msfnet.runtime.imageio import list_images, read_image, read_mask, write_png
from msfnet.runtime.stack import read_vectors

from .directions import Intrinsics, diagnostic_image, estimate_directions
from .intensities import estimate_intensities, target_normals
from .sphere import fit_circles_from_images, fit_circles_from_mask

EXCLUDE = ("mask", "normal", "albedo", "ambient", "dark", "diagnostic")


def _named(folder: Path, words: tuple[str, ...]) -> Path | None:
    hits = sorted(p for p in folder.iterdir() if p.is_file() and
                  any(w in p.stem.lower() for w in words) and p.suffix.lower() in
                  (".png", ".tif", ".tiff", ".tga", ".bmp"))
    return hits[0] if hits else None


def load_capture(folder: Path, ambient: Path | None, no_ambient: bool
                 ) -> tuple[np.ndarray, list[Path], np.ndarray | None]:
    if not folder.is_dir():
        raise InputError("images folder not found", folder)
    paths = list_images(folder, exclude=EXCLUDE)
    if not paths:
        raise InputError("no images found (PNG, TIFF or TGA)", folder)
    imgs = [read_image(p) for p in paths]
    for p, im in zip(paths, imgs, strict=True):
        if im.shape[:2] != imgs[0].shape[:2]:
            raise InputError(f"image size {im.shape[1]}x{im.shape[0]} differs from "
                             f"{paths[0].name}", p)
    amb_path = None if no_ambient else (ambient or _named(folder, ("ambient", "dark")))
    amb = read_image(amb_path) if amb_path else None
    if amb is not None and amb.shape[:2] != imgs[0].shape[:2]:
        raise InputError("ambient frame size differs from the images", amb_path)
    return np.stack(imgs), paths, amb


def _intrinsics(args: argparse.Namespace, shape: tuple[int, int]) -> Intrinsics | None:
    if args.intrinsics:
        fx, fy, cx, cy = args.intrinsics
        return Intrinsics(fx, fy, cx, cy)
    if args.focal:
        return Intrinsics(args.focal, args.focal, (shape[1] - 1) / 2, (shape[0] - 1) / 2)
    return None


def _circles(folder: Path, imgs: np.ndarray, mask: Path | None, spheres: int):
    mask_path = mask or _named(folder, ("mask",))
    if mask_path is not None:
        return fit_circles_from_mask(read_mask(mask_path, imgs.shape[1:3])), mask_path
    return fit_circles_from_images(imgs, spheres), None


def _refuse_clobber(path: Path, overwrite: bool) -> None:
    if path.exists() and not overwrite:
        raise InputError("output exists (pass --overwrite to replace it)", path)


def _write_rows(path: Path, rows: np.ndarray) -> None:
    text = "".join(" ".join(f"{v:.8f}" for v in r) + "\n" for r in rows)
    write_atomic(path, lambda tmp: tmp.write_text(text))


def cmd_directions(args: argparse.Namespace) -> None:
    out = Path(args.output)
    _refuse_clobber(out, args.overwrite)
    captures, circles, names, diag = [], [], None, []
    ambients = []
    for k, folder in enumerate(map(Path, args.images_dir)):
        imgs, paths, amb = load_capture(folder, args.ambient, args.no_ambient)
        circ, mpath = _circles(folder, imgs, args.mask, args.spheres)
        how = f"mask {mpath.name}" if mpath else "fitted from the images (no mask)"
        for c in circ:
            print(f"capture {k + 1}: sphere at ({c.cx:.2f}, {c.cy:.2f}) r={c.r:.2f} px, {how}")
        captures.append(imgs)
        circles.append(circ)
        ambients.append(amb)
        names = names or [p.name for p in paths]
        diag.append((imgs, circ))
    intr = _intrinsics(args, captures[0].shape[1:3])
    names = names or []
    res = estimate_directions(captures, circles, intr, ambients, names=names)
    for w in res.warnings:
        print(f"warning: {w}", file=sys.stderr)
    _write_rows(out, res.directions)
    print(f"{len(res.directions)} light directions -> {out} (x right, y up, z to camera)")
    for i, (d, c) in enumerate(zip(res.directions, res.confidence, strict=True)):
        print(f"  {names[i]:>20s}: {d[0]:+.4f} {d[1]:+.4f} {d[2]:+.4f}  confidence {c:.2f}")
    conf_path = out.with_name(out.stem + "_confidence.txt")
    write_atomic(conf_path, lambda t: t.write_text(
        "".join(f"{c:.4f} {s:.3f}\n" for c, s in zip(res.confidence, res.spread_deg,
                                                    strict=True))))
    if not args.no_diagnostic:
        for k, (imgs, circ) in enumerate(diag):
            suffix = "" if len(diag) == 1 else f"_{k + 1}"
            dpath = Path(args.diagnostic) if args.diagnostic and len(diag) == 1 else \
                out.with_name(out.stem + f"_diagnostic{suffix}.png")
            write_png(dpath, diagnostic_image(imgs, circ, res.estimates, capture=k))
            print(f"diagnostic image -> {dpath}")


def cmd_intensities(args: argparse.Namespace) -> None:
    out = Path(args.output)
    _refuse_clobber(out, args.overwrite)
    folder = Path(args.images_dir)
    imgs, paths, amb = load_capture(folder, args.ambient, args.no_ambient)
    lights = read_vectors(Path(args.lights), "light directions").astype(np.float64)
    if len(lights) != len(imgs):
        raise InputError(f"{len(lights)} light directions for {len(imgs)} images in {folder}",
                         args.lights)
    mask_path = args.mask or _named(folder, ("mask",))
    mask = read_mask(mask_path, imgs.shape[1:3]) if mask_path else None
    intr = _intrinsics(args, imgs.shape[1:3])
    if args.target == "sphere":
        circ = (fit_circles_from_mask(mask) if mask is not None
                else fit_circles_from_images(imgs))[0]
        normals, valid = target_normals(imgs.shape[1:3], circle=circ, mask=mask,
                                        intrinsics=intr)
    else:
        normals, valid = target_normals(imgs.shape[1:3], plane_normal=np.asarray(args.normal),
                                        mask=mask)
    ints, warnings = estimate_intensities(imgs, lights, normals, valid, amb,
                                          names=[p.name for p in paths])
    for w in warnings:
        print(f"warning: {w}", file=sys.stderr)
    _write_rows(out, ints)
    print(f"{len(ints)} RGB light intensities (mean 1) -> {out}"
          + ("" if amb is not None else " (no ambient frame subtracted)"))


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="msf-calib", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)

    def common(sp: argparse.ArgumentParser) -> None:
        sp.add_argument("-o", "--output", required=True, help="output text file")
        sp.add_argument("--mask", type=Path, help="target mask image (default: a file in the "
                        "folder with 'mask' in its name; else the sphere is fitted from images)")
        sp.add_argument("--ambient", type=Path, help="dark/ambient frame to subtract (default: a "
                        "file with 'ambient' or 'dark' in its name)")
        sp.add_argument("--no-ambient", action="store_true", help="do not subtract any frame")
        sp.add_argument("--focal", type=float, help="perspective: focal length in pixels, "
                        "principal point at the image centre (default: orthographic)")
        sp.add_argument("--intrinsics", type=float, nargs=4, metavar=("FX", "FY", "CX", "CY"),
                        help="perspective: full pinhole intrinsics in pixels")
        sp.add_argument("--overwrite", action="store_true", help="replace existing output")

    d = sub.add_parser("directions", help="light directions from mirror-sphere images",
                       description="One x y z row per image (natural file order), DiLiGenT "
                       "frame. Several folders = several captures of the same lights, averaged. "
                       "Several blobs in the mask = several spheres, averaged.")
    d.add_argument("images_dir", nargs="+", help="folder(s) of mirror-sphere images")
    d.add_argument("--spheres", type=int, default=1, help="spheres to find when there is no "
                   "mask (default 1)")
    d.add_argument("--diagnostic", help="diagnostic PNG path (default <output>_diagnostic.png)")
    d.add_argument("--no-diagnostic", action="store_true")
    common(d)
    d.set_defaults(func=cmd_directions)

    i = sub.add_parser("intensities", help="RGB light intensities from a matte white target",
                       description="One r g b row per image, scaled to mean 1.")
    i.add_argument("images_dir", help="folder of images of a matte white sphere or plane")
    i.add_argument("--lights", required=True, help="light_directions.txt for these images")
    i.add_argument("--target", choices=("sphere", "plane"), default="sphere")
    i.add_argument("--normal", type=float, nargs=3, default=(0.0, 0.0, 1.0),
                   metavar=("X", "Y", "Z"), help="plane normal (default 0 0 1, facing camera)")
    common(i)
    i.set_defaults(func=cmd_intensities)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        args.func(args)
    except InputError as exc:
        print(f"msf-calib: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
