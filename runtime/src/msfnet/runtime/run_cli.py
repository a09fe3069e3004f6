"""msf-run: photometric stack(s) -> normal map (+ metrics with ground truth, + latency profile)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .cliutil import make_parser, positive_float, positive_int, run_command
from .errors import InputError
from .files import check_output, json_text, numbered_folder
from .stack import LoadOptions, Stack
from .tiling import DEFAULT_MAX_MEMORY_MB, HALO

PROG = "msf-run"
EXAMPLES = (
    "msf-run --demo                                   # bundled model on a bundled sample",
    "msf-run ../shared/data/DiLiGenT/ballPNG          # -> msf-out/ballPNG/",
    "msf-run bearPNG --select 21-96 -o out/bear       # skip images, choose the folder",
    "msf-run obj/ --method l2                         # classical least squares, no model",
    "msf-run obj/ --onnx my_model.onnx --threads 2 --json",
)


def build_parser() -> argparse.ArgumentParser:
    p = make_parser(
        PROG,
        "Estimate per-pixel surface normals from a photometric stack with MSF-Net (ONNX, tiled "
        "to a memory budget) or classical least squares. STACK is a DiLiGenT-layout folder, a "
        "folder of images with a lights file (txt/json), or an .npz. Writes normals.npy, "
        "normals.png, profile.json and, with ground truth, metrics.json and error.png.",
        EXAMPLES)
    p.add_argument("stacks", type=Path, metavar="STACK", nargs="*",
                   help="stack folder(s) or .npz (omit with --demo)")
    p.add_argument("--demo", action="store_true",
                   help="run on the bundled 32-light synthetic sample with ground truth and "
                   "compare with least squares")
    p.add_argument("--onnx", type=Path, metavar="MODEL",
                   help="msfnet ONNX model (default: the bundled model)")
    p.add_argument("--method", choices=("msf", "l2"), default="msf",
                   help="msf: the network (default); l2: per-pixel least squares, no model")
    p.add_argument("-o", "--output", "--outdir", dest="output", type=Path, default=None,
                   help="output folder (default: a fresh ./msf-out/<stack name>[-N]/); with "
                   "several stacks, the parent of one folder per stack; an existing non-empty "
                   "folder is refused unless --overwrite")
    p.add_argument("--lights", type=Path, help="light directions file (txt or json), overrides "
                   "the stack's")
    p.add_argument("--intensities", type=Path, help="light intensities file (txt or json)")
    p.add_argument("--mask", type=Path, help="mask image (> 127 is object)")
    p.add_argument("--select", metavar="SPEC", help="1-based image subset, e.g. 21-96 or "
                   "1,3,5-9")
    p.add_argument("--max-lights", type=positive_int, metavar="K",
                   help="use K evenly spaced lights")
    p.add_argument("--threads", type=positive_int, metavar="T",
                   help="inference threads (default: all available cores)")
    p.add_argument("--provider", default="cpu", metavar="P",
                   help="ONNX Runtime execution provider: cpu (default), cuda, ... when "
                   "installed")
    p.add_argument("--tile", type=int, metavar="S",
                   help=f"tile edge in px including the {HALO} px halo (multiple of 4); 0 = no "
                   "tiling; default: the largest tile that fits --max-memory")
    p.add_argument("--max-memory", type=positive_float, default=DEFAULT_MAX_MEMORY_MB,
                   metavar="MB", help="peak memory target in MB (loaded stack + working set), "
                   f"least squares included (default {DEFAULT_MAX_MEMORY_MB})")
    p.add_argument("--repeat", type=positive_int, default=1, metavar="K",
                   help="run K times; the profile reports median and p90 per stage")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing output folder (only one msfnet wrote)")
    p.add_argument("--json", action="store_true",
                   help="print a machine-readable summary on stdout (one JSON object per stack)")
    return p


def _output_for(args: argparse.Namespace, name: str, many: bool) -> Path:
    if args.output is None:
        return numbered_folder(Path("msf-out") / name)
    return args.output / name if many else args.output


def _print_result(result, outdir: Path, files: list[Path], args) -> None:
    p = result.profile()
    if args.json:
        print(json_text({"stack": p["stack"], "output": str(outdir),
                         "files": [f.name for f in files], "profile": p,
                         "metrics": result.metrics.as_dict() if result.metrics else None}),
              end="")
        return
    if args.quiet:
        return
    print(f"{result.stack.name}: {p['lights']} lights, {p['width']}x{p['height']}, "
          f"{p['mask_pixels']} mask px, {p['method']} ({p['engine']} {p['precision']})")
    tiles = p.get("tiles")
    if tiles:
        size = tiles["tile_px"] or "untiled"
        print(f"tiles: {tiles['run']} run, {tiles['skipped']} skipped (tile {size}, halo "
              f"{tiles['halo_px']} px, {tiles['overhead_vs_image']:.2f} x image area computed)")
    if result.metrics is not None:
        m = result.metrics
        bad = f", {m.invalid} invalid" if m.invalid else ""
        print(f"MAE {m.mae_deg:.3f} deg, median {m.median_deg:.3f} deg, err15 "
              f"{m.err15 * 100:.1f} %, err30 {m.err30 * 100:.1f} % over {m.pixels} px{bad}")
    print(result.timings.table())
    print(f"wrote {outdir}/ ({', '.join(f.name for f in files)})")


def _run(args: argparse.Namespace) -> int:
    from .pipeline import Model

    if args.method == "l2" and args.onnx is not None:
        raise InputError("--method l2 needs no model; drop --onnx")
    if bool(args.stacks) == args.demo:
        raise InputError("give STACK folder(s) or .npz, or --demo, not both or neither")
    load = LoadOptions(args.lights, args.intensities, args.mask, args.select, args.max_lights)
    many = len(args.stacks) > 1
    sources: list[Path | Stack]
    if args.demo:
        from .demo import demo_stack

        sources = [demo_stack()]
    else:
        sources = list(args.stacks)
        names = [s.stem for s in args.stacks]
        if len(set(names)) != len(names):
            raise InputError("two stacks share a name; their output folders would clash")
    # every output location is checked before any work
    plans = []
    for src in sources:
        name = src.name if isinstance(src, Stack) else src.stem
        out = _output_for(args, name, many)
        inputs = [*load.inputs(), args.onnx] + ([src] if isinstance(src, Path) else [])
        check_output(out, inputs, overwrite=args.overwrite, folder=True)
        plans.append((src, out))
    model = Model(args.onnx, method=args.method, threads=args.threads, provider=args.provider,
                  tile=args.tile, max_memory_mb=args.max_memory)
    progress = sys.stderr.isatty() and not args.quiet and not args.json
    for src, out in plans:
        result = model(src, load, repeat=args.repeat, progress=progress)
        files = result.save(out, overwrite=args.overwrite, inputs=tuple(load.inputs()))
        _print_result(result, out, files, args)
        if args.demo and args.method != "l2" and not args.json and not args.quiet:
            l2 = Model.least_squares()(result.stack)
            assert l2.metrics is not None
            print(f"least squares on the same stack: MAE {l2.metrics.mae_deg:.3f} deg, median "
                  f"{l2.metrics.median_deg:.3f} deg, err15 {l2.metrics.err15 * 100:.1f} %")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run_command(PROG, lambda: _run(args), debug=args.debug)


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["build_parser", "main"]
