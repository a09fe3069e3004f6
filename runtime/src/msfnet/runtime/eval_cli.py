"""msf-eval: a model (ONNX, through the runtime) and the least-squares baseline over a benchmark.

ROOT is a benchmark folder with ``objects.txt`` (one object folder per line, optionally followed
by an image selection such as ``21-96`` for DiLiGenT bear) or, without it, every sub-folder that
holds a stack; ROOT may also be a single object folder. Objects need ground-truth normals.
Writes results.json, results.md and <object>/<method>_error.png (+ normals png) to OUTDIR.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from .cliutil import make_parser, positive_float, positive_int, run_command
from .errors import InputError
from .files import check_output, json_text, staged_folder
from .outputs import error_png, normals_png, write_rgb_png
from .pipeline import Model
from .stack import LIGHTS_NAMES, load_stack
from .tiling import DEFAULT_MAX_MEMORY_MB

PROG = "msf-eval"
COLUMNS = ("mae_deg", "err15", "err30")


def find_objects(root: Path) -> list[tuple[Path, str | None]]:
    """(object folder, --select spec or None) in benchmark order."""
    if not root.is_dir():
        raise InputError("benchmark root not found", root)
    listing = root / "objects.txt"
    if listing.is_file():
        out = []
        for line in listing.read_text().splitlines():
            parts = line.split("#", 1)[0].split()
            if not parts:
                continue
            folder = root / parts[0]
            if not folder.is_dir():
                raise InputError(f"object folder {parts[0]!r} listed but not found", listing)
            out.append((folder, parts[1] if len(parts) > 1 else None))
        if not out:
            raise InputError("objects.txt lists no objects", listing)
        names = [f.name for f, _ in out]
        dup = next((n for n in names if names.count(n) > 1), None)
        if dup is not None:
            raise InputError(f"object {dup!r} is listed twice (its results would clash)",
                             listing)
        return out
    if any((root / n).is_file() for n in LIGHTS_NAMES):
        return [(root, None)]
    found: list[tuple[Path, str | None]] = [(d, None) for d in sorted(root.iterdir())
             if d.is_dir() and any((d / n).is_file() for n in LIGHTS_NAMES)]
    if not found:
        raise InputError("no object folders (with light_directions.txt or lights.txt) and no "
                         "objects.txt", root)
    return found


def _fmt(v: float | None, pct: bool = False) -> str:
    if v is None:
        return "-"
    return f"{v * 100:.1f}" if pct else f"{v:.2f}"


def markdown_table(rows: list[dict], methods: list[str]) -> str:
    head = ["object", "lights"]
    for col in COLUMNS:
        label = {"mae_deg": "MAE deg", "err15": "<15° %", "err30": "<30° %"}[col]
        head += [f"{label} {m}" for m in methods]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [r["object"], str(r["lights"])]
        for col in COLUMNS:
            cells += [_fmt(r["results"].get(m, {}).get(col), col != "mae_deg") for m in methods]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def mean_row(rows: list[dict], methods: list[str]) -> dict:
    res = {}
    for m in methods:
        scored = [r["results"][m] for r in rows if m in r["results"]]
        if scored:
            res[m] = {c: float(np.mean([s[c] for s in scored])) for c in COLUMNS}
    return {"object": "**mean**", "lights": "", "results": res}


def evaluate(root: Path, outdir: Path, *, model: Model | None, use_l2: bool = True,
             max_lights: int | None = None, overwrite: bool = False,
             progress: bool = False) -> dict:
    """Score ``model`` (and least squares) on every object; write the results folder."""
    objects = find_objects(root)
    check_output(outdir, [root], overwrite=overwrite, folder=True)
    runners: dict[str, Model] = {}
    if model is not None:
        runners["msf"] = model
    if use_l2:
        runners["l2"] = Model.least_squares(max_memory_mb=model.tiling.max_memory_mb
                                            if model is not None else DEFAULT_MAX_MEMORY_MB)
    if not runners:
        raise InputError("nothing to evaluate: both the model and l2 are switched off")
    methods = list(runners)
    with staged_folder(outdir, overwrite=overwrite) as tmp:
        rows = []
        for folder, select in objects:
            stack = load_stack(folder, select=select, max_lights=max_lights)
            row: dict = {"object": folder.name, "lights": stack.num_lights, "results": {},
                         "select": select}
            if stack.normals_gt is None:
                row["note"] = "no ground truth"
                rows.append(row)
                continue
            (tmp / folder.name).mkdir()
            for m, runner in runners.items():
                res = runner(stack, progress=progress)
                assert res.metrics is not None and res.error_deg is not None
                write_rgb_png(tmp / folder.name / f"{m}_error.png",
                              error_png(res.error_deg, stack.mask))
                write_rgb_png(tmp / folder.name / f"{m}_normals.png",
                              normals_png(res.normals, stack.mask))
                row["results"][m] = {**res.metrics.as_dict(),
                                     "seconds": res.timings.median_s("total")}
            rows.append(row)
            if progress:
                print(f"{folder.name}: " + ", ".join(
                    f"{m} {row['results'][m]['mae_deg']:.2f} deg" for m in methods),
                    file=sys.stderr)
        summary = {"root": str(root),
                   "model": runners["msf"].describe().get("model") if "msf" in runners
                   else None, "methods": methods, "objects": rows,
                   "mean": mean_row(rows, methods)["results"]}
        table = markdown_table([*rows, mean_row(rows, methods)], methods)
        (tmp / "results.json").write_text(json_text(summary))
        (tmp / "results.md").write_text(table + "\n")
    summary["table"] = table
    return summary


def build_parser() -> argparse.ArgumentParser:
    p = make_parser(
        PROG,
        "Score a model (ONNX via the runtime) and the least-squares baseline on every object "
        "of a benchmark root (objects.txt, or every object folder). Prints a per-object "
        "MAE / err15 / err30 table and writes results.json, results.md and error maps.",
        ("msf-eval ../shared/data/DiLiGenT/ballPNG",
         "msf-eval benchmark/ --onnx my_model.onnx -o eval/mine"))
    p.add_argument("root", type=Path, metavar="ROOT", help="benchmark root or one object folder")
    p.add_argument("--onnx", type=Path, metavar="MODEL",
                   help="msfnet ONNX model (default: the bundled model)")
    p.add_argument("--l2-only", action="store_true", help="only the least-squares baseline")
    p.add_argument("--no-l2", action="store_true", help="skip the least-squares baseline")
    p.add_argument("-o", "--output", "--outdir", dest="output", type=Path, default=None,
                   help="output folder (default ./msf-eval/<root name>/)")
    p.add_argument("--max-lights", type=positive_int, metavar="K",
                   help="use K evenly spaced lights")
    p.add_argument("--threads", type=positive_int, metavar="T", help="inference threads")
    p.add_argument("--provider", default="cpu", metavar="P", help="execution provider")
    p.add_argument("--tile", type=int, metavar="S", help="tile edge in px (0 = untiled)")
    p.add_argument("--max-memory", type=positive_float, default=DEFAULT_MAX_MEMORY_MB,
                   metavar="MB", help=f"memory budget in MB (default {DEFAULT_MAX_MEMORY_MB})")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    p.add_argument("--json", action="store_true",
                   help="print results.json's content on stdout instead of the table")
    return p


def _run(args: argparse.Namespace) -> int:
    outdir = args.output or Path("msf-eval") / args.root.resolve().name
    if args.l2_only and args.onnx is not None:
        raise InputError("--l2-only and --onnx contradict each other")
    check_output(outdir, [args.root, args.onnx], overwrite=args.overwrite, folder=True)
    model = None if args.l2_only else Model(
        args.onnx, threads=args.threads, provider=args.provider, tile=args.tile,
        max_memory_mb=args.max_memory)
    summary = evaluate(args.root, outdir, model=model, use_l2=not args.no_l2,
                       max_lights=args.max_lights, overwrite=args.overwrite,
                       progress=sys.stderr.isatty() and not args.quiet and not args.json)
    if args.json:
        print(json_text({**{k: v for k, v in summary.items() if k != "table"},
                         "output": str(outdir)}), end="")
    elif not args.quiet:
        print(summary["table"])
        print(f"wrote {outdir}/ (results.json, results.md, error maps)")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run_command(PROG, lambda: _run(args), debug=args.debug)


if __name__ == "__main__":
    sys.exit(main())
