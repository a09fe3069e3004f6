"""Render photometric stacks with ground truth: shape + materials + rig -> ``Stack``.

Everything is vectorised over lights and pixels (numpy). Deterministic: one object is fully
defined by its seed, so object ``i`` of a set seeded ``s`` uses ``default_rng([s, i])`` and does
not depend on how many objects are rendered.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from typing import Any

import cv2
import numpy as np

from msfnet.runtime.stack import Stack
from msfnet.runtime.stack.transforms import area_downscale, downscale_mask, downscale_normals
from msfnet.synth.lights import rig_intensities, rig_lights, ring_rig
from msfnet.synth.materials import ALL_KINDS, KINDS, material_map, shade
from msfnet.synth.shapes import (
    ALL_SHAPES,
    CUP_DEPTH,
    DEFAULT_MAX_DEPTH,
    FOLD_DEPTH,
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
    fold_depth: tuple[float, float] = FOLD_DEPTH  # range of the folds' depth (shapes.FOLD_DEPTH)
    cup_depth: tuple[float, float] = CUP_DEPTH  # range of a cup's depth (shapes.CUP_DEPTH)

    @classmethod
    def hard(cls, **overrides: Any) -> RenderOptions:
        """Training preset aimed at the measured failures on real objects: steep rims,
        concavities with inter-reflections, pixel-scale relief, rough / painted / very dark
        materials, LED rings and mostly 8-bit captures. ``overrides`` set any field."""
        base = cls(
            shapes=ALL_SHAPES,
            # sphere blob bumps creases sculpted relief folds cup
            shape_weights=(0.05, 0.14, 0.12, 0.12, 0.17, 0.08, 0.17, 0.15),
            materials=ALL_KINDS,
            # diffuse plastic metal dark rough paint
            material_weights=(0.1, 0.3, 0.15, 0.1, 0.15, 0.2),
            steep=0.35,
            fine_relief=0.5,
            interreflection=0.5,
            very_dark=0.1,
            ring_rigs=0.25,
            bit_depths=(8, 8, 8, 10, 12, 16),
            # Up to twice as deep as the defaults: harvest's folds bounce ~0.3 of the
            # albedo onto walls facing away from the light; the default folds ~0.01.
            fold_depth=(0.25, 1.2),
            cup_depth=(0.5, 1.8),
        )
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


NEAR_PX = 4  # gathered pixel by pixel, at full resolution: the strongest, nearest light


def _near_offsets(near_px: int = NEAR_PX) -> tuple[np.ndarray, np.ndarray]:
    """Every pixel offset (K, 2), as (row, col), within ``near_px + 0.5`` of the centre
    (all of the disk the rings of :func:`_ring_offsets` leave out), each standing for 1 px^2."""
    span = np.arange(-near_px, near_px + 1)
    grid = np.stack(np.meshgrid(span, span, indexing="ij"), -1).reshape(-1, 2)
    d2 = (grid**2).sum(1)
    near = grid[(d2 > 0) & (d2 < (near_px + 0.5) ** 2)]
    return near, np.ones(len(near))


def _ring_offsets(
    inner_px: float, radius_px: float, rng: np.random.Generator, rings: int = 10, per_ring: int = 12
) -> tuple[np.ndarray, np.ndarray]:
    """Offsets (K, 2) in pixels, as (row, col) floats, and the image area (px^2) each stands
    for: one sample per sector of log-spaced rings from ``inner_px`` to ``radius_px``, each
    ring randomly turned per object.

    A form factor falls off as 1 / r^2 while the area at distance r grows as r, so every
    octave of distance matters about equally: log-spaced rings spend the samples evenly."""
    if radius_px <= inner_px + 1:
        return np.zeros((0, 2)), np.zeros(0)
    edges = np.geomspace(inner_px, radius_px, rings + 1)
    dtheta = 2.0 * np.pi / per_ring
    offsets, weights = [], []
    for lo, hi in itertools.pairwise(edges):
        theta = (np.arange(per_ring) + rng.uniform(0.0, 1.0)) * dtheta
        rho = np.sqrt(0.5 * (lo * lo + hi * hi))  # the sector's area centre
        offsets.append(np.stack([-rho * np.sin(theta), rho * np.cos(theta)], 1))
        weights.append(np.full(per_ring, 0.5 * (hi * hi - lo * lo) * dtheta))
    return np.concatenate(offsets), np.concatenate(weights)


def _gather(
    src: np.ndarray,
    height: np.ndarray,
    normals: np.ndarray,
    mask: np.ndarray,
    offsets: np.ndarray,
    px_area: np.ndarray,
    step: float,
) -> np.ndarray:
    """sum over offsets of src(q) cos_p cos_q / (pi r^2) dA_q, (N, H, W, C); ``step`` is the
    pixel pitch in grid units, ``px_area`` the image area (px^2) each offset stands for."""
    size_h, size_w = height.shape
    out = np.zeros(src.shape, np.float32)
    if len(offsets) == 0:
        return out
    pad = int(np.abs(offsets).max())
    z = np.where(mask, height, 0.0).astype(np.float32)
    n = np.where(mask[..., None], normals, 0.0).astype(np.float32)
    # A patch's surface area is its image area over n_z (a steep wall shows little area in
    # the image but emits from a lot of surface).
    emit_area = np.where(mask, step * step / np.clip(n[..., 2], 0.1, None), 0.0).astype(np.float32)
    zp, npad = np.pad(z, pad), np.pad(n, ((pad, pad), (pad, pad), (0, 0)))
    ap = np.pad(emit_area, pad)
    srcp = np.pad(src, ((0, 0), (pad, pad), (pad, pad), (0, 0)))
    min_r = np.float32(1.5 * step)
    for (dr, dc), weight in zip(offsets, px_area, strict=True):
        rows = slice(pad + dr, pad + dr + size_h)
        cols = slice(pad + dc, pad + dc + size_w)
        # vector p -> q in grid units: x right, y up (rows grow downwards), z towards the camera
        dx, dy = np.float32(dc * step), np.float32(-dr * step)
        dz = zp[rows, cols] - z
        r2 = np.maximum(dx * dx + dy * dy + dz * dz, min_r * min_r)
        nq = npad[rows, cols]
        # unnormalised dot products with d = q - p: their product over r^4 is cos cos / r^2
        cos_p = n[..., 0] * dx + n[..., 1] * dy + n[..., 2] * dz
        cos_q = -(nq[..., 0] * dx + nq[..., 1] * dy + nq[..., 2] * dz)
        w = np.clip(cos_p, 0, None) * np.clip(cos_q, 0, None) / (np.float32(np.pi) * r2 * r2)
        w *= ap[rows, cols] * np.float32(weight)
        if w.any():
            out += w[None, ..., None] * srcp[:, rows, cols]
    return out


def _masked_mean(arr: np.ndarray, k: int, mask: np.ndarray) -> np.ndarray:
    """Mean over the object's pixels of each k x k block of an (H, W, ...) array (H, W
    multiples of k), so rim blocks do not average in the background."""
    w = mask.reshape(mask.shape + (1,) * (arr.ndim - 2)).astype(np.float32)
    return area_downscale(arr * w, k) / np.maximum(area_downscale(w, k), 1e-6)


def _upsample(arr: np.ndarray, size_h: int, size_w: int) -> np.ndarray:
    """(N, h, w, C) -> (N, size_h, size_w, C), bilinear (OpenCV 5 resizes at most 128
    channels at a time)."""
    n, h, w, c = arr.shape
    flat = arr.transpose(1, 2, 0, 3).reshape(h, w, n * c)
    chunks = (np.ascontiguousarray(flat[..., i : i + 128]) for i in range(0, n * c, 128))
    parts = [cv2.resize(p, (size_w, size_h), interpolation=cv2.INTER_LINEAR) for p in chunks]
    up = np.concatenate([p.reshape(size_h, size_w, -1) for p in parts], axis=2)
    return up.reshape(size_h, size_w, n, c).transpose(2, 0, 1, 3)


def bounce_light(
    direct: np.ndarray | None,
    height: np.ndarray,
    normals: np.ndarray,
    mask: np.ndarray,
    rng: np.random.Generator,
    radius: float = 0.6,
    max_size: int = 96,
) -> np.ndarray:
    """Irradiance / pi that each pixel receives from the rest of the surface, (N, H, W, C).

    ``direct``: (N, H, W, C) outgoing (diffuse) radiance of every pixel under each light; None
    gives every pixel radiance 1 and returns (1, H, W, 1): the cosine-weighted share of each
    pixel's hemisphere that the surface covers (0 on convex shapes, 0.5 beside a wall).

    Gathered over surface patches q within ``radius`` grid units of the image's half-width
    with the point-to-patch form factor cos_p cos_q / (pi r^2) dA_q, where cos_p, cos_q say how
    squarely p and q face each other (both must face); visibility between them is not tested.
    This is what the bowl of a vase or the inside of cloth folds receives from the walls
    opposite when a light leaves them lit and the pixel itself in shadow (on DiLiGenT harvest's
    concave pixels, lights behind the surface still return about a quarter of the albedo).

    The nearest pixels (within ``NEAR_PX``) are gathered one by one at full resolution; the
    rest, which varies slowly across the surface, on a grid 2x (or more) coarser for renders
    larger than ``max_size``, upsampled with the mask's weight (timings: docs/benchmark.md).
    The coarse grid blurs steep walls, but what it loses of a full-resolution gather is small
    beside the 0.8-2x gain drawn per object."""
    size_h, size_w = height.shape
    step = 2.0 / (size_w - 1)
    src = np.ones((1, size_h, size_w, 1), np.float32)
    if direct is not None:
        src = direct.astype(np.float32, copy=False)
    out = _gather(src, height, normals, mask, *_near_offsets(), step)
    rings, ring_area = _ring_offsets(NEAR_PX + 0.5, radius / step, rng)
    k = -(-max(size_h, size_w) // max_size)
    if k == 1:
        out += _gather(src, height, normals, mask, np.rint(rings).astype(np.intp), ring_area, step)
    else:
        ph, pw = -size_h % k, -size_w % k
        wide = ((0, ph), (0, pw))
        m = np.pad(mask, wide)
        hc = _masked_mean(np.pad(height, wide), k, m)
        # the block mean of the object's normals (zeros elsewhere), renormalised
        nc = downscale_normals(np.pad(normals * mask[..., None], (*wide, (0, 0))), k)
        mc = downscale_mask(m, k)
        sc = _masked_mean(
            np.pad(src, ((0, 0), *wide, (0, 0))).transpose(1, 2, 0, 3), k, m
        ).transpose(2, 0, 1, 3)
        # one coarse pixel is k pixels: offsets shrink k times, areas k^2 times, pitch grows
        far = _gather(
            sc, hc, nc, mc, np.rint(rings / k).astype(np.intp), ring_area / k**2, step * k
        )
        # Upsample with the coarse mask as weight, so rim pixels are not dimmed by the zeros
        # of coarse pixels outside the object.
        weight = _upsample(mc.astype(np.float32)[None, ..., None], size_h + ph, size_w + pw)
        up = _upsample(far, size_h + ph, size_w + pw) / np.maximum(weight, 1e-3)
        out += np.where(weight > 1e-3, up, 0.0)[:, :size_h, :size_w]
    out[:, ~mask] = 0.0
    return out


def sensor(
    signal: np.ndarray, rng: np.random.Generator, bit_depths: Sequence[int] = BIT_DEPTHS
) -> np.ndarray:
    """Linear signal in [0, 1] (of full well) -> noisy, clipped, quantised values in [0, 1].

    The bit depth is drawn uniformly from ``bit_depths`` (8-bit captures, as cheap rigs give,
    leave a dark object only a few dozen levels)."""
    gain = rng.uniform(0.0, 2e-4)  # shot noise variance per unit signal
    read = rng.uniform(0.0, 2e-3)
    noisy = signal + rng.standard_normal(signal.shape, np.float32) * np.sqrt(
        gain * np.clip(signal, 0, None) + read * read
    ).astype(np.float32)
    levels = float(2 ** int(rng.choice(list(bit_depths))) - 1)
    return np.round(np.clip(noisy, 0.0, 1.0) * levels) / levels


def _chance(rng: np.random.Generator, p: float) -> bool:
    # No draw at all when a feature is off, so the default options keep the original stream.
    return p > 0 and bool(rng.random() < p)


def render_stack(
    rng: np.random.Generator | int,
    options: RenderOptions = RenderOptions(),
    *,
    shape: str | None = None,
    lights: np.ndarray | None = None,
    intensities: np.ndarray | None = None,
    name: str = "synth",
) -> Stack:
    """One random object under one random rig, as a Stack with normals_gt and mask."""
    rng = np.random.default_rng(rng)
    if shape is None:
        w = options.shape_weights
        w = None if w is None or len(w) != len(options.shapes) else np.asarray(w) / np.sum(w)
        shape = options.shapes[int(rng.choice(len(options.shapes), p=w))]
    steep = _chance(rng, options.steep)
    height, mask = make_shape(
        shape,
        options.size,
        rng,
        options.max_depth,
        steep=steep,
        fold_depth=options.fold_depth,
        cup_depth=options.cup_depth,
    )
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
    if intensities is None:
        ints = rig_intensities(len(dirs), rng)
    else:
        ints = np.asarray(intensities, np.float32)
    radiance = shade(normals, dirs, mat)  # (N, H, W, 3)
    shadow = cast_shadow_mask(height, mask, dirs)[..., None] if options.cast_shadows else None
    if shadow is not None:
        radiance *= shadow
    if _chance(rng, options.interreflection):
        direct = shade(normals, dirs, mat, diffuse_only=True)
        if shadow is not None:
            direct *= shadow
        # The gather overestimates where a ridge hides one wall from another (no visibility
        # test) and leaves out second and later bounces (bright materials: up to ~2x): the
        # gain spans both.
        gain = np.float32(rng.uniform(0.8, 2.0))
        kd = np.clip(mat.kd, 0.0, 0.95).astype(np.float32)
        radiance += gain * kd[None] * bounce_light(direct, height, normals, mask, rng)
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
    signal = sensor(signal, rng, options.bit_depths) if options.noise else np.clip(signal, 0.0, 1.0)
    images = (signal * FULL_SCALE).astype(np.float32)
    return Stack(
        name=f"{name}_{shape}",
        images=images,
        lights=dirs.astype(np.float32),
        intensities=ints,
        mask=mask,
        normals_gt=normals,
        filenames=[f"{i + 1:03d}.png" for i in range(len(dirs))],
    ).validate()


def render_set(
    seed: int,
    count: int,
    options: RenderOptions = RenderOptions(),
    start: int = 0,
    shapes: Sequence[str] | None = None,
) -> Iterator[Stack]:
    """Objects ``start .. start+count-1`` of the set seeded ``seed`` (each independent)."""
    for i in range(start, start + count):
        shape = shapes[i % len(shapes)] if shapes else None
        yield render_stack(
            np.random.default_rng([seed, i]), options, shape=shape, name=f"obj{i:04d}"
        )
