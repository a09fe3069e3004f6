"""Analytic renders of mirror (chrome) and matte spheres under distant lights.

Used by the calibration tests and by the simulated capture rig. Camera frame: x right, y up,
z toward the camera (the DiLiGenT convention); image row 0 is the top. The camera is either
orthographic (``focal=None``: ``scale`` pixels per scene unit) or a pinhole looking down -z.
Each pixel is supersampled ``ss`` x ``ss`` times so edges and small highlights are anti-aliased.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Camera:
    width: int
    height: int
    focal: float | None = None  # pixels; None = orthographic
    principal: tuple[float, float] | None = None  # (u, v); default: image centre
    scale: float = 1.0  # orthographic only: pixels per scene unit

    @property
    def centre(self) -> tuple[float, float]:
        if self.principal is not None:
            return self.principal
        return (self.width - 1) / 2.0, (self.height - 1) / 2.0


@dataclass(frozen=True)
class Sphere:
    centre: tuple[float, float, float]  # scene units; z < 0 in front of a pinhole camera
    radius: float
    kind: str = "mirror"  # "mirror" or "matte"
    albedo: tuple[float, float, float] = (1.0, 1.0, 1.0)


@dataclass
class Scene:
    camera: Camera
    spheres: list[Sphere]
    source_deg: float = 2.0  # angular radius of each light (mirror highlights need a size)
    environment: float = 0.02  # dim surroundings reflected by mirrors (keeps the rim visible)
    background: tuple[float, float, float] = (0.01, 0.01, 0.01)
    ss: int = 3
    _cache: dict = field(default_factory=dict, repr=False)


def _rays(cam: Camera, ss: int) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel ray origins and unit directions, shape (H, W, ss*ss, 3)."""
    off = (np.arange(ss) + 0.5) / ss - 0.5
    v, u = np.meshgrid(np.arange(cam.height, dtype=np.float64), np.arange(cam.width), indexing="ij")
    du, dv = np.meshgrid(off, off, indexing="ij")
    uu = u[..., None] + du.ravel()
    vv = v[..., None] + dv.ravel()
    cu, cv = cam.centre
    if cam.focal is None:
        org = np.stack([(uu - cu) / cam.scale, -(vv - cv) / cam.scale, np.full_like(uu, 1e6)], -1)
        d = np.zeros_like(org)
        d[..., 2] = -1.0
        return org, d
    d = np.stack([(uu - cu) / cam.focal, -(vv - cv) / cam.focal, -np.ones_like(uu)], -1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return np.zeros_like(d), d


def _geometry(scene: Scene) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Per sphere: hit (H,W,S) bool, depth t, normal and view vector (H,W,S,3). Cached."""
    if "geo" in scene._cache:
        return scene._cache["geo"]
    org, d = _rays(scene.camera, scene.ss)
    out = []
    for sp in scene.spheres:
        c = np.asarray(sp.centre, np.float64)
        oc = org - c
        b = np.sum(oc * d, -1)
        disc = b * b - (np.sum(oc * oc, -1) - sp.radius**2)
        hit = disc > 0
        t = np.where(hit, -b - np.sqrt(np.maximum(disc, 0)), np.inf)
        n = (org + np.where(hit, t, 0.0)[..., None] * d - c) / sp.radius
        n[~hit] = 0.0
        out.append((hit, t, n, -d))
    scene._cache["geo"] = out
    return out


def render(
    scene: Scene,
    light: np.ndarray | None,
    intensity: np.ndarray | None = None,
    ambient: float = 0.0,
) -> np.ndarray:
    """Linear radiance image (H, W, 3) float32 for one light (None = lights off)."""
    cam = scene.camera
    geo = _geometry(scene)
    bg = np.asarray(scene.background, np.float64)
    samples = cam.height, cam.width, scene.ss * scene.ss
    img = np.broadcast_to(bg * (1.0 + ambient), (*samples, 3)).copy()
    depth = np.full(samples, np.inf)
    e = np.ones(3) if intensity is None else np.asarray(intensity, np.float64)
    cos_src = np.cos(np.radians(scene.source_deg))
    for sp, (hit, t, n, v) in zip(scene.spheres, geo, strict=True):
        front = hit & (t < depth)
        if not front.any():
            continue
        depth = np.where(front, t, depth)
        alb = np.asarray(sp.albedo, np.float64)
        if sp.kind == "mirror":
            r = 2.0 * np.sum(n * v, -1, keepdims=True) * n - v
            env = scene.environment * (0.6 + 0.4 * r[..., 1:2]) * (1.0 + ambient)
            val = np.broadcast_to(env, (*samples, 1)) * alb
            if light is not None:
                l_ = np.asarray(light, np.float64) / np.linalg.norm(light)
                # Smooth-edged disc source: full inside its angular radius, fast fall-off.
                cosang = r @ l_
                z = np.clip((cosang - cos_src) / (0.15 * (1 - cos_src)), -50.0, 50.0)
                lobe = 1.0 / (1.0 + np.exp(-z))
                val = val + lobe[..., None] * e * alb * 50.0
        elif sp.kind == "matte":
            val = np.broadcast_to(alb * scene.environment * ambient, (*samples, 3)).copy()
            if light is not None:
                l_ = np.asarray(light, np.float64) / np.linalg.norm(light)
                val = val + np.maximum(n @ l_, 0.0)[..., None] * e * alb
        else:
            raise ValueError(f"unknown sphere kind {sp.kind!r}")
        img = np.where(front[..., None], val, img)
    return img.mean(axis=2).astype(np.float32)


def sphere_masks(scene: Scene) -> list[np.ndarray]:
    """Per sphere: pixels whose centre sees it (bool, H x W)."""
    geo = _geometry(scene)
    centre = (scene.ss * scene.ss) // 2 if scene.ss % 2 else None
    return [hit[..., centre] if centre is not None else hit.mean(-1) >= 0.5 for hit, *_ in geo]


def sphere_normals(scene: Scene, index: int = 0) -> np.ndarray:
    """Unit normals (H, W, 3) of one sphere at pixel centres (zeros outside)."""
    n = _geometry(scene)[index][2]
    nm = n.mean(axis=2)
    norm = np.linalg.norm(nm, axis=-1, keepdims=True)
    inside = sphere_masks(scene)[index]
    return np.where(inside[..., None], nm / np.maximum(norm, 1e-9), 0.0).astype(np.float32)


def expose(
    radiance: np.ndarray,
    gain: float,
    bit_depth: int = 8,
    noise: float = 0.0,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Radiance -> sensor values: gain, optional read noise (in LSB), clipping, quantisation."""
    top = 255 if bit_depth == 8 else 65535
    x = radiance.astype(np.float64) * gain * top
    if noise > 0:
        x = x + (rng or np.random.default_rng(0)).normal(0.0, noise, x.shape)
    return np.clip(np.rint(x), 0, top).astype(np.uint8 if bit_depth == 8 else np.uint16)


def ring_lights(
    n: int, elevation_deg: tuple[float, float] = (20.0, 55.0), seed: int = 0
) -> np.ndarray:
    """n unit light directions spread around the view axis (x right, y up, z to camera)."""
    rng = np.random.default_rng(seed)
    az = np.linspace(0, 2 * np.pi, n, endpoint=False) + rng.uniform(-0.2, 0.2, n)
    tilt = np.radians(rng.uniform(*elevation_deg, n))
    return np.stack([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)], 1)


