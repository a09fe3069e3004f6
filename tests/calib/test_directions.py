"""Mirror-sphere light directions: synthetic spheres with known lights and the real psm chrome."""

from __future__ import annotations

import shutil

import cv2
import numpy as np
import pytest

from msfnet.calib import cli
from msfnet.calib.directions import Intrinsics, diagnostic_image, estimate_directions
from msfnet.calib.sphere import fit_circles_from_images, fit_circles_from_mask
from msfnet.common.imageio import list_images, read_image, read_mask
from msfnet.runtime.evaluate.metrics import angular_error_deg
from msfnet.runtime.stack import read_vectors
from msfnet.synth import spheres as S


def render_stack(scene, lights, gain, bloom=0.0, noise=1.0):
    out = []
    for i, l_ in enumerate(lights):
        rad = S.render(scene, l_)
        if bloom:  # veiling glare around the saturated highlight
            rad = rad + bloom * cv2.GaussianBlur(rad, (0, 0), 4.0)
        out.append(S.expose(rad, gain, 8, noise, np.random.default_rng(i)))
    return np.stack(out)


def test_orthographic_saturated_with_bloom():
    lights = S.ring_lights(12, (10, 60), seed=3)
    scene = S.mirror_scene(190, 180, 80)
    imgs = render_stack(scene, lights, gain=1.0, bloom=0.3)  # highlight 50x over white
    assert (imgs == 255).sum() > 12 * 5, "the highlights should be saturated"
    circles = fit_circles_from_mask(S.sphere_masks(scene)[0])
    assert abs(circles[0].r - 80) < 0.3 and abs(circles[0].cx - 94.5) < 0.2
    res = estimate_directions([imgs], [circles])
    err = angular_error_deg(res.directions, lights)
    print(
        f"synthetic orthographic, saturated + bloom: mean {err.mean():.3f} max {err.max():.3f} deg"
    )
    assert err.max() < 0.5
    assert res.warnings == [] and np.all(res.confidence > 0.5)


def test_integer_capture_equals_its_float_copy():
    """Sphere fit, directions and the diagnostic picture read an 8-bit capture one light at a
    time as float64 (no float64 copy of the stack): the numbers of the float copy."""
    lights = S.ring_lights(6, (10, 60), seed=3)
    scene = S.mirror_scene(190, 180, 80)
    imgs = render_stack(scene, lights, gain=1.0, bloom=0.3)
    assert imgs.dtype == np.uint8
    floats = imgs.astype(np.float64)
    assert fit_circles_from_images(imgs) == fit_circles_from_images(floats)
    circles = fit_circles_from_mask(S.sphere_masks(scene)[0])
    got = estimate_directions([imgs], [circles])
    want = estimate_directions([floats], [circles], white_level=255.0)
    np.testing.assert_array_equal(got.directions, want.directions)
    np.testing.assert_array_equal(
        diagnostic_image(imgs, circles, got.estimates),
        diagnostic_image(floats, circles, want.estimates),
    )


def test_perspective_unsaturated():
    lights = S.ring_lights(10, (10, 55), seed=5)
    scene = S.mirror_scene(180, 160, 60, focal=250.0)
    imgs = render_stack(scene, lights, gain=0.02)  # peak just at the white level
    circles = fit_circles_from_mask(S.sphere_masks(scene)[0])
    intr = Intrinsics(250.0, 250.0, *scene.camera.centre)
    err = angular_error_deg(estimate_directions([imgs], [circles], intr).directions, lights)
    print(f"synthetic perspective f=250: mean {err.mean():.3f} max {err.max():.3f} deg")
    assert err.max() < 0.5
    # Ignoring the perspective is measurably worse (this is what --focal is for).
    err_ortho = angular_error_deg(estimate_directions([imgs], [circles]).directions, lights)
    assert err_ortho.mean() > err.mean() + 0.5


def test_two_spheres_two_captures_averaged_and_rim_warning():
    lights = np.vstack([S.ring_lights(6, (15, 50), seed=7), [[0.0, np.sin(3.0), np.cos(3.0)]]])
    scene = S.mirror_scene(220, 120, 48, centres_px=[(55.3, 60.0), (160.0, 58.6)])
    imgs = render_stack(scene, lights, gain=1.0)
    circles = fit_circles_from_mask(np.any(S.sphere_masks(scene), axis=0))
    assert len(circles) == 2
    res = estimate_directions(
        [imgs, imgs[:, :, ::-1][:, :, :, ::-1]],
        [circles, [type(c)(219 - c.cx, c.cy, c.r) for c in circles]],
    )
    # The mirrored capture gives mirrored directions: averaging them must collapse x to ~0.
    assert np.all(np.abs(res.directions[:, 0]) < 0.02)
    assert len(res.estimates[0]) == 4
    res = estimate_directions([imgs], [circles])
    err = angular_error_deg(res.directions[:6], lights[:6])
    assert err.max() < 0.6 and res.spread_deg[:6].max() < 0.6
    # Light 7 is 172 deg off-axis (behind the sphere): its highlight sits on the rim,
    # so it is warned about and gets a low confidence.
    assert any("image 7" in w and "rim" in w for w in res.warnings)
    assert res.confidence[6] < 0.3 < res.confidence[:6].min()


