"""Training batches rendered on the training device itself, as batched torch operations.

The numpy renderer (:mod:`msfnet.synth.render`) makes whole objects one at a time on the CPU;
on a GPU, its worker processes could not keep up (docs/training.md). This module renders the
*crops* a training step needs, B samples x N lights at once, on whatever device the network
trains on, so no process boundary or host copy is left.

Each sample is a patch of a height field seen through a crop, rendered on a grid with a margin
around the crop (shadows and bounced light come from outside it too):

- **shape**: a dome (ellipse outline; sphere-like or steep superquadric profile) or a surface
  that fills the frame, plus Gaussian bumps and dents, deep folds (concavities), and on some
  samples 1-3 px relief (grooves and fine ripples). Objects are 0.6-3x the crop, so crops see
  rims, interiors and everything between;
- **mask**: the outline, and on some samples a straight or round cut through a continuous
  surface (the network must not draw a rim where the mask merely ends);
- **materials**: two blended random materials with textured diffuse albedo and a GGX specular
  lobe (plastic, metal, dark), the same formulas as :func:`msfnet.synth.materials.shade`;
- **light**: cone or LED-ring rigs, per-light RGB intensities; attached shadows, cast shadows
  ray-marched over the height field, one bounce of diffuse light between facing surfaces
  (form factors over a fixed set of offsets, as :func:`msfnet.synth.render.bounce_light` does
  at full resolution, no visibility test);
- **sensor**: exposure from a high percentile, shot + read noise, clipping, quantisation to a
  random bit depth.

Directions: x right, y up (rows run down), z towards the camera, as everywhere in msfnet.
Deterministic per seed: every random number comes from one ``torch.Generator`` on the device,
seeded from (seed, step) by :func:`step_seed`. The same seed gives the same batch on the same
device type and torch version; CPU and CUDA streams differ.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from msfnet.runtime.contract import TRAIN_LIGHTS


@dataclass(frozen=True)
class TorchRenderOptions:
    """What :func:`render_batch` draws. Probabilities are per sample."""

    object_scale: tuple[float, float] = (0.6, 3.0)  # object radius / crop size
    margin: float = 0.25  # grid margin on each side, fraction of the crop
    full_frame: float = 0.2  # P(a surface filling the whole frame: no outline)
    steep: float = 0.25  # P(steep superquadric dome: tall, near-vertical rims)
    concave: float = 0.5  # P(deep folds and dents)
    relief: float = 0.4  # P(1-3 px grooves and ripples)
    cut: float = 0.3  # P(the mask cuts through a continuous surface)
    specular: float = 0.75  # P(a material has a specular lobe)
    metal: float = 0.15  # P(a material is a metal: tinted lobe, little diffuse)
    dark_material: float = 0.15  # P(a material is dark: albedo 0.03-0.12 of the others')
    dark: float = 0.1  # P(a very dark object: brightest value 25-43 / 255)
    ring_rigs: float = 0.25  # P(LED ring rig instead of a cone)
    max_light_deg: tuple[float, float] = (35.0, 65.0)  # cone half-angle drawn from this
    cast_shadows: bool = True
    shadow_steps: int = 20
    interreflection: float = 0.5  # P(one bounce of diffuse light)
    noise: bool = True
    bit_depths: tuple[int, ...] = (8, 8, 10, 12, 16)

    @classmethod
    def preset(cls, name: str) -> TorchRenderOptions:
        """``"hard"``: every hard case on (the defaults above); ``"default"``: mostly plain
        domes and materials, as the numpy renderer's default preset."""
        if name == "hard":
            return cls()
        if name == "default":
            return cls(
                steep=0.0,
                concave=0.2,
                relief=0.0,
                cut=0.1,
                metal=0.2,
                dark=0.0,
                ring_rigs=0.0,
                max_light_deg=(35.0, 55.0),
                interreflection=0.0,
                bit_depths=(8, 10, 12, 14, 16),
            )
        raise ValueError(f"unknown render preset {name!r}; choose default or hard")


