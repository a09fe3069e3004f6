"""msf-bench on an edge install: no torch, a given ONNX file (``msf-bench --onnx FILE``), and the
requirements table (``msf-bench --requirements``).

``--onnx``: every way this machine can run the file (ONNX Runtime in the model's precision,
OpenVINO fp32, OpenVINO bf16 where the CPU has native bf16, each --device present), one row
each, in the columns an Ultralytics ``benchmark`` user knows: format | status | size | MAE | ms
| peak MB. MAE: mean angular error against ground truth on 128 x 128 crops of the DiLiGenT
validation objects at 12 lights; ms: the median of the timed runs on the ball crop after one
warm-up; peak MB: the peak RSS of the fresh process that ran the row.

``--requirements``: time and peak memory of a whole stack through the runtime (tiling, memory
budget, normalisation: what msf-run does) by image size x light count x engine, on the ball's
images resized to each size with every pixel object (the worst case for a part of that size).

Each row runs in a fresh process (``python -m msfnet.bench.edge SPEC.json``), torch-free.
"""

from __future__ import annotations

import json
import math
import statistics
import sys
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from msfnet.bench.ladder import REPEAT, VALIDATION, validation_stacks
from msfnet.bench.worker import run_module, timed_runs
from msfnet.bench.workloads import centred_crop
from msfnet.common.errors import InputError
from msfnet.common.vocabulary import opt, speaking_as

if TYPE_CHECKING:
    from msfnet.runtime.engines.base import ModelInfo

CROP = 128
CROP_LIGHTS = 12
REQUIREMENT_SIZES = (128, 256, 512)
REQUIREMENT_LIGHTS = (12, 32)
QUICK_SIZES = (64, 128)
QUICK_LIGHTS = (8,)


@dataclass(frozen=True)
class EdgePath:
    """One way to run a model: engine, precision and device as dispatch understands them."""

    label: str  # the table's "format" column
    engine: str
    precision: str
    device: str | None = None  # --device name; None = the CPU


@dataclass(frozen=True)
class EdgeRow:
    format: str
    status: str  # "ok", or why the row did not run (one line)
    size_mb: float
    mae_deg: float | None
    ms: float | None
    peak_mb: float | None


def edge_paths(model: Path, info: ModelInfo | None = None) -> tuple[list[EdgePath], list[EdgeRow]]:
    """The paths this machine can run ``model`` on, and rows for those it cannot (status says
    why). Nothing is loaded but the model's metadata (``info``, when the caller has read it)."""
    from msfnet.common.cpu import detect_cpu
    from msfnet.runtime.engines import installed_engines, model_precision, read_model_file
    from msfnet.runtime.engines.dispatch import DEVICE_TARGETS, resolve_device

    if info is None:
        info = read_model_file(model)
    own = model_precision(info)
    have = installed_engines()
    size = model.stat().st_size / 2**20
    paths = [EdgePath(f"ONNX Runtime {own}", "onnxruntime", own)]
    skipped: list[EdgeRow] = []
    if "openvino" in have:
        paths.append(EdgePath(f"OpenVINO {own}", "openvino", own))
        if own == "fp32":
            if detect_cpu().has_bf16:
                paths.append(EdgePath("OpenVINO bf16", "openvino", "bf16"))
            else:
                skipped.append(
                    EdgeRow("OpenVINO bf16", "no native bf16 on this CPU", size, *[None] * 3)
                )
    else:
        skipped.append(EdgeRow(f"OpenVINO {own}", "openvino not installed", size, *[None] * 3))
    for name in DEVICE_TARGETS:
        if name == "cpu":
            continue
        try:
            device = resolve_device(name)
        except InputError as exc:
            # the table's status: the refusal's core ("OpenVINO sees no GPU here"); the
            # whole line (what it needs) is in report.json
            skipped.append(
                EdgeRow(opt("device", name), f"skipped: {_core(exc)}", size, *[None] * 3)
            )
            continue
        assert device is not None
        paths.append(EdgePath(opt("device", name), device.engine, own, name))
    return paths, skipped


def _core(exc: InputError) -> str:
    text = str(exc).split(": ", 1)[-1]
    return text.split(" (", 1)[0]