def test_missing_highlight_is_an_error():
    from msfnet.common.errors import InputError

    scene = S.mirror_scene(120, 120, 40)
    imgs = np.stack(
        [S.expose(S.render(scene, l_), 1.0) for l_ in S.ring_lights(3, seed=1)]
        + [S.expose(S.render(scene, None), 1.0)]
    )
    with pytest.raises(InputError, match="image 4"):
        estimate_directions(
            [imgs],
            fit_circles_from_mask(S.sphere_masks(scene)[0])
            and [fit_circles_from_mask(S.sphere_masks(scene)[0])],
        )


def test_psm_chrome_against_lights_txt(psm_dir):
    chrome = psm_dir / "chrome"
    imgs = np.stack([read_image(p) for p in list_images(chrome)])
    ref = read_vectors(psm_dir / "lights.txt", "lights")
    mask_circles = fit_circles_from_mask(read_mask(chrome / "chrome.mask.tga"))
    c = mask_circles[0]
    assert abs(c.cx - 253.27) < 0.3 and abs(c.cy - 147.77) < 0.3 and abs(c.r - 119.5) < 0.5
    err = angular_error_deg(estimate_directions([imgs], [mask_circles]).directions, ref)
    print(f"psmImages chrome (mask circle): mean {err.mean():.2f} max {err.max():.2f} deg")
    assert err.mean() < 3.5 and err.max() < 9.0
    auto = fit_circles_from_images(imgs)[0]
    assert np.hypot(auto.cx - c.cx, auto.cy - c.cy) < 2.5 and abs(auto.r - c.r) < 1.5
    err_auto = angular_error_deg(estimate_directions([imgs], [[auto]]).directions, ref)
    print(
        f"psmImages chrome (circle fitted from images): mean {err_auto.mean():.2f} "
        f"max {err_auto.max():.2f} deg"
    )
    assert err_auto.mean() < 3.5


def test_cli_directions_on_psm(psm_dir, tmp_path, capsys):
    folder = tmp_path / "chrome"
    shutil.copytree(psm_dir / "chrome", folder)  # the mask is found by its name
    out = tmp_path / "light_directions.txt"
    assert cli.main(["directions", str(folder), "-o", str(out)]) == 0
    rows = read_vectors(out, "lights")
    assert rows.shape == (12, 3) and np.allclose(np.linalg.norm(rows, axis=1), 1, atol=1e-5)
    assert angular_error_deg(rows, read_vectors(psm_dir / "lights.txt", "l")).mean() < 3.5
    assert (tmp_path / "light_directions_diagnostic.png").is_file()
    assert "chrome.mask.tga" in capsys.readouterr().out
    assert cli.main(["directions", str(folder), "-o", str(out)]) == 2  # no silent clobber
    assert "--overwrite" in capsys.readouterr().err
    assert cli.main(["directions", str(tmp_path / "nope"), "-o", str(tmp_path / "x.txt")]) == 2


@pytest.mark.parametrize(
    ("fill", "cause", "not_said"),
    [(0, "black", "saturated"), (255, "saturated", "too low")],
)
def test_a_frame_without_highlight_is_told_why(fill: int, cause: str, not_said: str) -> None:
    """A saturated chrome image was said to have "exposure too low"; a black one is said to
    be black."""
    from msfnet.common.errors import InputError

    scene = S.mirror_scene(120, 120, 40)
    imgs = render_stack(scene, S.ring_lights(4, seed=1), gain=1.0)
    imgs[2] = fill
    circles = [fit_circles_from_mask(S.sphere_masks(scene)[0])]
    with pytest.raises(InputError, match="image 3") as exc:
        estimate_directions([imgs], circles)
    assert cause in str(exc.value) and not_said not in str(exc.value), str(exc.value)


def test_two_spheres_asked_of_a_one_sphere_capture_are_refused(tmp_path) -> None:
    """``--spheres 2`` on one sphere took Hough's circle around it, mostly outside the
    picture, and averaged its estimates in (9 deg off, exit 0)."""
    from msfnet.common.errors import InputError

    scene = S.mirror_scene(256, 200, 70)
    lights = S.ring_lights(8, (15, 55), seed=3)
    body = S.sphere_masks(scene)[0][None, :, :, None] * 40  # the sphere's dull reflection
    imgs = np.clip(render_stack(scene, lights, gain=1.0) + body, 0, 255).astype(np.uint8)
    (one,) = fit_circles_from_images(imgs, 1)
    assert abs(one.r - 70) < 2
    with pytest.raises(InputError, match="found only 1 sphere in the images, not 2"):
        fit_circles_from_images(imgs, 2, source=tmp_path)
