"""msf-run: photometric stack(s) -> normal map (+ metrics with ground truth, + latency profile)."""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from tqdm import tqdm

from msfnet.common.cli import make_parser, positive_float, positive_int, run_command
from msfnet.common.errors import InputError
from msfnet.common.files import check_output, json_text, numbered_folder, writing_as
from msfnet.runtime.api import Model, Result
from msfnet.runtime.batch.runner import (
    SUMMARY_FILES,
    BatchItem,
    StackRow,
    check_batch_root,
    expand_stacks,
    run_batch,
)
from msfnet.runtime.infer.tiling import DEFAULT_MAX_MEMORY_MB, HALO
from msfnet.runtime.results.maps import MAP_NAMES, MapOptions
from msfnet.runtime.results.maps.integrate import METHODS as INTEGRATION_METHODS
from msfnet.runtime.stack import LoadOptions, Stack, parse_roi

PROG = "msf-run"
EXAMPLES = (
    "msf-run --demo                                   # bundled model on a bundled sample",
    "msf-run ../shared/data/DiLiGenT/ballPNG          # -> msf-out/ballPNG/",
    "msf-run bearPNG --select 21-96 -o out/bear       # skip images, choose the folder",
    "msf-run obj/ --method l2                         # classical least squares, no model",
    "msf-run obj/ --onnx my_model.onnx --threads 2 --json",
    "msf-run ballPNG harvestPNG bearPNG -o out/       # a batch: model loaded once",
    "msf-run DiLiGenT/ -o out/dili                    # every stack in a folder (or objects.txt)",
    "msf-run DiLiGenT/ --ray ray://head:10001         # the batch on a Ray cluster",
    "msf-run capture/ --srgb --auto-mask --roi 400,300,800,600 --downscale 2",
)


