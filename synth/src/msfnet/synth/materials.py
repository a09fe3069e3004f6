"""Spatially varying materials and their reflectance: diffuse + one or two GGX specular lobes.

A material map holds per-pixel diffuse albedo kd (RGB), specular reflectance at normal incidence
F0 (RGB; 0.04 for dielectrics, tinted for metals), a specular gain and the GGX roughness alpha.
Optional layers: an Oren-Nayar roughness sigma (rough diffuse: flatter, back-scattering shading
than Lambert) and a second, sharp dielectric lobe (the clear coat of metallic paint). Up to three
random materials are blended over the object by smooth random fields, so boundaries range from
soft to sharp.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from msfnet.synth.shapes import fourier_noise, grid

KINDS = ("diffuse", "plastic", "metal", "dark")
KIND_WEIGHTS = (0.15, 0.45, 0.2, 0.2)
# Added for real-object failures; kept out of KINDS so default renders are unchanged.
EXTRA_KINDS = ("rough", "paint")
ALL_KINDS = KINDS + EXTRA_KINDS
DEFAULT_WEIGHTS = dict(zip(ALL_KINDS, (*KIND_WEIGHTS, 0.2, 0.2), strict=True))


@dataclass
class MaterialMap:
    kd: np.ndarray  # (H, W, 3) diffuse albedo
    f0: np.ndarray  # (H, W, 3) Fresnel reflectance at normal incidence
    ks: np.ndarray  # (H, W) specular gain (0 for pure diffuse)
    alpha: np.ndarray  # (H, W) GGX roughness (alpha = perceptual roughness squared)
    sigma: np.ndarray | None = None  # (H, W) Oren-Nayar roughness, radians; None = Lambert
    ks2: np.ndarray | None = None  # (H, W) gain of a second, sharp lobe (F0 0.04); None = none
    alpha2: np.ndarray | None = None  # (H, W) GGX roughness of that lobe


def random_colour(rng: np.random.Generator, lo: float, hi: float) -> np.ndarray:
    """An RGB colour with random hue and saturation, brightness in [lo, hi]."""
    base = rng.uniform(lo, hi)
    tint = rng.dirichlet(np.ones(3) * rng.uniform(1.0, 12.0)) * 3.0
    return np.clip(base * tint, 0.005, 0.98)


def random_material(
    rng: np.random.Generator,
    kinds: tuple[str, ...] = KINDS,
    weights: tuple[float, ...] | None = None,
) -> dict[str, np.ndarray | float]:
    w = np.asarray(weights if weights is not None else [DEFAULT_WEIGHTS[k] for k in kinds], float)
    kind = kinds[int(rng.choice(len(kinds), p=w / w.sum()))]
    rough = rng.uniform(0.15, 0.8)  # perceptual roughness; GGX alpha = rough^2
    if kind == "diffuse":
        return {
            "kd": random_colour(rng, 0.2, 0.9),
            "f0": np.full(3, 0.04),
            "ks": 0.0,
            "alpha": rough**2,
        }
    if kind == "plastic":
        return {
            "kd": random_colour(rng, 0.1, 0.85),
            "f0": np.full(3, 0.04),
            "ks": rng.uniform(0.3, 2.0),
            "alpha": rough**2,
        }
    if kind == "metal":
        tint = random_colour(rng, 0.5, 0.95)
        return {
            "kd": tint * rng.uniform(0.0, 0.15),
            "f0": tint,
            "ks": rng.uniform(0.5, 1.0),
            "alpha": rng.uniform(0.25, 0.7) ** 2,
        }
    if kind == "rough":
        # Rough diffuse (plaster, clay, unglazed ceramic): Oren-Nayar with a faint broad sheen.
        return {
            "kd": random_colour(rng, 0.25, 0.9),
            "f0": np.full(3, 0.04),
            "ks": rng.uniform(0.0, 0.2),
            "alpha": rng.uniform(0.6, 0.9) ** 2,
            "sigma": rng.uniform(0.2, 0.7),
        }
    if kind == "paint":
        # Metallic paint: pigment diffuse, a broad tinted lobe from the flakes, and a sharp
        # clear-coat lobe on top.
        tint = random_colour(rng, 0.3, 0.9)
        return {
            "kd": tint * rng.uniform(0.1, 0.5),
            "f0": tint * rng.uniform(0.3, 0.8),
            "ks": rng.uniform(0.3, 1.0),
            "alpha": rng.uniform(0.35, 0.65) ** 2,
            "ks2": rng.uniform(0.5, 2.0),
            # GGX alpha 0.03-0.1: the coat's highlight is still a pixel or more wide on the
            # objects rendered here (a sharper one would fall between pixel centres).
            "alpha2": rng.uniform(0.03, 0.1),
        }
    if kind != "dark":
        raise ValueError(f"unknown material {kind!r}; choose from {', '.join(ALL_KINDS)}")
    # dark: little diffuse light, so the specular lobe and noise dominate
    return {
        "kd": random_colour(rng, 0.02, 0.1),
        "f0": np.full(3, 0.04),
        "ks": rng.uniform(0.5, 2.0),
        "alpha": rough**2,
    }


def material_map(
    size: int,
    rng: np.random.Generator,
    max_materials: int = 3,
    kinds: tuple[str, ...] = KINDS,
    kind_weights: tuple[float, ...] | None = None,
) -> MaterialMap:
    """Up to ``max_materials`` random materials of ``kinds`` (drawn with ``kind_weights``, one
    per kind; None = DEFAULT_WEIGHTS) blended over a size x size frame."""
    x, y = grid(size)
    count = int(rng.integers(1, max_materials + 1))
    mats = [random_material(rng, kinds, kind_weights) for _ in range(count)]
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

    def blend(key: str, missing: float = 0.0) -> np.ndarray:
        vals = np.stack(
            [np.broadcast_to(np.asarray(m.get(key, missing), float), (3,)) for m in mats]
        )
        return np.einsum("khw,kc->hwc", weights, vals)

    def optional(key: str, missing: float) -> np.ndarray | None:
        # Only built when some material has the layer, so older kinds render exactly as before.
        return blend(key, missing)[..., 0] if any(key in m for m in mats) else None

    alpha2 = optional("alpha2", 0.01)
    return MaterialMap(
        kd=blend("kd") * texture,
        f0=blend("f0"),
        ks=blend("ks")[..., 0],
        alpha=np.clip(blend("alpha")[..., 0], 0.005, 1.0),
        sigma=optional("sigma", 0.0),
        ks2=optional("ks2", 0.0),
        alpha2=None if alpha2 is None else np.clip(alpha2, 0.002, 1.0),
    )


def _ggx(
    ks: np.ndarray,
    nh: np.ndarray,
    nl: np.ndarray,
    nv: np.ndarray,
    vh: np.ndarray,
    alpha: np.ndarray,
    f0: np.ndarray | np.float32,
) -> np.ndarray:
    """ks * GGX lobe D * V * F (without the cosine), (N, H, W, C) for f0 (1|H, W, C)."""
    a2 = (alpha.astype(np.float32) ** 2)[None]
    d = a2 / (np.pi * (nh * nh * (a2 - 1.0) + 1.0) ** 2)
    # Height-correlated Smith visibility V = G / (4 nl nv).
    vis = 0.5 / (nl * np.sqrt(nv * nv * (1 - a2) + a2) + nv * np.sqrt(nl * nl * (1 - a2) + a2))
    fres = f0 + (1.0 - f0) * (1.0 - vh) ** 5
    return (ks.astype(np.float32)[None] * d * vis)[..., None] * fres


def oren_nayar(nl: np.ndarray, nv: np.ndarray, lv: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Oren-Nayar factor A + B max(0, cos(phi_i - phi_r)) sin(a) tan(b) (qualitative model).

    With the tangent projections of l and v, cos(dphi) sin(th_i) sin(th_r) = l.v - nl nv, and
    sin(a) tan(b) = sin(th_i) sin(th_r) / max(nl, nv), so no angle is needed."""
    s2 = (sigma.astype(np.float32) ** 2)[None]
    a = 1.0 - 0.5 * s2 / (s2 + 0.33)
    b = 0.45 * s2 / (s2 + 0.09)
    nlc = np.clip(nl, 1e-4, None)
    return a + b * np.clip(lv - nlc * nv, 0.0, None) / np.maximum(nlc, nv)


