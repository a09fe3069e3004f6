"""msf-eval: a model (ONNX, through the runtime) and the least-squares baseline over a benchmark.

ROOT: a benchmark folder (``objects.txt``, or stack sub-folders) or one object folder, objects
with ground-truth normals. Writes results.json, results.md and per-object error pictures to
OUTDIR. docs/run.md, "msf-eval".
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from msfnet.common.cli import Command, command_main, make_parser, path_arg
from msfnet.common.errors import InputError
from msfnet.common.files import check_output, json_text, staged_folder
from msfnet.runtime.api import Model
from msfnet.runtime.cli.flags import add_load_flags, add_model_flags, load_options, model_options
from msfnet.runtime.evaluate.datasets import (
    PUBLISHED_MAE,
    PUBLISHED_METHODS,
    BenchObject,
    check_unique,
    find_objects,
    known_object,
    protocol_note,
)
from msfnet.runtime.evaluate.detail_ratio import detail_ratio
from msfnet.runtime.evaluate.metrics import NormalMetrics
from msfnet.runtime.infer.tiling import DEFAULT_MAX_MEMORY_MB
from msfnet.runtime.results.maps import pictures
from msfnet.runtime.results.outputs import normals_png, write_rgb_png
from msfnet.runtime.results.provenance import Provenance
from msfnet.runtime.stack import LoadOptions, linked_reads, load_stack
from msfnet.runtime.stack.load import check_stack_files

PROG = "msf-eval"
COMMAND = Command(PROG, memory_advice="lower --max-memory (or --tile)")
COLUMNS = ("mae_deg", "err15", "err30")


def _fmt(v: object, pct: bool = False) -> str:
    if not isinstance(v, (int, float)) or v != v:
        return "-"
    return f"{v * 100:.1f}" if pct else f"{v:.2f}"


@dataclass(frozen=True)
class MethodScore:
    """One method on one object: its metrics (with ground truth) and median run time."""

    seconds: float
    metrics: NormalMetrics | None = None

    def column(self, name: str) -> float | None:
        return None if self.metrics is None else float(getattr(self.metrics, name))

    def as_dict(self) -> dict[str, object]:
        return {**(self.metrics.as_dict() if self.metrics else {}), "seconds": self.seconds}


@dataclass(frozen=True)
class ObjectResult:
    """One object of the benchmark, every method on it."""

    name: str
    lights: int
    select: str | None
    scores: dict[str, MethodScore]  # by method ("msf", "l2")
    published: dict[str, float] | None = None  # published MAE by method (ground truth only)
    detail_ratio: float | None = None  # model / least squares high-pass energy (no GT only)
    warnings: tuple[str, ...] = ()

    @property
    def has_ground_truth(self) -> bool:
        return self.published is not None

    def as_dict(self) -> dict[str, object]:
        """results.json's row."""
        row: dict[str, object] = {
            "object": self.name,
            "lights": self.lights,
            "results": {m: s.as_dict() for m, s in self.scores.items()},
            "select": self.select,
        }
        if self.warnings:
            row["warnings"] = list(self.warnings)
        if self.has_ground_truth:
            row["published"] = self.published
        else:
            row["note"] = "no ground truth"
            if self.detail_ratio is not None:
                row["detail_ratio"] = self.detail_ratio
        return row


