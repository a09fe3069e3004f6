"""``msf-synth``: render a benchmark root of synthetic objects in the DiLiGenT layout."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from msfnet.common.cli import (
    command_main,
    int_range,
    make_parser,
    nonnegative_int,
    path_arg,
    positive_int,
)
from msfnet.common.errors import InputError
from msfnet.common.files import check_output, json_text, staged_folder
from msfnet.runtime.stack import save_stack
from msfnet.synth.materials import ALL_KINDS
from msfnet.synth.render import PRESETS, RenderOptions, render_set
from msfnet.synth.shapes import ALL_SHAPES

PROG = "msf-synth"
MAX_SIZE = 4096  # px; one 4096^2 object with 32 lights is already 6 GB of float32 images
MAX_LIGHTS = 1024


def build_parser() -> argparse.ArgumentParser:
    p = make_parser(
        PROG,
        "Render synthetic photometric stacks (random shapes, spatially varying non-Lambertian "
        "materials, cast shadows, real-rig-like lights, sensor noise) with ground-truth "
        "normals, as DiLiGenT-layout folders plus objects.txt. Deterministic: the same --seed "
        "gives the same objects. The whole root is written at once or not at all.",
        (
            "msf-synth synth8/                       # 8 objects, 32 lights, 128 px",
            "msf-synth big/ --objects 2 --size 256 --lights 96 --seed 3",
            "msf-synth line/ --preset plates --objects 20 --size 256   # an inspection line",
        ),
    )
    p.add_argument("outdir", type=path_arg, help="output benchmark root (one folder per object)")
    p.add_argument("--objects", type=positive_int, default=8, help="number of objects (default 8)")
    p.add_argument(
        "--lights", type=int_range(3, MAX_LIGHTS), help="lights per object (default 32; plates 12)"
    )
    p.add_argument(
        "--size",
        type=int_range(8, MAX_SIZE),
        default=128,
        help="image side in pixels (default 128)",
    )
    p.add_argument("--seed", type=nonnegative_int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--preset",
        choices=(*PRESETS, "plates"),
        default="default",
        help="'default' (the renderer of docs/model-card.md's held-out figures), 'hard': "
        "steep rims, folds and cups with inter-reflections, pixel-scale relief, "
        "rough / painted / very dark materials, LED rings, mostly 8-bit; or 'plates': an "
        "inspection line, good/ (5 good parts to learn from) and parts/ (every other one "
        "with scratches and dents, listed in truth.json) under a 12-LED ring",
    )
    p.add_argument(
        "--shapes",
        default=None,
        help="comma list of shapes to cycle through (default: the preset's; "
        f"choose from {','.join(ALL_SHAPES)})",
    )
    p.add_argument(
        "--materials",
        default=None,
        help="comma list of material kinds to draw from (default: the preset's; "
        f"choose from {','.join(ALL_KINDS)})",
    )
    p.add_argument("--no-shadows", action="store_true", help="no cast shadows")
    p.add_argument("--no-noise", action="store_true", help="no sensor noise or quantisation")
    p.add_argument(
        "--bit-depth", type=int, choices=(8, 16), default=16, help="PNG bit depth (default 16)"
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing output root (only one msf-synth wrote)",
    )
    return p


def _names(spec: str, allowed: tuple[str, ...], what: str) -> tuple[str, ...]:
    names = tuple(s.strip() for s in spec.split(",") if s.strip())
    bad = [n for n in names if n not in allowed]
    if bad or not names:
        raise InputError(
            f"--{what} {spec!r}: unknown {bad or 'empty'}; choose from {', '.join(allowed)}"
        )
    return names


def run(args: argparse.Namespace) -> list[str]:
    if args.preset == "plates":
        return _plates(args)
    from tqdm import tqdm

    out: Path = args.outdir
    args.lights = args.lights or 32
    base = RenderOptions.preset(args.preset)
    shapes = base.shapes if args.shapes is None else _names(args.shapes, ALL_SHAPES, "shapes")
    materials = (
        base.materials if args.materials is None else _names(args.materials, ALL_KINDS, "materials")
    )
    # the hard preset draws 10 % of its objects in the dark material whatever the list: a
    # --materials that leaves it out must leave it out of those too
    dark = {} if args.materials is None or "dark" in materials else {"very_dark": 0.0}
    options = RenderOptions.preset(
        args.preset,
        size=args.size,
        lights=args.lights,
        materials=materials,
        cast_shadows=not args.no_shadows,
        noise=not args.no_noise,
        **dark,
    )
    # --overwrite replaces only a root msf-synth rendered (its help says so), never another
    # command's results; the manifest names the writer
    check_output(out, overwrite=args.overwrite, folder=True, command=PROG)
    names = []
    t0 = time.perf_counter()
    quiet = getattr(args, "quiet", False)
    with staged_folder(out, overwrite=args.overwrite, command=PROG) as tmp:
        for stack in tqdm(
            render_set(args.seed, args.objects, options, shapes=shapes),
            total=args.objects,
            desc="render",
            unit="obj",
            disable=quiet or not sys.stderr.isatty(),
        ):
            if args.bit_depth == 8:
                stack.images = stack.images / 257.0
            save_stack(stack, tmp / stack.name, bit_depth=args.bit_depth)
            names.append(stack.name)
        (tmp / "objects.txt").write_text("\n".join(names) + "\n")
    if not quiet:
        print(
            f"msf-synth: wrote {len(names)} objects ({args.lights} lights, {args.size}x"
            f"{args.size}) to {out} in {time.perf_counter() - t0:.1f} s"
        )
    return names


GOOD_PLATES = 5  # --preset plates: the good parts a variation model learns from


def _plates(args: argparse.Namespace) -> list[str]:
    """--preset plates: good/g1..g5 and parts/p001.. (odd ones with relief defects), the
    parts' truth in truth.json; one plate per seed (its tilt, bow and LED jitter)."""
    from msfnet.synth.plates import PlateOptions, render_plate

    out: Path = args.outdir
    if args.size < 96:
        raise InputError(f"--size {args.size}: a plate is at least 96 px")
    if args.lights is not None and not 3 <= args.lights <= 64:
        raise InputError(f"--lights {args.lights}: a plate's LED ring has 3-64 lights")
    if args.shapes is not None or args.materials is not None:
        raise InputError("--shapes and --materials are for the object presets, not plates")
    check_output(out, overwrite=args.overwrite, folder=True, command=PROG)
    lights = args.lights or 12
    noise = 0.0 if args.no_noise else 1e-3
    truth: dict[str, object] = {}
    names: list[str] = []
    with staged_folder(out, overwrite=args.overwrite, command=PROG) as tmp:
        for i in range(GOOD_PLATES + args.objects):
            good = i < GOOD_PLATES
            name = f"good/g{i + 1}" if good else f"parts/p{i - GOOD_PLATES + 1:03d}"
            relief = not good and (i - GOOD_PLATES) % 2 == 1
            opts = PlateOptions(
                height=args.size,
                width=args.size,
                lights=lights,
                mask_edge=None,
                relief=relief,
                noise=noise,
                seed=args.seed * 10_000 + i,
            )
            plate = render_plate(opts)
            stack = plate.stack
            if args.bit_depth == 8:
                stack.images = stack.images / 257.0
            save_stack(stack, tmp / name, bit_depth=args.bit_depth)
            names.append(name)
            if not good:
                truth[name.split("/")[1]] = [
                    {"kind": d.kind, "depth_px": d.depth, "width_px": d.width}
                    for d in plate.defect_list
                ]
        (tmp / "truth.json").write_text(json_text(truth), encoding="utf-8")
    if not getattr(args, "quiet", False):
        print(
            f"msf-synth: wrote {GOOD_PLATES} good parts and {args.objects} parts ({lights} "
            f"lights, {args.size}x{args.size}) to {out}"
        )
    return names


def main(argv: list[str] | None = None) -> int:
    def body(args: argparse.Namespace) -> int:
        run(args)
        return 0

    return command_main(PROG, build_parser(), body, argv)


if __name__ == "__main__":
    sys.exit(main())
