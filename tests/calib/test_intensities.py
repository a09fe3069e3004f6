"""Light intensities from a matte white sphere or plane, with ambient subtraction."""

from __future__ import annotations

import numpy as np

from msfnet.calib import cli
from msfnet.calib.intensities import estimate_intensities, target_normals
from msfnet.calib.sphere import fit_circles_from_mask
from msfnet.common.imageio import write_png
from msfnet.runtime.stack import read_vectors
from msfnet.synth import spheres as S


def _truth(n: int, rng) -> np.ndarray:
    e = rng.uniform(0.5, 1.5, (n, 3))
    return e / e.mean()


def test_matte_sphere_with_ambient(rng, tmp_path):
    lights = S.ring_lights(8, (10, 50), seed=2)
    truth = _truth(8, rng)
    scene = S.mirror_scene(150, 140, 60, kind="matte")
    amb = 3.0  # strong ambient: without subtraction the ratios come out wrong
    imgs = np.stack(
        [
            S.expose(S.render(scene, l_, e, ambient=amb), 0.5, 16, 2.0, np.random.default_rng(i))
            for i, (l_, e) in enumerate(zip(lights, truth, strict=True))
        ]
    )
    dark = S.expose(S.render(scene, None, ambient=amb), 0.5, 16, 2.0, np.random.default_rng(99))
    mask = S.sphere_masks(scene)[0]
    normals, valid = target_normals(mask.shape, circle=fit_circles_from_mask(mask)[0])
    est, warn = estimate_intensities(imgs, lights, normals, valid, ambient=dark)
    rel = np.abs(est / truth - 1)
    print(f"matte sphere intensities: max relative error {rel.max():.4f}")
    assert rel.max() < 0.01 and warn == []
    est_no_amb, _ = estimate_intensities(imgs, lights, normals, valid)
    assert np.abs(est_no_amb / truth - 1).max() > 0.02  # the dark frame matters here
    # The CLI: images + auto-found dark frame and mask in one folder.
    folder = tmp_path / "white"
    folder.mkdir()
    for i, im in enumerate(imgs):
        write_png(folder / f"w.{i}.png", im)
    write_png(folder / "dark.png", dark)
    write_png(folder / "sphere_mask.png", mask.astype(np.uint8) * 255)
    (tmp_path / "l.txt").write_text("".join(f"{a} {b} {c}\n" for a, b, c in lights))
    out = tmp_path / "light_intensities.txt"
    assert (
        cli.main(["intensities", str(folder), "--lights", str(tmp_path / "l.txt"), "-o", str(out)])
        == 0
    )
    assert np.abs(read_vectors(out, "i") / truth - 1).max() < 0.01


def test_plane_of_known_normal(rng):
    lights = S.ring_lights(6, (10, 40), seed=4)
    truth = _truth(6, rng)
    pn = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
    albedo = np.array([0.7, 0.6, 0.5])
    imgs = np.stack(
        [
            np.broadcast_to(albedo * e * max(pn @ l_, 0) * 200, (40, 50, 3))
            for l_, e in zip(lights, truth, strict=True)
        ]
    )
    normals, valid = target_normals((40, 50), plane_normal=pn)
    est, _ = estimate_intensities(imgs, lights, normals, valid, white_level=255)
    # Per-channel albedo stays in (it is the target's colour): compare per-channel ratios.
    ratio = est / truth
    assert np.allclose(ratio / ratio[0], 1, atol=1e-6)


def test_integer_images_equal_their_float_copy(rng):
    """One light at a time in float64 (no float64 copy of the stack), colour or grey: the
    intensities of the float copy."""
    lights = S.ring_lights(6, (10, 50), seed=2)
    scene = S.mirror_scene(150, 140, 60, kind="matte")
    imgs = np.stack(
        [
            S.expose(S.render(scene, l_, e), 0.5, 16, 2.0, np.random.default_rng(i))
            for i, (l_, e) in enumerate(zip(lights, _truth(6, rng), strict=True))
        ]
    )
    assert imgs.dtype == np.uint16
    mask = S.sphere_masks(scene)[0]
    normals, valid = target_normals(mask.shape, circle=fit_circles_from_mask(mask)[0])
    for stack in (imgs, imgs[..., 1]):  # RGB, grey
        got, _ = estimate_intensities(stack, lights, normals, valid)
        want, _ = estimate_intensities(
            stack.astype(np.float64), lights, normals, valid, white_level=65535.0
        )
        np.testing.assert_array_equal(got, want)


def _matte(n: int = 6) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    lights = S.ring_lights(n, (10, 50), seed=2)
    scene = S.mirror_scene(120, 110, 45, kind="matte")
    imgs = np.stack(
        [
            S.expose(S.render(scene, l_), 0.5, 16, 2.0, np.random.default_rng(i))
            for i, l_ in enumerate(lights)
        ]
    )
    mask = S.sphere_masks(scene)[0]
    normals, valid = target_normals(mask.shape, circle=fit_circles_from_mask(mask)[0])
    return imgs, lights, normals, valid


def test_a_black_image_is_not_blamed_on_an_ambient_frame() -> None:
    """A black image, with no ambient frame at all, was "ambient frame brighter than the lit
    image?"; now the light is named and the image called black."""
    import pytest

    from msfnet.common.errors import InputError

    imgs, lights, normals, valid = _matte()
    imgs[3] = 0
    with pytest.raises(InputError) as exc:
        estimate_intensities(imgs, lights, normals, valid)
    message = str(exc.value)
    assert "image 4" in message and "black" in message and "ambient" not in message, message


def test_a_saturated_target_is_not_called_under_exposed() -> None:
    import pytest

    from msfnet.common.errors import InputError

    imgs, lights, normals, valid = _matte()
    imgs[1] = np.iinfo(imgs.dtype).max
    with pytest.raises(InputError, match=r"image 2: the lit target is saturated .*lower the exp"):
        estimate_intensities(imgs, lights, normals, valid)
