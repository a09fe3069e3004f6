"""Rendered inspection plates: a flat part under an LED ring with known relief defects.

What an inspection station sees: a nearly flat plate (slightly tilted), lit by a ring of 12-16
LEDs, with relief defects of known size (scratches at least 2 px wide and a fraction of a pixel
deep, round dents) and printed marks that change only the albedo (ink: no relief, so they must
never be reported as defects). The plate fills the image except a strip of true background (a
dark, unlit region below the part, like a DiLiGenT silhouette), and the *user's* mask stops at a
column where the surface continues (``mask_edge``): the case where a network that sees zeros
beyond the mask draws a rim that is not there. ``roi`` is a crop whose right edge also cuts
through the surface.

Heights are in pixels (one unit of z = one pixel pitch), so "0.25 px deep" means what an
inspection engineer means. Shading is :func:`msfnet.synth.materials.shade` (Lambert for the
matte plate, Lambert + a GGX lobe for the glossy one); everything is a function of the seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from msfnet.runtime.stack import Stack
from msfnet.synth.lights import led_ring_lights
from msfnet.synth.materials import MaterialMap, shade

FULL_SCALE = 65535.0


@dataclass(frozen=True)
class PlateOptions:
    """height, width: image size; lights: LEDs on the ring, ``ring_deg`` off the camera axis;
    glossy: add a specular lobe (biases least squares); bend: the dome's slope at the edge
    midpoints (tan of the angle); relief: False renders the same plate (tilt, bow, marks,
    lights) without its defects, a golden reference; background_rows: true background strip
    at the bottom; mask_edge: the user's mask ends at this column (None: no cut); noise: the
    read/shot noise's standard deviation as a fraction of full scale."""

    height: int = 128
    width: int = 192
    lights: int = 12
    ring_deg: float = 35.0
    glossy: bool = False
    background_rows: int = 16
    mask_edge: int | None = 144
    noise: float = 1e-3
    bend: float = 0.3
    relief: bool = True
    seed: int = 0

    def __post_init__(self) -> None:
        if not 3 <= self.lights <= 64:
            raise ValueError(f"a plate needs 3-64 lights, got {self.lights}")
        if self.height < 64 or self.width < 96:
            raise ValueError("a plate is at least 96 x 64 px")


@dataclass(frozen=True)
class Defect:
    """A relief defect: ``kind`` "scratch" or "dent"; centre (row, col) in px; depth in px
    (below the surface); width in px (scratch: full width; dent: diameter); label in
    :attr:`Plate.defects`."""

    kind: str
    centre: tuple[float, float]
    depth: float
    width: float
    label: int


@dataclass
class Plate:
    """One rendered plate. ``stack.mask`` is the user's mask (cut at ``mask_edge``);
    ``surface`` is where the plate really is (everything but the background strip); ``height``
    (px) and ``normals`` are the ground truth over the whole surface; ``defects`` labels each
    relief defect's footprint (0 = none); ``marks`` is the printed ink; ``roi`` (x, y, w, h) a
    crop whose right edge cuts through the surface."""

    stack: Stack
    surface: np.ndarray
    height: np.ndarray
    normals: np.ndarray
    defects: np.ndarray
    marks: np.ndarray
    defect_list: tuple[Defect, ...]
    roi: tuple[int, int, int, int]
    options: PlateOptions


def _scratch(
    rows: np.ndarray, cols: np.ndarray, p0: np.ndarray, p1: np.ndarray, width: float, depth: float
) -> tuple[np.ndarray, np.ndarray]:
    """Depth profile (cosine cross-section, full width ``width``) of a straight scratch from p0 to
    p1 (row, col), and its footprint."""
    d = p1 - p0
    length = float(np.hypot(*d))
    t = ((rows - p0[0]) * d[0] + (cols - p0[1]) * d[1]) / length**2
    t = np.clip(t, 0.0, 1.0)
    dist = np.hypot(rows - (p0[0] + t * d[0]), cols - (p0[1] + t * d[1]))
    half = width / 2.0
    inside = dist < half
    profile = np.where(inside, 0.5 * (1.0 + np.cos(np.pi * dist / half)), 0.0)
    return depth * profile, inside


def _dent(
    rows: np.ndarray, cols: np.ndarray, centre: np.ndarray, diameter: float, depth: float
) -> tuple[np.ndarray, np.ndarray]:
    r = np.hypot(rows - centre[0], cols - centre[1])
    half = diameter / 2.0
    inside = r < half
    return depth * np.where(inside, 0.5 * (1.0 + np.cos(np.pi * r / half)), 0.0), inside


def _height_normals(z: np.ndarray) -> np.ndarray:
    """Unit normals of a height field in px (x right, y up: dz/dy = -dz/drow)."""
    dz_drow, dz_dcol = np.gradient(z)
    n = np.stack([-dz_dcol, dz_drow, np.ones_like(z)], axis=-1)
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


