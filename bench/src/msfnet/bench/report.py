"""msf-bench output: the printed table, report.json, REPORT.md with targets, and latency.png."""

from __future__ import annotations

from pathlib import Path

from msfnet.bench.workloads import VARIANTS
from msfnet.common.files import write_atomic, write_json, write_text
from msfnet.common.vocabulary import opt

FULL_IMAGE_NOTE = (
    "per-light loop on (d) extrapolated linearly in lights x pixels from its "
    "measured (b) run (same threads), untiled full image"
)


def _peak(result: dict, dtype: str, threads: int, engine: str = "torch") -> float | None:
    """A measured matmul peak; entries without an engine (older reports) are torch's."""
    for p in result["peaks"]:
        if (p.get("engine", "torch"), p["dtype"], p["threads"]) == (engine, dtype, threads):
            return p["gflops"]
    return None


def fp32_peak(result: dict, threads: int) -> tuple[float | None, str]:
    """The machine's fp32 reference: ONNX Runtime's own fp32 GEMM, else torch's (old reports)."""
    ort = _peak(result, "fp32", threads, "onnxruntime")
    return (ort, "onnxruntime") if ort else (_peak(result, "fp32", threads), "torch")


def _find(rows: list[dict], wl: str, variant: str, threads: int) -> dict | None:
    key = (wl, variant, threads)
    return next(
        (r for r in rows if (r["workload"], r["variant"], r["threads"]) == key and "median_s" in r),
        None,
    )


def per_light_estimate(
    rows: list[dict], lights: int, pixels: int, threads: int
) -> tuple[float, bool] | None:
    """Per-light loop seconds at (lights, pixels): measured if that cell exists, else scaled
    from the largest measured per-light cell (linear in lights x pixels). (seconds, measured)."""
    cands = [
        r
        for r in rows
        if r["variant"] == "per-light" and r["threads"] == threads and "median_s" in r
    ]
    for r in cands:
        if r["lights"] == lights and r["pixels"] == pixels:
            return r["median_s"], True
    # scaled from the crops only, as the report says: (d)'s whole-image row (--lights) serves
    # its own size, never the crops' or another light count's
    cands = [r for r in cands if r["workload"] != "d"]
    if not cands:
        return None
    base = max(cands, key=lambda r: r["lights"] * r["pixels"])
    return base["median_s"] * lights * pixels / (base["lights"] * base["pixels"]), False


def add_ratios(result: dict) -> None:
    rows = result["rows"]
    for r in rows:
        if "median_s" not in r:
            continue
        peak, _ = fp32_peak(result, r["threads"])
        r["fraction_fp32_peak"] = r["gflops_per_s"] / peak if peak else None
        # the variant's own precision on its own engine's kernels (int8 rows: GFLOP/s of the
        # analytic count over int8 GOP/s, a lower bound since part of the int8 model is fp32)
        row = VARIANTS.get(r["variant"])
        engine, dtype = (row.engine, row.precision) if row else ("torch", "fp32")
        own = _peak(result, dtype, r["threads"], engine)
        r["own_peak"] = f"{engine} {dtype}"
        r["fraction_own_peak"] = r["gflops_per_s"] / own if own else None
        for key, v in (("x_vs_ort_fp32", "ort-fp32"), ("x_vs_torch", "torch-fp32")):
            ref = _find(rows, r["workload"], v, r["threads"])
            r[key] = ref["median_s"] / r["median_s"] if ref else None
        est = per_light_estimate(rows, r["lights"], r["pixels"], r["threads"])
        r["x_vs_per_light"] = est[0] / r["median_s"] if est else None
        r["per_light_measured"] = bool(est and est[1])


def _fmt(v, spec: str, none: str = "-") -> str:
    return none if v is None else format(v, spec)