@dataclass
class RenderedBatch:
    """Raw renders of B crops under N lights (all on one device)."""

    images: Tensor  # (B, N, 3, S, S) linear values in [0, 1] of full scale
    lights: Tensor  # (B, N, 3) unit directions
    intensities: Tensor  # (B, N, 3) RGB light intensities
    normals: Tensor  # (B, 3, S, S) unit normals, zeros outside the mask
    mask: Tensor  # (B, S, S) bool
    height: Tensor  # (B, S, S) height field in pixels (for tests and inspection)


def step_seed(seed: int, step: int) -> int:
    """A 63-bit generator seed for (seed, step): independent streams per step, so a resumed
    run renders the same batches."""
    state = np.random.SeedSequence([seed, 3, step]).generate_state(2, np.uint64)
    return int(state[0]) & (2**63 - 1)


class _Draw:
    """Random draws from one generator, on one device, float32."""

    def __init__(self, gen: torch.Generator, device: torch.device) -> None:
        self.gen, self.device = gen, device

    def uniform(self, shape: tuple[int, ...], lo: float = 0.0, hi: float = 1.0) -> Tensor:
        u = torch.rand(shape, generator=self.gen, device=self.device)
        return lo + (hi - lo) * u

    def normal(self, shape: tuple[int, ...], std: float | Tensor = 1.0) -> Tensor:
        return torch.randn(shape, generator=self.gen, device=self.device) * std

    def chance(self, shape: tuple[int, ...], p: float) -> Tensor:
        return self.uniform(shape) < p


# ----------------------------------------------------------------------------- geometry


def _waves(draw: _Draw, b: int, x: Tensor, y: Tensor, terms: int, lo: float, hi: float) -> Tensor:
    """(B, P, P): sum of ``terms`` plane waves per sample, periods log-uniform in [lo, hi] px,
    unit amplitude each, random directions and phases."""
    period = torch.exp(draw.uniform((b, terms, 1, 1), math.log(lo), math.log(hi)))
    ang = draw.uniform((b, terms, 1, 1), 0.0, 2 * math.pi)
    phase = draw.uniform((b, terms, 1, 1), 0.0, 2 * math.pi)
    u = torch.cos(ang) * x[:, None] + torch.sin(ang) * y[:, None]
    return torch.sin(2 * math.pi * u / period + phase).sum(1)


