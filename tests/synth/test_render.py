"""The synthetic renderer: determinism, physical sanity, and the msf-synth CLI."""

from __future__ import annotations

import numpy as np
import pytest

from msfnet.runtime.evaluate.metrics import angular_error_deg
from msfnet.runtime.stack import load_stack
from msfnet.synth import RenderOptions, render_set, render_stack
from msfnet.synth.cli import main as synth_main
from msfnet.synth.lights import cone_lights
from msfnet.synth.render import cast_shadow_mask
from msfnet.synth.shapes import SHAPES, make_shape, normals_from_height


def test_same_seed_same_stack_and_set_independent_of_count():
    opts = RenderOptions(size=32, lights=8)
    a, b = render_stack(7, opts), render_stack(7, opts)
    np.testing.assert_array_equal(a.images, b.images)
    np.testing.assert_array_equal(a.normals_gt, b.normals_gt)
    assert not np.array_equal(a.images, render_stack(8, opts).images)
    first3 = [s.images for s in render_set(3, 3, opts)]
    last = next(render_set(3, 1, opts, start=2)).images
    np.testing.assert_array_equal(first3[2], last)


@pytest.mark.parametrize("shape", SHAPES)
def test_every_shape_gives_a_valid_stack(shape):
    s = render_stack(1, RenderOptions(size=48, lights=12), shape=shape)
    assert s.images.shape == (12, 48, 48, 3) and s.images.dtype == np.float32
    assert 0.15 < s.mask.mean() <= 1.0
    n = s.normals_gt[s.mask]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    assert np.all(n[:, 2] > 0)  # a height field only shows normals facing the camera
    assert s.images.min() >= 0 and s.images.max() <= 65535
    np.testing.assert_allclose(np.linalg.norm(s.lights, axis=1), 1.0, atol=1e-5)
    assert np.all(s.lights[:, 2] > np.cos(np.radians(66)))  # rig lights in front, <= 65 deg


def _ls_normals(images, lights, mask):
    grey = images.mean(axis=3)[:, mask]  # (N, P)
    b = np.linalg.lstsq(lights.astype(np.float64), grey, rcond=None)[0].T
    return b / np.linalg.norm(b, axis=1, keepdims=True)


def test_lambertian_sphere_solved_by_least_squares_under_1_degree():
    opts = RenderOptions(
        size=64,
        lights=20,
        shapes=("sphere",),
        materials=("diffuse",),
        max_materials=1,
        cast_shadows=False,
        noise=False,
    )
    lights = cone_lights(20, np.random.default_rng(0), 35.0)
    s = render_stack(3, opts, lights=lights, intensities=np.ones((20, 3), np.float32))
    # Pixels lit by every light (no attached shadow): the Lambertian model is exact there.
    lit = s.mask & np.all(np.einsum("hwc,kc->khw", s.normals_gt, lights) > 0.02, axis=0)
    assert lit.sum() > 500
    n = _ls_normals(s.images / s.intensities[:, None, None, :], lights, lit)
    err = angular_error_deg(n, s.normals_gt[lit])
    assert err.mean() < 0.2 and err.max() < 1.0


def test_height_field_normals_match_a_plane():
    size = 32
    t = np.linspace(-1, 1, size)
    x, y = np.meshgrid(t, -t)
    n = normals_from_height(0.3 * x - 0.5 * y)
    expect = np.array([-0.3, 0.5, 1.0]) / np.linalg.norm([-0.3, 0.5, 1.0])
    np.testing.assert_allclose(
        n.reshape(-1, 3), np.broadcast_to(expect, (size * size, 3)), atol=1e-9
    )


def test_cast_shadow_behind_a_tall_block():
    size = 40
    h = np.zeros((size, size))
    h[18:22, 18:22] = 1.0  # a tall pillar in the middle of a flat floor
    mask = np.ones((size, size), bool)
    light = np.array([[np.sin(np.radians(45)), 0.0, np.cos(np.radians(45))]], np.float32)
    lit = cast_shadow_mask(h, mask, light)[0]
    # Light comes from +x (the right): the floor just left of the pillar is dark, right is lit.
    assert lit[20, 10:17].max() == 0.0
    assert lit[20, 23:].min() == 1.0
    assert lit[5, :].min() == 1.0  # far from the pillar's rows: lit
    overhead = cast_shadow_mask(h, mask, np.array([[0, 0, 1.0]], np.float32))[0]
    assert overhead.min() == 1.0


def test_specular_material_is_not_lambertian():
    opts = RenderOptions(
        size=64,
        lights=24,
        shapes=("sphere",),
        materials=("metal",),
        max_materials=1,
        cast_shadows=False,
        noise=False,
    )
    lights = cone_lights(24, np.random.default_rng(1), 40.0)
    s = render_stack(5, opts, lights=lights, intensities=np.ones((24, 3), np.float32))
    lit = s.mask & np.all(np.einsum("hwc,kc->khw", s.normals_gt, lights) > 0.02, axis=0)
    err = angular_error_deg(_ls_normals(s.images, lights, lit), s.normals_gt[lit])
    assert err.mean() > 2.0  # least squares is biased by the highlights


def test_shapes_mask_excludes_outline_ring():
    _z, mask = make_shape("blob", 48, np.random.default_rng(0))
    assert not mask[0].any() and not mask[-1].any()


def test_cli_writes_readable_diligent_layout(tmp_path, capsys):
    out = tmp_path / "syn"
    assert (
        synth_main([str(out), "--objects", "2", "--lights", "6", "--size", "24", "--seed", "4"])
        == 0
    )
    names = (out / "objects.txt").read_text().split()
    assert len(names) == 2
    s = load_stack(out / names[1])
    ref = next(render_set(4, 1, RenderOptions(size=24, lights=6), start=1, shapes=SHAPES))
    assert s.num_lights == 6 and s.normals_gt is not None
    np.testing.assert_allclose(s.images, np.rint(ref.images), atol=0.5)
    np.testing.assert_allclose(s.normals_gt, ref.normals_gt, atol=1e-6)
    # refuses to clobber, one-line error, exit 2
    capsys.readouterr()
    assert synth_main([str(out), "--objects", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "msf-synth: error:" in err[0] and "--overwrite" in err[0]
    assert synth_main([str(tmp_path / "x"), "--shapes", "cube"]) == 2