def render_plate(options: PlateOptions | None = None) -> Plate:
    """Render one plate (see the module notes). Deterministic per ``options.seed``."""
    o = options or PlateOptions()
    rng = np.random.default_rng([o.seed, 2024])
    h, w = o.height, o.width
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    surface = np.ones((h, w), bool)
    surface[h - o.background_rows :] = False
    # the part's tilt: a plane of up to ~3 deg, which the height map must not be dominated by
    tilt = rng.uniform(-0.05, 0.05, 2)
    z = tilt[0] * (cols - w / 2) + tilt[1] * (rows - h / 2)
    # a gentle dome (slopes up to ``bend`` at the corners): real "flat" parts are not, and on a
    # perfectly flat one every pixel would see the same highlight
    u, v = (cols - w / 2) / (w / 2), (rows - h / 2) / (h / 2)
    z = z - 0.25 * o.bend * (u * u * w / 2 + v * v * h / 2)
    depth_map = np.zeros((h, w))
    labels = np.zeros((h, w), np.int32)
    found: list[Defect] = []
    usable_h = h - o.background_rows

    def add(kind: str, centre: np.ndarray, depth: float, width: float, shape: tuple) -> None:
        nonlocal depth_map
        prof, inside = shape
        depth_map = np.maximum(depth_map, prof)
        label = len(found) + 1
        labels[inside & (labels == 0)] = label
        found.append(Defect(kind, (float(centre[0]), float(centre[1])), depth, width, label))

    # scratches: >= 2 px wide, 0.2-0.3 px deep, roughly horizontal and vertical so one crosses
    # the region near the mask edge as well
    specs = [
        ("scratch", (0.25, 0.08), (0.25, 0.45)),
        ("scratch", (0.55, 0.30), (0.80, 0.62)),
        ("scratch", (0.15, 0.62), (0.70, 0.70)),
    ]
    for kind, a, b in specs:
        p0 = np.array([a[0] * usable_h, a[1] * w]) + rng.uniform(-2, 2, 2)
        p1 = np.array([b[0] * usable_h, b[1] * w]) + rng.uniform(-2, 2, 2)
        width = float(rng.uniform(2.0, 3.0))
        depth = float(rng.uniform(0.2, 0.3))
        add(kind, (p0 + p1) / 2, depth, width, _scratch(rows, cols, p0, p1, width, depth))
    for cy, cx in ((0.70, 0.15), (0.35, 0.70)):
        centre = np.array([cy * usable_h, cx * w]) + rng.uniform(-2, 2, 2)
        diameter = float(rng.uniform(7.0, 10.0))
        depth = float(rng.uniform(0.4, 0.7))
        add("dent", centre, depth, diameter, _dent(rows, cols, centre, diameter, depth))
    if o.relief:
        z = z - depth_map
    normals = _height_normals(z)
    normals[~surface] = 0.0
    labels[~surface] = 0
    # printed marks: dark ink bars and dots, albedo only (no relief)
    marks = np.zeros((h, w), bool)
    for cy, cx, bh, bw in ((0.12, 0.30, 4, 18), (0.85, 0.40, 6, 6), (0.50, 0.10, 10, 3)):
        y0, x0 = int(cy * usable_h), int(cx * w)
        marks[y0 : y0 + bh, x0 : x0 + bw] = True
    marks &= surface & (labels == 0)
    if not o.relief:  # the same marks as the defective plate's; no defect to label
        labels[:] = 0
        found = []
    kd = np.full((h, w, 3), 0.7, np.float32) * np.array([1.0, 0.95, 0.9], np.float32)
    kd[marks] *= 0.25
    ks = np.full((h, w), 1.0 if o.glossy else 0.0, np.float32)
    mat = MaterialMap(
        kd=kd,
        f0=np.full((h, w, 3), 0.04, np.float32),
        ks=ks,
        alpha=np.full((h, w), 0.08 if o.glossy else 0.15, np.float32),
    )
    lights = led_ring_lights(o.lights, rng, (o.ring_deg,), jitter_deg=0.5)
    radiance = shade(normals, lights, mat)  # (N, H, W, 3)
    radiance[:, ~surface] = 0.0
    scale = 0.6 / max(float(np.percentile(radiance[:, surface], 99.0)), 1e-12)
    signal = radiance * np.float32(scale)
    if o.noise > 0:
        signal = signal + rng.standard_normal(signal.shape).astype(np.float32) * np.float32(o.noise)
    images = np.rint(np.clip(signal, 0.0, 1.0) * FULL_SCALE).astype(np.uint16)
    mask = surface.copy()
    if o.mask_edge is not None:
        mask[:, o.mask_edge :] = False
    stack = Stack.from_arrays(
        images,
        lights,
        mask=mask,
        normals_gt=np.where(mask[..., None], normals, 0.0).astype(np.float32),
        name=f"plate-{'glossy' if o.glossy else 'matte'}-{o.seed}",
    )
    roi = (16, 0, min(112, w - 16), usable_h)  # x, y, w, h: right edge at x = 128 cuts the plate
    return Plate(stack, surface, z.astype(np.float32), normals, labels, marks, tuple(found), roi, o)


__all__ = ["Defect", "Plate", "PlateOptions", "render_plate"]