def _shapes(
    draw: _Draw, b: int, size: int, pad: int, opts: TorchRenderOptions
) -> tuple[Tensor, Tensor, Tensor]:
    """Height (B, P, P) in px, the object's support (where it occludes) and its mask, on the
    padded grid P = size + 2 pad."""
    p = size + 2 * pad
    t = torch.arange(p, device=draw.device, dtype=torch.float32) - (p - 1) / 2
    x = t[None, None, :].expand(1, p, p)  # columns, right
    y = -t[None, :, None].expand(1, p, p)  # rows run down, y up

    def col(v: Tensor) -> Tensor:
        return v[:, None, None]

    full = draw.chance((b,), opts.full_frame)
    steep = draw.chance((b,), opts.steep)
    scale = draw.uniform((b,), *opts.object_scale)
    scale = torch.where(full, draw.uniform((b,), 4.0, 10.0), scale)
    radius = scale * size
    # Centre: the crop's centre stays inside the outline, somewhere between centre and rim.
    off_r = draw.uniform((b,)).sqrt() * torch.clamp(radius - 0.3 * size, min=0.0) * 0.9
    off_a = draw.uniform((b,), 0.0, 2 * math.pi)
    cx, cy = off_r * torch.cos(off_a), off_r * torch.sin(off_a)
    ax = radius * draw.uniform((b,), 0.7, 1.0)
    ay = radius * draw.uniform((b,), 0.7, 1.0)
    rot = draw.uniform((b,), 0.0, math.pi)
    dx, dy = x - col(cx), y - col(cy)
    u = (dx * col(torch.cos(rot)) + dy * col(torch.sin(rot))) / col(ax)
    v = (-dx * col(torch.sin(rot)) + dy * col(torch.cos(rot))) / col(ay)
    rho = torch.sqrt(u * u + v * v)
    power = torch.where(steep, draw.uniform((b,), 2.0, 5.0), torch.full((b,), 2.0, device=x.device))
    depth = torch.where(steep, draw.uniform((b,), 1.5, 3.5), draw.uniform((b,), 0.4, 1.2))
    depth = torch.where(full, draw.uniform((b,), 0.1, 0.5), depth)
    inside = rho < 1.0
    r_in = torch.clamp(rho, max=1.0)
    profile = torch.clamp(1.0 - r_in ** col(power), min=0.0) ** (1.0 / col(power))
    height = col(depth * torch.minimum(ax, ay)) * profile
    # Bumps and dents, a few per sample; concave samples get more and deeper dents.
    concave = draw.chance((b,), opts.concave)
    k = 6
    bx = draw.uniform((b, k, 1, 1), -0.6, 0.6) * p
    by = draw.uniform((b, k, 1, 1), -0.6, 0.6) * p
    sig = draw.uniform((b, k, 1, 1), 0.06, 0.4) * size
    p_dent = torch.where(concave, 0.6, 0.3)[:, None, None, None]
    sign = torch.where(draw.uniform((b, k, 1, 1)) < p_dent, -1.0, 1.0)
    amp = sig * draw.uniform((b, k, 1, 1), 0.1, 0.6) * sign
    amp = amp * torch.where(concave, 1.6, 0.6)[:, None, None, None]
    g = torch.exp(-((x[:, None] - bx) ** 2 + (y[:, None] - by) ** 2) / (2 * sig * sig))
    height = height + (amp * g).sum(1)
    # Deep folds: ridges and valleys (amplitude / period up to 0.45) on half the concave samples.
    period = draw.uniform((b,), 0.3, 1.0) * size
    folds = concave & draw.chance((b,), 0.5)
    fold_amp = period * draw.uniform((b,), 0.05, 0.45) * folds
    # The other concave samples get a cup: one deep dent (depth / width 0.8-2) near the crop.
    cup_s = draw.uniform((b,), 0.15, 0.5) * size
    cup_d = cup_s * draw.uniform((b,), 0.8, 2.0) * (concave & ~folds)
    cup_x, cup_y = draw.uniform((b,), -0.4, 0.4) * size, draw.uniform((b,), -0.4, 0.4) * size
    height = height - col(cup_d) * torch.exp(
        -((x - col(cup_x)) ** 2 + (y - col(cup_y)) ** 2) / col(2 * cup_s * cup_s)
    )
    ang = draw.uniform((b,), 0.0, math.pi)
    along = x * col(torch.cos(ang)) + y * col(torch.sin(ang))
    height = height + col(fold_amp) * torch.sin(
        2 * math.pi * along / col(period) + col(draw.uniform((b,), 0.0, 2 * math.pi))
    )
    # 1-3 px relief: engraved grooves (Gaussian profile, 0.5-1.5 px wide) and fine ripples.
    relief = draw.chance((b,), opts.relief)
    lines = 3
    la = draw.uniform((b, lines, 1, 1), 0.0, math.pi)
    lo_ = draw.uniform((b, lines, 1, 1), -0.5, 0.5) * size
    dist = x[:, None] * torch.cos(la) + y[:, None] * torch.sin(la) - lo_
    width = draw.uniform((b, lines, 1, 1), 0.5, 1.5)
    groove = width * draw.uniform((b, lines, 1, 1), 0.3, 1.5)
    engraved = (groove * torch.exp(-(dist**2) / (2 * width * width))).sum(1)
    ripple = _waves(draw, b, x, y, 3, 2.5, 8.0) * col(draw.uniform((b,), 0.02, 0.12))
    height = height + col(relief.float()) * (ripple - engraved)
    support = inside | col(full)
    mask = support.clone()
    # Cuts through a continuous surface: a half plane or a disc, crossing the crop.
    cut = draw.chance((b,), opts.cut)
    disc = draw.chance((b,), 0.5)
    ca = draw.uniform((b,), 0.0, 2 * math.pi)
    co = draw.uniform((b,), -0.35, 0.35) * size
    half = (x * col(torch.cos(ca)) + y * col(torch.sin(ca))) > col(co)
    qx, qy = draw.uniform((b,), -0.3, 0.3) * size, draw.uniform((b,), -0.3, 0.3) * size
    qr = draw.uniform((b,), 0.3, 0.8) * size
    round_ = (x - col(qx)) ** 2 + (y - col(qy)) ** 2 < col(qr * qr)
    keep = torch.where(col(disc), round_, half)
    mask = mask & (keep | ~col(cut))
    return height, support, mask


