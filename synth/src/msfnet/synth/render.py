"""Render photometric stacks with ground truth: shape + materials + rig -> ``Stack``.

Everything is vectorised over lights and pixels (numpy). Deterministic: one object is fully
defined by its seed, so object ``i`` of a set seeded ``s`` uses ``default_rng([s, i])`` and does
not depend on how many objects are rendered.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from msfnet.runtime.stack import Stack

from .lights import rig_intensities, rig_lights, ring_rig
from .materials import ALL_KINDS, KINDS, material_map, shade
from .shapes import (
    ALL_SHAPES,
    DEFAULT_MAX_DEPTH,
    SHAPES,
    fine_relief,
    make_shape,
    normals_from_height,
)

FULL_SCALE = 65535.0  # images are returned in 16-bit counts, as save_stack writes them
BIT_DEPTHS = (8, 10, 12, 14, 16)
DARK_PEAK = (25.0 / 255, 43.0 / 255)  # very dark objects: brightest value, fraction of full scale
PRESETS = ("default", "hard")


@dataclass(frozen=True)
class RenderOptions:
    """What to render. The fields after ``max_depth`` are per-object probabilities of the harder
    cases real objects show (all 0 by default, so default renders are unchanged); ``hard()``
    turns them all on for training."""

    size: int = 64
    lights: int = 32
    shapes: tuple[str, ...] = SHAPES
    shape_weights: tuple[float, ...] | None = (0.08, 0.22, 0.18, 0.17, 0.25, 0.10)
    materials: tuple[str, ...] = KINDS
    max_materials: int = 3
    cast_shadows: bool = True
    noise: bool = True  # shot + read noise and quantisation to a random bit depth (bit_depths)
    max_depth: float = DEFAULT_MAX_DEPTH  # domes up to this height / radius (steeper above 1)
    material_weights: tuple[float, ...] | None = None  # one per materials entry; None = built in
    steep: float = 0.0  # P(steep superquadric dome: tall, near-vertical rims, many n_z < 0.3)
    fine_relief: float = 0.0  # P(1-3 px engraving / scratches / weave / lettering on top)
    interreflection: float = 0.0  # P(one-bounce diffuse light between concave parts)
    very_dark: float = 0.0  # P(dark materials, brightest value 25-43/255 of full scale)
    ring_rigs: float = 0.0  # P(LED ring rig instead of the cone / LED-board rigs)
    bit_depths: tuple[int, ...] = BIT_DEPTHS  # drawn uniformly (repeat one to favour it)

    @classmethod
    def hard(cls, **overrides: Any) -> RenderOptions:
        """Training preset aimed at the measured failures on real objects: steep rims,
        concavities with inter-reflections, pixel-scale relief, rough / painted / very dark
        materials, LED rings and mostly 8-bit captures. ``overrides`` set any field."""
        base = cls(shapes=ALL_SHAPES,
                   # sphere blob bumps creases sculpted relief folds cup
                   shape_weights=(0.05, 0.14, 0.12, 0.12, 0.17, 0.08, 0.17, 0.15),
                   materials=ALL_KINDS,
                   # diffuse plastic metal dark rough paint
                   material_weights=(0.1, 0.3, 0.15, 0.1, 0.15, 0.2),
                   steep=0.35, fine_relief=0.5, interreflection=0.5,
                   very_dark=0.1, ring_rigs=0.25, bit_depths=(8, 8, 8, 10, 12, 16))
        return replace(base, **overrides)

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> RenderOptions:
        """``"default"`` (the renderer as the README's held-out figures used it) or ``"hard"``."""
        if name == "default":
            return cls(**overrides)
        if name == "hard":
            return cls.hard(**overrides)
        raise ValueError(f"unknown render preset {name!r}; choose from {', '.join(PRESETS)}")


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


def concavity(height: np.ndarray, mask: np.ndarray, radius: float = 0.3,
              directions: int = 8, distances: int = 6) -> np.ndarray:
    """(H, W) float32 in [0, 1): the cosine-weighted share of each pixel's hemisphere that the
    surrounding surface covers, by horizon search within ``radius`` grid units.

    Along each image direction, the steepest rise of the surface *above the pixel's tangent
    plane* gives a horizon angle h; a wedge of the hemisphere below h holds sin^2 h of its
    cosine-weighted solid angle. Convex surfaces fall away from their tangent plane, so they
    score 0; folds, cups and grooves score up to ~0.5."""
    size_h, size_w = height.shape
    step = 2.0 / (size_w - 1)
    reach = max(radius / step, 2.0)
    dist = np.unique(np.rint(np.geomspace(1.0, reach, distances)))
    dz_drow, dz_dcol = np.gradient(height, step)
    z = np.where(mask, height, -1e6)
    ang = np.arange(directions) * (2 * np.pi / directions)
    rows, cols = np.mgrid[0:size_h, 0:size_w]
    best = np.zeros((directions, size_h, size_w))
    for d in dist:
        # Whole-pixel offsets, and the run and tangent-plane rise of *those* offsets (a rounded
        # diagonal step is longer than d: using d would make a sphere look concave).
        dr = np.rint(-d * np.sin(ang))[:, None, None]
        dc = np.rint(d * np.cos(ang))[:, None, None]
        run = np.hypot(dr, dc) * step
        r, c = (rows + dr).astype(np.intp), (cols + dc).astype(np.intp)
        ok = (r >= 0) & (r < size_h) & (c >= 0) & (c < size_w)
        zs = z[np.clip(r, 0, size_h - 1), np.clip(c, 0, size_w - 1)]
        ok &= zs > -1e5  # lookups off the object occlude nothing
        rise = (dz_drow[None] * dr + dz_dcol[None] * dc) * step
        tan_h = (zs - height[None] - rise) / run
        best = np.maximum(best, np.where(ok, tan_h, 0.0))
    occ = np.mean(best * best / (1.0 + best * best), axis=0)
    return np.where(mask, occ, 0.0).astype(np.float32)


def box_blur(a: np.ndarray, k: int, axes: tuple[int, int]) -> np.ndarray:
    """Sum over a (2k+1)-wide box along each of ``axes`` (zero padding), via cumulative sums."""
    for ax in axes:
        pad = [(0, 0)] * a.ndim
        pad[ax] = (k + 1, k)
        c = np.cumsum(np.pad(a, pad), axis=ax)
        n = a.shape[ax]
        hi = [slice(None)] * a.ndim
        lo = [slice(None)] * a.ndim
        hi[ax], lo[ax] = slice(2 * k + 1, n + 2 * k + 1), slice(0, n)
        a = c[tuple(hi)] - c[tuple(lo)]  # views: one subtraction, no index copies
    return a


def one_bounce(direct_diffuse: np.ndarray, kd: np.ndarray, occ: np.ndarray, mask: np.ndarray,
               radius: float = 0.3) -> np.ndarray:
    """Approximate one-bounce diffuse inter-reflection, (N, H, W, 3).

    A pixel whose hemisphere is a share ``occ`` (cosine-weighted) covered by nearby surface
    receives about occ * pi * L from it, L being that surface's outgoing radiance; a diffuse
    pixel returns kd / pi of that: kd * occ * L. L is taken as the mask-weighted local mean
    (three box passes ~ a Gaussian about radius / 2 wide) of the direct diffuse radiance."""
    step = 2.0 / (mask.shape[1] - 1)
    k = max(1, round(0.5 * radius / step / np.sqrt(3.0)))
    m = mask.astype(np.float32)
    num = direct_diffuse * m[None, ..., None]
    den = m
    for _ in range(3):
        num = box_blur(num, k, (1, 2))
        den = box_blur(den, k, (0, 1))
    mean = num / np.maximum(den, 1e-6)[None, ..., None]
    return (np.clip(kd, 0.0, 0.95).astype(np.float32)[None] * occ[None, ..., None] * mean)


def sensor(signal: np.ndarray, rng: np.random.Generator,
           bit_depths: Sequence[int] = BIT_DEPTHS) -> np.ndarray:
    """Linear signal in [0, 1] (of full well) -> noisy, clipped, quantised values in [0, 1].

    The bit depth is drawn uniformly from ``bit_depths`` (8-bit captures, as cheap rigs give,
    leave a dark object only a few dozen levels)."""
    gain = rng.uniform(0.0, 2e-4)  # shot noise variance per unit signal
    read = rng.uniform(0.0, 2e-3)
    noisy = signal + rng.standard_normal(signal.shape, np.float32) * np.sqrt(
        gain * np.clip(signal, 0, None) + read * read).astype(np.float32)
    levels = float(2 ** int(rng.choice(list(bit_depths))) - 1)
    return np.round(np.clip(noisy, 0.0, 1.0) * levels) / levels


def _chance(rng: np.random.Generator, p: float) -> bool:
    # No draw at all when a feature is off, so the default options keep the original stream.
    return p > 0 and bool(rng.random() < p)


def render_stack(rng: np.random.Generator | int, options: RenderOptions = RenderOptions(),
                 *, shape: str | None = None, lights: np.ndarray | None = None,
                 intensities: np.ndarray | None = None, name: str = "synth") -> Stack:
    """One random object under one random rig, as a Stack with normals_gt and mask."""
    rng = np.random.default_rng(rng)
    if shape is None:
        w = options.shape_weights
        w = None if w is None or len(w) != len(options.shapes) else np.asarray(w) / np.sum(w)
        shape = options.shapes[int(rng.choice(len(options.shapes), p=w))]
    steep = _chance(rng, options.steep)
    height, mask = make_shape(shape, options.size, rng, options.max_depth, steep=steep)
    if _chance(rng, options.fine_relief):
        height = height + fine_relief(options.size, rng)
    normals = normals_from_height(height, mask).astype(np.float32)
    dark = _chance(rng, options.very_dark)
    kind_w = options.material_weights
    if kind_w is not None and len(kind_w) != len(options.materials):
        kind_w = None  # as for shape_weights: weights that do not match fall back to the built-in
    kinds, kind_w = (("dark",), None) if dark else (options.materials, kind_w)
    mat = material_map(options.size, rng, options.max_materials, kinds, kind_w)
    n = options.lights
    if lights is not None:
        dirs = np.asarray(lights, np.float32)
    else:
        dirs = ring_rig(n, rng) if _chance(rng, options.ring_rigs) else rig_lights(n, rng)
    ints = rig_intensities(len(dirs), rng) if intensities is None else np.asarray(
        intensities, np.float32)
    radiance = shade(normals, dirs, mat)  # (N, H, W, 3)
    shadow = cast_shadow_mask(height, mask, dirs)[..., None] if options.cast_shadows else None
    if shadow is not None:
        radiance *= shadow
    if _chance(rng, options.interreflection):
        direct = shade(normals, dirs, mat, diffuse_only=True)
        if shadow is not None:
            direct *= shadow
        occ = concavity(height, mask)
        radiance += np.float32(rng.uniform(0.6, 1.2)) * one_bounce(direct, mat.kd, occ, mask)
    radiance *= ints[:, None, None, :]
    radiance[:, ~mask] = 0.0
    vals = radiance[:, mask]
    if dark:
        # A very dark object filmed as is: its brightest value only reaches 25-43 / 255.
        ref = float(vals.max()) if vals.size else 1.0
        signal = radiance / max(ref, 1e-8) * rng.uniform(*DARK_PEAK)
    else:
        # Exposure: put a high percentile of the object's values at 40-100 % of full scale, so
        # bright highlights saturate now and then, as they do in real captures.
        ref = float(np.percentile(vals, 99.5)) if vals.size else 1.0
        signal = radiance / max(ref, 1e-8) * rng.uniform(0.4, 1.0)
    signal = sensor(signal, rng, options.bit_depths) if options.noise else np.clip(
        signal, 0.0, 1.0)
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
