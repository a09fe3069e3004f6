"""msf-run: photometric stack(s) -> normal map (+ metrics with ground truth, + latency profile)."""

from __future__ import annotations

import argparse
import os
import re
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

from msfnet.common.cli import (
    Command,
    add_flags,
    command_main,
    make_parser,
    options_from_args,
    path_arg,
    positive_int,
)
from msfnet.common.errors import InputError
from msfnet.common.files import (
    check_not_holding,
    check_not_input,
    check_output,
    json_text,
    numbered_folder,
)
from msfnet.runtime.api import Model, Result
from msfnet.runtime.batch.ray_cluster import WORKER_MEMORY_MB
from msfnet.runtime.batch.runner import (
    SUMMARY_FILES,
    BatchItem,
    StackRow,
    check_batch_root,
    expand_stacks,
    run_batch,
)
from msfnet.runtime.cli.flags import (
    add_load_flags,
    add_map_flags,
    add_model_flags,
    load_options,
    model_options,
)
from msfnet.runtime.infer.tiling import BASE_MEMORY_MB
from msfnet.runtime.instrument import announce, announcing
from msfnet.runtime.options import ModelOptions
from msfnet.runtime.results.result import SaveOptions
from msfnet.runtime.stack import LoadOptions, Stack, folder_name, linked_reads

PROG = "msf-run"
COMMAND = Command(PROG, memory_advice="lower --max-memory (or --tile)")
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
        "(sub-folders, or an objects.txt as msf-eval reads). Writes normals.npy, "
        "normals_view.png, profile.json, with ground truth metrics.json and error.png, and "
        "unless --no-maps the inspection maps (height, albedo, curvature, TIFFs, mesh.ply, "
        "report.html; docs/run.md); for several stacks one folder each plus summary.json and "
        "summary.md.",
        EXAMPLES,
    )
    p.add_argument(
        "stacks",
        type=path_arg,
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
        "-o",
        "--output",
        "--outdir",
        dest="output",
        type=path_arg,
        default=None,
        help="output folder (default: a fresh ./msf-out/<stack name>[-N]/); with "
        "several stacks, the parent of one folder per stack and the summary "
        "(default ./msf-out/<folder name or 'batch'>[-N]/); an existing non-empty "
        "folder is refused unless --overwrite",
    )
    add_load_flags(p)
    add_model_flags(p)
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
    add_flags(p, SaveOptions, only=("normals_png",))
    p.add_argument(
        "--json",
        action="store_true",
        help="print a machine-readable summary on stdout (one JSON object per "
        "stack, then the batch summary for several)",
    )
    add_load_flags(p, (), camera=True)
    add_map_flags(p)
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
        help="Ray workers, with --ray, spread over the machines and pinned there (default: "
        "each machine's CPUs / --threads, at most one per "
        f"{WORKER_MEMORY_MB} MB of --max-memory on each and one per stack in all). With "
        "--ray, --max-memory is each machine's budget: the workers on one machine share it "
        f"equally (a share of {BASE_MEMORY_MB} MB or less is refused before any work)",
    )
    # Python < 3.13 takes "-5,0,10,10" for an option ("--roi: expected one argument"); read a
    # dash followed by a digit as a value, so --roi's own check speaks ("x and y must be >= 0")
    p._negative_number_matcher = re.compile(r"^-\d[\d,.]*$|^-\.\d+$")
    return p


@dataclass(frozen=True)
class RunRequest:
    """Everything one msf-run invocation asked for, built once from the flags: the model and
    load options, and what to do with the results."""

    stacks: tuple[Path, ...]
    demo: bool
    model: ModelOptions
    load: LoadOptions
    output: Path | None = None
    overwrite: bool = False
    repeat: int = 1
    json: bool = False
    quiet: bool = False
    save: SaveOptions = field(default_factory=SaveOptions)
    prefetch: bool = True
    ray: str | None = None
    workers: int | None = None

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> RunRequest:
        load = load_options(args)
        if args.ray:  # an address that cannot be valid: before any work, not after Ray's tries
            from msfnet.runtime.batch.ray_cluster import cluster_endpoint

            cluster_endpoint(args.ray)
        return cls(
            tuple(args.stacks),
            args.demo,
            model_options(args),
            load,
            output=args.output,
            overwrite=args.overwrite,
            repeat=args.repeat,
            json=args.json,
            quiet=args.quiet,
            save=options_from_args(SaveOptions, args),
            prefetch=not args.no_prefetch,
            ray=args.ray,
            workers=args.workers,
        )

    @property
    def chatty(self) -> bool:
        return not self.quiet and not self.json


