"""Every shell command the README shows, run as written in a sandbox with small stand-ins for the
inputs it names (obj/, bearPNG, ../shared/data/DiLiGenT, a checkpoint, ...), or a stated reason
why it cannot run here (a camera, a cluster, a GPU, hours of training).

A command added to the README without a plan here fails the fast test, so the README cannot gain
a command nobody has tried."""

from __future__ import annotations

import importlib.util
import os
import re
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest

from tests._runtime_helpers import BUNDLED_CHECKPOINT, sphere_stack

REPO = Path(__file__).resolve().parents[1]
BUNDLED_ONNX = REPO / "runtime" / "src" / "msfnet" / "runtime" / "weights" / "msfnet_default.onnx"


@dataclass(frozen=True)
class Run:
    """Run it; it must exit with ``code`` (msf-inspect: 1 = defects found)."""

    code: int = 0
    needs: str | None = None  # a module the command needs (the torch tools): skipped without


@dataclass(frozen=True)
class NotHere:
    """Cannot run on a CI machine, and why."""

    reason: str


HOURS = "hours of training on a CPU (tests/model runs msf-train for a few steps)"
# measured: msf-bench --quick took 16 min wall on 2 busy Zen 4 cores (2026-12-07); it calibrates
# int8 on the real ../shared/data ball, which a stand-in cannot replace
BENCH = "a benchmark of 10+ minutes on real data (tests/bench runs its parts on small data)"
# Every command of the README's ```sh blocks, in order, with what the test does with it.
PLAN: dict[str, Run | NotHere] = {
    "msf-calib directions chrome/ -o light_directions.txt": Run(),
    "msf-calib intensities white_sphere/ --lights light_directions.txt -o light_intensities.txt": (
        Run()
    ),
    "msf-capture obj/ --camera oak --light-rig serial --port /dev/ttyUSB0 --light-directions "
    "light_directions.txt --light-intensities light_intensities.txt --run": NotHere(
        "needs an OAK camera and a serial LED rig"
    ),
    "msf-capture demo/ --camera sim --light-rig sim --count 12 --run --method l2": Run(),
    "msf-run ../shared/data/DiLiGenT/ballPNG": Run(),
    "msf-run bearPNG --select 21-96 -o out/bear --json": Run(),
    "msf-run obj/ --method l2 --no-maps": Run(),
    "msf-run part/ --maps inspect": Run(),
    "msf-run obj/ --speed balanced": Run(),
    "msf-run obj/ --onnx mine.onnx --timeout 60": Run(),
    "msf-run coin/ --fine-detail": Run(),
    "msf-run A/ B/ C/ -o out/batch": Run(),
    "msf-run stacks/ --ray ray://head:10001 -o out/ray": NotHere(
        "needs a Ray cluster at ray://head:10001 (tests/runtime/batch runs a local one)"
    ),
    "msf-run cam/ --srgb --auto-mask --roi 400,300,800,600 --downscale 2": Run(),
    "msf-synth line/ --preset plates --objects 20 --size 256": Run(),
    "msf-inspect --train-good line/good/* --method l2 -o line/model": Run(),
    "msf-inspect line/parts/p002 --reference line/model --depth 0.05 --method l2 -o line/p002": (
        Run(code=1)
    ),
    "msf-inspect --watch line/parts --reference line/model --depth 0.05 --method l2 -o "
    "line/station --once": Run(code=1),
    "msf-eval ../shared/data/DiLiGenT": Run(),
    "msf-eval psmImages/cat psmImages/owl --lights psmImages/lights.txt": Run(),
    "msf-export checkp_30.pth.tar -o msfnet.onnx && msf-run obj/ --onnx msfnet.onnx": Run(
        needs="torch"
    ),
    "msf-export model.pth --plain -o plain.onnx": Run(needs="torch"),
    "msf-export --list-variants": Run(needs="torch"),
    "msf-export model.pth --variant staged-int8 --calib ballPNG cat/ -o int8.onnx": Run(
        needs="torch"
    ),
    "msf-train --out runs/mine": NotHere(HOURS),
    "msf-train --out runs/next --init model/src/msfnet/model/weights/msfnet_default.pth "
    "--lr 1.25e-4": NotHere(HOURS),
    "msf-train --out runs/gpu --device cuda --workers 12 --render-preset hard": NotHere(
        "needs a CUDA GPU"
    ),
    "msf-train --out runs/gpu --resume --snapshot-every 2": NotHere("continues the GPU run above"),
    "msf-average runs/gpu/snap_0008000.pth runs/gpu/snap_0010000.pth -o avg.pth": Run(
        needs="torch"
    ),
    "msf-synth /tmp/heldout --objects 12 --lights 32 --size 96 --seed 777 && msf-eval "
    "/tmp/heldout": Run(),
    "msf-bench --quick --report-dir /tmp/msf-bench-quick": NotHere(BENCH),
    "msf-bench --quick --cpu-proxy avx2 --report-dir /tmp/as-avx2": NotHere(BENCH),
}


