"""msf-run: photometric stack -> normal map (+ metrics with ground truth, + latency profile)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .errors import InputError
from .tiling import DEFAULT_MAX_MEMORY_MB, HALO

PROG = "msf-run"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Estimate per-pixel surface normals from a photometric stack with MSF-Net "
        "(ONNX Runtime, tiled to a memory budget) or classical least squares. STACK is a "
        "DiLiGenT-layout folder, a folder of images with a lights file (txt/json), or an .npz. "
        "Writes normals.npy, normals.png, profile.json and, with ground truth, metrics.json and "
        "error.png to OUTDIR.",
    )
    p.add_argument("stack", type=Path, metavar="STACK", nargs="?",
                   help="stack folder or .npz (omit with --demo)")
    p.add_argument("--demo", action="store_true",
                   help="run on a freshly rendered 32-light synthetic sample with ground truth "
                   "(bundled model by default) and compare with least squares")
    p.add_argument("--onnx", type=Path, metavar="MODEL",
                     help="msfnet ONNX model (default: the bundled model, if installed)")
    p.add_argument("--method", choices=("msf", "l2"), default="msf",
                   help="msf: the network (default); l2: per-pixel least squares, no model")
    p.add_argument("-o", "--outdir", type=Path, default=None,
                   help="output folder (default ./msf-out/<stack name>/); an existing non-empty "
                   "folder is refused unless --overwrite")
    p.add_argument("--lights", type=Path, help="light directions file (txt or json), overrides "
                   "the stack's")
    p.add_argument("--intensities", type=Path, help="light intensities file (txt or json)")
    p.add_argument("--mask", type=Path, help="mask image (> 127 is object)")
    p.add_argument("--select", metavar="SPEC", help="1-based image subset, e.g. 21-96 or "
                   "1,3,5-9")
    p.add_argument("--max-lights", type=int, metavar="K", help="use K evenly spaced lights")
    p.add_argument("--threads", type=int, metavar="T", help="ONNX Runtime intra-op threads "
                   "(default: all available cores)")
    p.add_argument("--provider", default="cpu", metavar="P",
                   help="ONNX Runtime execution provider: cpu (default), cuda, openvino, ... "
                   "when installed")
    p.add_argument("--tile", type=int, metavar="S",
                   help=f"tile edge in px including the {HALO} px halo (multiple of 4); 0 = no "
                   "tiling; default: the largest tile that fits --max-memory")
    p.add_argument("--max-memory", type=float, default=DEFAULT_MAX_MEMORY_MB, metavar="MB",
                   help="peak memory target in MB (loaded stack + inference working set); sets "
                   f"the tile size from the light count (default {DEFAULT_MAX_MEMORY_MB})")
    p.add_argument("--repeat", type=int, default=1, metavar="K",
                   help="run K times; the profile reports median and p90 per stage")
    p.add_argument("--overwrite", action="store_true", help="replace an existing OUTDIR")
    from msfnet.calib.capture_cli import add_device_arguments

    # --camera: capture (or resume capturing) into STACK first; the light back-end is named
    # --light-rig here because --lights already means a light-directions file.
    add_device_arguments(p, lights_flag="--light-rig", camera_default=None)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.method == "l2" and args.onnx is not None:
            raise InputError("--method l2 needs no model; drop --onnx")
        if (args.stack is None) == (not args.demo):
            raise InputError("give a STACK (folder or .npz) or --demo, not both or neither")
        from .run import run_stack

        stack = args.stack
        if args.camera is not None:
            from msfnet.calib.capture_cli import run_capture

            stack = run_capture(args, args.stack)
        if args.demo:
            from .demo import demo_stack

            stack = demo_stack()
            if args.outdir is None:
                from .outputs import fresh_outdir

                args.outdir = fresh_outdir(stack.name)
        result = run_stack(
            stack, onnx=args.onnx, method=args.method, outdir=args.outdir,
            overwrite=args.overwrite, lights=args.lights, intensities=args.intensities,
            mask=args.mask, select=args.select, max_lights=args.max_lights,
            threads=args.threads, provider=args.provider, tile=args.tile,
            max_memory_mb=args.max_memory, repeat=args.repeat, progress=sys.stderr.isatty())
    except InputError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    except MemoryError:
        print(f"{PROG}: error: out of memory; lower --max-memory or --tile", file=sys.stderr)
        return 2
    p = result.profile
    print(f"{result.stack.name}: {p['lights']} lights, {p['width']}x{p['height']}, "
          f"{p['mask_pixels']} mask px, method {p['method']}")
    tiles = p.get("tiles")
    if tiles:
        size = tiles["tile_px"] or "untiled"
        print(f"tiles: {tiles['run']} run, {tiles['skipped']} skipped (tile {size}, halo "
              f"{tiles['halo_px']} px, {tiles['overhead_vs_image']:.2f} x image area computed)")
    if result.metrics is not None:
        m = result.metrics
        print(f"MAE {m['mae_deg']:.3f} deg, median {m['median_deg']:.3f} deg, err15 "
              f"{m['err15'] * 100:.1f} %, err30 {m['err30'] * 100:.1f} % over {m['pixels']} px")
    print(result.table)
    if args.demo and args.method != "l2":
        from .least_squares import least_squares_normals
        from .metrics import normal_metrics

        l2 = normal_metrics(least_squares_normals(result.stack), result.stack.normals_gt,
                            result.stack.mask)
        print(f"least squares on the same stack: MAE {l2['mae_deg']:.3f} deg, median "
              f"{l2['median_deg']:.3f} deg, err15 {l2['err15'] * 100:.1f} %")
    if result.outdir is not None:
        print(f"wrote {result.outdir}/ ({', '.join(f.name for f in result.files)})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
