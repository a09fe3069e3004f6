"""Workloads and variants of msf-bench, and the worker that times one (variant, threads) cell.

Every cell runs in its own process (``python -m msfnet.bench.workloads SPEC.json``) so that its
peak RSS is its own and thread settings cannot leak between frameworks. Inputs are cut from the
real ballPNG stack (a crop centred on the ball, evenly spaced lights), so the accuracy figures
are on real data.
"""

from __future__ import annotations

import json
import os
import statistics
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from msfnet.bench.worker import row_limit, run_process, timed_runs
from msfnet.common.errors import InputError
from msfnet.runtime.engines.openvino import INT8_CHUNK
from msfnet.runtime.engines.staged_loop import DEFAULT_CHUNK
from msfnet.runtime.infer.flops import inference_flops
from msfnet.runtime.infer.normalise import network_input


@dataclass(frozen=True)
class Workload:
    key: str
    lights: int
    size: int  # square crop edge (px)

    @property
    def pixels(self) -> int:
        return self.size * self.size

    @property
    def flops(self) -> float:
        return inference_flops(self.lights, self.pixels)

    def label(self) -> str:
        return f"({self.key}) {self.lights} lights {self.size}x{self.size}"


WORKLOADS = (Workload("a", 16, 64), Workload("b", 32, 128), Workload("c", 96, 128))
QUICK_WORKLOADS = (Workload("a", 16, 64), Workload("b", 8, 64))


@dataclass(frozen=True)
class BenchVariant:
    """One way of running the network that msf-bench times: ``engine`` / ``precision`` are
    what it asks the runtime's dispatch for (``torch``: the PyTorch reference, outside the
    runtime) and the matmul peak it is compared with; ``model`` the export it runs."""

    name: str
    about: str
    engine: str  # onnxruntime, openvino or torch
    precision: str  # fp32, bf16 or int8
    model: str = "fp32"  # the export: fp32, fp32_staged, int8 or int8_staged

    @property
    def through_runtime(self) -> bool:
        return self.engine != "torch"


VARIANTS = {
    v.name: v
    for v in (
        BenchVariant("ort-fp32", "ONNX Runtime CPU, fp32 model (untiled)", "onnxruntime", "fp32"),
        BenchVariant(
            "ort-fp32-staged",
            "ONNX Runtime CPU, staged fp32 model (msf-export --staged), "
            f"{DEFAULT_CHUNK} lights a call",
            "onnxruntime",
            "fp32",
            "fp32_staged",
        ),
        BenchVariant(
            "ort-int8",
            "ONNX Runtime CPU, int8 QDQ model (extractor convs, calibrated on real stacks)",
            "onnxruntime",
            "int8",
            "int8",
        ),
        BenchVariant(
            "ov-bf16",
            "OpenVINO CPU, fp32 model with INFERENCE_PRECISION_HINT=bf16 (native bf16 only)",
            "openvino",
            "bf16",
        ),
        BenchVariant(
            "ov-bf16-staged",
            "OpenVINO CPU, staged fp32 model in bf16, four sub-models, "
            f"{DEFAULT_CHUNK} lights a call",
            "openvino",
            "bf16",
            "fp32_staged",
        ),
        BenchVariant(
            "ov-int8-staged",
            "OpenVINO CPU, staged int8 model (msf-export --variant staged-int8, as the bundled "
            f"twin), {INT8_CHUNK} lights a call: msf-run's default where the twin is",
            "openvino",
            "int8",
            "int8_staged",
        ),
        BenchVariant(
            "torch-fp32", "PyTorch eager fp32, lights folded into the batch", "torch", "fp32"
        ),
        BenchVariant(
            "per-light",
            "PyTorch per-light loop (published style: recomputes stages)",
            "torch",
            "fp32",
        ),
    )
}


def centred_crop(mask: np.ndarray, size: int) -> tuple[slice, slice]:
    """The (rows, cols) of a ``size`` px square centred on the mask, on a multiple of 4 px."""
    ys, xs = np.nonzero(mask)
    h, w = mask.shape
    y0 = int(np.clip(ys.mean() - size / 2, 0, h - size)) // 4 * 4
    x0 = int(np.clip(xs.mean() - size / 2, 0, w - size)) // 4 * 4
    return slice(y0, y0 + size), slice(x0, x0 + size)