@dataclass(frozen=True)
class EvalSummary:
    """What msf-eval measured; ``as_dict`` is results.json."""

    objects: list[str]
    model: str | None
    methods: list[str]
    results: list[ObjectResult]
    fine_detail: bool = False  # the model ran with --fine-detail
    provenance: Provenance | None = None  # input, model + checksum, engine, date, command
    figures: bool = True  # error pictures drawn (False: Pillow, their text, would not import)

    @property
    def scored(self) -> list[ObjectResult]:
        return [r for r in self.results if r.has_ground_truth]

    @property
    def unscored(self) -> list[ObjectResult]:
        return [r for r in self.results if not r.has_ground_truth]

    def mean(self) -> dict[str, dict[str, float]]:
        """Per method, the mean of each column over the objects with ground truth."""
        out = {}
        for m in self.methods:
            scores = [r.scores[m] for r in self.scored if m in r.scores]
            if scores and all(s.metrics is not None for s in scores):
                out[m] = {c: float(np.mean([s.column(c) for s in scores])) for c in COLUMNS}
        return out

    def table(self) -> str:
        tables = []
        if self.scored:
            tables.append(markdown_table(self.scored, self.methods, self.mean()))
        if self.unscored:
            tables.append(detail_table(self.unscored))
        if self.fine_detail:
            tables.append("msf: with --fine-detail (also run at 2x, fine detail from that run)")
        return "\n\n".join(tables)

    def warnings(self) -> list[str]:
        return [w for r in self.results for w in r.warnings]

    def written(self) -> str:
        """What evaluate() wrote, as the closing line lists it: error maps only for objects
        with ground truth."""
        return (
            "results.json, results.md, normal maps"
            + (" and error maps" if self.scored and self.figures else "")
            + " per object"
        )

    def as_dict(self) -> dict[str, object]:
        return {
            "objects": self.objects,
            "model": self.model,
            "methods": self.methods,
            "fine_detail": self.fine_detail,
            "results": [r.as_dict() for r in self.scored + self.unscored],
            "mean": self.mean(),
            "provenance": self.provenance.as_dict() if self.provenance else None,
        }

    def markdown(self) -> str:
        """results.md: where the numbers came from, then the tables."""
        head = f"{self.provenance.markdown()}\n\n" if self.provenance else ""
        return head + self.table() + "\n"


def markdown_table(
    rows: list[ObjectResult], methods: list[str], mean: dict[str, dict[str, float]]
) -> str:
    """Objects with ground truth: MAE per method beside the published figures, then err15/30,
    and a mean row."""
    # the papers' least squares beside ours where l2 is scored
    shown = (("L2 (paper)",) if "l2" in methods else ()) + PUBLISHED_METHODS
    published = [p for p in shown if any(p in (r.published or {}) for r in rows)]
    head = ["object", "lights"] + [f"MAE {m}" for m in methods] + published
    head += [f"<15° % {m}" for m in methods] + [f"<30° % {m}" for m in methods]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    Cells = dict[str, dict[str, float | None]]
    table_rows: list[tuple[str, str, Cells, dict[str, float]]] = [
        (
            r.name,
            str(r.lights),
            {m: {c: s.column(c) for c in COLUMNS} for m, s in r.scores.items()},
            r.published or {},
        )
        for r in rows
    ]
    table_rows.append(("**mean**", "", {m: dict(v) for m, v in mean.items()}, {}))
    for name, lights, res, paper in table_rows:
        cells = [name, lights]
        cells += [_fmt(res.get(m, {}).get("mae_deg")) for m in methods]
        cells += [_fmt(paper.get(p)) for p in published]
        cells += [_fmt(res.get(m, {}).get("err15"), True) for m in methods]
        cells += [_fmt(res.get(m, {}).get("err30"), True) for m in methods]
        lines.append("| " + " | ".join(cells) + " |")
    if published:
        lines.append(
            "\nPublished columns: the papers' figures, with every image of the benchmark's "
            "protocol (DiLiGenT: 96 lights; bear images 21-96); rows at fewer lights do not "
            "compare one to one."
        )
    return "\n".join(lines)


def detail_table(rows: list[ObjectResult]) -> str:
    """Objects without ground truth: the model's high-pass energy relative to least squares'."""
    lines = ["| object | lights | detail msf / l2 |", "|---|---|---|"]
    for r in rows:
        lines.append(f"| {r.name} | {r.lights} | {_fmt(r.detail_ratio)} |")
    return "\n".join(lines)


def _runners(model: Model | None, use_l2: bool) -> dict[str, Model]:
    """What is scored: the model ("msf") and least squares ("l2", normals only)."""
    runners: dict[str, Model] = {}
    if model is not None:
        runners["msf"] = model
    if use_l2:
        budget = model.tiling.max_memory_mb if model is not None else DEFAULT_MAX_MEMORY_MB
        runners["l2"] = Model.least_squares(max_memory_mb=budget, maps=None)
    if not runners:
        raise InputError("nothing to evaluate: both the model and l2 are switched off")
    return runners