def readme_commands() -> list[str]:
    """The README's shell commands in order: every ```sh block, continuation lines joined,
    trailing comments dropped."""
    text = (REPO / "README.md").read_text(encoding="utf-8")
    commands = []
    for block in re.findall(r"```sh\n(.*?)```", text, re.S):
        for line in re.sub(r"\\\n\s*", "", block).splitlines():
            command = line.split("  #")[0].strip()
            if command:
                commands.append(command)
    return commands


def test_every_readme_command_has_a_plan() -> None:
    assert readme_commands() == list(PLAN)


def _save(folder: Path, n: int, h: int = 36, w: int = 44, lights_file: bool = True) -> None:
    from msfnet.runtime.stack import save_stack

    stack = sphere_stack(n, h, w)
    save_stack(replace(stack, name=folder.name), folder)
    if not lights_file:  # as psmImages: the lights in one file beside the objects
        for f in folder.glob("light_*.txt"):
            f.unlink()


def _stand_ins(root: Path, bin_dir: Path) -> Path:
    """The inputs the README names, small, under ``root/work`` (the commands' folder); the
    README's ../shared/data is ``root/shared/data`` and its /tmp is ``root/tmp``."""
    work = root / "work"
    diligent = root / "shared" / "data" / "DiLiGenT"
    for name in ("ballPNG", "bearPNG", "harvestPNG"):
        _save(diligent / name, 96, 24, 28)
    _save(work / "bearPNG", 96, 24, 28)
    _save(work / "ballPNG", 12)
    for name in ("obj", "part", "coin", "A", "B", "C", "cat"):
        _save(work / name, 12)
    _save(work / "cam", 8, 900, 1200)
    for name in ("cat", "owl"):
        _save(work / "psmImages" / name, 12, lights_file=False)
    np.savetxt(work / "psmImages" / "lights.txt", sphere_stack(12).lights)
    for scene, folder in (("chrome", "chrome"), ("matte", "white_sphere")):
        subprocess.run(
            [bin_dir / "msf-capture", folder, "--camera", "sim", "--sim-scene", scene, "-q"],
            cwd=work,
            check=True,
        )
    shutil.copy(BUNDLED_ONNX, work / "mine.onnx")
    for copy in ("checkp_30.pth.tar", "model.pth", "runs/gpu/snap_0008000.pth"):
        (work / copy).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(BUNDLED_CHECKPOINT, work / copy)
    shutil.copy(BUNDLED_CHECKPOINT, work / "runs" / "gpu" / "snap_0010000.pth")
    (root / "tmp").mkdir()
    return work


@pytest.mark.slow
def test_every_readme_command_runs_as_written(tmp_path: Path) -> None:
    """Each command the README shows exits as the README says, in order, in one folder (the
    calibration writes the light file the next step reads, the station judges the line the
    synthesiser rendered), or is reported with the reason it cannot run here."""
    bin_dir = Path(sys.executable).parent
    if not (bin_dir / "msf-run").exists():
        pytest.skip("the msf-* commands are not installed beside this Python (pip install -e .)")
    work = _stand_ins(tmp_path, bin_dir)
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}"}
    failed, not_run = [], []
    for command, plan in PLAN.items():
        if isinstance(plan, NotHere):
            not_run.append(f"{command}: {plan.reason}")
            continue
        if plan.needs and importlib.util.find_spec(plan.needs) is None:
            not_run.append(f"{command}: needs {plan.needs}, not installed")
            continue
        start = time.perf_counter()
        done = subprocess.run(
            command.replace("/tmp/", f"{tmp_path}/tmp/"),
            shell=True,
            cwd=work,
            env=env,
            capture_output=True,
            text=True,
            timeout=900,
        )
        print(f"{time.perf_counter() - start:6.1f} s  exit {done.returncode}  {command}")
        if done.returncode != plan.code:
            failed.append(f"{command}: exit {done.returncode}\n{done.stderr[-2000:]}")
    print("not run here:\n  " + "\n  ".join(not_run))
    assert failed == []
    journal = (work / "line" / "station" / "parts.jsonl").read_text().splitlines()
    assert len(journal) == 20  # the station judged every part of the line once
