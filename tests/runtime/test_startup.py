"""Start-up of the Python API on an edge box: `from msfnet import Model` and `Model()` load only
what running the network needs. An inline station restarts processes, so each is meant to take
well under a second (measured in the README's Python API section); the bounds here are generous
for a loaded CI machine, and the module checks are the real guard: SciPy, matplotlib, tqdm and
plyfile are imported only when a map, a picture or a progress bar is made."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

# never needed to import the API or to open the network
LAZY = ("scipy", "matplotlib", "tqdm", "plyfile", "torch", "ray", "psutil")

SCRIPT = r"""
import json, sys, time
start = time.perf_counter()
from msfnet import Model
imported = time.perf_counter()
after_import = sorted({m.split(".")[0] for m in sys.modules})
model = Model()
opened = time.perf_counter()
print(json.dumps({
    "import_s": imported - start,
    "model_s": opened - imported,
    "after_import": after_import,
    "after_model": sorted({m.split(".")[0] for m in sys.modules}),
    "engine": model.describe().engine,
}))
"""


def _importers(stderr: str, module: str) -> str:
    """The -X importtime lines around the first import of ``module``: who pulled it in."""
    lines = stderr.splitlines()
    first = next((i for i, ln in enumerate(lines) if ln.rstrip().endswith(f"| {module}")), None)
    if first is None:
        first = next((i for i, ln in enumerate(lines) if f" {module}" in ln), 0)
    return "\n".join(lines[first : first + 40])


@pytest.mark.slow  # ~3 s: a fresh interpreter that opens the bundled model
def test_import_and_model_load_only_what_they_need() -> None:
    proc = subprocess.run(
        [sys.executable, "-X", "importtime", "-c", SCRIPT],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    for stage in ("after_import", "after_model"):
        loaded = [m for m in LAZY if m in got[stage]]
        assert not loaded, f"{stage}: {loaded}\n" + _importers(proc.stderr, loaded[0])
    # onnxruntime is what Model() needs; OpenVINO only once Model() chose it
    assert "openvino" not in got["after_import"]
    # generous: typically 0.3-0.6 s and 0.5-1.5 s on a 2-core CI machine (README)
    assert got["import_s"] < 5.0, got
    assert got["model_s"] < 10.0, got


def test_an_openvino_run_imports_neither_onnx_runtime_nor_tqdm(tmp_path) -> None:
    """Every run pays its imports (a station runs msf-run per part): ONNX Runtime (~30 ms) is
    imported when it runs the model, tqdm (~17 ms) when a bar is drawn. A whole msf-run on
    OpenVINO (open, infer, fuse, write; no terminal: no bar) imports neither, nor OpenVINO's
    telemetry (a network call from a forked child) and converter (~100 ms), nor
    importlib.metadata (~55 ms, for the version) or psutil (~25 ms, for the memory in use)."""
    pytest.importorskip("openvino")
    from _runtime_helpers import sphere_stack, tiny_msfnet_onnx

    from msfnet.runtime.stack import save_stack

    model = tiny_msfnet_onnx(tmp_path / "tiny.onnx")
    stack = save_stack(sphere_stack(n=6), tmp_path / "sphere")
    args = [str(stack), "--onnx", str(model), "--engine", "openvino", "-o", str(tmp_path / "o")]
    code = (
        "import sys; from msfnet.runtime.cli.run import main; "
        f"rc = main({args!r} + ['--no-maps', '--no-report']); "
        "print(rc, sorted(m for m in ('onnxruntime', 'tqdm', 'openvino_telemetry', "
        "'openvino.tools.ovc', 'importlib.metadata', 'psutil') if m in sys.modules))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().splitlines()[-1] == "0 []", done.stdout[-2000:]
    assert (tmp_path / "o" / "normals.npy").is_file()


def test_a_run_with_its_maps_does_not_import_scipy_ndimage(tmp_path) -> None:
    """SciPy's ndimage costs a fresh process 0.06 s: the maps label the mask's components and
    smooth the normals with OpenCV, which every run has loaded already."""
    from _runtime_helpers import sphere_stack, tiny_msfnet_onnx

    from msfnet.runtime.stack import save_stack

    model = tiny_msfnet_onnx(tmp_path / "tiny.onnx")
    stack = save_stack(sphere_stack(n=6), tmp_path / "sphere")
    args = [str(stack), "--onnx", str(model), "-o", str(tmp_path / "o")]
    code = (
        "import sys; from msfnet.runtime.cli.run import main; "
        f"rc = main({args!r}); "
        "print(rc, 'scipy.ndimage' in sys.modules, 'scipy.sparse' in sys.modules)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    # scipy.sparse proves the maps ran (the height's solver)
    assert done.stdout.strip().splitlines()[-1] == "0 False True", done.stdout[-2000:]
    assert (tmp_path / "o" / "curvature.tif").is_file()
