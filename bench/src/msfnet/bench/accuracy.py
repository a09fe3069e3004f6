"""Accuracy of every engine / precision path against ONNX Runtime fp32, on real ball crops.

This is the measurement behind dispatch.py's defaults (a precision is a default only within
0.5 deg mean of fp32 on real data). Run it again after changing a model or an engine:

    python -m msfnet.bench.accuracy [--data DIR] [--models DIR] [--lights 32,96] [--size 128]

``--models`` holds exports of the bundled checkpoint: fp32.onnx (``msf-export --plain``: the
plain graph, also the reference), fp32_staged.onnx (``msf-export``), int8.onnx (``--plain
--int8``), int8_staged.onnx (``--int8``). Without fp32.onnx the bundled model is the reference
only if it is a plain graph (the bundled one is staged); paths whose file is missing are left
out.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from msfnet.bench.data import data_root
from msfnet.bench.worker import timed_runs
from msfnet.bench.workloads import Workload, make_input
from msfnet.common.cli import command_main, make_parser, path_arg, positive_int, thread_count
from msfnet.common.cpu import CpuInfo, detect_cpu
from msfnet.common.errors import InputError
from msfnet.runtime.engines import installed_engines
from msfnet.runtime.engines.dispatch import open_engine
from msfnet.runtime.evaluate.metrics import deviation_deg


@dataclass(frozen=True)
class EnginePath:
    """One engine / precision / model combination."""

    engine: str
    precision: str
    model: str  # key: fp32, fp32_staged, int8, int8_staged

    @property
    def label(self) -> str:
        staged = " staged" if self.model.endswith("staged") else ""
        return f"{self.engine} {self.precision}{staged}"


PATHS = (
    EnginePath("onnxruntime", "fp32", "fp32_staged"),
    EnginePath("onnxruntime", "int8", "int8"),
    EnginePath("onnxruntime", "int8", "int8_staged"),
    EnginePath("openvino", "fp32", "fp32"),
    EnginePath("openvino", "bf16", "fp32"),
    EnginePath("openvino", "bf16", "fp32_staged"),
    EnginePath("openvino", "int8", "int8"),
    EnginePath("openvino", "int8", "int8_staged"),
)


def _timed(
    engine, images: np.ndarray, lights: np.ndarray, repeats: int
) -> tuple[np.ndarray, float]:
    out = engine.run(images, lights)  # warm-up (arena growth, lazy compilation)
    times, last = timed_runs(lambda: engine.run(images, lights), repeats)
    return out if last is None else last, statistics.median(times) if times else float("nan")


def unsupported(path: EnginePath, model: Path, cpu: CpuInfo) -> str | None:
    """Why ``cpu`` cannot run ``path`` as labelled (None if it can): bf16 without native bf16
    (OpenVINO would compute fp32 and refuses), full-range int8 weights in ONNX Runtime without
    VNNI (saturated: wrong numbers, refused by the engine)."""
    if path.precision == "bf16" and not cpu.has_bf16:
        return "no native bf16 on this CPU"
    if path.engine == "onnxruntime" and path.precision == "int8" and not cpu.int8_full_range:
        from msfnet.runtime.engines.base import read_model_file
        from msfnet.runtime.engines.onnxruntime import quantised_full_range

        if quantised_full_range(read_model_file(model)):
            return "full-range int8 weights saturate in ONNX Runtime without VNNI"
    return None


def _to_stderr(line: str) -> None:
    print(line, file=sys.stderr)


def measure(
    stack_dir: Path,
    models: dict[str, Path],
    lights: tuple[int, ...] = (32, 96),
    size: int = 128,
    threads: int = 2,
    repeats: int = 1,
    paths: tuple[EnginePath, ...] = PATHS,
    log: Callable[[str], object] | None = None,
    cpu: CpuInfo | None = None,
) -> list[dict[str, object]]:
    """Rows of (lights, path, mean/max deg vs ORT fp32, median s, x ORT fp32).

    ``models``: model key (fp32, fp32_staged, int8, int8_staged) -> ONNX file; ``fp32`` is the
    reference, and paths whose engine is not installed or whose file is missing are left out,
    as are paths this CPU (``cpu``, default this machine's) cannot run as labelled (a line says
    which and why: the others are still measured).
    ``log``: a line per measured or skipped path (default: stderr)."""
    emit = log or _to_stderr
    from msfnet.runtime.engines.dispatch import EngineChoice

    cpu = cpu or detect_cpu()
    have = installed_engines()
    rows: list[dict[str, object]] = []
    for n in lights:
        feed = make_input(stack_dir, Workload("acc", n, size))
        images, lights_, mask = feed["images"], feed["lights"], feed["mask"]
        ref_engine = open_engine(
            EngineChoice("onnxruntime", "fp32", "reference", models["fp32"]), threads
        )
        ref, ref_s = _timed(ref_engine, images, lights_, repeats)
        del ref_engine
        rows.append(
            {
                "lights": n,
                "size": size,
                "path": "onnxruntime fp32",
                "mean_deg": 0.0,
                "max_deg": 0.0,
                "median_s": ref_s,
                "x_ort_fp32": 1.0,
            }
        )
        for p in paths:
            model = models.get(p.model)
            if p.engine not in have or model is None or not Path(model).is_file():
                continue
            why = unsupported(p, Path(model), cpu)
            if why is not None:
                emit(f"{n} lights {p.label}: skipped ({why})")
                continue
            engine = open_engine(EngineChoice(p.engine, p.precision, "measurement", model), threads)
            out, secs = _timed(engine, images, lights_, repeats)
            mean, mx = deviation_deg(out, ref, mask)
            rows.append(
                {
                    "lights": n,
                    "size": size,
                    "path": p.label,
                    "mean_deg": mean,
                    "max_deg": mx,
                    "median_s": secs,
                    "x_ort_fp32": ref_s / secs,
                    "effective_precision": engine.precision,
                }
            )
            emit(f"{n} lights {p.label}: {mean:.3f} / {mx:.3f} deg, {secs:.2f} s")
    return rows


def table(rows: list[dict[str, object]]) -> str:
    lines = [
        "| lights | engine precision | mean deg vs ORT fp32 | max deg | median s | x ORT fp32 |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['lights']} | {r['path']} | {r['mean_deg']:.3f} | {r['max_deg']:.3f}"
            f" | {r['median_s']:.2f} | {r['x_ort_fp32']:.2f} |"
        )
    return "\n".join(lines)


PROG = "python -m msfnet.bench.accuracy"


def light_counts(text: str) -> tuple[int, ...]:
    """``32,96`` -> (32, 96); each a positive integer."""
    return tuple(positive_int(t) for t in text.split(",") if t.strip()) or (positive_int(text),)


def build_parser() -> argparse.ArgumentParser:
    p = make_parser(PROG, __doc__ or "", (f"{PROG} --models exports/ --lights 32,96",))
    p.add_argument(
        "--data",
        type=path_arg,
        default=None,
        help="data root holding DiLiGenT/ballPNG (default: $MSFNET_DATA, "
        "./shared/data or ../shared/data)",
    )
    p.add_argument(
        "--models",
        type=path_arg,
        default=None,
        help="folder with fp32.onnx, fp32_staged.onnx, int8.onnx, int8_staged.onnx",
    )
    p.add_argument(
        "--lights",
        type=light_counts,
        default=(32, 96),
        help="light counts, comma-separated (default 32,96)",
    )
    p.add_argument("--size", type=positive_int, default=128, help="crop edge, px (default 128)")
    p.add_argument("--threads", type=thread_count, default=2, help="threads (default 2)")
    p.add_argument(
        "--repeats",
        type=positive_int,
        default=1,
        help="timed runs per path after a warm-up (default 1)",
    )
    return p


def model_files(models_dir: Path | None) -> dict[str, Path]:
    """The models to compare: the plain fp32 reference and the exports found in ``models_dir``;
    InputError if the reference is a staged graph (its rows would be filed as plain-graph ones)."""
    from msfnet.runtime.api import default_model_path
    from msfnet.runtime.engines.base import read_model_file

    models = {"fp32": default_model_path()}
    if models_dir is not None:
        if not models_dir.is_dir():
            raise InputError("--models: folder not found", models_dir)
        models.update({k: models_dir / f"{k}.onnx" for k in ("fp32_staged", "int8", "int8_staged")})
        if (models_dir / "fp32.onnx").is_file():
            models["fp32"] = models_dir / "fp32.onnx"
    if read_model_file(models["fp32"]).staged:
        raise InputError(
            "the plain-graph reference is a staged model: put a plain export "
            "(msf-export --plain) in --models as fp32.onnx",
            models["fp32"],
        )
    return models


def _run(args: argparse.Namespace) -> int:
    stack = data_root(args.data) / "DiLiGenT" / "ballPNG"
    if not stack.is_dir():
        raise InputError("ballPNG not found under the data root", stack)
    rows = measure(
        stack,
        model_files(args.models),
        args.lights,
        args.size,
        args.threads,
        args.repeats,
        log=(lambda _line: None) if args.quiet else None,
    )
    if not args.quiet:
        print(table(rows))
    return 0


def main(argv: list[str] | None = None) -> int:
    return command_main(PROG, build_parser(), _run, argv)


__all__ = ["PATHS", "EnginePath", "measure", "model_files", "table", "unsupported"]

if __name__ == "__main__":
    sys.exit(main())