def print_result(result: Result, outdir: Path, files: list[Path], req: RunRequest) -> None:
    p = result.profile()
    if req.json:
        metrics = result.metrics.as_dict() if result.metrics else None
        data = {"stack": p["stack"], "output": str(outdir), "files": [f.name for f in files]}
        print(json_text(data | {"profile": p, "metrics": metrics}), end="")
        return
    if req.quiet:
        return
    ran = result.method
    print(
        f"{result.stack.name}: {p['lights']} lights, {p['width']}x{p['height']}, "
        f"{p['mask_pixels']} mask px, {ran.method} ({ran.engine} {ran.precision})"
    )
    if ran.choice:  # its first reason: the whole (~400 characters) filled a log's line
        first = ran.choice.partition("; ")[0]
        first = first if len(first) <= 110 else first[:107] + "..."
        rest = " (every reason: profile.json, choice)" if first != ran.choice else ""
        print(f"engine choice: {first}{rest}")
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


def _print_warnings(result: Result, req: RunRequest) -> None:
    """One line each on stderr, once the outputs are written (a run that then fails gives
    its one error line only)."""
    if not req.quiet:
        for line in result.stack.warnings:
            _stderr(f"{PROG}: warning: {line}")


def _warn_without_figures(req: RunRequest) -> None:
    """One line per command when the pictures cannot be drawn (Pillow, their text, missing):
    the figures were skipped, every other output was written."""
    from msfnet.runtime.results.maps import pictures

    if not req.quiet and not pictures.can_draw():
        _stderr(f"{PROG}: warning: {pictures.missing_note()}")


def _stderr(line: str) -> None:
    """A line on stderr, above any progress bar that is drawn. tqdm is imported only where a
    bar is drawn (~17 ms of a run's start otherwise): a line printed before is simply printed."""
    bars = sys.modules.get("tqdm")
    if bars is not None:
        bars.tqdm.write(line, file=sys.stderr)
    else:
        print(line, file=sys.stderr)


def _warn(line: str) -> None:
    _stderr(f"{PROG}: warning: {line}")


def _terminal() -> bool:
    return sys.stderr.isatty()


@contextmanager
def stage_status(name: str, enabled: bool, lines: bool = False) -> Iterator[Callable[[str], None]]:
    """Where a run stands, so that long work does not look dead. On a terminal (``enabled``):
    a status line on stderr naming the step under way and the time so far, ticking each
    second, erased when the run ends. In a pipe (``lines``): one line a step on stdout."""
    started = time.perf_counter()
    current = [""]
    bar = None
    done = threading.Event()

    def show() -> None:
        if bar is not None and current[0]:
            took = time.perf_counter() - started
            bar.set_description_str(f"{PROG}: {name}: {current[0]} ... ({took:.1f} s)", True)

    def step(what: str) -> None:
        nonlocal lines
        current[0] = what
        if lines:
            try:
                print(f"{PROG}: {name}: {what} ...", flush=True)
            except BrokenPipeError:  # `| head -1`: the run goes on to write its outputs
                lines = False
        show()

    ticker = None
    if enabled:
        from tqdm import tqdm

        bar = tqdm(total=0, bar_format="{desc}", leave=False, file=sys.stderr, dynamic_ncols=True)

        def tick() -> None:
            while not done.wait(1.0):
                show()

        ticker = threading.Thread(target=tick, name="msfnet-status", daemon=True)
        ticker.start()
    try:
        yield step
    finally:
        done.set()
        try:
            if ticker is not None:
                ticker.join(2.0)
        finally:
            if bar is not None:
                bar.close()