def _score(
    obj: BenchObject, opts: LoadOptions, runners: dict[str, Model], out: Path, progress: bool
) -> ObjectResult:
    """Run every method on one object; its normals (and error pictures) into ``out``."""
    stack = load_stack(obj.folder, opts)
    out.mkdir()
    outs, errors, scores = {}, {}, {}
    said: dict[str, None] = dict.fromkeys(stack.warnings)  # and each run's own
    for m, runner in runners.items():
        res = runner(stack, progress=progress)
        said.update(dict.fromkeys(res.stack.warnings))
        outs[m] = res.normals
        write_rgb_png(out / f"{m}_normals.png", normals_png(res.normals, stack.mask))
        scored = res.metrics is not None and res.error_deg is not None
        if res.error_deg is not None:
            errors[m] = res.error_deg
        scores[m] = MethodScore(res.timings.median_s("total"), res.metrics if scored else None)
    # one colour range for every method of an object, so the pictures compare
    vmax = max((pictures.error_range(e, stack.mask) for e in errors.values()), default=None)
    for m, err in errors.items() if pictures.can_draw() else ():
        picture = pictures.error_picture(err, stack.mask, vmax=vmax)
        (out / f"{m}_error.png").write_bytes(pictures.png_bytes(picture))
    gt = stack.normals_gt is not None
    both = not gt and "msf" in outs and "l2" in outs
    return ObjectResult(
        obj.name,
        stack.num_lights,
        opts.select,
        scores,
        published=PUBLISHED_MAE.get(known_object(obj.folder), {}) if gt else None,
        detail_ratio=detail_ratio(outs["msf"], outs["l2"], stack.mask) if both else None,
        warnings=tuple(said),
    )


def _done_line(row: ObjectResult, k: int, n: int, seconds: float) -> str:
    got = [f"{m} {s.metrics.mae_deg:.2f} deg" for m, s in row.scores.items() if s.metrics]
    if row.detail_ratio is not None:
        got.append(f"detail msf / l2 {row.detail_ratio:.2f}")
    return f"{PROG}: [{k}/{n}] {row.name}: {row.lights} lights, {', '.join(got) or 'done'} " + (
        f"({seconds:.1f} s)"
    )


def evaluate(
    objects: list[BenchObject],
    outdir: Path,
    *,
    model: Model | None,
    use_l2: bool = True,
    load: LoadOptions | None = None,
    overwrite: bool = False,
    progress: bool = False,
    lines: bool = False,
) -> EvalSummary:
    """Score ``model`` (and least squares) on every object; write the results folder.
    ``progress``: tile bars (a terminal); ``lines``: a line on stderr as each object is done
    (a run over DiLiGenT takes minutes: logs and pipes see it move too)."""
    load = load or LoadOptions()
    check_unique(objects)
    check_output(
        outdir,
        [o.folder for o in objects] + [o.lights for o in objects if o.lights] + load.inputs(),
        overwrite=overwrite,
        folder=True,
        reads=[f for o in objects for f in linked_reads(o.folder)],  # read through links
    )
    runners = _runners(model, use_l2)

    def options_for(obj: BenchObject) -> LoadOptions:
        # --select / --lights override the benchmark's selection and shared light file
        # "is not None": --select '' is a typo the parser refuses, not "the benchmark's own"
        select = load.select if load.select is not None else obj.select
        return replace(load, select=select, lights=load.lights or obj.lights)

    for obj in objects:  # a light file that does not fit the 3rd object, found before the 1st
        check_stack_files(obj.folder, options_for(obj))
    if lines:  # what msf-run says of a benchmark's own selection, said here too
        for obj in objects:
            if load.select is None and obj.select is not None:
                print(f"{PROG}: {protocol_note(obj.folder, obj.select)}", file=sys.stderr)
    results = []
    with staged_folder(outdir, overwrite=overwrite) as tmp:
        for k, obj in enumerate(objects, 1):
            started = time.perf_counter()
            row = _score(obj, options_for(obj), runners, tmp / obj.name, progress)
            results.append(row)
            if lines:
                took = time.perf_counter() - started
                print(_done_line(row, k, len(objects), took), file=sys.stderr, flush=True)
        first = runners["msf"] if "msf" in runners else runners["l2"]
        summary = EvalSummary(
            [str(o.folder) for o in objects],
            runners["msf"].describe().model if "msf" in runners else None,
            list(runners),
            results,
            fine_detail="msf" in runners and runners["msf"].describe().fine_detail is not None,
            provenance=Provenance.of([o.folder for o in objects], first.describe()),
            figures=pictures.can_draw(),
        )
        (tmp / "results.json").write_text(json_text(summary.as_dict()))
        (tmp / "results.md").write_text(summary.markdown())
    return summary