def shade(
    normals: np.ndarray, lights: np.ndarray, mat: MaterialMap, diffuse_only: bool = False
) -> np.ndarray:
    """Reflected radiance for unit-intensity white lights: (N, H, W, 3), attached shadows included.

    Camera looks along -z (orthographic), so the view vector is (0, 0, 1) everywhere.
    ``diffuse_only``: just the diffuse part (what inter-reflections carry, roughly).
    """
    n = normals.astype(np.float32)
    lv = lights.astype(np.float32)
    nl = np.einsum("hwc,kc->khw", n, lv)  # (N, H, W)
    nv = np.clip(n[..., 2], 1e-3, None)
    diffuse = mat.kd.astype(np.float32)[None] / np.float32(np.pi)
    cos_in = np.clip(nl, 0.0, None)
    if mat.sigma is not None:
        cos_in = cos_in * oren_nayar(nl, nv, lv[:, 2, None, None], mat.sigma)
    if diffuse_only:
        return diffuse * cos_in[..., None]
    half = lv + np.array([0, 0, 1], np.float32)
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    nh = np.clip(np.einsum("hwc,kc->khw", n, half), 0.0, 1.0)
    vh = np.clip(half[:, 2], 0.0, 1.0)[:, None, None, None]  # (N,1,1,1)
    nlc = np.clip(nl, 1e-4, None)
    spec = _ggx(mat.ks, nh, nlc, nv, vh, mat.alpha, mat.f0.astype(np.float32)[None])
    if mat.ks2 is not None and mat.alpha2 is not None:
        spec = spec + _ggx(mat.ks2, nh, nlc, nv, vh, mat.alpha2, np.float32(0.04))
    if mat.sigma is None:  # the original expression, so default renders stay bit-identical
        return (diffuse + spec) * np.clip(nl, 0.0, None)[..., None]
    return diffuse * cos_in[..., None] + spec * np.clip(nl, 0.0, None)[..., None]
