"""Spatially varying materials and their reflectance: Lambertian diffuse + a GGX specular lobe.

A material map holds per-pixel diffuse albedo kd (RGB), specular reflectance at normal incidence
F0 (RGB; 0.04 for dielectrics, tinted for metals), a specular gain and the GGX roughness alpha.
Up to three random materials are blended over the object by smooth random fields, so boundaries
range from soft to sharp.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .shapes import fourier_noise, grid

KINDS = ("diffuse", "plastic", "metal", "dark")
KIND_WEIGHTS = (0.15, 0.45, 0.2, 0.2)


@dataclass
class MaterialMap:
    kd: np.ndarray  # (H, W, 3) diffuse albedo
    f0: np.ndarray  # (H, W, 3) Fresnel reflectance at normal incidence
    ks: np.ndarray  # (H, W) specular gain (0 for pure diffuse)
    alpha: np.ndarray  # (H, W) GGX roughness (alpha = perceptual roughness squared)


def random_colour(rng: np.random.Generator, lo: float, hi: float) -> np.ndarray:
    """An RGB colour with random hue and saturation, brightness in [lo, hi]."""
    base = rng.uniform(lo, hi)
    tint = rng.dirichlet(np.ones(3) * rng.uniform(1.0, 12.0)) * 3.0
    return np.clip(base * tint, 0.005, 0.98)


def random_material(rng: np.random.Generator, kinds: tuple[str, ...] = KINDS,
                    weights: tuple[float, ...] | None = None) -> dict[str, np.ndarray | float]:
    w = np.asarray(weights if weights is not None else
                   [KIND_WEIGHTS[KINDS.index(k)] for k in kinds], float)
    kind = kinds[int(rng.choice(len(kinds), p=w / w.sum()))]
    rough = rng.uniform(0.15, 0.8)  # perceptual roughness; GGX alpha = rough^2
    if kind == "diffuse":
        return {"kd": random_colour(rng, 0.2, 0.9), "f0": np.full(3, 0.04), "ks": 0.0,
                "alpha": rough ** 2}
    if kind == "plastic":
        return {"kd": random_colour(rng, 0.1, 0.85), "f0": np.full(3, 0.04),
                "ks": rng.uniform(0.3, 2.0), "alpha": rough ** 2}
    if kind == "metal":
        tint = random_colour(rng, 0.5, 0.95)
        return {"kd": tint * rng.uniform(0.0, 0.15), "f0": tint, "ks": rng.uniform(0.5, 1.0),
                "alpha": rng.uniform(0.25, 0.7) ** 2}
    # dark: little diffuse light, so the specular lobe and noise dominate
    return {"kd": random_colour(rng, 0.02, 0.1), "f0": np.full(3, 0.04),
            "ks": rng.uniform(0.5, 2.0), "alpha": rough ** 2}


def material_map(size: int, rng: np.random.Generator, max_materials: int = 3,
                 kinds: tuple[str, ...] = KINDS) -> MaterialMap:
    x, y = grid(size)
    count = int(rng.integers(1, max_materials + 1))
    mats = [random_material(rng, kinds) for _ in range(count)]
    if count == 1:
        weights = np.ones((1, size, size))
    else:
        fields = np.stack([fourier_noise(x, y, rng, 8, 0.5, 3.0) for _ in range(count)])
        sharp = np.exp(rng.uniform(np.log(2.0), np.log(60.0)))
        weights = np.exp(sharp * (fields - fields.max(axis=0)))
        weights /= weights.sum(axis=0)
    # Albedo texture: mild multiplicative variation inside each material.
    texture = 1.0 + rng.uniform(0.0, 0.25) * fourier_noise(x, y, rng, 12, 2.0, 16.0, slope=1.0)
    texture = np.clip(texture, 0.3, 1.7)[..., None]

    def blend(key: str) -> np.ndarray:
        vals = np.stack([np.broadcast_to(np.asarray(m[key], float), (3,)) for m in mats])
        return np.einsum("khw,kc->hwc", weights, vals)

    return MaterialMap(kd=blend("kd") * texture, f0=blend("f0"), ks=blend("ks")[..., 0],
                       alpha=np.clip(blend("alpha")[..., 0], 0.005, 1.0))


def shade(normals: np.ndarray, lights: np.ndarray, mat: MaterialMap) -> np.ndarray:
    """Reflected radiance for unit-intensity white lights: (N, H, W, 3), attached shadows included.

    Camera looks along -z (orthographic), so the view vector is (0, 0, 1) everywhere.
    """
    n = normals.astype(np.float32)
    lv = lights.astype(np.float32)
    nl = np.einsum("hwc,kc->khw", n, lv)  # (N, H, W)
    nv = np.clip(n[..., 2], 1e-3, None)
    half = lv + np.array([0, 0, 1], np.float32)
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    nh = np.clip(np.einsum("hwc,kc->khw", n, half), 0.0, 1.0)
    vh = np.clip(half[:, 2], 0.0, 1.0)[:, None, None, None]  # (N,1,1,1)
    a2 = (mat.alpha.astype(np.float32) ** 2)[None]
    d = a2 / (np.pi * (nh * nh * (a2 - 1.0) + 1.0) ** 2)
    nlc = np.clip(nl, 1e-4, None)
    # Height-correlated Smith visibility V = G / (4 nl nv).
    vis = 0.5 / (nlc * np.sqrt(nv * nv * (1 - a2) + a2) + nv * np.sqrt(nlc * nlc * (1 - a2) + a2))
    f0 = mat.f0.astype(np.float32)[None]
    fres = f0 + (1.0 - f0) * (1.0 - vh) ** 5
    spec = (mat.ks.astype(np.float32)[None] * d * vis)[..., None] * fres
    diffuse = mat.kd.astype(np.float32)[None] / np.float32(np.pi)
    return (diffuse + spec) * np.clip(nl, 0.0, None)[..., None]
