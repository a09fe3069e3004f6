"""msf-inspect: relief defects from a run's registered maps, a verdict and a PLC exit code.

    msf-inspect out/part17 --depth 0.02 -o verdicts/part17           # an msf-run output folder
    msf-inspect captures/part17 --pixel-size 0.05 --depth 0.02 -o v/  # a stack: runs msf-run's
                                                                      # pipeline first
    msf-inspect out/part17 --reference out/golden --depth 0.02 -o v/ # against a good part

Exit code: 0 pass (no defect), 1 defects found, 2 bad input (one line on stderr, nothing
written), 3 a failure of the tool itself (never read as a verdict; Ctrl-C 130, SIGTERM 143).
The verdict (verdict.json) and the overlay picture (overlay.png, the input's size)
are written together into the -o folder, or not at all.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from msfnet.common.cli import command_main, make_parser, path_arg, positive_float, positive_int
from msfnet.common.errors import InputError
from msfnet.common.files import check_output, staged_folder
from msfnet.common.imageio import encode_png
from msfnet.runtime.results.defects import (
    POLARITIES,
    DefectOptions,
    InspectionInput,
    find_defects,
    from_maps,
    overlay_picture,
    read_run,
)

PROG = "msf-inspect"


def _finite(text: str) -> float:
    """A threshold: positive and finite (NaN and inf are refused with the flag's name)."""
    value = positive_float(text)
    if value != value or value in (float("inf"), float("-inf")):
        raise argparse.ArgumentTypeError(f"must be a positive, finite number, got {text!r}")
    return value


def build_parser() -> argparse.ArgumentParser:
    from msfnet.runtime.cli.flags import add_load_flags, add_map_flags, add_model_flags

    p = make_parser(
        PROG,
        "Find relief defects (scratches, dents, bumps) in a part's local shape and "
        "curvature; printed marks (albedo only) are not defects. Exit code: 0 pass, 1 "
        "defects found, 2 bad input, 3 a failure of the tool itself.",
        examples=(
            "msf-inspect out/part17 --depth 0.02 -o verdicts/part17",
            "msf-inspect captures/part17 --pixel-size 0.05 --depth 0.02 -o verdicts/part17",
            "msf-inspect out/part17 --reference out/golden --depth 0.02 -o v17",
        ),
    )
    p.add_argument(
        "input",
        type=path_arg,
        help="an msf-run output folder (maps.json, local_shape.tif) or a stack (then msf-run's "
        "pipeline runs first, with the flags below)",
    )
    p.add_argument("-o", "--output", type=path_arg, required=True, help="folder for the verdict")
    p.add_argument("--overwrite", action="store_true", help="replace an earlier verdict folder")
    t = p.add_argument_group("thresholds (in the maps' units: mm with --pixel-size, else px)")
    t.add_argument("--depth", type=_finite, help="|local shape| at or above this is a defect")
    t.add_argument(
        "--curvature", type=_finite, help="|mean curvature| at or above this is a defect"
    )
    t.add_argument(
        "--min-area", type=positive_int, default=4, metavar="PX", help="smallest region (px)"
    )
    t.add_argument(
        "--polarity",
        choices=POLARITIES,
        default="both",
        help="down: dents and scratches only; up: bumps only (default both)",
    )
    t.add_argument(
        "--reference",
        type=path_arg,
        help="a good part (run folder or stack, same fixture and size): only what differs "
        "from it counts (aligned by phase correlation first)",
    )
    # when INPUT is a stack: how it is run (msf-run's own flags)
    add_model_flags(p)
    add_load_flags(p, camera=True)
    add_map_flags(p)
    return p


def _is_run(path: Path) -> bool:
    return path.is_dir() and (path / "maps.json").is_file()


def _prepare(path: Path, args: argparse.Namespace) -> InspectionInput:
    """A run folder's maps, or a stack run through msf-run's pipeline (in memory)."""
    if _is_run(path):
        return read_run(path)
    if not path.exists():
        raise InputError("no such file or folder", path)
    from msfnet.runtime.api import Model
    from msfnet.runtime.cli.flags import load_options, model_options
    from msfnet.runtime.results.maps import MapOptions
    from msfnet.runtime.stack import load_stack

    opts = model_options(args)
    maps = opts.maps or MapOptions()
    need = tuple(dict.fromkeys((*maps.maps, "albedo", "height", "curvature")))
    maps = MapOptions(
        maps=tuple(n for n in need if n != "mesh"),
        method=maps.method,
        intrinsics=maps.intrinsics,
        curvature_sigma=maps.curvature_sigma,
        pixel_size_mm=maps.pixel_size_mm,
        local_size_px=maps.local_size_px,
    )
    stack = load_stack(path, load_options(args))
    result = Model(options=opts.replace(maps=maps))(stack)
    assert result.maps is not None
    return from_maps(result.maps, str(path))


def _run(args: argparse.Namespace) -> int:
    options = DefectOptions(
        depth=args.depth,
        curvature=args.curvature,
        min_area_px=args.min_area,
        polarity=args.polarity,
    )
    from msfnet.runtime.cli.flags import load_options, model_options

    # every file read is an input: the part, the reference, and the files the load and model
    # flags name (an --overwrite over a folder holding the --mask read deleted it)
    read = [args.input, args.reference, *load_options(args).inputs(), model_options(args).model]
    inputs = tuple(p for p in read if p is not None)
    check_output(args.output, inputs, overwrite=args.overwrite, folder=True)
    part = _prepare(args.input, args)
    reference = None if args.reference is None else _prepare(args.reference, args)
    verdict, labels = find_defects(part, options, reference)
    picture = overlay_picture(part, labels)
    with staged_folder(args.output, overwrite=args.overwrite) as tmp:
        (tmp / "verdict.json").write_text(verdict.json_text(), encoding="utf-8")
        encode_png(tmp / "overlay.png", picture)
    if not args.quiet:
        if verdict.passed:
            print(f"PASS: no defect ({verdict.pixels} px inspected) -> {args.output}")
        else:
            worst = max(verdict.regions, key=lambda r: r.depth)
            x, y = worst.centroid
            print(
                f"FAIL: {len(verdict.regions)} defect(s); deepest {worst.depth:.4g} "
                f"{verdict.units['depth']} at x={x:.0f}, y={y:.0f} -> {args.output}"
            )
    return verdict.exit_code


def main(argv: list[str] | None = None) -> int:
    return command_main(PROG, build_parser(), _run, argv)


if __name__ == "__main__":
    sys.exit(main())