def build_parser() -> argparse.ArgumentParser:
    p = make_parser(
        PROG,
        "Score a model (ONNX via the runtime) and the least-squares baseline on every object "
        "of a benchmark root (objects.txt, or every object folder). Objects with ground truth: "
        "MAE / err15 / err30 beside the published figures (DiLiGenT); without: the detail "
        "ratio (high-pass energy of the model's normals over least squares'). Writes "
        "results.json, results.md, normal and error maps.",
        (
            "msf-eval ../shared/data/DiLiGenT      # ball, bear (21-96), harvest",
            "msf-eval psmImages        # every object, sharing psmImages/lights.txt; detail only",
            "msf-eval psmImages/cat psmImages/owl --lights psmImages/lights.txt",
            "msf-eval benchmark/ --onnx my_model.onnx -o eval/mine",
        ),
    )
    p.add_argument(
        "roots",
        type=path_arg,
        metavar="ROOT",
        nargs="+",
        help="benchmark root(s) or object folder(s)",
    )
    p.add_argument("--l2-only", action="store_true", help="only the least-squares baseline")
    p.add_argument("--no-l2", action="store_true", help="skip the least-squares baseline")
    p.add_argument(
        "-o",
        "--output",
        "--outdir",
        dest="output",
        type=path_arg,
        default=None,
        help="output folder (default ./msf-eval/<root name>/, ./msf-eval/objects/ for several "
        "ROOTs)",
    )
    add_load_flags(p, ("max_lights", "select"))
    p.add_argument(
        "--lights",
        type=path_arg,
        help="light directions file shared by all objects (e.g. psmImages/lights.txt)",
    )
    add_model_flags(
        p,
        skip=("method",),  # --l2-only / --no-l2 choose the methods here
        fine_detail="the model with msf-run's --fine-detail (also run at 2x, fine detail "
        "from that run; about 5x the time)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    p.add_argument(
        "--json",
        action="store_true",
        help="print results.json's content on stdout instead of the table",
    )
    return p


def _run(args: argparse.Namespace) -> int:
    name = args.roots[0].resolve().name if len(args.roots) == 1 else "objects"
    outdir = args.output or Path("msf-eval") / name
    if args.l2_only and args.model is not None:
        raise InputError("--l2-only and --onnx contradict each other")
    given = args.select is not None
    objects = [o for root in args.roots for o in find_objects(root, select_given=given)]
    check_unique(objects)
    load = load_options(args)
    check_output(
        outdir, [*args.roots, args.model, *load.inputs()], overwrite=args.overwrite, folder=True
    )
    if args.l2_only and args.fine_detail:
        raise InputError("--l2-only and --fine-detail contradict each other")
    if args.l2_only and (args.engine or args.precision):
        raise InputError("--l2-only and --engine / --precision contradict each other")
    options = model_options(args, maps=None)  # scoring needs normals only
    model = None if args.l2_only else Model(options=options)
    summary = evaluate(
        objects,
        outdir,
        model=model,
        use_l2=not args.no_l2,
        load=load,
        overwrite=args.overwrite,
        progress=sys.stderr.isatty() and not args.quiet and not args.json,
        lines=not args.quiet,
    )
    if not args.quiet:
        for line in summary.warnings():
            print(f"{PROG}: warning: {line}", file=sys.stderr)
        if summary.scored and not summary.figures:
            print(f"{PROG}: warning: {pictures.missing_note()}", file=sys.stderr)
    if args.json:
        print(json_text({**summary.as_dict(), "output": str(outdir)}), end="")
    elif not args.quiet:
        print(summary.table())
        print(f"wrote {outdir}/ ({summary.written()})")
    return 0


def main(argv: list[str] | None = None) -> int:
    return command_main(COMMAND, build_parser(), _run, argv)


if __name__ == "__main__":
    sys.exit(main())