def build_parser() -> argparse.ArgumentParser:
    p = make_parser(
        PROG,
        "Estimate per-pixel surface normals from a photometric stack with MSF-Net (ONNX, tiled "
        "to a memory budget) or classical least squares. STACK is a DiLiGenT-layout folder, a "
        "folder of images with a lights file (txt/json), an .npz, or a folder of such stacks "
        "(sub-folders, or an objects.txt as msf-eval reads). Writes normals.npy, normals.png, "
        "profile.json and, with ground truth, metrics.json and error.png; for several stacks "
        "one folder each plus summary.json and summary.md.",
        EXAMPLES,
    )
    p.add_argument(
        "stacks",
        type=Path,
        metavar="STACK",
        nargs="*",
        help="stack folder(s), .npz, or folders of stacks (omit with --demo)",
    )
    p.add_argument(
        "--demo",
        action="store_true",
        help="run on the bundled 32-light synthetic sample with ground truth and "
        "compare with least squares",
    )
    p.add_argument(
        "--onnx", type=Path, metavar="MODEL", help="msfnet ONNX model (default: the bundled model)"
    )
    p.add_argument(
        "--method",
        choices=("msf", "l2"),
        default="msf",
        help="msf: the network (default); l2: per-pixel least squares, no model",
    )
    p.add_argument(
        "-o",
        "--output",
        "--outdir",
        dest="output",
        type=Path,
        default=None,
        help="output folder (default: a fresh ./msf-out/<stack name>[-N]/); with "
        "several stacks, the parent of one folder per stack and the summary "
        "(default ./msf-out/<folder name or 'batch'>[-N]/); an existing non-empty "
        "folder is refused unless --overwrite",
    )
    p.add_argument(
        "--lights", type=Path, help="light directions file (txt or json), overrides the stack's"
    )
    p.add_argument("--intensities", type=Path, help="light intensities file (txt or json)")
    p.add_argument("--mask", type=Path, help="mask image (> 127 is object)")
    p.add_argument(
        "--select",
        metavar="SPEC",
        help="1-based image subset, e.g. 21-96 or "
        "1,3,5-9 (default: all images, or the benchmark's own selection, e.g. "
        "DiLiGenT bear 21-96, which a line reports and --select overrides)",
    )
    p.add_argument(
        "--max-lights", type=positive_int, metavar="K", help="use K evenly spaced lights"
    )
    p.add_argument(
        "--threads",
        type=positive_int,
        metavar="T",
        help="inference threads (default: all available cores; 1 per Ray worker)",
    )
    p.add_argument(
        "--engine",
        choices=("onnxruntime", "openvino"),
        default=None,
        help="inference engine (default: chosen for this CPU and the installed "
        "engines; the choice and its reason are printed and kept in profile.json)",
    )
    p.add_argument(
        "--precision",
        choices=("fp32", "bf16", "int8"),
        default=None,
        help="compute precision (default: the fastest one measured within 0.5 deg "
        "of fp32 on real data for this CPU; bf16 needs OpenVINO and a CPU with "
        "native bf16)",
    )
    p.add_argument(
        "--fine-detail",
        action="store_true",
        help="keep relief of a few pixels (engravings, scratches, fabric): also run "
        "the network on the stack enlarged 2x and take the fine detail from that run "
        "(about 5x the time; the stack and its enlargement, 5x its memory, must fit "
        "--max-memory; docs/run.md)",
    )
    p.add_argument(
        "--provider",
        default="cpu",
        metavar="P",
        help="ONNX Runtime execution provider: cpu (default), cuda, ... when installed",
    )
    p.add_argument(
        "--tile",
        type=int,
        metavar="S",
        help=f"tile edge in px including the {HALO} px halo (multiple of 4); 0 = no "
        "tiling; default: the largest tile that fits --max-memory",
    )
    p.add_argument(
        "--max-memory",
        type=positive_float,
        default=DEFAULT_MAX_MEMORY_MB,
        metavar="MB",
        help="peak memory target in MB (loaded stack + working set), "
        f"least squares included (default {DEFAULT_MAX_MEMORY_MB})",
    )
    p.add_argument(
        "--repeat",
        type=positive_int,
        default=1,
        metavar="K",
        help="run K times; the profile reports median and p90 per stage (one stack only)",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing output folder (only one msfnet wrote)",
    )
    p.add_argument(
        "--json",
        action="store_true",
        help="print a machine-readable summary on stdout (one JSON object per "
        "stack, then the batch summary for several)",
    )
    cam = p.add_argument_group(
        "real-camera inputs (applied while loading: ROI -> downscale -> linearise -> auto-mask)"
    )
    cam.add_argument(
        "--roi",
        type=parse_roi,
        metavar="X,Y,W,H",
        help="crop images, mask and ground truth to this rectangle (pixels of "
        "the stored images, origin top-left)",
    )
    cam.add_argument(
        "--downscale",
        type=positive_int,
        default=1,
        metavar="K",
        help="average each K x K block (integer K; mask: majority of the block)",
    )
    lin = cam.add_mutually_exclusive_group()
    lin.add_argument(
        "--srgb",
        action="store_true",
        help="images are sRGB-encoded (8-bit camera output): linearise them",
    )
    lin.add_argument(
        "--gamma",
        type=positive_float,
        metavar="G",
        help="images are power-law encoded: linear = (value / white) ** G",
    )
    cam.add_argument(
        "--white-level",
        type=positive_float,
        metavar="V",
        help="full-scale value for --srgb / --gamma (default 255 / 65535 by bit "
        "depth; needed for floating-point images above 1)",
    )
    cam.add_argument(
        "--auto-mask",
        action="store_true",
        help="compute the object mask from the stack (object on a dark "
        "background); written beside the outputs as mask.png",
    )
    insp = p.add_argument_group(
        "inspection maps (written by default: albedo, height, curvature, mesh, report.html)"
    )
    insp.add_argument("--no-maps", action="store_true", help="write the normals only")
    insp.add_argument(
        "--maps",
        type=parse_maps,
        metavar="LIST",
        help=f"which maps, comma-separated from {','.join(MAP_NAMES)} (default: all)",
    )
    insp.add_argument(
        "--integration",
        choices=INTEGRATION_METHODS,
        default="poisson",
        help="normal integration for the height map: poisson (masked least "
        "squares, default), bini (keeps depth discontinuities sharp, slower), "
        "fc (Frankot-Chellappa FFT, full frame)",
    )
    insp.add_argument(
        "--intrinsics",
        type=float,
        nargs=4,
        metavar=("FX", "FY", "CX", "CY"),
        help="perspective camera (pixels) for the height map; default orthographic",
    )
    insp.add_argument("--no-report", action="store_true", help="no report.html")
    bat = p.add_argument_group("batches")
    bat.add_argument(
        "--no-prefetch",
        action="store_true",
        help="decode each stack only when its turn comes (default: the next "
        "stack is decoded while the current one runs)",
    )
    bat.add_argument(
        "--ray",
        nargs="?",
        const="",
        default=None,
        metavar="ADDRESS",
        help="run the stacks on Ray (pip install 'msfnet[ray]'): no ADDRESS = "
        "$RAY_ADDRESS or a local instance, 'auto' = the running cluster, "
        "ray://head:10001 = a remote one; stack paths must be visible to the "
        "workers",
    )
    bat.add_argument(
        "--workers",
        type=positive_int,
        metavar="K",
        help="Ray workers, with --ray (default: the cluster's CPUs / --threads, at "
        "most one per stack)",
    )
    # Python < 3.13 takes "-5,0,10,10" for an option ("--roi: expected one argument"); read a
    # dash followed by a digit as a value, so --roi's own check speaks ("x and y must be >= 0")
    p._negative_number_matcher = re.compile(r"^-\d[\d,.]*$|^-\.\d+$")
    return p


