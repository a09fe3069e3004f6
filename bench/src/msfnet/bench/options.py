"""What one msf-bench run is asked to do: one typed options object, built once from the flags.

Each user-set field of :class:`BenchOptions` declares its command-line spelling once
(:func:`msfnet.common.vocabulary.flag`); msf-bench's parser is generated from the fields
(:func:`msfnet.common.cli.add_flags`) and its body reads the options, never the parsed
arguments. Category ``"edge"``: the torch-free modes, a help group of their own.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from msfnet.bench.data import ENV_VAR
from msfnet.bench.workloads import VARIANTS
from msfnet.common.cli import int_range, path_arg, positive_float, thread_count
from msfnet.common.cpu import PROXY_CLASSES
from msfnet.common.vocabulary import flag, options_type
from msfnet.runtime.stack.types import MIN_LIGHTS

# relative to the data root (--data, $MSFNET_DATA, ./shared/data or ../shared/data)
STACK_IN_DATA = Path("DiLiGenT") / "ballPNG"
CALIB_IN_DATA = [STACK_IN_DATA, *(Path("psmImages") / o for o in ("cat", "owl", "horse"))]

DEFAULT_THREADS = (2, 1)
ALL_VARIANTS = ",".join(VARIANTS)  # --variants' default

# --lights N: the per-light loop is timed on (d)'s whole N-light image up to this many lights
# (a full DiLiGenT object: 5.4 s a light and run on the AMX machine, 2 threads, quiet); above it
# its time is extrapolated from (b), as without --lights (96 lights would take 9 min a run).
PER_LIGHT_FULL_MAX_LIGHTS = 16
MAX_BENCH_LIGHTS = 10_000  # only to refuse absurd values at parse time

EDGE = "edge"  # the category of the torch-free modes' flags


def thread_counts(text: str) -> list[int]:
    """``2,1`` -> [2, 1]; each in 1..MAX_THREADS, refused here at parse time rather than when
    the matmul peaks start (``--threads 100000`` once ran for 15+ minutes before failing)."""
    return [thread_count(t) for t in text.split(",") if t.strip()] or [thread_count(text)]


@options_type
@dataclass(frozen=True)
class BenchOptions:
    """Every setting of one msf-bench run, in the order its help lists them. ``stack`` and
    ``calib`` are what was given (None: from the data root, see cli.resolve_paths)."""

    checkpoint: Path | None = flag(
        None,
        "MSF-Net checkpoint (.pth); default: the bundled trained model "
        "(msfnet/model/weights/msfnet_default.pth)",
        type=path_arg,
    )
    random_weights: bool = flag(
        False,
        "seeded random weights instead of a checkpoint (accuracy figures then "
        "only measure numerical deviation; int8 errors of a trained model differ)",
        action="store_true",
    )
    data: Path | None = flag(
        None,
        f"data root holding DiLiGenT/ballPNG and psmImages/ (default: "
        f"${ENV_VAR}, else ./shared/data or ../shared/data from the current folder)",
        type=path_arg,
    )
    stack: Path | None = flag(
        None,
        f"real stack for the inputs and workload (d) (default DATA/{STACK_IN_DATA.as_posix()})",
        type=path_arg,
    )
    calib: tuple[Path, ...] | None = flag(
        None,
        "stacks to calibrate int8 on (default: the stack + DATA/psmImages cat/"
        "owl/horse when present)",
        type=path_arg,
        nargs="+",
    )
    report_dir: Path = flag(
        Path("msf-bench-out"),
        "report folder, written as a whole: REPORT.md, report.json, "
        "latency.png, models/, e2e/ (default ./msf-bench-out)",
        name="-o",
        aliases=("--output", "--report-dir"),
        type=path_arg,
    )
    # what the full benchmark measures: variants, threads, CPU class, workload (d)
    quick: bool = flag(
        False,
        "smoke test: tiny workloads, one timed run each (about 4-8 minutes on 2 cores: "
        "the models are exported and int8-calibrated first)",
        action="store_true",
    )
    variants: str = flag(
        ALL_VARIANTS, f"comma list from {', '.join(VARIANTS)} (default: all available)"
    )
    threads: tuple[int, ...] = flag(
        DEFAULT_THREADS,
        "thread counts, comma-separated (default 2,1; --onnx, --ladder and "
        "--requirements take one, and measure the largest of the default)",
        type=thread_counts,
    )
    cpu_proxy: str | None = flag(
        None,
        "run as if on a smaller x86 CPU class: cpuid masked for every library of the "
        "run (numpy, ONNX Runtime, OpenVINO, torch) through Linux's CPUID faulting and a small "
        "library built with the system C compiler (msfnet.bench.cpu_proxy). A proxy: caches, "
        "clocks and cores stay this machine's, and the report names the class",
        choices=tuple(sorted(PROXY_CLASSES)),
    )
    max_memory: float | None = flag(
        None,
        "msf-run --max-memory for workload (d), MB (default: msf-run's own)",
        type=positive_float,
    )
    no_e2e: bool = flag(False, "skip workload (d)", action="store_true")
    lights: int | None = flag(
        None,
        "workload (d) on N evenly spaced lights of the stack (msf-run --max-lights N), "
        "and the published per-light forward timed on that same whole N-light image in its "
        f"own process (up to {PER_LIGHT_FULL_MAX_LIGHTS} lights; above, extrapolated from (b)); "
        "the (d) target is then >= 60x on CPUs with native bf16, >= 30x elsewhere "
        "(default: every light, per-light time extrapolated from (b))",
        type=int_range(MIN_LIGHTS, MAX_BENCH_LIGHTS),
        metavar="N",
    )
    # the torch-free modes: a given ONNX file, the speed ladder, the requirements grid
    onnx: Path | None = flag(
        None,
        "benchmark this msfnet ONNX file on every engine, precision and device this "
        "machine offers: format | status | size | MAE | ms | peak MB (no torch needed); with "
        "--ladder / --requirements: the model those measure (default: the bundled model)",
        type=path_arg,
        metavar="MODEL",
        category=EDGE,
    )
    ladder: bool = flag(
        False,
        "the speed ladder (msf-run --speed): time, peak memory, MAE on the DiLiGenT "
        "validation objects at 12 lights and detail ratio, per rung",
        action="store_true",
        category=EDGE,
    )
    requirements: bool = flag(
        False,
        "time and peak memory by image size x light count x engine (default engine and "
        "ONNX Runtime fp32), whole stacks through the runtime; with --quick a small grid",
        action="store_true",
        category=EDGE,
    )
    timeout: float | None = flag(
        None,
        "stop a row, cell or speed rung still running after S seconds and report it as "
        "failed (a model that never ends; default: no limit)",
        type=positive_float,
        metavar="S",
    )
    overwrite: bool = flag(
        False,
        "replace an earlier report folder (only one msfnet wrote: a folder "
        "holding other files is refused, never deleted)",
        action="store_true",
    )
    quiet: bool = False  # msf-bench -q (a flag every command has): errors only

    @property
    def edge_mode(self) -> bool:
        """--onnx / --ladder / --requirements: the torch-free modes."""
        return self.onnx is not None or self.ladder or self.requirements


def flag_categories() -> tuple[tuple[str, str], ...]:
    """(field, category) of each flagged field of :class:`BenchOptions`, in declaration order:
    the order of msf-bench's usage line, whatever help group each flag is listed in."""
    return tuple(
        (f.name, f.metadata["flag"].category)
        for f in dataclasses.fields(BenchOptions)
        if "flag" in f.metadata
    )


__all__ = [
    "ALL_VARIANTS",
    "CALIB_IN_DATA",
    "DEFAULT_THREADS",
    "EDGE",
    "MAX_BENCH_LIGHTS",
    "PER_LIGHT_FULL_MAX_LIGHTS",
    "STACK_IN_DATA",
    "BenchOptions",
    "flag_categories",
    "thread_counts",
]