def table(result: dict) -> str:
    head = (
        "| workload | variant | thr | median s | p90 s | peak RSS MB | GFLOP/s | % fp32 peak "
        "| % own peak | x ORT fp32 | x torch | x per-light | max deg | mean deg |"
    )
    lines = [head, "|" + "---|" * 14]
    for r in result["rows"]:
        if "median_s" not in r:
            lines.append(
                f"| {r['label']} | {r['variant']} | {r['threads']} | error: "
                f"{r.get('error', '')[:80]} |" + " |" * 10
            )
            continue
        pl = _fmt(r["x_vs_per_light"], ".2f")
        if r["x_vs_per_light"] is not None and not r["per_light_measured"]:
            pl = "~" + pl
        frac = r["fraction_fp32_peak"]
        own = r.get("fraction_own_peak")
        lines.append(
            f"| {r['label']} | {r['variant']} | {r['threads']} | {r['median_s']:.3f} | "
            f"{r['p90_s']:.3f} | {_fmt(r.get('peak_rss_mb'), '.0f')} | {r['gflops_per_s']:.1f} | "
            f"{_fmt(None if frac is None else 100 * frac, '.0f')} | "
            f"{_fmt(None if own is None else 100 * own, '.0f')} | "
            f"{_fmt(r['x_vs_ort_fp32'], '.2f')} | {_fmt(r['x_vs_torch'], '.2f')} | {pl} | "
            f"{_fmt(r.get('max_deg'), '.3f')} | {_fmt(r.get('mean_deg'), '.3f')} |"
        )
    return "\n".join(lines)


def _x_per_light(r: dict, key: str = "x_vs_per_light") -> str:
    """A (d) ratio to the per-light loop, ``~`` in front where that loop's time is extrapolated."""
    x = r.get(key)
    return _fmt(x, ".1f") if x is None or r.get("per_light_measured") else "~" + format(x, ".1f")


def e2e_table(result: dict) -> str:
    runs = result.get("e2e") or []
    if not runs:
        return "(workload (d) not run)"
    lines = [
        "| row | engine precision graph | thr | lights | image | tiles run/skipped | "
        "median wall s (runs) | peak RSS MiB | inference GFLOP/s | MAE vs GT deg | "
        "vs ORT fp32 max/mean deg | x per-light | inference s | x per-light, inference only |",
        "|" + "---|" * 14,
    ]
    for r in runs:
        tiles = r.get("tiles") or {}
        dev = "-"
        if "mean_deg_vs_fp32" in r:
            dev = f"{r['max_deg_vs_fp32']:.2f} / {r['mean_deg_vs_fp32']:.3f}"
        path = " ".join(str(r.get(k) or "?") for k in ("engine", "precision", "graph"))
        lines.append(
            f"| {r['variant']} | {path} | {r['threads']} | {r['lights']} | "
            f"{r['width']}x{r['height']} | "
            f"{tiles.get('run', '-')}/{tiles.get('skipped', '-')} | {r['median_s']:.1f} "
            f"({len(r.get('walls_s') or [1])}) | {_fmt(r.get('peak_rss_mb'), '.0f')} | "
            f"{_fmt(r.get('inference_gflops_per_s'), '.1f')} | "
            f"{_fmt(r.get('mae_vs_gt_deg'), '.2f')} | {dev} | {_x_per_light(r)} | "
            f"{_fmt(r.get('inference_s'), '.2f')} | "
            f"{_x_per_light(r, 'x_vs_per_light_inference')} |"
        )
    default = next((r for r in runs if r["variant"] == "default"), None)
    if default and default.get("choice"):
        lines += [
            "",
            f"`default` is `{default['command']}`; msf-run's engine choice: {default['choice']}",
        ]
    note = per_light_note(result, runs[0])
    return "\n".join([*lines, "", note] if note else lines)


def per_light_note(result: dict, run: dict) -> str | None:
    """Where the (d) rows' per-light time comes from: measured on (d)'s own input (--lights)
    or extrapolated from (b); None where there is none."""
    row = _find(result["rows"], "d", "per-light", run["threads"])
    if run.get("per_light_measured") and row:
        times = ", ".join(f"{t:.1f}" for t in row.get("times_s") or [])
        return (
            f"per-light loop measured on the same whole image and {row['lights']} lights, "
            f"untiled, in its own process: {row['median_s']:.1f} s (median of {times}), "
            f"peak RSS {_fmt(row.get('peak_rss_mb'), '.0f')} MiB"
        )
    est = run.get("per_light_estimate_s")
    return None if est is None else f"per-light loop {est:.0f} s: {FULL_IMAGE_NOTE} (`~`)"


