"""DiLiGenT ball (real data, slow): least-squares normals -> height.tif is a sphere of the
mask's radius."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from msfnet.runtime.infer.least_squares import least_squares_normals
from msfnet.runtime.results.maps import MapOptions, stack_maps, write_maps
from msfnet.runtime.results.maps.registered import read_tiff
from msfnet.runtime.stack import load_stack

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def ball(ball_dir: Path):
    stack = load_stack(ball_dir)
    return stack, least_squares_normals(stack)


def fit_sphere(height: np.ndarray, mask: np.ndarray) -> tuple[float, np.ndarray]:
    """Algebraic least-squares sphere through the points (col, -row, height): radius, centre."""
    rows, cols = np.nonzero(mask)
    x, y, z = cols.astype(float), -rows.astype(float), height[mask].astype(float)
    a = np.stack([2 * x, 2 * y, 2 * z, np.ones_like(x)], axis=1)
    sol, *_ = np.linalg.lstsq(a, x * x + y * y + z * z, rcond=None)
    centre = sol[:3]
    return float(np.sqrt(sol[3] + centre @ centre)), centre


@pytest.mark.parametrize("method", ("fc", "poisson", "bini"))
def test_ball_height_is_a_sphere_of_the_mask_radius(ball, tmp_path: Path, method: str) -> None:
    stack, normals = ball
    maps = stack_maps(
        stack, normals, MapOptions(maps=("albedo", "height", "curvature"), integration=method)
    )
    write_maps(tmp_path, maps, report=False)
    height = read_tiff(tmp_path / "height.tif")
    mask = stack.mask
    assert np.isfinite(height[mask]).all() and np.isnan(height[~mask]).all()
    mask_radius = np.sqrt(mask.sum() / np.pi)
    radius, _ = fit_sphere(height, mask)
    assert radius == pytest.approx(mask_radius, rel=0.05), (
        f"{method}: sphere radius {radius:.2f} px, mask radius {mask_radius:.2f} px"
    )
    # the mean curvature of a ball of that radius is 1/R inside
    inner = mask & np.isfinite(maps.curvature)
    assert np.median(maps.curvature[inner]) == pytest.approx(1 / mask_radius, rel=0.15)
    # the ball is uniformly painted: away from the rim (where its non-Lambertian reflectance
    # and the steep normals take over) the albedo varies little
    rows, cols = np.nonzero(mask)
    r = np.hypot(rows - rows.mean(), cols - cols.mean())
    grey = maps.albedo[mask].mean(axis=1)[r < 0.8 * mask_radius]
    spread = np.percentile(grey, 90) / np.percentile(grey, 10)
    assert spread < 1.25
