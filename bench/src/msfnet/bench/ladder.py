"""The speed ladder's trade-off table (``msf-bench --ladder``): time, peak memory, MAE on the
DiLiGenT validation objects and detail, per rung (runtime/infer/ladder.py), on this CPU.

Each rung runs in a fresh process (``python -m msfnet.bench.ladder SPEC.json``) so its peak
RSS is its own. Torch-free: it runs the ONNX model through the runtime's engines, as msf-run
does, so it runs on an edge install.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path

import numpy as np

from msfnet.bench.worker import run_process, timed_runs
from msfnet.common.errors import InputError
from msfnet.common.files import writing_as
from msfnet.common.vocabulary import opt, speaking_as

# The validation objects (never calibration or training data) and their protocol selections.
VALIDATION = (("ballPNG", None), ("bearPNG", "21-96"), ("harvestPNG", None))
LADDER_LIGHTS = 12


REPEAT = 3  # timed runs of each object on each rung (and of each requirements cell)


@dataclass(frozen=True)
class LadderRow:
    rung: str
    summary: str
    engine: str  # engine and precision that ran, e.g. "openvino bf16"
    seconds: float  # estimate time summed over the objects, each its median of REPEAT runs
    peak_mb: float  # peak RSS of the process that ran the rung
    mae_deg: dict[str, float]  # object -> mean angular error vs ground truth
    detail: float  # mean over objects of the detail ratio to least squares (1 = all kept)
    samples_s: dict[str, list[float]] = field(default_factory=dict)  # object -> every run

    @property
    def mean_mae(self) -> float:
        return float(np.mean(list(self.mae_deg.values())))


def validation_stacks(root: Path, lights: int) -> list:
    """The validation objects at ``lights`` evenly spaced lights (after the protocol's
    selection); InputError naming a missing object."""
    from msfnet.runtime.stack import load_stack

    stacks = []
    for name, select in VALIDATION:
        folder = root / "DiLiGenT" / name
        if not folder.is_dir():
            raise InputError("validation object not found (DiLiGenT)", folder)
        stacks.append(load_stack(folder, select=select, max_lights=lights))
    return stacks


def measure_rung(spec: dict) -> dict:
    """One rung on every validation object, in this process (the worker's body), through the
    Python API with the rung's --speed: what msf-run runs, detail fusion included."""
    from msfnet.runtime.api import Model
    from msfnet.runtime.evaluate.detail_ratio import detail_ratio
    from msfnet.runtime.infer.estimators import LeastSquaresEstimator, TilingOptions
    from msfnet.runtime.infer.ladder import rung
    from msfnet.runtime.instrument import StageTimer, peak_rss_mb

    step = rung(spec["rung"])
    model = Model(
        Path(spec["model"]) if spec.get("model") else None,  # None: the bundled pair's choice
        speed=step.name,
        threads=spec.get("threads"),
        engine=spec.get("engine"),
        precision=spec.get("precision"),
        maps=None,
    )
    stacks = validation_stacks(Path(spec["data"]), int(spec["lights"]))
    model(stacks[0])  # warm-up: first-call allocations and compilation at these sizes
    seconds, mae, detail, samples = 0.0, {}, [], {}
    for stack in stacks:
        # a shared edge box is noisy: the median of a few runs
        runs, result = timed_runs(partial(model, stack), REPEAT)
        assert result is not None
        samples[stack.name] = runs
        seconds += float(np.median(runs))
        if result.metrics is None:
            raise InputError("validation object without ground-truth normals", stack.source)
        mae[stack.name] = result.metrics.mae_deg
        ls = LeastSquaresEstimator().estimate(stack, TilingOptions(), StageTimer()).normals
        detail.append(detail_ratio(result.normals, ls, stack.mask))
    described = model.describe()
    row = LadderRow(
        step.name,
        step.summary,
        f"{described.engine} {described.precision}",
        seconds,
        peak_rss_mb(),
        mae,
        float(np.mean(detail)),
        samples,
    )
    return asdict(row)


def ladder_rows(
    model: Path | None,
    data: Path,
    *,
    lights: int = LADDER_LIGHTS,
    threads: int | None = None,
    engine: str | None = None,
    precision: str | None = None,
    rungs: tuple[str, ...] | None = None,
    scratch: Path,
    say: Callable[[str], None] = lambda line: None,
) -> list[LadderRow]:
    """Every rung (or ``rungs``), each in a fresh process; InputError where a worker refused
    its input (a static-shape model, an object without ground truth), RuntimeError with the
    worker's last error line where it failed otherwise. ``model`` None: the bundled model
    msf-run would open here (its int8 twin where it is the faster default,
    engines.dispatch.bundled_precision)."""
    from msfnet.runtime.infer.ladder import RUNGS

    rows = []
    names = rungs or tuple(RUNGS)
    for k, name in enumerate(names, 1):
        say(f"[{k}/{len(names)}] rung {name} ...")
        result = scratch / f"ladder-{name}.json"
        spec: dict[str, object] = {
            "rung": name,
            "model": None if model is None else str(model),
            "data": str(data),
            "lights": lights,
            "threads": threads,
            "engine": engine,
            "precision": precision,
            "result": str(result),
        }
        spec_file = scratch / f"ladder-{name}.spec.json"
        spec_file.write_text(json.dumps(spec))
        proc = run_process([sys.executable, "-m", "msfnet.bench.ladder", str(spec_file)])
        if isinstance(proc, str):  # the model given did not finish: the user's to change
            raise InputError(f"speed rung {name}: {proc}")
        if proc.returncode == 2 and result.is_file():  # the input, in the worker's words
            refused = json.loads(result.read_text())
            raise InputError(f"speed rung {name}: {refused['input_error']}", refused["path"])
        if proc.returncode != 0:
            last = (proc.stderr.strip().splitlines() or ["failed"])[-1]
            raise RuntimeError(f"speed rung {name}: {last[:300]}")
        rows.append(LadderRow(**json.loads(result.read_text())))
    return rows


def ladder_table(rows: list[LadderRow], lights: int = LADDER_LIGHTS) -> str:
    """Markdown: one line per rung, time and MAE also as ratios to the first (full) rung."""
    names = [name.removesuffix("PNG") for name, _ in VALIDATION]
    head = (
        f"| {opt('speed')} | engine | s ({len(names)} objects, {lights} lights) | x full "
        "| peak MB | " + " | ".join(f"MAE {n}" for n in names) + " | mean MAE | vs full | detail |"
    )
    lines = [head, "|" + "---|" * (8 + len(names))]
    ref = rows[0] if rows else None
    for r in rows:
        assert ref is not None
        maes = " | ".join(f"{v:.2f}" for v in r.mae_deg.values())
        lines.append(
            f"| {r.rung} | {r.engine} | {r.seconds:.2f} | {ref.seconds / r.seconds:.2f} | "
            f"{r.peak_mb:.0f} | {maes} | {r.mean_mae:.2f} | {r.mean_mae - ref.mean_mae:+.2f} | "
            f"{r.detail:.2f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    spec_path = Path((argv or sys.argv[1:])[0])
    spec = json.loads(spec_path.read_text())
    try:
        # errors name msf-bench's options, not the Python API's
        with writing_as("msf-bench"), speaking_as("msf-bench"):
            row = measure_rung(spec)
    except InputError as exc:  # bad input, not a bug: handed back for one error line
        path = None if exc.path is None else str(exc.path)
        Path(spec["result"]).write_text(json.dumps({"input_error": exc.message, "path": path}))
        return 2
    Path(spec["result"]).write_text(json.dumps(row))
    return 0


__all__ = [
    "LADDER_LIGHTS",
    "VALIDATION",
    "LadderRow",
    "ladder_rows",
    "ladder_table",
    "measure_rung",
    "validation_stacks",
]

if __name__ == "__main__":
    sys.exit(main())