def add_e2e_ratios(result: dict) -> None:
    for r in result.get("e2e") or []:
        est = per_light_estimate(
            result["rows"], r["lights"], r["height"] * r["width"], r["threads"]
        )
        r["per_light_estimate_s"] = est[0] if est else None
        r["per_light_measured"] = bool(est and est[1])
        r["x_vs_per_light"] = est[0] / r["median_s"] if est else None
        infer = r.get("inference_s")
        r["x_vs_per_light_inference"] = est[0] / infer if est and infer else None


# (engine, precision, graph) of a run -> the (a)-(c) variant that times the same path
PATH_VARIANT = {
    (v.engine, v.precision, "staged" if v.model.endswith("_staged") else "monolithic"): name
    for name, v in VARIANTS.items()
    if v.through_runtime
}
# the full-stack targets (docs/benchmark.md): >= 60x the per-light loop, <= 1.5 GiB
FULL_STACK_X, FULL_STACK_MIB = 60.0, 1536.0
# msf-bench --lights N (issue #25: 8 lights, the default export and msf-run against the
# published forward in the same run): >= 60x on CPUs with native bf16, >= 30x elsewhere
FEW_LIGHTS_X_BF16, FEW_LIGHTS_X = 60.0, 30.0


def targets(result: dict) -> list[str]:
    """The speed targets (docs/benchmark.md), each with its measured figure and met / not met."""
    rows, out = result["rows"], []
    t = max(r["threads"] for r in rows) if rows else 2
    runs = {r["variant"]: r for r in result.get("e2e") or []}
    default = runs.get("default")
    feats = result.get("machine", {}).get("cpu_features") or {}
    bf16_cpu = bool(feats.get("avx512_bf16") or feats.get("amx_bf16"))
    if default and result.get("lights"):
        out.append(few_lights_target(result, default, bf16_cpu))
    elif default:
        x, rss = default.get("x_vs_per_light"), default.get("peak_rss_mb")
        ok = x is not None and x >= FULL_STACK_X and rss is not None and rss <= FULL_STACK_MIB
        walls = ", ".join(f"{w:.1f}" for w in default.get("walls_s") or [])
        out.append(
            f"- (d) the default command (`{default['command']}`): median "
            f"{default['median_s']:.1f} s ({walls}), {_fmt(x, '.1f')}x the per-light loop "
            f"({_fmt(default.get('per_light_estimate_s'), '.0f')} s, {FULL_IMAGE_NOTE}); "
            f"peak RSS {_fmt(rss, '.0f')} MiB: target >= {FULL_STACK_X:.0f}x and <= "
            f"{FULL_STACK_MIB:.0f} MiB **{'met' if ok else 'not met'}**."
        )
    goal = 3.0 if bf16_cpu else 1.5
    key = default and (default.get("engine"), default.get("precision"), default.get("graph"))
    variant = PATH_VARIANT.get(key) if key else None
    r = _find(rows, "b", variant, t) if variant else None
    if key and all(key) and not r:  # said, not dropped
        engine, precision, graph = key
        why = (
            "no (a)-(c) variant runs it (its figures: (d) above)"
            if variant is None  # e.g. OpenVINO fp32 staged
            else f"no {variant} row at {t} threads in this run"
        )
        out.append(
            f"- the default path on (b) ({engine} {precision} {graph}, what msf-run picks "
            f"here): not measured, {why}."
        )
    if r:
        x, mean = r.get("x_vs_ort_fp32") or 0.0, r.get("mean_deg")
        ok = x >= goal and mean is not None and mean <= 0.5
        out.append(
            f"- the default path on (b) ({variant}, what msf-run picks here), {t} "
            f"threads: {x:.2f}x ORT fp32, mean deviation {_fmt(mean, '.3f')} deg: target "
            f">= {goal}x within 0.5 deg on a {'bf16' if bf16_cpu else 'non-bf16'} CPU "
            f"**{'met' if ok else 'not met'}**."
        )
    best = min(
        (
            r
            for r in rows
            if r["workload"] == "b"
            and r["threads"] == t
            and r.get("fraction_own_peak")
            and r["variant"] in VARIANTS
        ),
        key=lambda r: r["median_s"],
        default=None,
    )
    if best:
        f = best["fraction_own_peak"]
        out.append(
            f"- fastest variant on (b), {best['variant']}: {100 * f:.0f} % of the "
            f"same-run {best['own_peak']} matmul peak: target >= 80 % "
            f"**{'met' if f >= 0.8 else 'not met'}**."
        )
    return out


