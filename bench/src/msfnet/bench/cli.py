"""msf-bench: latency, throughput and accuracy of MSF-Net variants on this CPU, in one run.

Runs the matmul peak measurement, workloads (a)-(c) for every variant and thread count (each
cell in a fresh process), workload (d) end to end through msf-run, and writes REPORT.md,
report.json and a latency plot to the report folder: one output, built in a staging folder
(common/files.py), with the models it measured (exported afresh on every run, never cached).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import cast

import numpy as np
from tqdm import tqdm

from msfnet.bench.data import ENV_VAR, data_root
from msfnet.bench.options import (
    ALL_VARIANTS,
    CALIB_IN_DATA,
    DEFAULT_THREADS,
    EDGE,
    PER_LIGHT_FULL_MAX_LIGHTS,
    STACK_IN_DATA,
    BenchOptions,
    flag_categories,
    thread_counts,
)
from msfnet.bench.peak import engine_peaks, merge_peaks
from msfnet.bench.report import write_report
from msfnet.bench.worker import row_time_limit, run_module
from msfnet.bench.workloads import (
    QUICK_WORKLOADS,
    VARIANTS,
    WORKLOADS,
    Workload,
    full_input,
    make_input,
    time_msf_run,
    time_warm_model,
)
from msfnet.common.cli import Command, add_flags, command_main, make_parser, options_from_args
from msfnet.common.cpu import detect_cpu, proxy_class
from msfnet.common.errors import InputError
from msfnet.common.files import check_output, scratch_folder, staged_folder, write_json, write_text
from msfnet.runtime.engines import installed_engines
from msfnet.runtime.engines.dispatch import choose_engine
from msfnet.runtime.evaluate.metrics import deviation_deg, normal_metrics
from msfnet.runtime.infer.flops import inference_flops
from msfnet.runtime.stack.types import MIN_LIGHTS

PROG = "msf-bench"
COMMAND = Command(PROG, extra="bench", memory_advice="lower --max-memory")
PER_LIGHT_FULL_REPEATS = 2  # timed runs in its one process: the median of two

# variants that need the int8 exports (and so the calibration stacks)
INT8_MODEL_VARIANTS = tuple(n for n, v in VARIANTS.items() if v.model.startswith("int8"))
EDGE_GROUP = "torch-free modes (run on an edge install; each writes REPORT.md and report.json)"


def build_parser() -> argparse.ArgumentParser:
    p = make_parser(
        PROG,
        "Benchmark MSF-Net on this CPU: ONNX Runtime fp32 / int8, OpenVINO bf16 / int8 "
        "(if installed), PyTorch eager and the published per-light loop, on workloads (a) 16 "
        "lights 64x64, (b) 32 lights 128x128, (c) 96 lights 128x128 and (d) a full stack "
        "through msf-run. Reports median/p90 latency, peak RSS, GFLOP/s, fraction of the "
        "matmul peak measured in the same run, and angular deviation from PyTorch fp32.",
        (
            "msf-bench --quick --report-dir /tmp/msf-bench-quick",
            "msf-bench --report-dir bench/full --overwrite",
        ),
    )
    p.epilog = (
        (p.epilog or "")
        + """