def normals_from_height(height: Tensor) -> Tensor:
    """(B, P, P) height in px -> (B, 3, P, P) unit normals (central differences, edges
    one-sided through replicate padding)."""
    hp = F.pad(height[:, None], (1, 1, 1, 1), mode="replicate")[:, 0]
    dz_dcol = (hp[:, 1:-1, 2:] - hp[:, 1:-1, :-2]) / 2
    dz_drow = (hp[:, 2:, 1:-1] - hp[:, :-2, 1:-1]) / 2
    # rows run down, y up: dz/dy = -dz/drow, and n ~ (-dz/dx, -dz/dy, 1)
    n = torch.stack([-dz_dcol, dz_drow, torch.ones_like(height)], 1)
    return n / n.norm(dim=1, keepdim=True)


# ----------------------------------------------------------------------------- lights


def _lights(draw: _Draw, b: int, n: int, opts: TorchRenderOptions) -> tuple[Tensor, Tensor]:
    """(B, N, 3) directions (cone or LED ring) and (B, N, 3) RGB intensities."""
    max_deg = draw.uniform((b, 1), *opts.max_light_deg)
    cos_lo = torch.cos(torch.deg2rad(max_deg))
    cz = cos_lo + (1.0 - cos_lo) * draw.uniform((b, n))
    polar = torch.acos(cz.clamp(-1.0, 1.0))
    azim = draw.uniform((b, n), 0.0, 2 * math.pi)
    ring = draw.chance((b, 1), opts.ring_rigs)
    ring_polar = torch.deg2rad(draw.uniform((b, 1), 15.0, 55.0) + draw.uniform((b, n), -1.0, 1.0))
    steps = torch.arange(n, device=draw.device, dtype=torch.float32)[None] * (2 * math.pi / n)
    ring_azim = steps + draw.uniform((b, 1), 0.0, 2 * math.pi)
    polar = torch.where(ring, ring_polar, polar)
    azim = torch.where(ring, ring_azim, azim)
    s = torch.sin(polar)
    dirs = torch.stack([s * torch.cos(azim), s * torch.sin(azim), torch.cos(polar)], -1)
    cast = torch.exp(draw.normal((b, 1, 3), 0.25))
    per_light = torch.exp(draw.normal((b, n, 1)) * draw.uniform((b, 1, 1), 0.05, 0.5))
    per_channel = torch.exp(draw.normal((b, n, 3), 0.05))
    return dirs, cast * per_light * per_channel


# ----------------------------------------------------------------------------- materials


@dataclass
class TorchMaterial:
    """Per-pixel material maps on the padded grid."""

    kd: Tensor  # (B, 3, P, P) diffuse albedo
    f0: Tensor  # (B, 3, P, P) Fresnel reflectance at normal incidence
    ks: Tensor  # (B, P, P) specular gain
    alpha: Tensor  # (B, P, P) GGX roughness


def _colour(draw: _Draw, shape: tuple[int, ...], lo: float, hi: float) -> Tensor:
    """(*shape, 3) random colours, brightness in [lo, hi], random hue and saturation."""
    base = draw.uniform((*shape, 1), lo, hi)
    tint = draw.uniform((*shape, 3)) ** draw.uniform((*shape, 1), 0.1, 2.0)
    tint = tint / tint.mean(-1, keepdim=True).clamp_min(1e-3)
    return (base * tint).clamp(0.005, 0.98)