def few_lights_target(result: dict, default: dict, bf16_cpu: bool) -> str:
    """The (d) target line of a --lights run: the default command on N lights against the
    per-light loop (measured on the same input where the run could), end to end and counting
    msf-run's inference stage only."""
    goal = FEW_LIGHTS_X_BF16 if bf16_cpu else FEW_LIGHTS_X
    x = default.get("x_vs_per_light")
    walls = ", ".join(f"{w:.1f}" for w in default.get("walls_s") or [])
    where = f"whole {default['lights']}-light image"
    measured = default.get("per_light_measured")
    how = f"measured on the same {where}" if measured else f"extrapolated from (b) to the {where}"
    return (
        f"- (d) the default command on {default['lights']} lights (`{default['command']}`): "
        f"median {default['median_s']:.1f} s ({walls}), {_fmt(x, '.1f')}x the per-light loop "
        f"({_fmt(default.get('per_light_estimate_s'), '.1f')} s, {how}); msf-run's inference "
        f"stage alone {_fmt(default.get('inference_s'), '.2f')} s, "
        f"{_fmt(default.get('x_vs_per_light_inference'), '.1f')}x; peak RSS "
        f"{_fmt(default.get('peak_rss_mb'), '.0f')} MiB: target >= {goal:.0f}x on a "
        f"{'CPU with native bf16' if bf16_cpu else 'CPU without native bf16'} "
        f"**{'met' if x is not None and x >= goal else 'not met'}**."
    )


def plot(result: dict, path: Path) -> bool:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    rows = [r for r in result["rows"] if "median_s" in r]
    t = max((r["threads"] for r in rows), default=2)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for v in sorted({r["variant"] for r in rows}):
        pts = sorted(
            (r["lights"], r["pixels"], r["median_s"])
            for r in rows
            if r["variant"] == v and r["threads"] == t
        )
        if not pts:
            continue
        axes[0].plot([p[0] for p in pts], [p[2] for p in pts], "o-", label=v)
        axes[1].plot([p[1] for p in pts], [p[2] for p in pts], "o-", label=v)
    for r in result.get("e2e") or []:
        px = (r.get("tiles") or {}).get("pixels_computed", r["height"] * r["width"])
        axes[0].plot([r["lights"]], [r["median_s"]], "s", label=f"(d) {r['variant']} e2e")
        axes[1].plot([px], [r["median_s"]], "s", label=f"(d) {r['variant']} e2e")
    axes[0].set_xlabel("lights")
    axes[1].set_xlabel("pixels computed")
    for ax in axes:
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_ylabel(f"median latency, s ({t} threads)")
        ax.grid(True, which="both", alpha=0.3)
    axes[1].legend(fontsize=7)
    fig.suptitle("MSF-Net latency (workloads (a)-(c) crops of ballPNG; (d) full stack)")
    fig.tight_layout()
    write_atomic(path, lambda tmp: fig.savefig(tmp, format="png", dpi=110), overwrite=False)
    plt.close(fig)
    return True


def _machine_lines(result: dict) -> list[str]:
    """The report's header about the machine: CPU, features, libraries, matmul peaks."""
    m = result["machine"]
    peaks = ", ".join(
        f"{p.get('engine', 'torch')} {p['dtype']} {p['threads']} thr {p['gflops']:.1f}"
        for p in result["peaks"]
    )
    feats = m.get("cpu_features") or {}
    shown = ["avx2", "avx512f", "avx512_vnni", "avx_vnni", "avx512_bf16", "amx_bf16", "amx_int8"]
    cpu_line = ", ".join(f"{k} {'yes' if feats[k] else 'no'}" for k in shown if k in feats)
    return [
        f"- machine: {m['cpu']}, {m['cores']} cores, ISA {' '.join(m['isa_flags'])}; "
        f"{m['platform']}; Python {m['python']}, onnxruntime {m['onnxruntime']}",
        *(
            [f"- CPU features (msfnet.common.cpu, via {feats.get('source')}): {cpu_line}"]
            if feats
            else []
        ),
        *([f"- openvino {m['openvino']}"] if m.get("openvino") else []),
        *(
            [
                "- Python's bytecode cache is off here (PYTHONDONTWRITEBYTECODE is set and "
                "msfnet's modules have no up-to-date cached bytecode): every "
                "fresh process compiles msfnet's modules again, which a default Python does "
                "once; the fresh-process (msf-run) times include it"
            ]
            if m.get("python_bytecode_cache") is False
            else []
        ),
        f"- matmul peaks measured in this run, each engine's own kernels (GFLOP/s; int8: "
        f"GOP/s; the fastest call of two measurements, before and after the cells): {peaks}",
    ]