def _say(req: RunRequest, line: str | None) -> None:
    if line and req.chatty:
        print(line)


def _default_name(path: Path) -> str:
    """A single run's default output folder name: the stem of the stack's absolute path
    (``part.npz`` -> part; ``ballPNG/..`` is named after the folder it means, not "..")."""
    return Path(os.path.abspath(path)).stem or "stack"


@contextmanager
def naming_the_stack(src: Path | Stack) -> Iterator[None]:
    """A problem found while running a stack (a map its normals cannot make) names the stack,
    as the command's one error line does for a file."""
    try:
        yield
    except InputError as exc:
        if exc.path is not None or not isinstance(src, Path):
            raise
        raise InputError(exc.message, src) from exc


def _run_single(req: RunRequest, src: Path | Stack, item: BatchItem | None = None) -> int:
    load = req.load
    if req.workers is not None:
        raise InputError("--workers is for --ray (workers of a batch on a cluster)")
    name = src.name if isinstance(src, Stack) else _default_name(src)
    out = req.output if req.output is not None else numbered_folder(Path("msf-out") / name)
    inputs = [*load.inputs(), req.model.model] + ([src] if isinstance(src, Path) else [])
    # and what the stack reads from elsewhere, through links
    reads = linked_reads(src) if isinstance(src, Path) else []
    check_output(out, inputs, overwrite=req.overwrite, folder=True, reads=reads)  # before work
    model = Model(options=req.model)
    progress = sys.stderr.isatty() and req.chatty
    if item is not None:
        _say(req, item.note(load))
    with (
        stage_status(name, not req.quiet and _terminal(), req.chatty and not _terminal()) as step,
        announcing(step),
        naming_the_stack(src),
    ):
        result = model(
            src,
            item.options(load) if item is not None else load,
            repeat=req.repeat,
            progress=progress,
        )
        if item is not None:
            result.input = item.describe_input(model._loading(load))  # the ROI's halo
        report = req.save.report and result.maps is not None  # the report shows the maps
        announce("writing the outputs" + (" and report.html" if report else ""))
        files = result.save(
            out, overwrite=req.overwrite, inputs=tuple(load.inputs()), options=req.save
        )
    _print_warnings(result, req)
    _warn_without_figures(req)
    print_result(result, out, files, req)
    if req.demo and req.model.is_network and req.chatty:
        l2 = Model.least_squares()(result.stack)
        assert l2.metrics is not None
        print(
            f"least squares on the same stack: MAE {l2.metrics.mae_deg:.3f} deg, median "
            f"{l2.metrics.median_deg:.3f} deg, err15 {l2.metrics.err15 * 100:.1f} %"
        )
    return 0


def _batch_root(req: RunRequest, items: list[BatchItem]) -> Path:
    """The batch's output folder, checked with every stack's before anything is made: bad
    input leaves no output, not even an empty folder (the stacks' folders and the summary
    create it)."""
    load = req.load
    if req.repeat != 1:
        raise InputError("--repeat profiles one stack; give a single STACK")
    if req.workers is not None and req.ray is None:
        raise InputError("--workers is for --ray")
    if req.output is not None:
        root = req.output
    else:
        one_folder = len(req.stacks) == 1 and req.stacks[0].is_dir()
        root = numbered_folder(
            Path("msf-out") / (folder_name(req.stacks[0]) if one_folder else "batch")
        )
    # the folders named on the command line and a light file the stacks share are inputs
    # too: a batch's results never go inside the batch folder
    inputs = [*load.inputs(), req.model.model, *req.stacks]
    inputs += [p for i in items for p in i.options(load).inputs() if p not in inputs]
    stacks = [i.path for i in items]
    # what the stacks read from elsewhere can only be replaced where the root exists already
    check_not_input(root, [*inputs, *stacks], folder=True, holding=False)
    clash = next((i for i in items if i.name in SUMMARY_FILES), None)
    if clash is not None:  # found up front, not after the batch ran
        raise InputError(
            f"a stack is named {clash.name!r}, as the batch's summary file; rename it", clash.path
        )
    check_batch_root(root, [i.name for i in items], req.overwrite)
    if os.path.lexists(root):  # one it will replace: does it hold a file the stacks read
        reads = [f for p in stacks for f in linked_reads(p)]
        check_not_holding(root, [*inputs, *stacks], reads, folder=True)
    for item in items:
        check_output(root / item.name, [*inputs, item.path], overwrite=req.overwrite, folder=True)
    for name in SUMMARY_FILES:
        check_output(root / name, [*inputs, *stacks], overwrite=req.overwrite)
    return root