def load_options(args: argparse.Namespace) -> LoadOptions:
    if args.white_level is not None and not (args.srgb or args.gamma is not None):
        # linear images need no full scale (normals do not depend on it): refuse, not ignore
        raise InputError(
            "--white-level is the full scale for linearising: it applies with "
            "--srgb or --gamma only"
        )
    return LoadOptions(
        args.lights,
        args.intensities,
        args.mask,
        args.select,
        args.max_lights,
        roi=args.roi,
        downscale=args.downscale,
        srgb=args.srgb,
        gamma=args.gamma,
        white_level=args.white_level,
        auto_mask=args.auto_mask,
        max_memory_mb=args.max_memory,
    )


def open_model(args: argparse.Namespace, threads: int | None = None) -> Model:
    """The estimator msf-run's options describe, loaded once (``threads`` overrides
    --threads)."""
    from msfnet.runtime.api import Model

    return Model(
        args.onnx,
        method=args.method,
        engine=args.engine,
        precision=args.precision,
        threads=threads or args.threads,
        provider=args.provider,
        tile=args.tile,
        max_memory_mb=args.max_memory,
        maps=map_options(args),
        fine_detail=args.fine_detail,
    )


def parse_maps(text: str) -> tuple[str, ...]:
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    bad = [n for n in names if n not in MAP_NAMES]
    if bad or not names:
        raise argparse.ArgumentTypeError(f"expected names from {','.join(MAP_NAMES)}, got {text!r}")
    return names


def map_options(args: argparse.Namespace) -> MapOptions | None:
    """The inspection maps msf-run's options ask for (None: normals only)."""
    if args.no_maps and args.maps is not None:
        raise InputError("--maps and --no-maps contradict each other: give one of them")
    if args.no_maps:
        return None
    intr = tuple(args.intrinsics) if args.intrinsics else None
    if intr is not None and not (intr[0] > 0 and intr[1] > 0):
        raise InputError(
            f"--intrinsics: focal lengths must be positive, got {intr[0]:g}, {intr[1]:g}"
        )
    return MapOptions(maps=args.maps or MAP_NAMES, method=args.integration, intrinsics=intr)