def markdown(result: dict, has_plot: bool) -> str:
    models = result["models"]
    weights = (
        "seeded random weights (no trained checkpoint given): the deviation columns "
        "measure numerics only"
        if models.get("random_weights")
        else f"checkpoint {models['checkpoint']}"
    )
    lines = [
        "# msf-bench report",
        "",
        f"- date: {result['date']}; mode: {'quick' if result['quick'] else 'full'}; "
        f"elapsed {result['elapsed_s'] / 60:.1f} min",
        *_machine_lines(result),
        *[
            f"- dispatch on this machine, {k} model: {v}"
            for k, v in (result.get("dispatch") or {}).items()
        ],
        f"- weights: {weights}",
        "- inputs: crops of the real ballPNG stack centred on the ball, evenly spaced lights; "
        "deviation = angle to PyTorch fp32 (lights folded) over mask pixels",
        "- GFLOP/s from the analytic count (runtime/infer/flops.py, 2 FLOP per MAC); '% fp32 peak' "
        "divides by ONNX Runtime's fp32 matmul peak at the same thread count, for every "
        "variant; '% own peak' by the peak of the variant's own engine and precision (ORT int8 "
        "MatMulInteger for int8, OpenVINO bf16 for bf16, torch fp32 for the PyTorch rows)",
        "- the machine is shared and noisy: compare ratios within this run, not across runs",
        "- `~` marks a per-light ratio extrapolated from the measured (b) per-light run "
        "(linear in lights x pixels)",
        "",
        *[f"- note: {n}" for n in result.get("notes", [])],
        *(
            [
                "- note: a row above 100 % of its own peak ran faster than its engine's MatMul "
                "kernel does at that precision (convolution kernels can beat a plain "
                "f32-in/f32-out MatMul, "
                "e.g. OpenVINO bf16's): the peak is a reference, not a ceiling"
            ]
            if any((r.get("fraction_own_peak") or 0) > 1 for r in result["rows"])
            else []
        ),
        "",
        "## Targets",
        "",
        *targets(result),
        "",
        "## Workloads (a)-(c)"
        + (
            f", and the per-light loop on (d)'s input ({opt('lights')})"
            if any(r["workload"] == "d" for r in result["rows"])
            else ""
        ),
        "",
        table(result),
        "",
        "## Workload (d): full stack end to end through msf-run (fresh process: load -> "
        "normals on disk)",
        "",
        e2e_table(result),
        "",
    ]
    if has_plot:
        lines += ["![latency](latency.png)", ""]
    lines += ["## Variants", ""] + [f"- `{k}`: {v}" for k, v in result["variants"].items()]
    return "\n".join(lines) + "\n"


def write_report(result: dict, folder: Path) -> dict:
    """REPORT.md, report.json and latency.png in ``folder`` (msf-bench: the report's staging
    folder, published as a whole). Never replaces a file: InputError if one exists."""
    add_ratios(result)
    add_e2e_ratios(result)
    has_plot = plot(result, folder / "latency.png")
    md = markdown(result, has_plot)
    write_json(folder / "report.json", result, overwrite=False)
    write_text(folder / "REPORT.md", md, overwrite=False)
    paths = [folder / "REPORT.md", folder / "report.json"]
    if has_plot:
        paths.append(folder / "latency.png")
    return {"table": table(result) + "\n\n" + e2e_table(result), "paths": paths}
