"""Random height-field shapes: a silhouette, a base profile and surface detail.

Every shape is a height field z(x, y) over the image plane (x right, y up, both in [-1, 1];
row 0 is the top of the image), with an object mask. Normals follow from the gradient:
n = normalise(-dz/dx, -dz/dy, 1). Heights are in the same units as x and y.
"""

from __future__ import annotations

import numpy as np

SHAPES = ("sphere", "blob", "bumps", "creases", "sculpted", "relief")
DEFAULT_MAX_DEPTH = 1.2  # dome height / radius drawn from [0.5, this] (see make_shape)


def grid(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre coordinates (x right, y up) in [-1, 1], each (size, size) float64."""
    t = np.linspace(-1.0, 1.0, size)
    x, y = np.meshgrid(t, -t)  # row 0 is y = +1 (the top)
    return x, y


def fourier_noise(x: np.ndarray, y: np.ndarray, rng: np.random.Generator, terms: int,
                  fmin: float, fmax: float, slope: float = 1.5) -> np.ndarray:
    """Sum of random plane waves, amplitude ~ 1/f^slope: smooth multi-scale relief, unit-ish RMS."""
    f = np.exp(rng.uniform(np.log(fmin), np.log(fmax), terms))
    ang = rng.uniform(0, 2 * np.pi, terms)
    phase = rng.uniform(0, 2 * np.pi, terms)
    amp = f ** -slope
    amp /= np.sqrt(np.sum(amp ** 2) / 2)
    u = np.cos(ang)[:, None, None] * x + np.sin(ang)[:, None, None] * y
    return np.einsum("k,khw->hw", amp, np.cos(np.pi * f[:, None, None] * u + phase[:, None, None]))


def gaussian_bumps(x: np.ndarray, y: np.ndarray, rng: np.random.Generator, count: int,
                   amp: tuple[float, float], sigma: tuple[float, float]) -> np.ndarray:
    cx, cy = rng.uniform(-0.8, 0.8, (2, count))
    s = rng.uniform(*sigma, count)
    a = rng.uniform(*amp, count) * rng.choice([-1.0, 1.0], count, p=[0.3, 0.7])
    d2 = (x - cx[:, None, None]) ** 2 + (y - cy[:, None, None]) ** 2
    return np.einsum("k,khw->hw", a, np.exp(-d2 / (2 * s[:, None, None] ** 2)))


def creases(x: np.ndarray, y: np.ndarray, rng: np.random.Generator, count: int) -> np.ndarray:
    """Ridges and valleys: softened |distance to a line|, sharp when softness is small."""
    out = np.zeros_like(x)
    for _ in range(count):
        ang = rng.uniform(0, np.pi)
        c = rng.uniform(-0.6, 0.6)
        d = np.cos(ang) * x + np.sin(ang) * y - c
        soft = rng.uniform(0.005, 0.06)
        slope = rng.uniform(0.2, 0.8) * rng.choice([-1.0, 1.0])
        out += slope * (np.sqrt(d * d + soft * soft) - soft)
    return out


def silhouette(x: np.ndarray, y: np.ndarray, rng: np.random.Generator,
               wobble: float) -> tuple[np.ndarray, np.ndarray]:
    """Normalised radius rho (< 1 inside) of a star-shaped outline, and the local radius R."""
    theta = np.arctan2(y, x)
    r0 = rng.uniform(0.6, 0.92)
    radius = np.ones_like(x)
    for k in range(2, 6):
        radius += wobble * rng.uniform(0, 0.15) / k * np.cos(k * theta + rng.uniform(0, 2 * np.pi))
    radius *= r0
    cx, cy = rng.uniform(-0.05, 0.05, 2)
    return np.hypot(x - cx, y - cy) / radius, radius


def make_shape(kind: str, size: int, rng: np.random.Generator,
               max_depth: float = DEFAULT_MAX_DEPTH) -> tuple[np.ndarray, np.ndarray]:
    """(height (H, W) float64, mask (H, W) bool) for one random shape of ``kind``.

    ``max_depth``: the dome's height over its radius is drawn from [0.5, max_depth]; above 1 the
    sides get steeper than a sphere's, so more of the object is seen at grazing slant."""
    x, y = grid(size)
    if kind == "relief":
        # A full-frame sculpted surface (like a bas-relief or a cloth patch): no silhouette.
        z = 0.12 * fourier_noise(x, y, rng, 24, 1.0, 6.0) + 0.5 * creases(x, y, rng, 2)
        z += gaussian_bumps(x, y, rng, 6, (0.05, 0.2), (0.06, 0.25))
        return z, np.ones_like(z, bool)
    wobble = 0.0 if kind == "sphere" else 1.0
    rho, radius = silhouette(x, y, rng, wobble)
    inside = rho < 1.0
    dome = np.sqrt(np.clip(1.0 - rho ** 2, 0.0, None))
    depth = 1.0 if kind == "sphere" else rng.uniform(0.5, max_depth)
    # Scale by the mean radius, not the local one: a theta-dependent height at the centre would
    # make a cone-like singular point there.
    z = depth * float(np.median(radius[inside])) * dome
    # Detail fades out towards the outline so silhouettes stay clean.
    fade = np.clip(1.0 - rho ** 2, 0.0, None)
    if kind == "blob":
        z += fade * (0.06 * fourier_noise(x, y, rng, 8, 1.0, 3.0))
        z += fade * gaussian_bumps(x, y, rng, 3, (0.03, 0.1), (0.15, 0.35))
    elif kind == "bumps":
        z += fade * gaussian_bumps(x, y, rng, int(rng.integers(6, 20)), (0.02, 0.12),
                                   (0.04, 0.18))
    elif kind == "creases":
        z += fade * 0.5 * creases(x, y, rng, int(rng.integers(1, 4)))
    elif kind == "sculpted":
        z += fade * (0.08 * fourier_noise(x, y, rng, 32, 1.0, 10.0, slope=1.2))
        z += fade * 0.3 * creases(x, y, rng, int(rng.integers(0, 3)))
        z += fade * gaussian_bumps(x, y, rng, 5, (0.02, 0.08), (0.04, 0.12))
    elif kind != "sphere":
        raise ValueError(f"unknown shape {kind!r}; choose from {', '.join(SHAPES)}")
    # Drop the outermost pixel ring: finite differences across the outline are meaningless.
    mask = inside.copy()
    mask[1:] &= inside[:-1]
    mask[:-1] &= inside[1:]
    mask[:, 1:] &= inside[:, :-1]
    mask[:, :-1] &= inside[:, 1:]
    return np.where(inside, z, 0.0), mask


def normals_from_height(z: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Unit normals (H, W, 3) of a height field on the [-1, 1] grid (zeros outside the mask)."""
    size = z.shape[1]
    step = 2.0 / (size - 1)
    dz_drow, dz_dcol = np.gradient(z, step)
    # Rows run downwards, y upwards: dz/dy = -dz/drow.
    n = np.stack([-dz_dcol, dz_drow, np.ones_like(z)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    if mask is not None:
        n[~mask] = 0.0
    return n


def sphere_normals(size: int, radius: float = 0.9) -> tuple[np.ndarray, np.ndarray]:
    """Analytic normals and mask of a centred sphere (used by tests and simple samples)."""
    x, y = grid(size)
    r2 = (x * x + y * y) / radius ** 2
    mask = r2 < 1.0
    n = np.stack([x / radius, y / radius, np.sqrt(np.clip(1 - r2, 0, None))], axis=-1)
    n[~mask] = 0.0
    return n, mask