def mirror_scene(
    width: int = 240,
    height: int = 200,
    radius_px: float = 80.0,
    focal: float | None = None,
    centres_px: list[tuple[float, float]] | None = None,
    source_deg: float = 2.0,
    ss: int = 3,
    kind: str = "mirror",
) -> Scene:
    """A scene of one or more spheres given by their image centres and radius in pixels.

    Orthographic (scale 1 px/unit) unless ``focal`` is given; then the spheres sit at a distance
    that makes their silhouette roughly ``radius_px`` wide.
    """
    cam = Camera(width, height, focal)
    centres_px = centres_px or [((width - 1) / 2.0, (height - 1) / 2.0)]
    cu, cv = cam.centre
    spheres = []
    for u, v in centres_px:
        if focal is None:
            spheres.append(Sphere((u - cu, -(v - cv), 0.0), radius_px, kind))
        else:
            dist = 10.0
            c = np.array([(u - cu) / focal, -(v - cv) / focal, -1.0]) * dist
            spheres.append(Sphere(tuple(c), radius_px * dist / focal, kind))
    return Scene(cam, spheres, source_deg=source_deg, ss=ss)


__all__ = [
    "Camera",
    "Scene",
    "Sphere",
    "expose",
    "mirror_scene",
    "render",
    "ring_lights",
    "sphere_masks",
    "sphere_normals",
]
