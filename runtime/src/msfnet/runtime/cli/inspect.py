"""msf-inspect: relief defects from a run's registered maps, a verdict and a PLC exit code.

Input: an msf-run output folder, or a stack (msf-run's pipeline runs first); ``--watch`` a
folder of parts, ``--train-good`` good parts. Output: verdict.json, regions.csv, overlay.png and
deviation.png written together into -o, or nothing. Exit codes as ``--help`` lists them (3: the
tool's own failure). docs/run.md, "Inspection: ... msf-inspect" and "Inspection station".
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import replace
from pathlib import Path

from msfnet.common.cli import (
    Command,
    add_flags,
    command_main,
    flag_names,
    make_parser,
    options_from_args,
    path_arg,
)
from msfnet.common.errors import InputError
from msfnet.common.files import check_output, staged_folder
from msfnet.common.imageio import encode_png
from msfnet.common.vocabulary import word
from msfnet.runtime.engines.method import RunMethod
from msfnet.runtime.inspection.defects import (
    DefectOptions,
    InspectionInput,
    Verdict,
    check_run_memory,
    deviation_picture,
    find_defects,
    from_maps,
    is_run,
    kinds_text,
    overlay_picture,
    read_run,
)
from msfnet.runtime.inspection.watch import WatchOptions
from msfnet.runtime.inspection.zones import Zones, read_zones
from msfnet.runtime.options import ModelOptions
from msfnet.runtime.results.provenance import Provenance

PROG = "msf-inspect"
COMMAND = Command(PROG, failure_exit=3, memory_advice="lower --max-memory (or --tile)")
# msf-inspect's own options: never "a flag for running a stack"
_OWN = (
    "input",
    "output",
    "overwrite",
    "depth",
    "curvature",
    "min_area_px",
    "polarity",
    "sigmas",
    "reference",
    "train_good",
    "zones",
    "quiet",
    "debug",
    "watch",
    "once",
    "poll_s",
    "stale_s",
)


def build_parser() -> argparse.ArgumentParser:
    from msfnet.runtime.cli.flags import add_load_flags, add_map_flags, add_model_flags

    p = make_parser(
        PROG,
        "Find relief defects (scratches, dents, bumps) in a part's local shape and "
        "curvature; printed marks (albedo only) are not defects. Exit code: 0 pass, 1 "
        "defects found, 2 bad input or output, 3 a failure of the tool itself, 4 the part "
        "does not match its reference.",
        examples=(
            "msf-inspect out/part17 --depth 0.02 -o verdicts/part17",
            "msf-inspect captures/part17 --pixel-size 0.05 --depth 0.02 -o verdicts/part17",
            "msf-inspect out/part17 --reference out/golden --depth 0.02 -o v17",
            "msf-inspect --train-good good1 good2 good3 good4 good5 -o model",
            "msf-inspect --watch incoming/ --reference model --depth 0.05 -o station/",
        ),
    )
    p.add_argument(
        "input",
        type=path_arg,
        nargs="?",
        help="an msf-run output folder (maps.json, local_shape.tif) or a stack (then msf-run's "
        "pipeline runs first, with the flags below); not with --watch",
    )
    p.add_argument(
        "-o",
        "--output",
        type=path_arg,
        required=True,
        help="folder for the verdict (with --watch: the station's folder, resumed if it exists)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an earlier verdict folder")
    t = p.add_argument_group("thresholds (in the maps' units: mm with --pixel-size, else px)")
    add_flags(t, DefectOptions)
    t.add_argument(
        "--reference",
        type=path_arg,
        help="a good part (run folder or stack, same fixture and size), or a variation model "
        "(--train-good): only what differs from it counts (aligned by phase correlation "
        "first); a part one of whose regions covers over 80 %% of it is a MISMATCH (exit 4)",
    )
    t.add_argument(
        "--zones",
        type=path_arg,
        metavar="JSON",
        help='areas with their own --depth / --curvature, or left out: {"zones": [{"name": '
        '"logo", "polygon": [[x, y], ...], "ignore": true}, ...]} in camera image pixels',
    )
    t.add_argument(
        "--train-good",
        type=path_arg,
        nargs="+",
        metavar="GOOD",
        help="learn a variation model from these good parts (run folders or stacks, 3 or "
        "more; 5+ recommended) into -o, for --reference; prints a suggested --depth",
    )
    s = p.add_argument_group(
        "station (a warm loop: the model and reference loaded once, then each part that "
        "appears in DIR judged once; one JSON line per part in OUT/parts.jsonl)"
    )
    s.add_argument(
        "--watch",
        type=path_arg,
        metavar="DIR",
        help="judge each complete part (a stack sub-folder) that appears in DIR; stop with "
        "SIGTERM or Ctrl-C (after the part in hand)",
    )
    add_flags(s, WatchOptions)
    # when INPUT is a stack: how it is run (msf-run's own flags)
    add_model_flags(p)
    add_load_flags(p, camera=True)
    add_map_flags(p)
    for action in p._actions:  # msf-run's output choices: msf-inspect writes its verdict only
        if action.dest in WRITING_FLAGS:
            action.help = argparse.SUPPRESS
    return p


# msf-run flags about what it writes, by dest, and the value each leaves when not given (--no-tiff
# clears tiff): nothing here writes them, so they are refused
WRITING_FLAGS = {"no_maps": False, "maps": None, "tiff": True, "report": True, "normals_png": False}
# how a stack would be run, not what its maps mean: harmless beside a run folder (a PLC
# wrapper that always caps threads and memory must keep working)
RESOURCE_FLAGS = flag_names(ModelOptions, "resources")


def _stack_flags(argv: list[str] | None) -> list[str]:
    """The msf-run flags on the command line that change what a stack's maps mean (given at
    all, defaults included: "--local-size 12" on a 30 px run would be ignored just the same)."""
    parser = build_parser()
    for action in parser._actions:
        action.default = argparse.SUPPRESS  # parsed again: only what was typed remains
        action.required = False
    given = vars(parser.parse_known_args(argv)[0])
    names = []
    for action in parser._actions:
        dest = action.dest
        if not action.option_strings or dest not in given:
            continue
        if dest in ("help", "version", *_OWN, *RESOURCE_FLAGS, *WRITING_FLAGS):
            continue
        names.append(max(action.option_strings, key=len))
    return names


def _check_input_kind(path: Path) -> None:
    """A folder msfnet wrote that holds no maps is named as such, not read as a stack."""
    if is_run(path) or not path.is_dir():
        return
    if (path / "summary.json").is_file():
        raise InputError("an msf-run batch output: give one stack's folder inside it", path)
    if (path / "profile.json").is_file() and (path / "normals.npy").is_file():
        raise InputError(
            "an msf-run output without maps (written with --no-maps or --no-tiff?): run "
            "msf-run again with maps, or give the stack itself",
            path,
        )


def _prepare(path: Path, args: argparse.Namespace) -> InspectionInput:
    """A run folder's maps, or a stack run through msf-run's pipeline (in memory); ``path``
    exists (:func:`_run` checks both inputs first)."""
    if is_run(path):
        return read_run(path)
    from msfnet.runtime.api import Model
    from msfnet.runtime.cli.flags import load_options, model_options
    from msfnet.runtime.results.maps import MapOptions
    from msfnet.runtime.stack import load_stack

    load = load_options(args)
    opts = model_options(args)
    maps = opts.maps or MapOptions()
    need = tuple(dict.fromkeys((*maps.maps, "albedo", "height", "curvature")))
    # replace() keeps what the flags set (frame, the stored image's pixel size, ...)
    maps = replace(maps, maps=tuple(n for n in need if n != "mesh"))
    stack = load_stack(path, load)
    model = Model(options=opts.replace(maps=maps))
    result = model(stack)
    assert result.maps is not None
    part = from_maps(result.maps, str(path))
    part.method = result.method  # what ran (least squares where too few lights for the net)
    return part


def _rule(args: argparse.Namespace) -> DefectOptions:
    return options_from_args(DefectOptions, args)


def _run(args: argparse.Namespace, argv: list[str] | None = None) -> int:
    if args.train_good is not None:
        return _train(args)
    if args.watch is not None:
        return _station(args)
    loop = [
        f
        for f, d in (("--once", "once"), ("--poll", "poll_s"), ("--stale", "stale_s"))
        if getattr(args, d) != getattr(WatchOptions(), d)
    ]
    if loop:
        raise InputError(f"{', '.join(loop)}: for a station's loop, with --watch DIR")
    if args.input is None:
        raise InputError("give INPUT (a run folder or a stack), or --watch DIR")
    options = _rule(args)
    from msfnet.runtime.cli.flags import load_options, model_options
    from msfnet.runtime.stack import linked_reads

    zones = _zones(args)
    # every file read is an input: the part, the reference, and the files the load and model
    # flags name (an --overwrite over a folder holding the --mask read deleted it)
    read = [args.input, args.reference, args.zones, *load_options(args).inputs()]
    read.append(model_options(args).model)
    inputs = tuple(p for p in read if p is not None)
    # and what the part's and the reference's stacks read from elsewhere, through links
    reads = linked_reads(args.input) + (
        linked_reads(args.reference) if args.reference is not None else []
    )
    check_output(args.output, inputs, overwrite=args.overwrite, folder=True, reads=reads)
    # given at all: --maps none parses to () (no map), still an output choice
    given = [d for d, unset in WRITING_FLAGS.items() if getattr(args, d, unset) != unset]
    writing = [word(d).flag for d in given]
    if writing:
        raise InputError(
            f"{', '.join(writing)}: msf-run's output choices; msf-inspect writes only its "
            "verdict and overlay"
        )
    given = _stack_flags(argv)
    runs = [p for p in (args.input, args.reference) if p is not None and is_run(p)]
    if given and len(runs) == (1 if args.reference is None else 2):
        # a run folder's maps are used as written: --pixel-size 0.05 --depth 0.005 on a px
        # run was 0.005 px, silently
        raise InputError(
            f"{', '.join(given)} {'applies' if len(given) == 1 else 'apply'} only when "
            "INPUT is a stack; this is an msf-run "
            f"output, whose maps are used as written ({read_run(runs[0]).units['depth']}): "
            "leave them out, or give the stack",
            runs[0],
        )
    budget = model_options(args).max_memory_mb
    for path in (args.input, args.reference):
        if path is not None:
            if not path.exists():  # the reference too, before the part's whole run
                raise InputError("no such file or folder", path)
            _check_input_kind(path)
            if is_run(path):
                check_run_memory(path, budget, args.reference is not None)
    part = _prepare(args.input, args)
    reference = None if args.reference is None else _prepare(args.reference, args)
    verdict, labels = find_defects(part, options, reference, zones)
    verdict = replace(verdict, provenance=_provenance(args, part).as_dict())
    picture = overlay_picture(part, labels, verdict.regions)
    with staged_folder(args.output, overwrite=args.overwrite) as tmp:
        (tmp / "verdict.json").write_text(verdict.json_text(), encoding="utf-8")
        (tmp / "regions.csv").write_text(verdict.csv_text(), encoding="utf-8")
        encode_png(tmp / "overlay.png", picture)
        encode_png(tmp / "deviation.png", deviation_picture(verdict))
    if not args.quiet:
        print(_summary(verdict, args.output))
        for judged in verdict.statistics:  # what a threshold is chosen from, in its units
            print(judged.line())
    return verdict.exit_code


def _zones(args: argparse.Namespace) -> Zones | None:
    """--zones, read and checked before any part is run."""
    return None if args.zones is None else read_zones(args.zones)


def _train(args: argparse.Namespace) -> int:
    """--train-good: a variation model from good parts (inspection.variation)."""
    from msfnet.runtime.inspection.variation import MIN_GOOD_PARTS, train_variation

    if args.input is not None or args.watch is not None or args.reference is not None:
        raise InputError("--train-good takes no INPUT, --watch or --reference")

    goods = list(args.train_good)
    if len(goods) < MIN_GOOD_PARTS:
        raise InputError(
            f"a variation model needs at least {MIN_GOOD_PARTS} good parts (5 or more "
            f"recommended), got {len(goods)}"
        )
    seen: dict[str, Path] = {}
    for path in goods:
        if not path.exists():
            raise InputError("no such file or folder", path)
        _check_input_kind(path)
        real = os.path.realpath(path)
        if real in seen:
            raise InputError(f"given twice (also as {seen[real]}): each good part once", path)
        seen[real] = path
    check_output(args.output, goods, overwrite=args.overwrite, folder=True)
    # the rule the parts will be judged by, its depth searched per good part
    rule = options_from_args(DefectOptions, args, overrides={"depth": 1.0, "curvature": None})
    mapped = []
    for i, path in enumerate(goods, 1):  # seconds each with the network: say where it is
        mapped.append(_prepare(path, args))
        if not args.quiet:
            print(f"mapped good part {i}/{len(goods)}: {path}", flush=True)
    model = train_variation(mapped, rule)
    model.save(args.output, overwrite=args.overwrite)
    if not args.quiet:
        print(f"variation model of {len(goods)} good parts -> {args.output}")
        if model.statistics is not None:
            print(model.statistics.line())
    return 0


def _station(args: argparse.Namespace) -> int:
    """--watch: the warm loop (inspection.watch) until a signal, or once with --once."""
    from msfnet.runtime.cli.flags import load_options, model_options
    from msfnet.runtime.inspection.station import Station
    from msfnet.runtime.inspection.watch import JOURNAL, watch

    rule = _rule(args)
    zones = _zones(args)
    if args.input is not None:
        raise InputError(f"INPUT ({args.input}) and --watch: give one")
    if args.overwrite:
        raise InputError(
            "--overwrite with --watch: a station's folder is resumed, never replaced; give a "
            "new -o to start afresh"
        )
    folder, out = args.watch, args.output
    if not folder.is_dir():
        raise InputError("no such folder" if not folder.exists() else "not a folder", folder)
    if args.reference is not None and not args.reference.exists():
        raise InputError("no such file or folder", args.reference)
    load, opts = load_options(args), model_options(args)
    inputs = [folder, args.reference, args.zones, *load.inputs(), opts.model]
    held = out.is_dir() and any(not p.name.startswith(".") for p in out.iterdir())
    if held and not (out / JOURNAL).is_file():
        raise InputError(f"holds other files and no {JOURNAL}: give a new or empty folder", out)
    check_output(out / JOURNAL, [p for p in inputs if p is not None], overwrite=True)
    station = Station(rule, opts, load=load, reference=args.reference, zones=zones)
    report = (lambda record: None) if args.quiet else _print_part
    summary = watch(
        station,
        folder,
        out,
        options_from_args(WatchOptions, args),
        skip=tuple(p for p in (args.reference,) if p is not None),
        report=report,
    )
    if not args.quiet:
        print("\n".join(summary.lines()))
    return summary.exit_code if args.once else 0


def _print_part(record: object) -> None:
    from msfnet.runtime.inspection.watch import PartRecord

    assert isinstance(record, PartRecord)
    ms = record.times_ms.get("total")
    took = f" ({ms:.0f} ms)" if ms is not None else ""
    if record.verdict == "error":
        print(f"{record.part}: error: {record.error}", flush=True)
    elif record.verdict == "pass":
        print(f"{record.part}: PASS{took}", flush=True)
    elif record.verdict == "mismatch":
        print(f"{record.part}: MISMATCH (not the reference's part, or misplaced){took}", flush=True)
    else:
        what = kinds_text(str(region.get("kind")) for region in record.regions)
        print(f"{record.part}: FAIL, {record.defects} defect(s): {what}{took}", flush=True)


def _provenance(args: argparse.Namespace, part: InspectionInput) -> Provenance:
    """What made the part's maps: this run's model, or the run folder's own record."""
    method = part.method
    if method is None and is_run(args.input):
        try:
            profile = json.loads((args.input / "profile.json").read_text(encoding="utf-8"))
            made = Provenance.from_dict(profile.get("provenance") or {})
            method = RunMethod(model=made.model, engine=made.engine, precision=made.precision)
        except (OSError, ValueError, TypeError, AttributeError):
            method = None  # a run without a readable profile: the verdict still stands
    inputs = [p for p in (args.input, args.reference) if p is not None]
    return Provenance.of(inputs, method)


def _summary(verdict: Verdict, output: Path) -> str:
    if verdict.mismatch is not None:
        return f"MISMATCH: {verdict.mismatch}: another part, or not in its place -> {output}"
    if verdict.passed:
        return f"PASS: no defect ({verdict.pixels} px inspected) -> {output}"
    by_depth = verdict.options.depth is not None
    worst = max(verdict.regions, key=lambda r: r.depth if by_depth else r.curvature)
    x, y = worst.image_peak
    where = "image " if not verdict.frame.is_identity else ""
    size = (
        f"deepest {worst.depth:.4g} {verdict.units['depth']}"
        if by_depth
        else f"most bent {worst.curvature:.4g} {verdict.units['curvature']}"
    )
    return (
        f"FAIL: {len(verdict.regions)} defect(s) ({verdict.kinds()}); {size} at "
        f"{where}x={x:.0f}, y={y:.0f} -> {output}"
    )


def main(argv: list[str] | None = None) -> int:
    return command_main(COMMAND, build_parser(), lambda args: _run(args, argv), argv)


if __name__ == "__main__":
    sys.exit(main())