the report folder holds REPORT.md, report.json, latency.png, models/ (the ONNX exports
it measured) and e2e/ (msf-run's outputs for workload (d)). It is built beside the
target and appears complete or not at all (on Ctrl-C or kill too; staging left by
kill -9 goes with the next run). It may not be, contain or lie inside an input
(--stack, --calib, --checkpoint, the data root). Models are exported afresh on every
run, never cached between runs, so a report always measures the models it holds."""
    )
    # one flag per BenchOptions field, in its order (the usage line's), each in its help group
    groups: dict[str, argparse.ArgumentParser | argparse._ArgumentGroup] = {
        "": p,
        EDGE: p.add_argument_group(EDGE_GROUP),
    }
    for name, category in flag_categories():
        add_flags(groups[category], BenchOptions, only=(name,))
    return p


def machine_description() -> dict[str, object]:
    """CPU model and the features that decide engines and precisions (common/cpu.py)."""
    import onnxruntime

    cpu = detect_cpu()
    flags = sorted(f for f in cpu.all_flags if f.startswith(("avx", "amx", "fma")))
    out: dict[str, object] = {
        "cpu": cpu.model,
        "vendor": cpu.vendor,
        "cores": cpu.cores,
        "isa_flags": flags,
        "cpu_features": cpu.as_dict(),
        "python": platform.python_version(),
        "python_bytecode_cache": bytecode_cached(),
        "onnxruntime": onnxruntime.__version__,
        "platform": platform.platform(),
    }
    from msfnet.runtime.engines.openvino import import_openvino

    try:
        out["openvino"] = import_openvino().__version__
    except InputError:  # not installed
        out["openvino"] = None
    return out


def bytecode_cached(modules: dict[str, ModuleType] | None = None) -> bool:
    """Whether a fresh process (the msf-run rows) loads msfnet's runtime modules from cached
    bytecode rather than compiling them (~0.1 s a run): Python may write the cache
    (PYTHONDONTWRITEBYTECODE unset; a child started by sys.executable does not inherit -B),
    or every module already has an up-to-date one (read even when writing is off).
    ``modules``: the loaded modules to look at (default: this process's)."""
    import importlib.util

    if not os.environ.get("PYTHONDONTWRITEBYTECODE"):
        return True
    for name, module in list((sys.modules if modules is None else modules).items()):
        source = getattr(module, "__file__", None)
        if not name.startswith("msfnet.runtime") or not source or not source.endswith(".py"):
            continue
        cached = importlib.util.cache_from_source(source)
        if not os.path.exists(cached) or os.path.getmtime(cached) < os.path.getmtime(source):
            return False
    return True


def dispatch_choices(models: dict) -> dict[str, str]:
    """What msfnet.runtime.engines.dispatch picks on this machine for each exported model."""
    out = {}
    for key in ("fp32", "fp32_staged", "int8", "int8_staged"):
        if key in models:
            try:
                out[key] = choose_engine(models[key], detect_cpu(), installed_engines()).reason
            except InputError as exc:
                out[key] = f"error: {exc}"
    return out


def resolve_paths(opts: BenchOptions) -> tuple[Path, tuple[Path, ...], Path | None]:
    """--stack and --calib, from the data root where not given; InputError with what was
    tried. Returns them and the data root, or None where none was needed or found."""
    root = None
    if opts.stack is None or opts.calib is None:
        try:
            root = data_root(opts.data)
        except InputError:
            # without a data root a given --stack is enough, but a root the user named
            # (--data, $MSFNET_DATA) that is not there is a typo: int8 would calibrate on
            # the one stack instead of four, silently
            if opts.stack is None or opts.data is not None or os.environ.get(ENV_VAR):
                raise
    stack = opts.stack if opts.stack is not None else cast(Path, root) / STACK_IN_DATA
    calib = opts.calib
    if calib is None:
        found = [root / p for p in CALIB_IN_DATA[1:] if (root / p).exists()] if root else []
        calib = (stack, *found)
    if not stack.is_dir():
        raise InputError(f"stack folder not found (set --data or ${ENV_VAR}, or --stack)", stack)
    return stack, calib, root


@dataclass(frozen=True)
class Plan:
    """What one msf-bench run does, settled before anything is written or printed."""

    variants: list[str]
    notes: list[str]  # variants skipped on this machine, and why
    threads: list[int]  # descending
    checkpoint: Path | None  # None: seeded random weights
    stack: Path  # --stack, or the data root's
    calib: tuple[Path, ...]  # --calib, or the stack and the data root's


def plan_run(opts: BenchOptions) -> Plan:
    """Check every option and input path, and the report folder against them (InputError),
    before any work: the report folder is no input, does not hold one, and replaces an earlier
    report only with --overwrite."""
    from msfnet.model.checkpoint import default_checkpoint_path
    from msfnet.runtime.api import default_model_path

    variants = [v.strip() for v in opts.variants.split(",") if v.strip()]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        raise InputError(f"--variants: unknown {', '.join(unknown)} (known: {', '.join(VARIANTS)})")
    if opts.random_weights and opts.checkpoint is not None:
        raise InputError("--random-weights and --checkpoint exclude each other")
    if opts.lights is not None and opts.no_e2e:
        raise InputError("--lights sets workload (d)'s light count: drop --no-e2e")
    checkpoint = None if opts.random_weights else opts.checkpoint or default_checkpoint_path()
    if checkpoint is not None and not checkpoint.is_file():
        raise InputError("checkpoint not found", checkpoint)
    if opts.max_memory is not None and not opts.no_e2e:
        # workload (d) comes last: a budget no tile fits in would end a long run there
        from msfnet.runtime.infer.tiling import tile_size_for_memory

        try:
            tile_size_for_memory(opts.max_memory, lights=opts.lights or MIN_LIGHTS)
        except InputError as exc:
            raise InputError(
                f"--max-memory {opts.max_memory:g} MB is too small for workload (d), msf-run "
                f"on any stack: {exc.message.split(': ', 1)[-1]}"
            ) from None
    stack, calibs, root = resolve_paths(opts)
    for calib in calibs:
        if not calib.exists():
            raise InputError("--calib: stack not found", calib)
    inputs = [stack, *calibs, checkpoint, root, None if opts.no_e2e else default_model_path()]
    # --overwrite replaces an earlier report, nothing else
    check_output(opts.report_dir, inputs, overwrite=opts.overwrite, folder=True, command=PROG)
    notes: list[str] = []
    engines = installed_engines()
    for v in [v for v in variants if VARIANTS[v].engine == "openvino"]:
        if "openvino" not in engines:
            notes.append(f"{v} skipped: openvino not installed (pip install openvino)")
            variants.remove(v)
        elif VARIANTS[v].precision == "bf16" and not detect_cpu().has_bf16:
            notes.append(f"{v} skipped: this CPU has no native bf16 (OpenVINO would run fp32)")
            variants.remove(v)
    threads = sorted(set(opts.threads), reverse=True)
    return Plan(variants, notes, threads, checkpoint, stack, calibs)


@dataclass
class Inputs:
    """The data every cell and export reads, loaded (and so checked) before any work."""

    feeds: dict[str, dict[str, np.ndarray]]  # workload key -> make_input's crop
    calib: list | None  # int8 calibration stacks (None: no int8 variant)


def load_inputs(opts: BenchOptions, plan: Plan) -> Inputs:
    """The workload crops of --stack and the int8 calibration stacks: a stack that cannot be
    read is one InputError line before anything is written or printed."""
    feeds = {
        wl.key: make_input(plan.stack, wl) for wl in (QUICK_WORKLOADS if opts.quick else WORKLOADS)
    }
    calib = None
    if any(v in INT8_MODEL_VARIANTS for v in plan.variants):
        from msfnet.export.quantize import load_calibration_stacks

        calib = load_calibration_stacks(list(plan.calib))
    return Inputs(feeds, calib)


def prepare_models(plan: Plan, workdir: Path, calib: list | None) -> dict:
    """fp32 ONNX (and int8 when ``calib`` stacks are given) from the checkpoint, or from seeded
    random weights, exported into ``workdir`` (a new folder inside the report's staging)."""
    import torch

    from msfnet.export.pipeline import export_variant
    from msfnet.model.checkpoint import save_checkpoint
    from msfnet.model.network import MSFNet

    workdir.mkdir()
    ckpt = plan.checkpoint
    if ckpt is None:
        torch.manual_seed(0)
        ckpt = workdir / "random_seed0.pth"
        save_checkpoint(MSFNet().eval(), ckpt)
    models: dict = {"checkpoint": str(ckpt), "random_weights": plan.checkpoint is None}
    # The export variants table: every file is verified as msf-export verifies it.
    rows = [("fp32", "fp32"), ("fp32_staged", "staged")]
    if calib is not None:
        rows += [("int8", "int8"), ("int8_staged", "staged-int8")]
    for key, variant in rows:
        out = workdir / f"msfnet_{key}.onnx"
        result = export_variant(ckpt, variant, out, calib=calib)
        models[key] = str(out)
        if key.startswith("int8"):
            models[f"{key}_summary"] = {
                "variant": variant,
                "mean_deg": result.mean_deg,
                "max_deg": result.max_deg,
                "notes": result.notes,
            }
    return models


def schedule(quick: bool, variants: list[str], threads: list[int]):
    """(workload, variant, threads, warmup, repeats) cells; the torch-fp32 reference first.

    Full mode keeps the total near 10-15 min on 2 cores: the slowest variants run once, and
    only where they add a ratio the issue asks for.
    """
    cells = []
    wls = QUICK_WORKLOADS if quick else WORKLOADS
    for wl in wls:
        for t in threads:
            for v in ["torch-fp32", *[x for x in variants if x != "torch-fp32"]]:
                if v not in variants and v != "torch-fp32":
                    continue
                if quick:
                    cells.append((wl, v, t, 0 if v == "per-light" else 1, 1))
                    continue
                heavy = wl.key != "a"
                if t != max(threads) and heavy and v not in ("ort-fp32", "ort-int8"):
                    continue  # 1 thread on big inputs: the two shipped ORT variants only
                if wl.key == "c" and (t != max(threads) or v == "per-light"):
                    continue  # per-light on (c) is extrapolated from (b) (linear in N)
                if v == "torch-fp32" and t != max(threads) and heavy:
                    continue
                if v == "per-light":
                    cells.append((wl, v, t, 0, 1 if heavy else 2))
                elif heavy:
                    cells.append((wl, v, t, 1, 2 if wl.key == "c" else 3))
                else:
                    cells.append((wl, v, t, 1, 5))
    return cells


def run_cell_subprocess(spec: dict, tmp: Path) -> dict:
    return run_module("msfnet.bench.workloads", spec, tmp / "spec.json")


def _say(opts: BenchOptions, line: str) -> None:
    if not opts.quiet:
        print(f"msf-bench: {line}", file=sys.stderr)


def bench(opts: BenchOptions, plan: Plan, data: Inputs, work: Path, scratch: Path) -> dict:
    """Run everything; the models and (d)'s msf-run outputs go to ``work`` (the report's
    staging folder), intermediate files to ``scratch``. Paths in the result name ``work``."""
    variants, threads = plan.variants, plan.threads
    engines = installed_engines()
    started = time.time()
    result: dict = {
        "date": time.strftime("%Y-%m-%d %H:%M %Z"),
        "machine": machine_description(),
        "quick": opts.quick,
        "variants": {v: VARIANTS[v].about for v in variants},
        "notes": plan.notes,
        "data": {"stack": str(plan.stack), "calib": [str(p) for p in plan.calib]},
        "lights": opts.lights,  # --lights: (d) on N lights against a measured per-light loop
    }
    _say(opts, "exporting models ...")
    models = prepare_models(plan, work / "models", data.calib)
    result["models"] = models
    result["dispatch"] = dispatch_choices(models)
    _say(opts, "measuring matmul peaks (torch, ONNX Runtime, OpenVINO) ...")
    peaks_before = engine_peaks(threads, engines)
    rows = []
    inputs: dict[str, tuple[Path, np.ndarray]] = {}
    refs: dict[str, np.ndarray] = {}
    cells = schedule(opts.quick, variants, threads)
    for wl, v, t, warm, reps in tqdm(cells, desc="msf-bench", unit="cell", disable=opts.quiet):
        if wl.key not in inputs:
            feed = data.feeds[wl.key]
            path = scratch / f"input_{wl.key}.npz"
            np.savez(path, images=feed["images"], lights=feed["lights"])
            inputs[wl.key] = (path, feed["mask"])
        spec = {
            "variant": v,
            "threads": t,
            "warmup": warm,
            "repeats": reps,
            "input": str(inputs[wl.key][0]),
            "checkpoint": models["checkpoint"],
            "onnx": models[VARIANTS[v].model],
            "output": str(scratch / "out.npy"),
            "result": str(scratch / "result.json"),
        }
        cell = run_cell_subprocess(spec, scratch)
        row = {
            "workload": wl.key,
            "label": wl.label(),
            "lights": wl.lights,
            "pixels": wl.pixels,
            "variant": v,
            "threads": t,
            "gflop": wl.flops / 1e9,
            **cell,
        }
        if "error" not in cell:
            out = np.load(scratch / "out.npy")
            if v == "torch-fp32" and wl.key not in refs:
                refs[wl.key] = out
            if wl.key in refs:
                mean, mx = deviation_deg(out, refs[wl.key], inputs[wl.key][1])
                row.update({"max_deg": mx, "mean_deg": mean})
            row["gflops_per_s"] = wl.flops / cell["median_s"] / 1e9
        rows.append(row)
    result["rows"] = rows
    _say(opts, "measuring matmul peaks again ...")
    result["peaks"] = merge_peaks(peaks_before, engine_peaks(threads, engines))
    if not opts.no_e2e:
        result["e2e"] = end_to_end(opts, plan, models, work / "e2e")
        whole = per_light_whole_image(opts, plan, models, scratch)
        if whole is not None:
            rows.append(whole)
    result["elapsed_s"] = time.time() - started
    return result


def per_light_whole_image(
    opts: BenchOptions, plan: Plan, models: dict, scratch: Path
) -> dict | None:
    """With --lights N (N up to PER_LIGHT_FULL_MAX_LIGHTS): the published per-light forward on
    (d)'s own input, the whole image on the N lights msf-run used, untiled, timed in a fresh
    process (median of PER_LIGHT_FULL_REPEATS runs; one with --quick). A row like (a)-(c)'s,
    workload "d", which the (d) ratios then use instead of an extrapolation. None otherwise."""
    if opts.lights is None or opts.lights > PER_LIGHT_FULL_MAX_LIGHTS:
        return None
    threads = max(plan.threads)
    feed = full_input(plan.stack, opts.lights)
    path = scratch / "input_d.npz"
    np.savez(path, images=feed["images"], lights=feed["lights"])
    h, w = feed["mask"].shape
    lights = int(feed["images"].shape[1])  # the stack may hold fewer than N
    spec = {
        "variant": "per-light",
        "threads": threads,
        "warmup": 0,  # a run takes tens of seconds: first-call set-up is ~1 % of it
        "repeats": 1 if opts.quick else PER_LIGHT_FULL_REPEATS,
        "input": str(path),
        "checkpoint": models["checkpoint"],
        "onnx": models["fp32"],
        "output": str(scratch / "out.npy"),
        "result": str(scratch / "result.json"),
    }
    _say(opts, f"timing the published per-light forward on the whole {lights}-light image ...")
    cell = run_cell_subprocess(spec, scratch)
    flops = inference_flops(lights, h * w)
    row = {
        "workload": "d",
        "label": f"(d) {lights} lights {w}x{h}, whole image",
        "lights": lights,
        "pixels": h * w,
        "variant": "per-light",
        "threads": threads,
        "gflop": flops / 1e9,
        **cell,
    }
    if "error" not in cell:
        row["gflops_per_s"] = flops / cell["median_s"] / 1e9
    return row


def end_to_end(opts: BenchOptions, plan: Plan, models: dict, folder: Path) -> list[dict]:
    """Workload (d): msf-run on the whole stack in a fresh process, normals only.

    First the default command (bundled model, no engine or precision flag: what dispatch picks
    on this CPU), then each export pinned to an engine, so rows say what they measure."""
    from msfnet.runtime.stack import load_stack

    # --lights N: msf-run --max-lights N. Without it, quick runs 8 lights (a smoke test of the
    # path, not a figure) and a full run every light.
    variants, threads = plan.variants, plan.threads
    max_lights = opts.lights or (8 if opts.quick else None)
    stack = load_stack(plan.stack, max_lights=max_lights)
    ort = ["--engine", "onnxruntime"]
    budget = opts.max_memory  # None: msf-run's own default, as a user runs it
    # The default row runs the bundled model as msf-run picks it (fp32, or its int8 twin where
    # dispatch.bundled_precision prefers it: then it differs from the fp32 rows by the
    # quantisation); for other weights (--checkpoint, --random-weights) it runs their staged
    # fp32 export.
    from msfnet.model.checkpoint import default_checkpoint_path

    bundled = (
        not models.get("random_weights")
        and Path(models["checkpoint"]).resolve() == default_checkpoint_path().resolve()
    )
    names: list[tuple[str, Path | None, list[str]]] = [
        ("default", None if bundled else Path(models["fp32_staged"]), []),
        ("ort-fp32", Path(models["fp32"]), ort),
        ("ort-fp32-staged", Path(models["fp32_staged"]), ort),
    ]
    if "ov-bf16" in variants:
        names.append(
            ("ov-bf16", Path(models["fp32"]), ["--engine", "openvino", "--precision", "bf16"])
        )
    if "ort-int8" in variants:
        names += [
            ("ort-int8", Path(models["int8"]), ort),
            ("ort-int8-staged", Path(models["int8_staged"]), ort),
        ]
    runs, outs = [], {}
    for v, onnx, extra in tqdm(names, desc="msf-bench (d)", unit="run", disable=opts.quiet):
        outdir = folder / v
        # The default command carries the target: the median of 3 fresh processes (single runs
        # varied by +-10 % here); one run for the other rows keeps the full mode short.
        repeats = 3 if v == "default" and not opts.quick else 1
        walls = [
            time_msf_run(plan.stack, onnx, outdir, max(threads), budget, max_lights, extra)
            for _ in range(repeats)
        ]
        w = walls[-1]
        normals = np.load(outdir / "normals.npy")
        outs[v] = normals
        prof = w["profile"]
        runs.append(
            {
                "variant": v,
                "threads": max(threads),
                "lights": stack.num_lights,
                "height": stack.shape[0],
                "width": stack.shape[1],
                "walls_s": [x["wall_s"] for x in walls],
                "median_s": float(np.median([x["wall_s"] for x in walls])),
                "peak_rss_mb": max(x["peak_rss_mb"] for x in walls),
                "command": w["command"],
                **_what_ran(prof),
                # msf-run's own inference stage (its profile), median over the runs: the ratio
                # without process start, loading, engine compile and writing
                "inference_s": _median_stage([x["profile"] for x in walls], "inference"),
                "mae_vs_gt_deg": _mae(normals, stack),
            }
        )
    if bundled:
        runs.append(_warm_row(opts, plan, stack, budget, max_lights, runs[0]))
    for run in runs:
        if run["variant"] in outs and run["variant"] != "ort-fp32":
            mean, mx = deviation_deg(outs[run["variant"]], outs["ort-fp32"], stack.mask)
            run.update({"max_deg_vs_fp32": mx, "mean_deg_vs_fp32": mean})
    return runs


def _warm_row(
    opts: BenchOptions,
    plan: Plan,
    stack,
    budget: float | None,
    max_lights: int | None,
    default: dict,
) -> dict:
    """The default path again, in one warm process (workloads.time_warm_model): what a stream
    or a station loop pays per stack once the model is open."""
    repeats = 1 if opts.quick else 3
    warm = time_warm_model(plan.stack, max(plan.threads), budget, max_lights, repeats=repeats)
    prof = warm["profile"]
    return {
        **{k: default[k] for k in ("threads", "lights", "height", "width")},
        "variant": "default-warm",
        "walls_s": warm["walls_s"],
        "median_s": float(np.median(warm["walls_s"])),
        "peak_rss_mb": warm["peak_rss_mb"],
        "command": "Model(threads=...) opened once, then model(stack) per call (no files)",
        **_what_ran(prof),
        "inference_s": _median_stage([prof], "inference"),
        "mae_vs_gt_deg": warm["mae"],
    }


def _what_ran(profile: dict) -> dict:
    """The (d) row's fields taken from a run's profile (engine, graph, tiles, stage times)."""
    keys = ("engine", "precision", "graph", "choice", "tiles", "stages", "inference_gflops_per_s")
    return {k: profile.get(k) for k in keys}


def _median_stage(profiles: list[dict], stage: str) -> float | None:
    secs = [p["stages"][stage]["median_s"] for p in profiles if stage in p.get("stages", {})]
    return float(np.median(secs)) if secs else None


def _mae(normals: np.ndarray, stack) -> float | None:
    if stack.normals_gt is None:
        return None
    return normal_metrics(normals, stack.normals_gt, stack.mask).mae_deg


def _run(opts: BenchOptions) -> int:
    # The models are exported with torch and onnx: find them missing before anything is
    # written or printed.
    import onnx  # noqa: F401
    import torch  # noqa: F401

    plan = plan_run(opts)  # every check before anything is written or printed
    data = load_inputs(opts, plan)
    for note in plan.notes:
        _say(opts, note)
    final = opts.report_dir
    with staged_folder(final, overwrite=opts.overwrite) as work, scratch_folder(final) as scratch:
        result = published(bench(opts, plan, data, work, scratch), work, final)
        files = write_report(result, work)
    if not opts.quiet:
        print(files["table"])
        for f in files["paths"]:
            print(f"wrote {final / Path(f).relative_to(work)}")
    return 0


def published(result: dict, work: Path, final: Path) -> dict:
    """``result`` with every path inside the staging folder ``work`` named where the report
    ends up (``final``): report.json and REPORT.md name the published files."""

    def rebase(value: object) -> object:
        if isinstance(value, str):
            return value.replace(str(work), str(final))
        if isinstance(value, dict):
            return {k: rebase(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return type(value)(rebase(v) for v in value)
        return value

    return {k: rebase(v) for k, v in result.items()}


def _check_crop_shape(model: Path, static: tuple[int, int, int] | None) -> None:
    """--onnx scores fixed crops; a static-shape export cannot take them (msf-run tiles it)."""
    from msfnet.bench.edge import CROP, CROP_LIGHTS

    if static is not None and static != (CROP_LIGHTS, CROP, CROP):
        n, h, w = static
        raise InputError(
            f"static shape: {n} lights at {h} x {w} px; --onnx scores {CROP_LIGHTS} lights "
            f"on {CROP} px crops (export with dynamic shapes, or time it with msf-run)",
            model,
        )


def _check_validation_objects(root: Path) -> None:
    """Each DiLiGenT validation object with its ground truth (it is scored against it)."""
    from msfnet.bench.edge import VALIDATION
    from msfnet.runtime.stack.load import GT_NAMES

    for name, _ in VALIDATION:
        folder = root / "DiLiGenT" / name
        if not folder.is_dir():
            raise InputError("validation object not found (DiLiGenT)", folder)
        if not any((folder / gt).is_file() for gt in GT_NAMES):
            raise InputError(
                f"no ground-truth normals ({', '.join(GT_NAMES[:3])}); --onnx and --ladder "
                "score against them",
                folder,
            )


def _check_stack(stack: Path) -> None:
    """The requirements grid's stack, read once (a few lights) before any cell runs."""
    from msfnet.runtime.stack.load import load_stack

    load_stack(stack, max_lights=MIN_LIGHTS)


def _run_edge(opts: BenchOptions) -> int:
    """--onnx / --ladder / --requirements: torch-free, inputs checked first, one report folder
    (REPORT.md, report.json) written as a whole."""
    from msfnet.bench import edge, ladder
    from msfnet.runtime.api import bundled_model_path, default_model_path
    from msfnet.runtime.engines import read_model_file

    model = opts.onnx or default_model_path()
    info = read_model_file(model)  # an unreadable or foreign file is one line before any work
    scoring = opts.ladder or not opts.requirements  # --onnx and --ladder score on DiLiGenT
    if opts.onnx is not None and not (opts.ladder or opts.requirements):
        _check_crop_shape(model, info.static_shape)
    root = data_root(opts.data) if scoring or opts.stack is None else None
    if scoring:
        assert root is not None
        _check_validation_objects(root)
    stack = opts.stack if opts.stack is not None else cast(Path, root) / STACK_IN_DATA
    if opts.requirements:
        _check_stack(stack)  # the grid's every cell would fail on it
    check_output(
        opts.report_dir,
        [model, *([root] if root is not None else []), stack],
        overwrite=opts.overwrite,
        folder=True,
        command=PROG,
    )
    threads = max(opts.threads)

    def progress(line: str) -> None:  # fresh-process cells take minutes on a slow box
        _say(opts, f"  {line}")

    bundled = bundled_model_path().name  # what Model() opens here with nothing named
    result: dict = {
        "date": time.strftime("%Y-%m-%d %H:%M %Z"),
        "machine": machine_description(),
        # without --onnx the ladder and the requirements run what msf-run opens here
        "model": str(model) if opts.onnx else f"bundled ({bundled})",
        "threads": threads,
    }
    sections = []
    final = opts.report_dir
    with staged_folder(final, overwrite=opts.overwrite) as work, scratch_folder(final) as scratch:
        if opts.onnx is not None and not (opts.ladder or opts.requirements):
            _say(opts, f"measuring {model.name} on every engine and device here ...")
            assert root is not None
            rows = edge.onnx_rows(model, root, threads, scratch, say=progress, info=info)
            result["onnx"] = [edge.asdict(r) for r in rows]
            sections.append(("Engines and devices", edge.edge_table(rows)))
        if opts.ladder:
            _say(opts, "measuring the speed ladder (each rung in a fresh process) ...")
            # without --onnx: the bundled model as msf-run picks it (fp32 or its int8 twin)
            assert root is not None
            rungs = ladder.ladder_rows(
                opts.onnx, root, threads=threads, scratch=scratch, say=progress
            )
            result["ladder"] = [ladder.asdict(r) for r in rungs]
            sections.append(("Speed ladder (--speed)", ladder.ladder_table(rungs)))
        if opts.requirements:
            _say(opts, "measuring the requirements grid (each cell in a fresh process) ...")
            given = info if opts.onnx is not None else None  # None: the bundled model's
            reqs = edge.requirement_rows(
                opts.onnx, stack, threads, scratch, quick=opts.quick, say=progress, info=given
            )
            result["requirements"] = [edge.asdict(r) for r in reqs]
            sections.append(("Requirements", edge.requirements_table(reqs)))
        m = result["machine"]
        head = (
            f"# msf-bench, {result['date']}\n\nCPU: {m['cpu']} ({m['cores']} cores); "
            f"{threads} threads; onnxruntime {m['onnxruntime']}, openvino {m['openvino']}; "
            f"model {model.name if opts.onnx else 'bundled, ' + bundled}\n"
        )
        text = head + "".join(f"\n## {t}\n\n{body}\n" for t, body in sections)
        write_text(work / "REPORT.md", text)
        write_json(work / "report.json", result)
    if not opts.quiet:
        print("\n\n".join(body for _, body in sections))
        print(f"wrote {final / 'REPORT.md'}")
    return 0


def _body(opts: BenchOptions, argv: list[str]) -> int:
    if opts.cpu_proxy is not None and proxy_class() != opts.cpu_proxy:
        from msfnet.bench.cpu_proxy import proxy_env

        env = proxy_env(opts.cpu_proxy)  # where no proxy can run: one line, before anything
        print(f"{PROG}: running as {opts.cpu_proxy} (cpuid proxy)", file=sys.stderr, flush=True)
        sys.stdout.flush()
        os.execvpe(sys.executable, [sys.executable, "-m", "msfnet.bench.cli", *argv], env)
    with row_time_limit(opts.timeout):
        if opts.edge_mode:
            _refuse_torch_options(opts)
            return _run_edge(opts)
        return _run(opts)


def _refuse_torch_options(opts: BenchOptions) -> None:
    """--onnx / --ladder / --requirements measure ONNX files torch-free: the torch benchmark's
    options would be ignored in silence (a report on X that never names the --checkpoint Y)."""
    given = [
        flag
        for flag, value in (
            ("--checkpoint", opts.checkpoint is not None),
            ("--random-weights", opts.random_weights),
            ("--calib", opts.calib is not None),
            ("--variants", opts.variants != ALL_VARIANTS),
            ("--no-e2e", opts.no_e2e),
            ("--lights", opts.lights is not None),
            ("--max-memory", opts.max_memory is not None),
        )
        if value
    ]
    mode = "--onnx" if opts.onnx is not None else "--ladder" if opts.ladder else "--requirements"
    if given:
        raise InputError(
            f"{', '.join(given)}: options of the torch benchmark, not used with {mode} "
            "(it measures ONNX files torch-free); drop them"
        )
    # what only the requirements grid reads, given to a mode that would drop it in silence
    grid = [f for f, v in (("--stack", opts.stack is not None), ("--quick", opts.quick)) if v]
    unused = [] if opts.requirements else grid
    if unused:
        raise InputError(
            f"{', '.join(unused)}: used by --requirements only, not by {mode} (it scores the "
            "DiLiGenT validation objects at fixed sizes); drop them"
        )
    if len(set(opts.threads)) > 1 and opts.threads != DEFAULT_THREADS:
        raise InputError(
            f"--threads {','.join(map(str, opts.threads))}: {mode} measures one thread count; "
            "give one (or run once per count)"
        )


def main(argv: list[str] | None = None) -> int:
    given = list(sys.argv[1:] if argv is None else argv)
    return command_main(COMMAND, build_parser(), lambda args: _body(options(args), given), argv)


def options(args: argparse.Namespace) -> BenchOptions:
    """The run's options, from msf-bench's parsed flags (-q among them)."""
    return options_from_args(BenchOptions, args, overrides={"quiet": args.quiet})


__all__ = [
    "Inputs",
    "Plan",
    "Workload",
    "build_parser",
    "inference_flops",
    "load_inputs",
    "main",
    "per_light_whole_image",
    "plan_run",
    "published",
    "schedule",
    "thread_counts",
]

if __name__ == "__main__":
    sys.exit(main())
