"""Render photometric stacks with ground truth: shape + materials + rig -> ``Stack``.

Everything is vectorised over lights and pixels (numpy). Deterministic: one object is fully
defined by its seed, so object ``i`` of a set seeded ``s`` uses ``default_rng([s, i])`` and does
not depend on how many objects are rendered.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from msfnet.runtime.stack import Stack

from .lights import rig_intensities, rig_lights
from .materials import KINDS, material_map, shade
from .shapes import DEFAULT_MAX_DEPTH, SHAPES, make_shape, normals_from_height

FULL_SCALE = 65535.0  # images are returned in 16-bit counts, as save_stack writes them


@dataclass(frozen=True)
class RenderOptions:
    size: int = 64
    lights: int = 32
    shapes: tuple[str, ...] = SHAPES
    shape_weights: tuple[float, ...] | None = (0.08, 0.22, 0.18, 0.17, 0.25, 0.10)
    materials: tuple[str, ...] = KINDS
    max_materials: int = 3
    cast_shadows: bool = True
    noise: bool = True  # shot + read noise and quantisation to a random bit depth (8-16)
    max_depth: float = DEFAULT_MAX_DEPTH  # domes up to this height / radius (steeper above 1)


def cast_shadow_mask(height: np.ndarray, mask: np.ndarray, lights: np.ndarray) -> np.ndarray:
    """(N, H, W) float32, 0 where the height field blocks the light, by ray marching.

    From each pixel, step towards the light in the image plane (nearest-pixel height lookups at
    growing distances) and test whether the surface rises above the ray.
    """
    size_h, size_w = height.shape
    step = 2.0 / (size_w - 1)  # grid units per pixel
    z = np.where(mask, height, -1e6).astype(np.float32).ravel()
    zmax, zmin = float(height[mask].max()), float(height[mask].min())
    lights = np.asarray(lights, np.float32)
    lxy = np.hypot(lights[:, 0], lights[:, 1])
    slanted = np.flatnonzero(lxy > 1e-3)
    lit = np.ones((len(lights), size_h, size_w), np.float32)
    if slanted.size == 0:
        return lit
    ls, lxy = lights[slanted], lxy[slanted]
    drow = (-ls[:, 1] / lxy)[:, None, None]
    dcol = (ls[:, 0] / lxy)[:, None, None]
    rise = (step * ls[:, 2] / lxy)[:, None, None]  # ray height gained per pixel travelled
    reach = min((zmax - zmin) / max(float(rise.min()), 1e-6), 2.0 * max(size_h, size_w))
    # Only object pixels need a test; work on their flat indices.
    pix = np.flatnonzero(mask.ravel())
    rows = (pix // size_w).astype(np.float32)[None]
    cols = (pix % size_w).astype(np.float32)[None]
    drow, dcol, rise = drow[:, :, 0], dcol[:, :, 0], rise[:, :, 0]  # (L, 1)
    # Bias against self-shadowing from the nearest-pixel lookup on sloped, smooth surfaces.
    base = z[pix][None] + np.float32(0.5 * step)
    blocked = np.zeros((len(ls), pix.size), bool)
    t, k = 1.0, 0
    while t <= reach:
        r = np.rint(rows + t * drow).astype(np.intp)
        c = np.rint(cols + t * dcol).astype(np.intp)
        inside = (r >= 0) & (r < size_h) & (c >= 0) & (c < size_w)
        zs = z[np.clip(r, 0, size_h - 1) * size_w + np.clip(c, 0, size_w - 1)]
        blocked |= inside & (zs > base + np.float32(t) * rise)
        k += 1
        t += 1.0 + 0.3 * k  # denser near the pixel, where small occluders matter most
    flat = lit.reshape(len(lights), -1)
    sub = flat[slanted]
    sub[:, pix] = np.where(blocked, 0.0, 1.0)
    flat[slanted] = sub
    return lit


def sensor(signal: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Linear signal in [0, 1] (of full well) -> noisy, clipped, quantised values in [0, 1]."""
    gain = rng.uniform(0.0, 2e-4)  # shot noise variance per unit signal
    read = rng.uniform(0.0, 2e-3)
    noisy = signal + rng.standard_normal(signal.shape, np.float32) * np.sqrt(
        gain * np.clip(signal, 0, None) + read * read).astype(np.float32)
    levels = float(2 ** int(rng.choice([8, 10, 12, 14, 16])) - 1)
    return np.round(np.clip(noisy, 0.0, 1.0) * levels) / levels


def render_stack(rng: np.random.Generator | int, options: RenderOptions = RenderOptions(),
                 *, shape: str | None = None, lights: np.ndarray | None = None,
                 intensities: np.ndarray | None = None, name: str = "synth") -> Stack:
    """One random object under one random rig, as a Stack with normals_gt and mask."""
    rng = np.random.default_rng(rng)
    if shape is None:
        w = options.shape_weights
        w = None if w is None or len(w) != len(options.shapes) else np.asarray(w) / np.sum(w)
        shape = options.shapes[int(rng.choice(len(options.shapes), p=w))]
    height, mask = make_shape(shape, options.size, rng, options.max_depth)
    normals = normals_from_height(height, mask).astype(np.float32)
    mat = material_map(options.size, rng, options.max_materials, options.materials)
    n = options.lights
    dirs = rig_lights(n, rng) if lights is None else np.asarray(lights, np.float32)
    ints = rig_intensities(len(dirs), rng) if intensities is None else np.asarray(
        intensities, np.float32)
    radiance = shade(normals, dirs, mat)  # (N, H, W, 3)
    if options.cast_shadows:
        radiance *= cast_shadow_mask(height, mask, dirs)[..., None]
    radiance *= ints[:, None, None, :]
    radiance[:, ~mask] = 0.0
    # Exposure: put a high percentile of the object's values at 40-100 % of full scale, so
    # bright highlights saturate now and then, as they do in real captures.
    vals = radiance[:, mask]
    ref = float(np.percentile(vals, 99.5)) if vals.size else 1.0
    signal = radiance / max(ref, 1e-8) * rng.uniform(0.4, 1.0)
    signal = sensor(signal, rng) if options.noise else np.clip(signal, 0.0, 1.0)
    images = (signal * FULL_SCALE).astype(np.float32)
    return Stack(name=f"{name}_{shape}", images=images, lights=dirs.astype(np.float32),
                 intensities=ints, mask=mask, normals_gt=normals,
                 filenames=[f"{i + 1:03d}.png" for i in range(len(dirs))]).validate()


def render_set(seed: int, count: int, options: RenderOptions = RenderOptions(),
               start: int = 0, shapes: Sequence[str] | None = None) -> Iterator[Stack]:
    """Objects ``start .. start+count-1`` of the set seeded ``seed`` (each independent)."""
    for i in range(start, start + count):
        shape = shapes[i % len(shapes)] if shapes else None
        yield render_stack(np.random.default_rng([seed, i]), options, shape=shape,
                           name=f"obj{i:04d}")