def make_input(stack_dir: Path, wl: Workload) -> dict[str, np.ndarray]:
    """Normalised (1, N, 3, s, s) crop centred on the mask, N evenly spaced lights."""
    from msfnet.runtime.stack import load_stack

    stack = load_stack(stack_dir, max_lights=wl.lights)
    rows, cols = centred_crop(stack.mask, wl.size)
    images, lights = network_input(stack, rows, cols)
    return {"images": images, "lights": lights, "mask": stack.mask[rows, cols]}


def full_input(stack_dir: Path, lights: int) -> dict[str, np.ndarray]:
    """The whole image on ``lights`` evenly spaced lights (the lights msf-run --max-lights
    keeps), zero-padded to multiples of 4 and untiled: the input the published code runs on."""
    from msfnet.runtime.stack import load_stack

    stack = load_stack(stack_dir, max_lights=lights)
    h, w = stack.mask.shape
    images, dirs = network_input(stack, shape=(-(-h // 4) * 4, -(-w // 4) * 4))
    return {"images": images, "lights": dirs, "mask": stack.mask}


def _max_rss_mb() -> float:
    """Peak RSS of this process (VmHWM on Linux: see msfnet.runtime.results.profile.peak_rss_mb)."""
    from msfnet.runtime.instrument import peak_rss_mb

    return peak_rss_mb()


# Runs msf-run's main in this process, then records VmHWM (see _max_rss_mb) for the parent.
_E2E_WRAPPER = """
import runpy, sys
from msfnet.bench.workloads import _max_rss_mb
out, sys.argv = sys.argv[1], ["msf-run", *sys.argv[2:]]
try:
    runpy.run_module("msfnet.runtime.cli.run", run_name="__main__")
finally:
    open(out, "w").write(str(_max_rss_mb()))
"""


def _runner(variant: str, spec: dict):
    """Build the variant once; return (callable(images, lights) -> normals (1,3,H,W), info)."""
    threads = int(spec["threads"])
    row = VARIANTS[variant]
    if row.through_runtime:
        # through the runtime's own engines: the bench times what msf-run would run
        from msfnet.runtime.engines.dispatch import EngineChoice, open_engine

        engine = open_engine(
            EngineChoice(row.engine, row.precision, "msf-bench", Path(spec["onnx"])), threads
        )
        return engine.run, {"precision": engine.precision, "engine": engine.describe().as_json()}
    import torch

    from msfnet.model.checkpoint import load_model
    from msfnet.model.reference import per_light_forward

    torch.set_num_threads(threads)
    net = load_model(spec["checkpoint"]).eval()

    def run_torch(images, lights):
        with torch.no_grad():
            a, b = torch.from_numpy(images), torch.from_numpy(lights)
            out = net(a, b) if variant == "torch-fp32" else per_light_forward(net, a, b)
        return out.numpy()

    return run_torch, {"precision": "fp32"}


def run_cell(spec: dict) -> dict:
    """Time one variant on one input: warm-up runs, then ``repeats`` timed runs."""
    data = np.load(spec["input"])
    images, lights = data["images"], data["lights"]
    t0 = time.perf_counter()
    run, info = _runner(spec["variant"], spec)
    init_s = time.perf_counter() - t0
    for _ in range(int(spec["warmup"])):
        run(images, lights)
    times, out = timed_runs(lambda: run(images, lights), int(spec["repeats"]))
    np.save(spec["output"], np.asarray(out, dtype=np.float32))
    return {
        "times_s": times,
        "median_s": statistics.median(times),
        "p90_s": float(np.percentile(times, 90)),
        "init_s": init_s,
        "peak_rss_mb": _max_rss_mb(),
        **info,
    }


def time_msf_run(
    stack_dir: Path,
    onnx: Path | None,
    outdir: Path,
    threads: int,
    max_memory_mb: float | None,
    max_lights: int | None = None,
    extra: Sequence[str] = (),
) -> dict:
    """One end-to-end ``msf-run`` in a fresh process (load -> normals on disk).

    ``onnx`` None runs the bundled model and ``max_memory_mb`` None msf-run's own budget: the
    command a user types. ``extra``: more msf-run options (e.g. ``--engine onnxruntime``)."""
    import subprocess

    rss_file = outdir.parent / f".{outdir.name}.rss"
    rss_file.parent.mkdir(parents=True, exist_ok=True)
    cmd = [
        sys.executable,
        "-c",
        _E2E_WRAPPER,
        str(rss_file),
        str(stack_dir),
        *(["--onnx", str(onnx)] if onnx is not None else []),
        "-o",
        str(outdir),
        "--overwrite",
        "--threads",
        str(threads),
        "--no-maps",
        *(["--max-memory", str(max_memory_mb)] if max_memory_mb is not None else []),
        *extra,
    ]
    if max_lights:
        cmd += ["--max-lights", str(max_lights)]
    limit = row_limit()
    if limit is not None:  # msf-bench --timeout: msf-run bounds its own compile and inference
        cmd += ["--timeout", f"{limit:g}"]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        _, status, _ = os.wait4(proc.pid, 0)
    except BaseException:  # Ctrl-C, SIGTERM: the run must not go on writing into the report
        proc.kill()
        proc.wait()
        raise
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
    if proc.returncode == 2:  # msf-run refused its input or options: say it in its words
        lines = err.strip().splitlines()
        raise InputError(f"workload (d): {lines[-1] if lines else 'msf-run: error'}")
    if proc.returncode != 0:
        raise RuntimeError(f"msf-run failed ({proc.returncode}): {err.strip()[-400:]}")
    profile = {}
    pfile = outdir / "profile.json"
    if pfile.is_file():
        profile = json.loads(pfile.read_text())
    peak = float(rss_file.read_text())
    rss_file.unlink()
    return {
        "wall_s": wall,
        "peak_rss_mb": peak,
        "profile": profile,
        "command": " ".join(["msf-run", *cmd[4:]]),
    }


# One process, the model opened once: a warm-up call, then timed calls of the whole per-stack
# work a stream or a station loop repeats (load -> normals, metrics; no files written).
_WARM_WORKER = """
import json, sys, time
from msfnet import Model
from msfnet.runtime.stack.load import LoadOptions
from msfnet.bench.workloads import _max_rss_mb
spec = json.loads(sys.argv[1])
budget = {} if spec["max_memory_mb"] is None else {"max_memory_mb": spec["max_memory_mb"]}
model = Model(threads=spec["threads"], maps=None, **budget)
load = LoadOptions(max_lights=spec["max_lights"]) if spec["max_lights"] else None
model(spec["stack"], load)
walls = []
for _ in range(spec["repeats"]):
    t = time.perf_counter()
    result = model(spec["stack"], load)
    walls.append(time.perf_counter() - t)
print(json.dumps({"walls_s": walls, "profile": result.profile(), "peak_rss_mb": _max_rss_mb(),
                  "mae": None if result.metrics is None else result.metrics.mae_deg}))
"""


def time_warm_model(
    stack_dir: Path,
    threads: int,
    max_memory_mb: float | None,
    max_lights: int | None = None,
    repeats: int = 3,
) -> dict:
    """The default path in one warm process (``Model`` opened once, a warm-up call, then
    ``repeats`` timed calls on the stack path: loading, inference, fusion, metrics; no files):
    the per-stack time of a stream or a station loop, without process start and compile."""
    spec = {
        "stack": str(stack_dir),
        "threads": threads,
        "max_memory_mb": max_memory_mb,
        "max_lights": max_lights,
        "repeats": repeats,
    }
    proc = run_process([sys.executable, "-c", _WARM_WORKER, json.dumps(spec)])
    if isinstance(proc, str):
        raise InputError(f"the warm model run {proc}")
    if proc.returncode != 0:
        raise RuntimeError(f"warm model run failed ({proc.returncode}): {proc.stderr[-400:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    spec_path = Path((argv or sys.argv[1:])[0])
    spec = json.loads(spec_path.read_text())
    result = run_cell(spec)
    Path(spec["result"]).write_text(json.dumps(result))
    return 0


__all__ = [
    "QUICK_WORKLOADS",
    "VARIANTS",
    "WORKLOADS",
    "BenchVariant",
    "Workload",
    "asdict",
    "full_input",
    "make_input",
    "run_cell",
    "time_msf_run",
    "time_warm_model",
]

if __name__ == "__main__":
    sys.exit(main())
