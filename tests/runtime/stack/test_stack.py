"""Stack loaders (DiLiGenT folder, generic folder + lights.json, npz, psmImages TGA) and l2."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from _runtime_helpers import sphere_stack

from msfnet.common.errors import InputError
from msfnet.common.imageio import read_mask
from msfnet.runtime.evaluate.metrics import angular_error_deg
from msfnet.runtime.infer.least_squares import least_squares_normals
from msfnet.runtime.stack import load_stack


def test_diligent_folder(ball_dir: Path) -> None:
    s = load_stack(ball_dir, select="21-96")
    assert s.num_lights == 76 and s.shape == (512, 612)
    assert s.filenames[0] == "021.png"
    assert int(s.mask.sum()) == 15791  # RGB mask, > 127
    assert s.normals_gt is not None and s.normals_gt.shape == (512, 612, 3)
    assert s.images.dtype == np.uint16 and s.images.max() == 65535  # 16 bits, as decoded
    np.testing.assert_allclose(np.linalg.norm(s.lights, axis=1), 1.0, atol=1e-6)


def test_generic_folder_with_lights_json(tmp_path: Path) -> None:
    ref = sphere_stack(n=5)
    folder = tmp_path / "generic"
    folder.mkdir()
    for i, img in enumerate(ref.images):  # 8-bit, names that only sort right naturally
        cv2.imwrite(
            str(folder / f"shot_{i * 5}.png"),
            np.clip(img / 256, 0, 255).astype(np.uint8)[:, :, ::-1],
        )
    (folder / "lights.json").write_text(json.dumps({"lights": ref.lights.tolist()}))
    cv2.imwrite(str(folder / "object_mask.png"), ref.mask.astype(np.uint8) * 200)
    s = load_stack(folder)
    assert s.filenames == ["shot_0.png", "shot_5.png", "shot_10.png", "shot_15.png", "shot_20.png"]
    np.testing.assert_allclose(s.lights, ref.lights, atol=1e-6)
    np.testing.assert_array_equal(s.mask, ref.mask)
    np.testing.assert_array_equal(s.intensities, 1.0)  # no intensities file
    assert s.images.dtype == np.uint8  # held as decoded (no value-changing option)
    np.testing.assert_array_equal(
        s.images[2], np.clip(ref.images[2] / 256, 0, 255).astype(np.uint8)
    )


def test_npz_stack_and_exact_least_squares(tmp_path: Path) -> None:
    ref = sphere_stack(n=10)
    path = tmp_path / "sphere.npz"
    np.savez(
        path,
        images=ref.images,
        lights=ref.lights,
        intensities=ref.intensities,
        mask=ref.mask,
        normals=ref.normals_gt,
    )
    s = load_stack(path)
    assert s.name == "sphere" and s.num_lights == 10 and s.normals_gt is not None
    n = least_squares_normals(s)
    lit = s.mask & np.all(np.einsum("hwc,nc->nhw", ref.normals_gt, ref.lights) > 0, axis=0)
    assert lit.sum() > 200
    assert angular_error_deg(n[lit], ref.normals_gt[lit]).max() < 0.01  # Lambertian: exact
    assert np.all(n[~s.mask] == 0)
    # trimming the darkest lights removes attached-shadow bias at the rim
    rim = s.mask & ~lit
    plain = angular_error_deg(n[rim], ref.normals_gt[rim]).mean()
    trimmed = least_squares_normals(s, trim_shadows=0.3)
    assert angular_error_deg(trimmed[rim], ref.normals_gt[rim]).mean() < plain
    np.savez(tmp_path / "bad.npz", images=ref.images)
    with pytest.raises(InputError, match="'lights'"):
        load_stack(tmp_path / "bad.npz")


def test_psm_tga_folder(psm_dir: Path) -> None:
    s = load_stack(psm_dir / "cat", lights=psm_dir / "lights.txt")  # count line "12" first
    assert s.num_lights == 12 and s.shape == (340, 512)
    assert s.filenames[:3] == ["cat.0.tga", "cat.1.tga", "cat.2.tga"]
    assert s.filenames[-2:] == ["cat.10.tga", "cat.11.tga"]  # natural order, not cat.1, cat.10
    first = [float(v) for v in (psm_dir / "lights.txt").read_text().split()[1:4]]
    np.testing.assert_allclose(s.lights[0], np.array(first) / np.linalg.norm(first), atol=1e-6)
    np.testing.assert_array_equal(s.mask, read_mask(psm_dir / "cat" / "cat.mask.tga"))
    assert 0 < s.mask.mean() < 1 and s.normals_gt is None
    n = least_squares_normals(s)
    assert np.all(n[~s.mask] == 0) and np.median(n[s.mask][:, 2]) > 0.5  # faces the camera
