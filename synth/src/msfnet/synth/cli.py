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
from msfnet.common.files import check_output, staged_folder
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
        ),
    )
    p.add_argument("outdir", type=path_arg, help="output benchmark root (one folder per object)")
    p.add_argument("--objects", type=positive_int, default=8, help="number of objects (default 8)")
    p.add_argument(
        "--lights", type=int_range(3, MAX_LIGHTS), default=32, help="lights per object (default 32)"
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
        choices=PRESETS,
        default="default",
        help="'default' (the renderer of docs/model-card.md's held-out figures) or 'hard': "
        "steep rims, folds and cups with inter-reflections, pixel-scale relief, "
        "rough / painted / very dark materials, LED rings, mostly 8-bit",
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
    from tqdm import tqdm

    out: Path = args.outdir
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


def main(argv: list[str] | None = None) -> int:
    def body(args: argparse.Namespace) -> int:
        run(args)
        return 0

    return command_main(PROG, build_parser(), body, argv)


if __name__ == "__main__":
    sys.exit(main())