def _batch_reporter(req: RunRequest) -> Callable[[StackRow, Result | None], None]:
    """What msf-run prints as each stack of a batch ends (above the batch's progress bar)."""
    from tqdm import tqdm

    def report(row: StackRow, result: Result | None) -> None:
        if row.error is not None:
            _stderr(f"{PROG}: error: {row.error}")
            return
        if result is not None:
            _print_warnings(result, req)
        if req.json and result is not None:
            files = sorted(
                p.name for p in Path(row.output or ".").iterdir() if not p.name.startswith(".")
            )
            print_result(result, Path(row.output or "."), [Path(f) for f in files], req)
        elif req.chatty:
            mae = row.metrics.mae_deg if row.metrics else None
            score = "" if mae is None else f", MAE {mae:.2f} deg"
            tqdm.write(
                f"{row.name}: {row.lights} lights, {row.width}x{row.height}{score}; "
                f"decode {row.decode_s:.2f} s (waited {row.wait_s:.2f}), infer "
                f"{row.compute_s:.2f} s -> {row.output}/"
            )

    return report


def _run_batch(req: RunRequest, items: list[BatchItem]) -> int:
    load = req.load
    root = _batch_root(req, items)
    model = None
    if req.ray is not None:
        from msfnet.runtime.batch.ray_cluster import ModelSpec, import_ray, run_batch_ray

        import_ray()  # not installed: say so now
        one_thread = req.model.replace(threads=req.model.threads or 1)
        spec = ModelSpec.of(one_thread)
        # the workers open it far away; a file they would all refuse is refused here, once
        Model(options=one_thread.replace(threads=1))
    else:
        model = Model(options=req.model)
    for item in items:
        _say(req, item.note(load))
    report = _batch_reporter(req)
    progress = None if req.chatty else False
    batch = (
        partial(run_batch, model, prefetch=req.prefetch)
        if model is not None
        else partial(
            run_batch_ray,
            spec,
            address=req.ray or None,
            workers=req.workers,
            on_note=None if req.quiet else _warn,
        )
    )
    summary = batch(
        items,
        load,
        lambda n: root / n,
        overwrite=req.overwrite,
        save=req.save,
        summary_dir=root,
        on_result=report,
        progress=progress,
        inputs=tuple(load.inputs()),
    )
    if summary.rows and len(summary.failed) < len(summary.rows):
        _warn_without_figures(req)  # once for the batch, not once per stack
    if req.json:
        print(json_text({"summary": summary.as_dict(), "output": str(root)}), end="")
    elif not req.quiet:
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
    req = RunRequest.from_args(args)  # every option checked here, before any work
    if req.demo:
        from msfnet.runtime.demo import demo_stack

        if req.ray is not None:
            raise InputError("--demo runs here; --ray is for stacks on disk")
        return _run_single(req, demo_stack())
    items = expand_stacks(list(req.stacks), select_given=req.load.select is not None)
    if len(items) == 1 and req.ray is None and items[0].path == req.stacks[0]:
        return _run_single(req, req.stacks[0], items[0])
    return _run_batch(req, items)


def main(argv: list[str] | None = None) -> int:
    return command_main(COMMAND, build_parser(), _run, argv)


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["RunRequest", "build_parser", "main", "print_result"]
