"""Curvature signs and magnitudes on a sphere, a dimple and a saddle."""

from __future__ import annotations

import numpy as np
import pytest

from msfnet.common.errors import InputError
from msfnet.runtime.results.maps.curvature import curvature_maps, masked_derivative, symmetric_range


def test_sphere_is_convex_with_mean_curvature_one_over_r(surfaces) -> None:
    radius = 30.0
    _, mask, n = surfaces["sphere_cap"](h=60, w=60, radius=radius, cap=24.0)
    c = curvature_maps(n, mask)
    inner = mask & np.isfinite(c.mean)
    assert np.all(c.mean[inner] > 0)
    assert np.median(c.mean[inner]) == pytest.approx(1 / radius, rel=0.03)
    assert np.median(c.gaussian[inner]) == pytest.approx(1 / radius**2, rel=0.06)
    assert np.median(c.shape_index[inner]) == pytest.approx(1.0, abs=0.02)  # a cap
    assert np.isnan(c.mean[~mask]).all() and c.mean.dtype == np.float32


def test_dimple_is_concave(surfaces) -> None:
    _, mask, n = surfaces["sphere_cap"](h=40, w=40, radius=25.0, cap=18.0)
    n_cup = n * np.array([-1.0, -1.0, 1.0])  # z -> -z: the inside of the sphere
    c = curvature_maps(n_cup, mask)
    assert np.median(c.mean[mask]) == pytest.approx(-1 / 25.0, rel=0.03)
    assert np.median(c.shape_index[mask]) == pytest.approx(-1.0, abs=0.02)


def test_saddle_has_mixed_signs_and_zero_mean(surfaces) -> None:
    a = 0.01
    _, mask, n = surfaces["saddle"](a=a)
    c = curvature_maps(n, mask, sigma=0.0)
    h, w = mask.shape
    centre = (slice(h // 2 - 3, h // 2 + 3), slice(w // 2 - 3, w // 2 + 3))
    assert np.abs(c.mean[centre]).max() < 0.05 * 2 * a  # |H| << principal curvatures 2a
    assert np.median(c.gaussian[centre]) == pytest.approx(-((2 * a) ** 2), rel=0.05)
    assert np.abs(c.shape_index[centre]).max() < 0.05  # saddle: shape index 0
    # away from the centre the mean curvature takes both signs (the saddle's two valleys)
    assert (c.mean[mask] > 1e-4).any() and (c.mean[mask] < -1e-4).any()


def test_curvature_robust_range_and_edge_cases() -> None:
    vals = np.concatenate([np.linspace(-1, 1, 99), [50.0]])
    assert symmetric_range(vals, 95) < 2.0  # one outlier does not set the scale
    assert symmetric_range(np.array([np.nan])) > 0
    f = np.arange(12.0).reshape(3, 4)
    valid = np.ones((3, 4), bool)
    valid[:, 2] = False
    d = masked_derivative(f, valid, axis=1)
    assert d[0, 0] == 1.0 and d[0, 1] == 1.0 and d[0, 3] == 0.0  # one-sided, then no neighbour
    one = np.zeros((5, 5), bool)
    one[2, 2] = True
    n = np.zeros((5, 5, 3))
    n[2, 2] = (0, 0, 1)
    c = curvature_maps(n, one)
    assert c.mean[2, 2] == 0 and np.isnan(c.shape_index[2, 2])  # planar: shape undefined
    empty = curvature_maps(n, np.zeros((5, 5), bool))
    assert np.isnan(empty.mean).all()
    bad = n.copy()
    bad[2, 2] = np.inf
    with pytest.raises(InputError):
        curvature_maps(bad, one)


def test_an_empty_map_gives_empty_maps() -> None:
    # OpenCV's blur and labelling refuse empty images: the maps of a 0 x N crop are empty
    from msfnet.runtime.results.maps.integrate import integrate_normals

    normals, mask = np.zeros((0, 5, 3)), np.zeros((0, 5), bool)
    assert integrate_normals(normals, mask).height.shape == (0, 5)
    assert curvature_maps(normals, mask).mean.shape == (0, 5)