def _materials(
    draw: _Draw, b: int, x: Tensor, y: Tensor, opts: TorchRenderOptions
) -> tuple[TorchMaterial, Tensor]:
    """Two random materials per sample blended by a smooth random field, and which samples
    are very dark objects (B,) bool."""
    m = 2
    kd = _colour(draw, (b, m), 0.1, 0.9)
    f0 = torch.full((b, m, 3), 0.04, device=draw.device)
    has_spec = draw.chance((b, m), opts.specular)
    ks = draw.uniform((b, m), 0.2, 2.0) * has_spec
    alpha = draw.uniform((b, m), 0.1, 0.8) ** 2  # GGX alpha: perceptual roughness squared
    metal = draw.chance((b, m), opts.metal)
    tint = _colour(draw, (b, m), 0.5, 0.95)
    kd = torch.where(metal[..., None], tint * draw.uniform((b, m, 1), 0.0, 0.15), kd)
    f0 = torch.where(metal[..., None], tint, f0)
    ks = torch.where(metal, draw.uniform((b, m), 0.5, 1.0), ks)
    # dark materials (little diffuse light: the lobe and the noise dominate), and whole very
    # dark objects
    dark_mat = draw.chance((b, m), opts.dark_material)
    kd = torch.where(dark_mat[..., None], kd * draw.uniform((b, m, 1), 0.03, 0.12), kd)
    ks = torch.where(dark_mat, draw.uniform((b, m), 0.5, 2.0), ks)
    dark = draw.chance((b,), opts.dark)
    kd = torch.where(dark[:, None, None], kd * 0.1, kd)
    p = x.shape[-1]
    field = _waves(draw, b, x, y, 3, 0.5 * p, 3.0 * p)
    sharp = torch.exp(draw.uniform((b, 1, 1), math.log(0.5), math.log(20.0)))
    one = draw.chance((b, 1, 1), 0.4)  # a single material
    w = torch.where(one, torch.ones_like(field), torch.sigmoid(sharp * field))  # weight of m 0
    texture = 1.0 + draw.uniform((b, 1, 1), 0.0, 0.25) * _waves(draw, b, x, y, 4, 3.0, 0.5 * p) / 2
    texture = texture.clamp(0.3, 1.7)

    def blend(v: Tensor) -> Tensor:  # (B, m, 3) -> (B, 3, P, P)
        return w[:, None] * v[:, 0, :, None, None] + (1 - w[:, None]) * v[:, 1, :, None, None]

    mat = TorchMaterial(
        kd=blend(kd) * texture[:, None],
        f0=blend(f0),
        ks=w * ks[:, 0, None, None] + (1 - w) * ks[:, 1, None, None],
        alpha=(w * alpha[:, 0, None, None] + (1 - w) * alpha[:, 1, None, None]).clamp(0.005, 1),
    )
    return mat, dark


def shade(
    normals: Tensor, lights: Tensor, mat: TorchMaterial, diffuse_only: bool = False
) -> Tensor:
    """Radiance for unit white lights, (B, N, 3, P, P): diffuse kd / pi + one GGX lobe (the
    formulas of :func:`msfnet.synth.materials.shade` without its optional layers), times the
    clamped cosine; the view is (0, 0, 1)."""
    nl = torch.einsum("bchw,bnc->bnhw", normals, lights)
    cos = nl.clamp_min(0.0)[:, :, None]
    diffuse = mat.kd[:, None] / math.pi
    if diffuse_only:
        return diffuse * cos
    nv = normals[:, 2].clamp_min(1e-3)[:, None]  # (B, 1, P, P)
    half = lights + torch.tensor([0.0, 0.0, 1.0], device=lights.device)
    half = half / half.norm(dim=-1, keepdim=True)
    nh = torch.einsum("bchw,bnc->bnhw", normals, half).clamp(0.0, 1.0)
    vh = half[..., 2].clamp(0.0, 1.0)[..., None, None, None]  # (B, N, 1, 1, 1)
    nlc = nl.clamp_min(1e-4)
    a2 = (mat.alpha**2)[:, None]
    d = a2 / (math.pi * (nh * nh * (a2 - 1.0) + 1.0) ** 2)
    vis = 0.5 / (
        nlc * torch.sqrt(nv * nv * (1 - a2) + a2) + nv * torch.sqrt(nlc * nlc * (1 - a2) + a2)
    )
    fres = mat.f0[:, None] + (1.0 - mat.f0[:, None]) * (1.0 - vh) ** 5
    spec = (mat.ks[:, None] * d * vis)[:, :, None] * fres
    return (diffuse + spec) * cos


