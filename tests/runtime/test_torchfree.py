"""The runtime imports and runs with torch absent (an import blocker in a fresh interpreter)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
from _runtime_helpers import sphere_stack

SCRIPT = r"""
import importlib.abc, sys

class BlockTorch(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "torch" or name.startswith("torch."):
            raise ImportError(f"blocked for this test: {name}")
        return None

sys.meta_path.insert(0, BlockTorch())
try:
    import torch  # noqa: F401
    raise SystemExit("blocker failed")
except ImportError:
    pass

import importlib
import pkgutil
import msfnet.runtime
for info in pkgutil.walk_packages(msfnet.runtime.__path__, "msfnet.runtime."):
    importlib.import_module(info.name)  # every runtime module, present and future
import msfnet
msfnet.Model, msfnet.load_stack
from msfnet.runtime.cli.run import main

npz, onnx, out = sys.argv[1:4]
assert main(["--onnx", onnx, npz, "-o", out + "/msf", "--tile", "48", "--threads", "1"]) == 0
assert main(["--method", "l2", npz, "-o", out + "/l2"]) == 0
assert not any(m == "torch" or m.startswith("torch.") for m in sys.modules)
print("TORCH-FREE OK")
"""


def test_runtime_without_torch(random_onnx: Path, tmp_path: Path) -> None:
    ref = sphere_stack(n=5, h=28, w=32)
    npz = tmp_path / "sphere.npz"
    np.savez(
        npz,
        images=ref.images,
        lights=ref.lights,
        intensities=ref.intensities,
        mask=ref.mask,
        normals=ref.normals_gt,
    )
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(npz), str(random_onnx), str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "TORCH-FREE OK" in proc.stdout
    assert (tmp_path / "msf" / "normals.npy").is_file()
    assert (tmp_path / "l2" / "metrics.json").is_file()
