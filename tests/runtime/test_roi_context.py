"""--roi with the network: the ROI is loaded with a halo of real pixels around it (the network
sees what continues past the crop, as inside an image) and every output is cut back to the ROI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from msfnet.common.errors import InputError
from msfnet.runtime.api import Model
from msfnet.runtime.evaluate.metrics import angular_error_deg
from msfnet.runtime.infer.tiling import HALO
from msfnet.runtime.stack import LoadOptions, Stack, save_stack

H, W = 96, 112
ROI = (34, 30, 44, 36)  # x, y, w, h: more than HALO from every image border
BAND = 4  # px: the crop-edge band where a plain crop draws its rim
# fp32 on ONNX Runtime on every CPU: a bf16 default (AMX) would differ by rounding alone
EXACT = {"engine": "onnxruntime", "precision": "fp32"}


def wavy_stack(n: int = 10, seed: int = 3) -> Stack:
    """A Lambertian surface that runs past every border (gentle waves, textured albedo), lit
    everywhere by upper-hemisphere lights: no background, nothing for a mask to cut."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    # height z(x, y); normal (-dz/dx, dz/dy, 1) with y up
    dzdx = 0.5 * np.cos(xx / 9.0) * np.cos(yy / 13.0)
    dzdy = -0.4 * np.sin(xx / 9.0) * np.sin(yy / 13.0)
    normals = np.stack([-dzdx, dzdy, np.ones_like(dzdx)], axis=-1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    lights = rng.normal(size=(n, 3))
    lights[:, 2] = np.abs(lights[:, 2]) + 2.0
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    albedo = 0.6 + 0.3 * rng.random((H, W, 3))
    shading = np.clip(np.einsum("hwc,nc->nhw", normals, lights), 0, None)
    images = 30000.0 * shading[..., None] * albedo[None]
    return Stack.from_arrays(
        images.astype(np.float32),
        lights.astype(np.float32),
        normals_gt=normals.astype(np.float32),
        name="wavy",
    )


@pytest.fixture(scope="module")
def wavy_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return save_stack(wavy_stack(), tmp_path_factory.mktemp("wavy") / "wavy", bit_depth=16)


def _band(shape: tuple[int, int], width: int = BAND) -> np.ndarray:
    band = np.ones(shape, bool)
    band[width:-width, width:-width] = False
    return band


def _inside(normals: np.ndarray, roi: tuple[int, int, int, int], k: int = 1) -> np.ndarray:
    x, y, w, h = roi
    return normals[y // k : y // k + h // k, x // k : x // k + w // k]


@pytest.mark.slow  # ~4 s: three network runs
def test_network_roi_with_halo_matches_the_full_image_and_a_plain_crop_does_not(
    sensitive_onnx: Path, wavy_dir: Path
) -> None:
    settings = {"detail_fusion": False, "maps": None, **EXACT}
    model = Model(sensitive_onnx, **settings)
    plain_model = Model(sensitive_onnx, edge_context=False, **settings)
    full = _inside(model(wavy_dir).normals, ROI)
    load = LoadOptions(roi=ROI)
    halo = model(wavy_dir, load)
    plain = plain_model(wavy_dir, load)
    # the outputs are the ROI's size, stack and ground truth included
    for r in (halo, plain):
        assert r.normals.shape == (ROI[3], ROI[2], 3)
        assert r.stack.shape == (ROI[3], ROI[2]) and r.stack.roi_box is None
        assert r.error_deg is not None and r.error_deg.shape == (ROI[3], ROI[2])
    assert halo.input is not None and halo.input["roi_halo"] == HALO
    assert plain.input is not None and "roi_halo" not in plain.input
    band = _band(full.shape[:2])
    err_halo = angular_error_deg(halo.normals, full)
    err_plain = angular_error_deg(plain.normals, full)
    # the halo covers the receptive field: the same numbers as the full image, up to fp32
    assert float(err_halo.max()) < 0.05
    # the plain crop sees zeros past its edges and draws a rim there
    assert float(err_plain[band].mean()) > 1.0
    assert float(err_plain[~band].mean()) < 0.5 * float(err_plain[band].mean())


def test_network_roi_with_halo_and_downscale(sensitive_onnx: Path, wavy_dir: Path) -> None:
    model = Model(sensitive_onnx, detail_fusion=False, maps=None, **EXACT)
    k = 2
    full = _inside(model(wavy_dir, LoadOptions(downscale=k)).normals, ROI, k)
    r = model(wavy_dir, LoadOptions(roi=ROI, downscale=k))
    assert r.normals.shape == (ROI[3] // k, ROI[2] // k, 3) == full.shape
    assert float(angular_error_deg(r.normals, full).max()) < 0.05


def test_default_model_outputs_and_maps_have_the_roi_size(
    sensitive_onnx: Path, wavy_dir: Path
) -> None:
    """Detail fusion and the maps run on the grown crop and are cut back with the normals."""
    r = Model(sensitive_onnx, **EXACT)(wavy_dir, LoadOptions(roi=ROI))
    assert r.normals.shape == (ROI[3], ROI[2], 3)
    assert r.maps is not None and r.maps.albedo is not None
    assert r.maps.albedo.shape[:2] == (ROI[3], ROI[2])
    assert r.stack.mask.shape == (ROI[3], ROI[2]) and r.stack.mask.all()
    # --speed balanced: the network at 2/5 of the resolution sees 2.5x as far in held pixels
    balanced = Model(sensitive_onnx, speed="balanced", maps=None, **EXACT)
    assert balanced._loading(LoadOptions(roi=ROI)).roi_halo == 50  # 2.5 x HALO
    assert balanced(wavy_dir, LoadOptions(roi=ROI)).normals.shape == (ROI[3], ROI[2], 3)


def test_least_squares_keeps_the_plain_crop(wavy_dir: Path) -> None:
    model = Model.least_squares(maps=None)
    load = LoadOptions(roi=ROI)
    assert model._loading(load) is load  # per pixel: no context to load
    full = _inside(model(wavy_dir).normals, ROI)
    r = model(wavy_dir, load)
    assert r.normals.shape == full.shape
    assert np.array_equal(r.normals, full)


def test_stream_and_an_in_memory_stack_get_the_halo_too(
    sensitive_onnx: Path, wavy_dir: Path
) -> None:
    model = Model(sensitive_onnx, detail_fusion=False, maps=None, **EXACT)
    load = LoadOptions(roi=ROI)
    ref = model(wavy_dir, load).normals
    (streamed,) = list(model.stream([wavy_dir], load, prefetch=False))
    assert np.array_equal(streamed.normals, ref)
    in_memory = model(wavy_stack(), load)
    assert in_memory.normals.shape == ref.shape
    assert float(angular_error_deg(in_memory.normals, ref).max()) < 0.05


def test_an_roi_with_no_object_in_it_is_refused(sensitive_onnx: Path, tmp_path: Path) -> None:
    stack = wavy_stack()
    mask = np.zeros((H, W), bool)
    mask[:20, :20] = True
    folder = save_stack(Stack.from_arrays(stack.images, stack.lights, mask=mask), tmp_path / "m")
    with pytest.raises(InputError, match="mask is empty"):
        Model(sensitive_onnx, maps=None, **EXACT)(folder, LoadOptions(roi=ROI))


@pytest.mark.slow  # ~6 s: the bundled network on a 512 x 340 stack
def test_bundled_model_roi_on_psm_horse_matches_the_full_image(psm_dir: Path) -> None:
    """A real object with its own mask and shadows: the halo keeps the object's mask around
    the ROI, and the grown crop starts on the full-image run's tile grid (x = 223 is not), so
    the ROI's normals are the full-image run's (a plain crop: 4.6 deg off within 4 px of its
    edges; a crop off the grid: 0.8 deg everywhere)."""
    from msfnet.runtime.api import default_model_path

    if not default_model_path().is_file():
        pytest.skip("no bundled model")
    model = Model(maps=None, detail_fusion=False, **EXACT)
    load = LoadOptions(lights=psm_dir / "lights.txt")
    roi = (223, 143, 120, 120)  # through the middle of the horse
    x, y, w, h = roi
    full = model(psm_dir / "horse", load).normals[y : y + h, x : x + w]
    r = model(psm_dir / "horse", LoadOptions(lights=psm_dir / "lights.txt", roi=roi))
    band = _band((h, w)) & r.stack.mask
    err = angular_error_deg(r.normals, full)[r.stack.mask]
    assert r.normals.shape == (h, w, 3) and band.sum() > 100
    assert float(err.max()) < 0.05


def test_msf_run_roi_writes_every_output_at_the_roi_size(
    sensitive_onnx: Path, wavy_dir: Path, tmp_path: Path
) -> None:
    from msfnet.common.imageio import read_image
    from msfnet.runtime.cli.run import main as run_main

    out = tmp_path / "out"
    args = [str(wavy_dir), "--onnx", str(sensitive_onnx), "--engine", "onnxruntime"]
    args += ["--precision", "fp32", "--roi", ",".join(map(str, ROI)), "--downscale", "2"]
    assert run_main([*args, "-o", str(out), "-q", "--no-report"]) == 0
    size = (ROI[3] // 2, ROI[2] // 2)
    assert np.load(out / "normals.npy").shape == (*size, 3)
    arrays = sorted(out.glob("*.npy")) + sorted(out.glob("*.tif*")) + sorted(out.glob("*.png"))
    # error.png and the *_view.png are figures with a colour bar, not registered maps
    pictures = [p for p in arrays if not p.name.endswith("_view.png") and p.name != "error.png"]
    assert len(pictures) > 3
    for p in pictures:
        arr = np.load(p) if p.suffix == ".npy" else read_image(p)
        assert arr.shape[:2] == size, p.name
    profile = json.loads((out / "profile.json").read_text())
    assert profile["input"]["roi"] == list(ROI) and profile["input"]["roi_halo"] == HALO
    assert (profile["height"], profile["width"]) == size


def test_a_batch_crops_each_stack_with_the_halo(
    sensitive_onnx: Path, wavy_dir: Path, tmp_path: Path
) -> None:
    from msfnet.runtime.cli.run import main as run_main

    other = save_stack(wavy_stack(seed=5), tmp_path / "other", bit_depth=16)
    out = tmp_path / "out"
    args = [str(wavy_dir), str(other), "--onnx", str(sensitive_onnx), "--engine", "onnxruntime"]
    args += ["--precision", "fp32", "--roi", ",".join(map(str, ROI)), "--no-maps"]
    assert run_main([*args, "-o", str(out), "-q", "--no-report"]) == 0
    single = Model(sensitive_onnx, maps=None, **EXACT)(wavy_dir, LoadOptions(roi=ROI))
    found = sorted(out.rglob("normals.npy"))
    assert len(found) == 2
    for p in found:
        assert np.load(p).shape == (ROI[3], ROI[2], 3)
    first = np.load(out / "wavy" / "normals.npy")
    assert float(angular_error_deg(first, single.normals).max()) < 0.05