# ----------------------------------------------------------------------------- light transport


def cast_shadows(height: Tensor, support: Tensor, lights: Tensor, steps: int) -> Tensor:
    """(B, N, 1, P, P) 1 where lit, 0 where the height field blocks the light (ray marching
    towards the light with nearest-pixel height look-ups at growing distances)."""
    b, p, _ = height.shape
    n = lights.shape[1]
    q = p + 2  # a border of "no surface" around the grid: rays leaving it are never blocked
    z = torch.where(support, height, torch.full_like(height, -1e6))
    z = F.pad(z, (1, 1, 1, 1), value=-1e6).reshape(b, 1, q * q).expand(b, n, q * q)
    lxy = torch.sqrt(lights[..., 0] ** 2 + lights[..., 1] ** 2).clamp_min(1e-3)
    dcol = (lights[..., 0] / lxy)[..., None]
    drow = (-lights[..., 1] / lxy)[..., None]
    rise = (lights[..., 2] / lxy)[..., None]
    idx = torch.arange(p * p, device=height.device)
    rows = (idx // p + 1).float()[None, None]  # in the bordered grid
    cols = (idx % p + 1).float()[None, None]
    base = torch.gather(z, 2, (rows * q + cols).long().expand(b, n, -1)) + 0.5  # self-shadow bias
    blocked = torch.zeros(b, n, p * p, dtype=torch.bool, device=height.device)
    t = 1.0
    for k in range(steps):
        r = torch.round(rows + t * drow).clamp_(0, q - 1)
        c = torch.round(cols + t * dcol).clamp_(0, q - 1)
        zs = torch.gather(z, 2, (r * q + c).long())
        blocked |= zs > base + t * rise
        t += 1.0 + 0.35 * k
        if t > 2 * p:
            break
    return (~blocked).float().reshape(b, n, 1, p, p)


def _bounce_offsets(radii: tuple[float, ...] = (1.5, 3.0, 6.0, 10.0), dirs: int = 8):
    """(row, col) integer offsets on rings and the image area (px^2) each stands for."""
    out = []
    edges = [1.0] + [0.5 * (a + b) for a, b in itertools.pairwise(radii)] + [radii[-1] * 1.3]
    for i, r in enumerate(radii):
        area = math.pi * (edges[i + 1] ** 2 - edges[i] ** 2) / dirs
        for j in range(dirs):
            a = 2 * math.pi * (j + 0.5 * (i % 2)) / dirs
            out.append((round(-r * math.sin(a)), round(r * math.cos(a)), area))
    return out


def bounce(direct: Tensor, height: Tensor, normals: Tensor, support: Tensor, crop: slice) -> Tensor:
    """Irradiance / pi that the pixels of the crop (``crop`` of each grid axis) receive from the
    surface they face, one bounce: the sum over offsets of direct(q) cos_p cos_q / (pi r^2) dA_q
    (no visibility test). ``direct``: (B, N, C, P, P) outgoing diffuse radiance of every grid
    pixel (sources may lie in the margin); returns (B, N, C, S, S)."""
    b, p, _ = height.shape
    offsets = _bounce_offsets()
    pad = max(max(abs(dr), abs(dc)) for dr, dc, _ in offsets)
    s = support.float()
    z = height * s
    n = normals * s[:, None]
    emit = s / normals[:, 2].clamp_min(0.1)  # a wall shows little image area but emits a lot
    zp = F.pad(z, (pad, pad, pad, pad))
    np_ = F.pad(n, (pad, pad, pad, pad))
    ep = F.pad(emit, (pad, pad, pad, pad))
    dp = F.pad(direct.reshape(b, -1, p, p), (pad, pad, pad, pad))
    zc, nc = z[:, crop, crop], n[:, :, crop, crop]
    size = crop.stop - crop.start
    out = direct.new_zeros((b, dp.shape[1], size, size))
    for dr, dc, area in offsets:
        rs = slice(pad + crop.start + dr, pad + crop.stop + dr)
        cs = slice(pad + crop.start + dc, pad + crop.stop + dc)
        dx, dy = float(dc), float(-dr)
        dz = zp[:, rs, cs] - zc
        r2 = (dx * dx + dy * dy + dz * dz).clamp_min(2.25)
        nq = np_[:, :, rs, cs]
        cos_p = (nc[:, 0] * dx + nc[:, 1] * dy + nc[:, 2] * dz).clamp_min(0.0)
        cos_q = (-(nq[:, 0] * dx + nq[:, 1] * dy + nq[:, 2] * dz)).clamp_min(0.0)
        w = cos_p * cos_q / (math.pi * r2 * r2) * ep[:, rs, cs] * area
        out += w[:, None] * dp[:, :, rs, cs]
    out = out * s[:, None, crop, crop]
    return out.reshape(*direct.shape[:3], size, size)


# ----------------------------------------------------------------------------- sensor


def _exposure(draw: _Draw, radiance: Tensor, mask: Tensor, dark: Tensor) -> Tensor:
    """Scale each sample so a high percentile of its object values lands at 40-100 % of full
    scale (very dark ones: the maximum at 25-43 / 255)."""
    b = radiance.shape[0]
    vals = radiance.reshape(b, -1)
    m = mask[:, None, None].expand_as(radiance).reshape(b, -1)
    # the 99.5th percentile of a strided subsample of object values (a quantile of millions
    # per sample would cost more than the render)
    stride = max(1, vals.shape[1] // 8192)
    sub = torch.where(m[:, ::stride], vals[:, ::stride], float("nan"))
    ref = torch.nanquantile(sub, 0.995, dim=1)
    top = torch.where(m, vals, torch.zeros_like(vals)).amax(1)
    ref = torch.where(torch.isnan(ref), torch.ones_like(ref), ref)
    scale = torch.where(
        dark,
        draw.uniform((b,), 25 / 255, 43 / 255) / top.clamp_min(1e-8),
        draw.uniform((b,), 0.4, 1.0) / ref.clamp_min(1e-8),
    )
    return radiance * scale[:, None, None, None, None]


def _sensor(draw: _Draw, signal: Tensor, bit_depths: tuple[int, ...]) -> Tensor:
    b = signal.shape[0]
    shape = (b, 1, 1, 1, 1)
    gain = draw.uniform(shape, 0.0, 2e-4)
    read = draw.uniform(shape, 0.0, 2e-3)
    noisy = signal + draw.normal(tuple(signal.shape)) * torch.sqrt(
        gain * signal.clamp_min(0) + read * read
    )
    depths = torch.tensor(bit_depths, device=signal.device, dtype=torch.float32)
    pick = (draw.uniform((b,)) * len(bit_depths)).long().clamp(max=len(bit_depths) - 1)
    levels = (2.0 ** depths[pick] - 1.0).reshape(shape)
    return torch.round(noisy.clamp(0.0, 1.0) * levels) / levels


# ----------------------------------------------------------------------------- batches


def render_batch(
    batch: int,
    lights: int,
    crop: int,
    gen: torch.Generator,
    options: TorchRenderOptions = TorchRenderOptions(),
    device: torch.device | str | None = None,
) -> RenderedBatch:
    """``batch`` random crops of ``crop`` x ``crop`` px under ``lights`` lights each."""
    dev = torch.device(device) if device is not None else gen.device
    draw = _Draw(gen, dev)
    pad = max(2, round(options.margin * crop))
    p = crop + 2 * pad
    height, support, mask = _shapes(draw, batch, crop, pad, options)
    normals = normals_from_height(height)
    dirs, ints = _lights(draw, batch, lights, options)
    t = torch.arange(p, device=dev, dtype=torch.float32) - (p - 1) / 2
    x, y = t[None, None, :].expand(1, p, p), -t[None, :, None].expand(1, p, p)
    mat, dark = _materials(draw, batch, x, y, options)
    radiance = shade(normals, dirs, mat)
    lit = torch.ones_like(radiance[:, :, :1])
    if options.cast_shadows:
        lit = cast_shadows(height, support, dirs, options.shadow_steps)
    radiance = radiance * lit
    bounced = draw.chance((batch,), options.interreflection)
    gain = draw.uniform((batch,), 0.8, 2.0)
    crop_rows = slice(pad, pad + crop)
    radiance = radiance[..., crop_rows, crop_rows]
    if options.interreflection > 0 and bool(bounced.any()):
        # Only the samples that bounce, only the crop's pixels receiving, and the light carried
        # grey (the source's mean albedo; the receiver's own colour applies): the gather is the
        # renderer's costliest step.
        i = bounced.nonzero().squeeze(1)
        sub = TorchMaterial(mat.kd[i], mat.f0[i], mat.ks[i], mat.alpha[i])
        grey = TorchMaterial(sub.kd.mean(1, keepdim=True), sub.f0, sub.ks, sub.alpha)
        direct = shade(normals[i], dirs[i], grey, diffuse_only=True) * lit[i]
        got = bounce(direct, height[i], normals[i], support[i], crop_rows)
        kd = mat.kd[i][..., crop_rows, crop_rows].clamp(0.0, 0.95)[:, None]
        radiance = radiance.index_add(0, i, gain[i, None, None, None, None] * kd * got)
    radiance = radiance * ints[..., None, None]
    mask_c = mask[:, crop_rows, crop_rows]
    radiance = radiance * mask_c[:, None, None]
    signal = _exposure(draw, radiance, mask_c, dark)
    signal = _sensor(draw, signal, options.bit_depths) if options.noise else signal.clamp(0.0, 1.0)
    normals_c = (normals[..., crop_rows, crop_rows] * mask_c[:, None]).contiguous()
    height_c = height[:, crop_rows, crop_rows].contiguous()
    return RenderedBatch(signal.contiguous(), dirs, ints, normals_c, mask_c.contiguous(), height_c)


def normalise(
    images: Tensor, intensities: Tensor, mask: Tensor, train_lights: int = TRAIN_LIGHTS
) -> Tensor:
    """The network's input normalisation (:func:`msfnet.runtime.infer.normalise.normalise`)
    on batches: images (B, N, 3, H, W), intensities (B, N, 3), mask (B, H, W)."""
    x = images / intensities[..., None, None]
    norm = torch.sqrt((x.double() ** 2).sum(1)).float()  # (B, 3, H, W), float64 sums as there
    scale = math.sqrt(images.shape[1] / train_lights)
    return x * (scale / (norm + 1e-10))[:, None] * mask[:, None, None].to(x.dtype)


def training_tensors(
    rendered: RenderedBatch, gen: torch.Generator, calib_jitter: float = 0.02
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(images, lights, normals, mask) as the training step takes them: the renders normalised
    with slightly wrong intensities (imperfect calibration, as on real rigs)."""
    ints = rendered.intensities
    if calib_jitter > 0:
        noise = torch.randn(ints.shape, generator=gen, device=ints.device) * calib_jitter
        ints = ints * torch.exp(noise)
    x = normalise(rendered.images, ints, rendered.mask)
    return x, rendered.lights, rendered.normals, rendered.mask


__all__ = [
    "RenderedBatch",
    "TorchMaterial",
    "TorchRenderOptions",
    "bounce",
    "cast_shadows",
    "normalise",
    "normals_from_height",
    "render_batch",
    "shade",
    "step_seed",
    "training_tensors",
]
