"""Helpers for the tests: a small synthetic stack, a random-weight ONNX model, a command run
without torch."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from msfnet.runtime.stack import Stack

# The bundled checkpoint in a checkout, found without importing the model part (it needs torch)
BUNDLED_CHECKPOINT = (
    Path(__file__).resolve().parents[1]
    / "model"
    / "src"
    / "msfnet"
    / "model"
    / "weights"
    / "msfnet_default.pth"
)

# What a run with the default inspection maps writes beside the normals (results.maps and
# results.maps.registered): each map's data once, as its registered TIFF
MAP_FILES = frozenset(
    {
        "albedo.png",
        "height.png",
        "curvature.png",
        "shape_index.npy",
        "mesh.ply",
        "maps.json",
        "report.html",
        "local_shape.png",
        "gradient_p.tif",
        "gradient_q.tif",
        "height.tif",
        "local_shape.tif",
        "curvature.tif",
        "gaussian_curvature.tif",
        "albedo.tif",
    }
)


def ring_lights(n: int = 12, tilt_deg: float = 35.0) -> np.ndarray:
    """(n, 3) float32 unit directions of an LED ring ``tilt_deg`` off the camera axis."""
    k = np.arange(n)
    th = np.radians(tilt_deg)
    return np.stack(
        [
            np.sin(th) * np.cos(2 * np.pi * k / n),
            np.sin(th) * np.sin(2 * np.pi * k / n),
            np.full(n, np.cos(th)),
        ],
        axis=1,
    ).astype(np.float32)


def sphere_stack(
    n: int = 8, h: int = 36, w: int = 44, seed: int = 0, name: str = "sphere"
) -> Stack:
    """A Lambertian sphere (albedo 0.8, radius ~ 0.45 min(h, w)) under n upper-hemisphere lights."""
    rng = np.random.default_rng(seed)
    lights = rng.normal(size=(n, 3))
    lights[:, 2] = np.abs(lights[:, 2]) + 1.0
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    r = 0.45 * min(h, w)
    x, y = (xx - w / 2 + 0.5) / r, -(yy - h / 2 + 0.5) / r  # y up
    mask = x**2 + y**2 < 0.95
    normals = np.zeros((h, w, 3))
    normals[..., 0], normals[..., 1] = x, y
    normals[..., 2] = np.sqrt(np.clip(1 - x**2 - y**2, 0, None))
    normals[~mask] = 0
    ints = rng.uniform(0.5, 1.5, size=(n, 3))
    shading = np.clip(np.einsum("hwc,nc->nhw", normals, lights), 0, None)
    images = 0.8 * 40000.0 * shading[..., None] * ints[:, None, None, :]
    return Stack(
        name,
        images.astype(np.float32),
        lights.astype(np.float32),
        ints.astype(np.float32),
        mask,
        normals.astype(np.float32),
        [f"{i + 1:03d}.png" for i in range(n)],
    )


def png_stack(
    folder: Path, bit_depth: int, n: int = 8, h: int = 36, w: int = 44, seed: int = 0
) -> Path:
    """:func:`sphere_stack` written as 8- or 16-bit PNGs (DiLiGenT layout, ground truth
    included): a stack on disk whose values are integers, 8-bit ones scaled to 0..255."""
    from msfnet.runtime.stack import save_stack

    stack = sphere_stack(n, h, w, seed)
    if bit_depth == 8:
        stack = replace(stack, images=stack.images * np.float32(255 / 65535))
    return save_stack(stack, folder, bit_depth=bit_depth)


def as_float32(stack: Stack) -> Stack:
    """The same stack with float32 images: what the loaders held before integer stacks."""
    return replace(stack, images=stack.images.astype(np.float32))


def build_random_onnx(folder: Path, sensitive: bool = False, staged: bool = False) -> Path:
    """Random-weight MSF-Net (seed 0) exported to ONNX by msf-export's route (the verified
    ``fp32`` variant, or ``staged``).

    PyTorch's default init shrinks activations layer by layer, so that model's output hardly
    depends on the images (8 vs 96 ball lights: 0.001 deg apart). ``sensitive`` re-initialises
    the convolutions with He-normal weights (gain for LeakyReLU 0.1), keeping the signal alive
    through all 17 layers: tests of spatial exactness (tiling) need that to be able to fail.
    ``staged``: the same weights as a staged export (``msf-export --staged``).
    """
    torch = pytest.importorskip("torch")
    from msfnet.export.pipeline import export_variant
    from msfnet.export.variants import ExportOptions
    from msfnet.model.checkpoint import save_checkpoint
    from msfnet.model.network import MSFNet

    stem = "sensitive" if sensitive else "rand"
    onnx_path = folder / f"{stem}{'_staged' if staged else ''}.onnx"
    if onnx_path.is_file():
        return onnx_path
    torch.manual_seed(0)
    model = MSFNet()
    if sensitive:
        for module in model.modules():
            if isinstance(module, torch.nn.Conv2d | torch.nn.ConvTranspose2d):
                torch.nn.init.kaiming_normal_(module.weight, a=0.1, nonlinearity="leaky_relu")
    save_checkpoint(model, folder / f"{stem}.pth")
    export_variant(
        folder / f"{stem}.pth",
        "staged" if staged else "fp32",
        onnx_path,
        options=ExportOptions(checks=((3, 8, 8),)),
        overwrite=True,
    )
    return onnx_path


def tiny_msfnet_onnx(path: Path, **metadata: str) -> Path:
    """A cheap model that honours the msfnet contract (inputs images (B,N,3,H,W) and lights
    (B,N,3), output unit normals (B,3,H,W), msfnet metadata) without being the network: the
    per-channel mean over lights, normalised. For tests of the runtime's handling of inputs, not
    of accuracy. ``metadata`` overrides entries (e.g. ``{"msfnet.train_lights": "0"}``)."""
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper

    from msfnet.runtime.contract import model_metadata

    nodes = [
        helper.make_node("ReduceMean", ["images"], ["mean"], axes=[1], keepdims=0),
        helper.make_node("ReduceSum", ["lights"], ["lsum"], keepdims=0),
        helper.make_node("Mul", ["lsum", "zero"], ["lzero"]),  # uses lights, adds nothing
        helper.make_node("Add", ["mean", "lzero"], ["m"]),
        helper.make_node("Mul", ["m", "m"], ["sq"]),
        helper.make_node("ReduceSum", ["sq", "axis1"], ["ss"], keepdims=1),
        helper.make_node("Sqrt", ["ss"], ["norm"]),
        helper.make_node("Add", ["norm", "eps"], ["den"]),
        helper.make_node("Div", ["m", "den"], ["normals"]),
    ]
    inits = [
        helper.make_tensor("zero", TensorProto.FLOAT, [], [0.0]),
        helper.make_tensor("eps", TensorProto.FLOAT, [], [1e-12]),
        helper.make_tensor("axis1", TensorProto.INT64, [1], [1]),
    ]
    graph = helper.make_graph(
        nodes,
        "tiny_msfnet",
        [
            helper.make_tensor_value_info("images", TensorProto.FLOAT, ["B", "N", 3, "H", "W"]),
            helper.make_tensor_value_info("lights", TensorProto.FLOAT, ["B", "N", 3]),
        ],
        [helper.make_tensor_value_info("normals", TensorProto.FLOAT, ["B", 3, "H", "W"])],
        inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    meta = model_metadata(
        train_lights=32,
        checkpoint_sha256="0" * 64,
        version="test",
        static_shape=None,
        precision="fp32",
        staged=False,
    )
    meta.update(metadata)
    helper.set_model_props(model, meta)
    onnx.save(model, str(path))
    return path


def write_npz_bomb(path: Path, descr: str, shape: tuple[int, ...], zeros_mb: int = 1) -> Path:
    """An .npz whose images header claims ``shape`` of ``descr`` (e.g. '<f4') but holds only
    ``zeros_mb`` MB of zeros: a loader must refuse it from the header, without inflating it."""
    import zipfile

    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        with z.open("images.npy", "w", force_zip64=True) as f:
            np.lib.format.write_array_header_1_0(
                f, {"descr": descr, "fortran_order": False, "shape": shape}
            )
            for _ in range(zeros_mb):
                f.write(bytes(2**20))
        with z.open("lights.npy", "w") as f:
            np.save(f, np.eye(3, dtype=np.float32))
    return path


def run_without_torch(
    cli_module: str, argv: list[str], cwd: Path | None = None
) -> subprocess.CompletedProcess[str]:
    """Run ``cli_module``'s main(argv) in a fresh interpreter where ``import torch`` fails, as
    on the edge install (torch is installed here, so it is blocked, not removed)."""
    code = (
        f"import sys\nsys.modules['torch'] = None\nfrom {cli_module} import main\n"
        "sys.exit(main(sys.argv[1:]))"
    )
    return subprocess.run(
        [sys.executable, "-c", code, *argv],
        capture_output=True,
        text=True,
        check=False,
        timeout=120,
        cwd=cwd,
    )


def staging_leftovers(folder: Path) -> list[str]:
    """Staging files or folders the atomic writer left anywhere below ``folder``."""
    from msfnet.common.files import STAGING_TAG

    return sorted(p.name for p in folder.rglob("*") if STAGING_TAG in p.name)


def msfnet_folder(path: Path, names: tuple[str, ...] = ("a.txt",)) -> Path:
    """An output folder msfnet wrote (with its manifest), holding ``names``."""
    from msfnet.common.files import staged_folder

    with staged_folder(path, overwrite=True) as tmp:
        for n in names:
            (tmp / n).write_text(n)
    return path


@contextmanager
def folder_held(folder: Path, command: str) -> Iterator[subprocess.Popen[str]]:
    """Another process holding ``folder``'s lock as ``command`` (common.files.folder_lock)
    while the block runs; it lets go when the block ends. ``kill()`` it inside the block to
    leave a stale lock file behind, as kill -9 would."""
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys\n"
            "from msfnet.common.files import folder_lock\n"
            "with folder_lock(sys.argv[1], sys.argv[2]):\n"
            "    print('held', flush=True)\n"
            "    sys.stdin.readline()\n",
            str(folder),
            command,
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        yield holder
    finally:
        if holder.poll() is None:
            assert holder.stdin is not None
            holder.stdin.write("\n")
            holder.stdin.close()
        holder.wait(timeout=30)


# msf-train's validation at its smallest (one 16 px object, one thread): a test's run then
# validates in well under a second
QUICK_VALIDATION = ["--val-objects", "1", "--val-size", "16", "--threads", "1"]