def validation_crops(
    data: Path, train_lights: int, lights: int = CROP_LIGHTS, size: int = CROP
) -> list[dict]:
    """(images, lights, mask, gt) network inputs: a ``size`` px crop of each validation object
    centred on its mask, ``lights`` evenly spaced lights (after the protocol's selection),
    normalised for a model trained with ``train_lights`` (its metadata, as msf-run reads it)."""
    from msfnet.runtime.infer.normalise import network_input

    crops = []
    for (name, _), stack in zip(VALIDATION, validation_stacks(data, lights), strict=True):
        rows, cols = centred_crop(stack.mask, size)
        images, lit = network_input(stack, rows, cols, train_lights=train_lights)
        if stack.normals_gt is None:
            raise InputError("validation object without ground-truth normals", stack.source)
        mask, gt = stack.mask[rows, cols], stack.normals_gt[rows, cols]
        crops.append({"name": name, "images": images, "lights": lit, "mask": mask, "gt": gt})
    return crops


def _open(spec: dict):  # type: ignore[no-untyped-def]
    from msfnet.common.cpu import detect_cpu
    from msfnet.runtime.engines import installed_engines
    from msfnet.runtime.engines.dispatch import choose_engine, open_engine, resolve_device

    device = resolve_device(spec.get("device"))
    asked = (spec.get("engine"), spec.get("precision"))
    choice = choose_engine(
        Path(spec["model"]), detect_cpu(), installed_engines(), *asked, device=device
    )
    return open_engine(choice, spec.get("threads"))


def measure_path(spec: dict) -> dict:
    """One --onnx row, in this process."""
    from msfnet.runtime.evaluate.metrics import normal_metrics
    from msfnet.runtime.instrument import peak_rss_mb

    engine = _open(spec)
    crops = read_crops(Path(spec["crops"]))  # cut by the parent: peak MB is the engine's
    maes = []
    for c in crops:
        out = engine.run(c["images"], c["lights"])[0].transpose(1, 2, 0)
        maes.append(normal_metrics(out, c["gt"], c["mask"]).mae_deg)
    parity = None
    if spec.get("device"):  # an accelerator: verified against ONNX Runtime fp32 on the CPU
        from msfnet.runtime.engines.dispatch import EngineChoice, open_engine
        from msfnet.runtime.evaluate.metrics import deviation_deg

        precision = engine.precision if engine.precision == "int8" else "fp32"
        ref = EngineChoice("onnxruntime", precision, "parity reference", Path(spec["model"]))
        cpu = open_engine(ref, spec.get("threads"))
        devs = [
            deviation_deg(
                engine.run(c["images"], c["lights"]), cpu.run(c["images"], c["lights"]), c["mask"]
            )
            for c in crops
        ]
        parity = (float(np.mean([d[0] for d in devs])), float(max(d[1] for d in devs)))
    ball = crops[0]
    engine.run(ball["images"], ball["lights"])  # warm-up at this size
    times, _ = timed_runs(
        lambda: engine.run(ball["images"], ball["lights"]), int(spec.get("repeats", 3))
    )
    return {
        "mae_deg": float(np.mean(maes)),
        "ms": 1e3 * statistics.median(times),
        "peak_mb": peak_rss_mb(),
        "parity_deg": parity,
    }


@dataclass(frozen=True)
class Requirement:
    size: int  # square image edge, px
    lights: int
    engine: str  # engine and precision that ran
    seconds: float | None  # the median of REPEAT runs
    peak_mb: float | None
    status: str = "ok"
    samples_s: tuple[float, ...] = ()  # every run


def measure_requirement(spec: dict) -> dict:
    """One requirements cell, in this process: the whole stack through the Python API with
    msf-run's defaults (memory budget, detail fusion; no maps), after a small warm-up."""
    import cv2

    from msfnet.runtime.api import Model
    from msfnet.runtime.instrument import peak_rss_mb
    from msfnet.runtime.stack import Stack, load_stack

    model = Model(
        Path(spec["model"]) if spec.get("model") else None,  # None: the bundled pair's choice
        threads=spec.get("threads"),
        engine=spec.get("engine"),
        precision=spec.get("precision"),
        device=spec.get("device"),
        maps=None,
    )
    size, lights = int(spec["size"]), int(spec["lights"])
    src = load_stack(Path(spec["stack"]), max_lights=lights)
    images = np.stack(
        [cv2.resize(im, (size, size), interpolation=cv2.INTER_AREA) for im in src.images]
    )
    stack = Stack.from_arrays(
        images, src.lights, intensities=src.intensities, mask=np.ones((size, size), bool)
    )
    del src
    model(Stack.from_arrays(images[:, :32, :32], stack.lights, intensities=stack.intensities))
    runs, _ = timed_runs(lambda: model(stack), REPEAT)  # a noisy box: the median of a few
    d = model.describe()
    return {
        "seconds": float(np.median(runs)),
        "samples_s": runs,
        "peak_mb": peak_rss_mb(),
        "engine": f"{d.engine} {d.precision}",
    }