def print_result(result: Result, outdir: Path, files: list[Path], args: argparse.Namespace) -> None:
    p = result.profile()
    if args.json:
        print(
            json_text(
                {
                    "stack": p["stack"],
                    "output": str(outdir),
                    "files": [f.name for f in files],
                    "profile": p,
                    "metrics": result.metrics.as_dict() if result.metrics else None,
                }
            ),
            end="",
        )
        return
    if args.quiet:
        return
    print(
        f"{result.stack.name}: {p['lights']} lights, {p['width']}x{p['height']}, "
        f"{p['mask_pixels']} mask px, {p['method']} ({p['engine']} {p['precision']})"
    )
    if p.get("choice"):
        print(f"engine choice: {p['choice']}")
    tiles = p.get("tiles")
    if isinstance(tiles, dict):
        size = tiles["tile_px"] or "untiled"
        print(
            f"tiles: {tiles['run']} run, {tiles['skipped']} skipped (tile {size}, halo "
            f"{tiles['halo_px']} px, {tiles['overhead_vs_image']:.2f} x image area computed)"
        )
    if result.metrics is not None:
        m = result.metrics
        bad = f", {m.invalid} invalid" if m.invalid else ""
        print(
            f"MAE {m.mae_deg:.3f} deg, median {m.median_deg:.3f} deg, err15 "
            f"{m.err15 * 100:.1f} %, err30 {m.err30 * 100:.1f} % over {m.pixels} px{bad}"
        )
    print(result.timings.table())
    print(f"wrote {outdir}/ ({', '.join(f.name for f in files)})")


def _print_warnings(result: Result, args: argparse.Namespace) -> None:
    """One line each on stderr, once the outputs are written (a run that then fails gives
    its one error line only)."""
    if not args.quiet:
        for line in result.stack.warnings:
            tqdm.write(f"{PROG}: warning: {line}", file=sys.stderr)


def _say(args: argparse.Namespace, line: str | None) -> None:
    if line and not args.quiet and not args.json:
        print(line)


def _run_single(
    args: argparse.Namespace, src: Path | Stack, load: LoadOptions, item: BatchItem | None = None
) -> int:
    if args.workers is not None:
        raise InputError("--workers is for --ray (workers of a batch on a cluster)")
    name = src.name if isinstance(src, Stack) else src.stem
    out = args.output if args.output is not None else numbered_folder(Path("msf-out") / name)
    inputs = [*load.inputs(), args.onnx] + ([src] if isinstance(src, Path) else [])
    check_output(out, inputs, overwrite=args.overwrite, folder=True)  # before any work
    model = open_model(args)
    progress = sys.stderr.isatty() and not args.quiet and not args.json
    if item is not None:
        _say(args, item.note(load))
    result = model(
        src, item.options(load) if item is not None else load, repeat=args.repeat, progress=progress
    )
    if item is not None:
        result.input = item.describe_input(load)
    files = result.save(
        out, overwrite=args.overwrite, inputs=tuple(load.inputs()), report=not args.no_report
    )
    _print_warnings(result, args)
    print_result(result, out, files, args)
    if args.demo and args.method != "l2" and not args.json and not args.quiet:
        l2 = Model.least_squares()(result.stack)
        assert l2.metrics is not None
        print(
            f"least squares on the same stack: MAE {l2.metrics.mae_deg:.3f} deg, median "
            f"{l2.metrics.median_deg:.3f} deg, err15 {l2.metrics.err15 * 100:.1f} %"
        )
    return 0


