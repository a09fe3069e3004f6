"""Issue #27 item 7, the rest: the inspection maps (albedo, height, curvature, mesh, their TIFFs
and pictures, the report) stay within --max-memory, the whole process's peak, as least squares
does; a map that cannot fit is skipped before its work with one warning line naming it and the
budget. And a float64 .npz stack is counted at what reading it holds, not at its float32 size.

Each case runs in a fresh interpreter that reports its peak resident memory (VmHWM: the
child's own address space)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from _runtime_helpers import sphere_stack

pytest.importorskip("resource", reason="peak memory via resource (POSIX)")
pytest.importorskip("psutil", reason="the budget is checked against resident memory (psutil)")

RUN = """
import json, sys
from pathlib import Path
import numpy as np
from msfnet.runtime.api import Model
from msfnet.runtime.options import ModelOptions
from msfnet.runtime.results.result import write_result
from msfnet.runtime.stack import Stack
from msfnet.runtime.infer.least_squares import memory_in_use_mb

# VmHWM on Linux: ru_maxrss would count the test runner's size at fork time (kept over exec)
from msfnet.runtime.instrument import peak_rss_mb as peak

room, out = float(sys.argv[1]), Path(sys.argv[2])
n, h, w = 16, 600, 800  # a sphere filling the frame: every pixel in the mask
yy, xx = np.mgrid[0:h, 0:w]
x, y = (xx - w / 2) / (0.6 * w), -(yy - h / 2) / (0.6 * w)
normals = np.dstack([x, y, np.ones_like(x)])
normals /= np.linalg.norm(normals, axis=2, keepdims=True)
rng = np.random.default_rng(0)
lights = rng.normal(size=(n, 3))
lights[:, 2] = np.abs(lights[:, 2]) + 1.5
lights /= np.linalg.norm(lights, axis=1, keepdims=True)
images = np.empty((n, h, w, 3), np.uint16)
for i in range(n):
    images[i] = (np.clip(normals @ lights[i], 0, 1) * 50000 + 300)[..., None].astype(np.uint16)
stack = Stack.from_arrays(images, lights.astype(np.float32))
del images, normals, x, y, xx, yy
budget = memory_in_use_mb() + room  # what the process holds with its stack, plus ``room``
result = Model(options=ModelOptions(method="l2", max_memory_mb=budget))(stack)
write_result(result, out)
print(json.dumps({
    "peak": peak(), "budget": budget, "warnings": list(result.stack.warnings),
    "files": sorted(p.name for p in out.iterdir()),
}))
"""


def _run(room_mb: float, out: Path) -> dict:
    proc = subprocess.run(
        [sys.executable, "-c", RUN, str(room_mb), str(out)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-800:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.slow
@pytest.mark.parametrize("room_mb", [150, 300])
def test_maps_keep_the_whole_process_within_max_memory(room_mb: float, tmp_path: Path) -> None:
    """0.48 MP, all of it in the mask: the Poisson height alone took ~350 MB beyond the stack
    and the pictures several float64 copies of the frame; the old maps stage ignored the
    budget and ran ~500 MB over it."""
    got = _run(room_mb, tmp_path / "out")
    assert got["peak"] <= got["budget"], got
    said = [w for w in got["warnings"] if "max_memory_mb=" in w]  # the API's words
    assert len(said) == 1 and "height" in said[0] and "skipped" in said[0], got
    assert "height.tif" not in got["files"] and "mesh.ply" not in got["files"], got
    assert {"normals.npy", "maps.json", "report.html"} <= set(got["files"]), got


@pytest.mark.slow
def test_a_large_enough_budget_computes_every_map_within_it(tmp_path: Path) -> None:
    got = _run(1400, tmp_path / "out")
    assert got["peak"] <= got["budget"], got
    assert not [w for w in got["warnings"] if "max_memory_mb" in w], got
    assert {"albedo.tif", "height.tif", "curvature.tif", "mesh.ply"} <= set(got["files"]), got


LOAD = """
import json, sys
from pathlib import Path
from msfnet.common.errors import InputError
from msfnet.runtime.stack import LoadOptions, load_stack

def status(key):
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) / 1024 for line in f if line.startswith(key))

# the peak is reset here (Linux): a peak reached while importing would hide the load's growth
with open("/proc/self/clear_refs", "w") as f:
    f.write("5")