CROP_FIELDS = ("images", "lights", "mask", "gt")


def write_crops(crops: list[dict], path: Path) -> Path:
    """The validation crops as one .npz (plain arrays, no pickle) for the row processes:
    loading three full DiLiGenT objects to cut them added ~66 MB to each row's peak."""
    arrays = {f"{k}:{field}": c[field] for k, c in enumerate(crops) for field in CROP_FIELDS}
    np.savez(path, names=np.array([c["name"] for c in crops]), **arrays)
    return path


def read_crops(path: Path) -> list[dict]:
    with np.load(path, allow_pickle=False) as data:
        return [
            {"name": str(name), **{f: data[f"{k}:{f}"] for f in CROP_FIELDS}}
            for k, name in enumerate(data["names"])
        ]


def run_worker(kind: str, spec: dict, scratch: Path) -> dict:
    """``spec`` run by ``kind`` (path | requirement) in a fresh process; {"error": line} if it
    failed."""
    spec = {**spec, "kind": kind, "result": str(scratch / "edge-result.json")}
    return run_module("msfnet.bench.edge", spec, scratch / "edge-spec.json")


def onnx_rows(
    model: Path,
    data: Path,
    threads: int | None,
    scratch: Path,
    say: Callable[[str], None] = lambda line: None,
    info: ModelInfo | None = None,
) -> list[EdgeRow]:
    """One row per engine / device path, each in a fresh process; ``say``: a line per row;
    ``info``: the model's metadata, when the caller has read it."""
    from msfnet.runtime.engines import read_model_file

    if info is None:
        info = read_model_file(model)
    paths, rows = edge_paths(model, info)
    size = model.stat().st_size / 2**20
    # normalised as the file declares (its train_lights), as msf-run feeds it
    crops = validation_crops(data, info.train_lights)
    crop_file = write_crops(crops, scratch / "edge-crops.npz")
    del crops
    measured = []
    for k, p in enumerate(paths, 1):
        say(f"[{k}/{len(paths)}] {p.label} ...")
        spec = {
            "model": str(model),
            "crops": str(crop_file),
            "threads": threads,
            "engine": p.engine,
            "precision": p.precision,
            "device": p.device,
        }
        r = run_worker("path", spec, scratch)
        if "error" in r:
            measured.append(EdgeRow(p.label, f"failed: {r['error']}", size, None, None, None))
            continue
        status = _answer_status(r["mae_deg"]) or _parity_status(r.get("parity_deg"))
        measured.append(EdgeRow(p.label, status, size, r["mae_deg"], r["ms"], r["peak_mb"]))
    return measured + rows


# A mean error this large is no estimate at all (normals facing the camera score ~30-40 deg on
# the crops; NaN or zero output scores 180): such a row must not show a tick.
UNUSABLE_MAE_DEG = 90.0


def _answer_status(mae_deg: float) -> str | None:
    """'failed: ...' when the path's normals are unusable (NaN, zeros, nonsense), else None."""
    if not math.isfinite(mae_deg) or mae_deg >= UNUSABLE_MAE_DEG:
        return (
            f"failed: MAE {mae_deg:.0f} deg, the model's normals are unusable "
            "(NaN, zeros or nonsense)"
        )
    return None


def _parity_status(parity: list[float] | tuple[float, float] | None) -> str:
    """'ok' for CPU rows; for a device, its agreement with CPU fp32 (mean / max deg), failed
    above the accuracy bound."""
    from msfnet.runtime.engines.dispatch import ACCURACY_BOUND_DEG

    if parity is None:
        return "ok"
    mean, worst = parity
    verdict = "ok" if mean <= ACCURACY_BOUND_DEG else "failed"
    return f"{verdict}: parity {mean:.3f} / {worst:.2f} deg vs CPU fp32"