def _run_batch(args: argparse.Namespace, items: list[BatchItem], load: LoadOptions) -> int:
    if args.repeat != 1:
        raise InputError("--repeat profiles one stack; give a single STACK")
    if args.workers is not None and args.ray is None:
        raise InputError("--workers is for --ray")
    if args.output is not None:
        root = args.output
    else:
        one_folder = len(args.stacks) == 1 and args.stacks[0].is_dir()
        root = numbered_folder(Path("msf-out") / (args.stacks[0].name if one_folder else "batch"))
    # Everything is checked, and the model opened, before anything is made: bad input leaves
    # no output, not even an empty folder (the stacks' folders and the summary create it).
    inputs = [*load.inputs(), args.onnx]
    check_batch_root(root, [i.name for i in items], args.overwrite)
    for item in items:
        check_output(root / item.name, [*inputs, item.path], overwrite=args.overwrite, folder=True)
    for name in SUMMARY_FILES:
        check_output(root / name, [*inputs, *(i.path for i in items)], overwrite=args.overwrite)
    model = None
    if args.ray is not None:
        from msfnet.runtime.batch.ray_cluster import ModelSpec, import_ray, run_batch_ray

        import_ray()  # not installed: say so now
        spec = ModelSpec.from_args(
            args.onnx,
            method=args.method,
            engine=args.engine,
            precision=args.precision,
            threads=args.threads or 1,
            provider=args.provider,
            tile=args.tile,
            max_memory_mb=args.max_memory,
            maps=map_options(args),
            fine_detail=args.fine_detail,
        )
        # the workers open it far away; a file they would all refuse is refused here, once
        open_model(args, threads=1)
    else:
        model = open_model(args)
    show = not args.quiet and not args.json
    for item in items:
        _say(args, item.note(load))

    def report(row: StackRow, result: Result | None) -> None:
        if row.error is not None:
            tqdm.write(f"{PROG}: error: {row.error}", file=sys.stderr)
            return
        if result is not None:
            _print_warnings(result, args)
        if args.json and result is not None:
            files = sorted(
                p.name for p in Path(row.output or ".").iterdir() if not p.name.startswith(".")
            )
            print_result(result, Path(row.output or "."), [Path(f) for f in files], args)
        elif show:
            mae = row.metrics.mae_deg if row.metrics else None
            score = "" if mae is None else f", MAE {mae:.2f} deg"
            tqdm.write(
                f"{row.name}: {row.lights} lights, {row.width}x{row.height}{score}; "
                f"decode {row.decode_s:.2f} s (waited {row.wait_s:.2f}), infer "
                f"{row.compute_s:.2f} s -> {row.output}/"
            )

    progress = None if show else False
    if model is None:
        summary = run_batch_ray(
            spec,
            items,
            load,
            lambda n: root / n,
            address=args.ray or None,
            workers=args.workers,
            overwrite=args.overwrite,
            summary_dir=root,
            on_result=report,
            progress=progress,
            inputs=tuple(load.inputs()),
        )
    else:
        summary = run_batch(
            model,
            items,
            load,
            lambda n: root / n,
            overwrite=args.overwrite,
            prefetch=not args.no_prefetch,
            summary_dir=root,
            on_result=report,
            progress=progress,
            inputs=tuple(load.inputs()),
        )
    if args.json:
        print(json_text({"summary": summary.as_dict(), "output": str(root)}), end="")
    elif not args.quiet:
        print(summary.text())
        print(f"wrote {root}/ (one folder per stack, summary.json, summary.md)")
    if summary.failed:
        print(
            f"{PROG}: error: {len(summary.failed)} of {len(summary.rows)} stack(s) failed "
            "(see above and summary.md)",
            file=sys.stderr,
        )
        return 2
    return 0


def _run(args: argparse.Namespace) -> int:
    if args.ray and Path(args.ray).exists():
        # argparse gives --ray's optional ADDRESS the first stack of "--ray A B"
        raise InputError(
            f"--ray took the stack {args.ray!r} for a cluster address: put --ray "
            "after the stacks (or write --ray=ADDRESS)"
        )
    if bool(args.stacks) == args.demo:
        raise InputError("give STACK folder(s) or .npz, or --demo, not both or neither")
    load = load_options(args)
    map_options(args)  # contradicting map options are refused before any work
    if args.demo:
        from msfnet.runtime.demo import demo_stack

        if args.ray is not None:
            raise InputError("--demo runs here; --ray is for stacks on disk")
        return _run_single(args, demo_stack(), load)
    items = expand_stacks(args.stacks)
    if len(items) == 1 and args.ray is None and items[0].path == args.stacks[0]:
        return _run_single(args, args.stacks[0], load, items[0])
    return _run_batch(args, items, load)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)

    def body() -> int:
        with writing_as(PROG):  # output manifests name their writer
            return _run(args)

    return run_command(PROG, body, debug=args.debug)


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["build_parser", "load_options", "main", "open_model", "print_result"]