before = status("VmRSS:")
try:
    stack = load_stack(Path(sys.argv[1]), LoadOptions(max_memory_mb=float(sys.argv[2])))
    said, dtype = None, str(stack.images.dtype)
except InputError as exc:
    said, dtype = str(exc), None
print(json.dumps({"grew": status("VmHWM:") - before, "error": said, "dtype": dtype}))
"""


@pytest.fixture(scope="module")
def float64_npz(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """8 float64 RGB images of 500 x 500: 48 MB stored, 24 MB held as float32."""
    path = tmp_path_factory.mktemp("npz") / "f64.npz"
    rng = np.random.default_rng(1)
    images = rng.uniform(0.0, 1.0, (8, 500, 500, 3))
    lights = np.tile([[0.0, 0.0, 1.0]], (8, 1)) + rng.normal(0, 0.3, (8, 3))
    np.savez(path, images=images, lights=lights)
    return path


def _load(path: Path, budget_mb: float) -> dict:
    if not Path("/proc/self/clear_refs").exists():
        pytest.skip("resets the peak resident memory through /proc/self/clear_refs (Linux)")
    proc = subprocess.run(
        [sys.executable, "-c", LOAD, str(path), str(budget_mb)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-800:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_a_float64_npz_is_counted_at_what_reading_it_holds(float64_npz: Path) -> None:
    """24 MB held fits 60 MB, but reading holds the 48 MB stored array beside it: refused
    (it was accepted, and reading grew the process by ~150 MB)."""
    got = _load(float64_npz, 60)
    assert got["error"] is not None and "reading them holds 69 MB" in got["error"], got
    assert got["grew"] < 20, got


def test_a_float64_npz_that_fits_is_read_within_what_was_counted(float64_npz: Path) -> None:
    """With room for it, reading grows the process by no more than what was counted: the
    stored array and the float32 copy (69 MB), plus one frame's range-check temporaries (its
    6 MB of absolute values, its finite mask) and the zip reader's buffers: 76 MB measured.
    A finite-check copy of the whole stack and its absolute values were two more float64
    copies (138 MB measured with them)."""
    got = _load(float64_npz, 100)
    assert got["error"] is None and got["dtype"] == "float32", got
    assert got["grew"] <= 69 + 12, got


def test_msf_inspect_reads_a_maps_size_from_its_header_first(tmp_path: Path, capsys) -> None:
    """Issue #48: a few-KB sparse BigTIFF declaring 60000 x 60000 float32 as local_shape.tif
    reached 13.8 GB before the mismatch was reported; msf-run refused the same header up
    front."""
    import tifffile

    from msfnet import Model
    from msfnet.runtime.cli.inspect import main as inspect_main
    from msfnet.runtime.results.maps import MapOptions

    run = tmp_path / "run"
    Model.least_squares(maps=MapOptions(maps=("height",)))(sphere_stack(n=6, h=24, w=24)).save(run)
    (run / "local_shape.tif").unlink()
    with tifffile.TiffWriter(run / "local_shape.tif", bigtiff=True) as tw:
        tw.write(shape=(60000, 60000), dtype=np.float32)  # declared, never written: sparse
    assert (run / "local_shape.tif").stat().st_blocks * 512 < 10**6
    out = tmp_path / "v"
    assert inspect_main([str(run), "--depth", "0.1", "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "local_shape.tif" in err[0] and "MP limit" in err[0], err
    assert not out.exists()


def test_msf_inspect_holds_a_run_folders_maps_to_max_memory(tmp_path: Path, capsys) -> None:
    """Issue #48: --max-memory did not apply to msf-inspect on a run folder (msf-run refuses
    the same headers up front). A 3000 x 3000 map needs about 650 MB to inspect."""
    import tifffile

    from msfnet import Model
    from msfnet.runtime.cli.inspect import main as inspect_main
    from msfnet.runtime.results.maps import MapOptions

    run = tmp_path / "run"
    Model.least_squares(maps=MapOptions(maps=("height",)))(sphere_stack(n=6, h=24, w=24)).save(run)
    (run / "local_shape.tif").unlink()
    with tifffile.TiffWriter(run / "local_shape.tif") as tw:
        tw.write(shape=(3000, 3000), dtype=np.float32)  # declared, never written: sparse
    out = tmp_path / "v"
    argv = [str(run), "--depth", "0.1", "-o", str(out), "--max-memory", "500"]
    assert inspect_main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "above --max-memory 500 MB" in err[0], err
    assert not out.exists()