def edge_table(rows: list[EdgeRow]) -> str:
    """Markdown, Ultralytics' benchmark columns."""

    def num(v: float | None, fmt: str) -> str:
        return "-" if v is None else format(v, fmt)

    # the objects behind the MAE: one mean over their crops read as one object's score
    objects = " / ".join(name.removesuffix("PNG") for name, _ in VALIDATION)
    lines = [
        f"| format | status | size (MB) | MAE (deg, mean of DiLiGenT {objects} {CROP} px crops, "
        f"{CROP_LIGHTS} lights) | ms ({CROP} px crop) | peak MB |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        ok = r.status == "ok" or r.status.startswith("ok:")
        status = ("✅" + r.status[2:]) if ok else f"❌ {r.status}"
        lines.append(
            f"| {r.format} | {status} | {r.size_mb:.1f} | {num(r.mae_deg, '.2f')} | "
            f"{num(r.ms, '.0f')} | {num(r.peak_mb, '.0f')} |"
        )
    return "\n".join(lines)


def requirement_rows(
    model: Path | None,
    stack: Path,
    threads: int | None,
    scratch: Path,
    *,
    quick: bool = False,
    engines: tuple[tuple[str | None, str | None], ...] | None = None,
    say: Callable[[str], None] = lambda line: None,
    info: ModelInfo | None = None,
) -> list[Requirement]:
    """The grid, each cell in a fresh process; ``engines``: (engine, precision) pairs, None =
    dispatch's default; by default that and ONNX Runtime in the model's own precision (fp32,
    or int8 for an int8 file: ONNX Runtime cannot run an int8 file in fp32). ``model`` None:
    the bundled model msf-run would open here (its int8 twin where dispatch.bundled_precision
    prefers it; an engine or precision named keeps the fp32 file)."""
    if engines is None:
        from msfnet.runtime.engines import model_precision, read_model_file

        if model is None:
            own = "fp32"
        else:
            own = model_precision(info if info is not None else read_model_file(model))
        engines = ((None, None), ("onnxruntime", own))
    sizes, lights = (
        (QUICK_SIZES, QUICK_LIGHTS) if quick else (REQUIREMENT_SIZES, REQUIREMENT_LIGHTS)
    )
    out: list[Requirement] = []
    total = len(engines) * len(lights) * len(sizes)
    for engine, precision in engines:
        for n in lights:
            for s in sizes:
                name = f"{engine or 'default engine'} {precision or ''}".strip()
                say(f"[{len(out) + 1}/{total}] {s} x {s} px, {n} lights, {name} ...")
                spec = {
                    "model": None if model is None else str(model),
                    "stack": str(stack),
                    "threads": threads,
                    "engine": engine,
                    "precision": precision,
                    "size": s,
                    "lights": n,
                }
                r = run_worker("requirement", spec, scratch)
                label = r.get("engine", f"{engine or 'default'} {precision or ''}".strip())
                if "error" in r:
                    out.append(Requirement(s, n, label, None, None, f"failed: {r['error']}"))
                    continue
                runs = tuple(r["samples_s"])
                out.append(Requirement(s, n, label, r["seconds"], r["peak_mb"], "ok", runs))
    return out


def requirements_table(rows: list[Requirement]) -> str:
    lines = ["| image | lights | engine | time s | peak MB |", "|---|---|---|---|---|"]
    for r in rows:
        if r.status != "ok":
            lines.append(f"| {r.size}x{r.size} | {r.lights} | {r.engine} | {r.status} | - |")
            continue
        assert r.seconds is not None and r.peak_mb is not None
        lines.append(
            f"| {r.size}x{r.size} | {r.lights} | {r.engine} | {r.seconds:.2f} | {r.peak_mb:.0f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    spec = json.loads(Path((argv or sys.argv[1:])[0]).read_text())
    with speaking_as("msf-bench"):  # a row's refusal names msf-bench's options
        result = measure_path(spec) if spec["kind"] == "path" else measure_requirement(spec)
    Path(spec["result"]).write_text(json.dumps(result))
    return 0


__all__ = [
    "EdgePath",
    "EdgeRow",
    "Requirement",
    "asdict",
    "edge_paths",
    "edge_table",
    "onnx_rows",
    "requirement_rows",
    "requirements_table",
    "validation_crops",
]

if __name__ == "__main__":
    sys.exit(main())
