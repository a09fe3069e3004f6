"""Random height-field shapes: a silhouette, a base profile and surface detail.

Every shape is a height field z(x, y) over the image plane (x right, y up, both in [-1, 1];
row 0 is the top of the image), with an object mask. Normals follow from the gradient:
n = normalise(-dz/dx, -dz/dy, 1). Heights are in the same units as x and y.
"""

from __future__ import annotations

import numpy as np

SHAPES = ("sphere", "blob", "bumps", "creases", "sculpted", "relief")
# Shapes aimed at measured failures on real objects (deep concavities); kept out of SHAPES so the
# default shape draw (and every default render) stays as it was.
EXTRA_SHAPES = ("folds", "cup")
ALL_SHAPES = SHAPES + EXTRA_SHAPES
DEFAULT_MAX_DEPTH = 1.2  # dome height / radius drawn from [0.5, this] (see make_shape)
STEEP_DEPTH = (1.5, 3.5)  # steep profile: height / radius drawn from this range
STEEP_POWER = (2.0, 5.0)  # steep profile: superquadric exponent (2 = ellipsoid, more = boxier)
FOLD_DEPTH = (0.25, 0.6)  # cloth fold amplitude x folds per grid unit (depth / period ~ this / 2)
CUP_DEPTH = (0.5, 1.0)  # cup hollow depth over its opening radius (x max(dome depth, 0.8))


def grid(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre coordinates (x right, y up) in [-1, 1], each (size, size) float64."""
    t = np.linspace(-1.0, 1.0, size)
    x, y = np.meshgrid(t, -t)  # row 0 is y = +1 (the top)
    return x, y


def fourier_noise(
    x: np.ndarray,
    y: np.ndarray,
    rng: np.random.Generator,
    terms: int,
    fmin: float,
    fmax: float,
    slope: float = 1.5,
) -> np.ndarray:
    """Sum of random plane waves, amplitude ~ 1/f^slope: smooth multi-scale relief, unit-ish RMS."""
    f = np.exp(rng.uniform(np.log(fmin), np.log(fmax), terms))
    ang = rng.uniform(0, 2 * np.pi, terms)
    phase = rng.uniform(0, 2 * np.pi, terms)
    amp = f**-slope
    amp /= np.sqrt(np.sum(amp**2) / 2)
    u = np.cos(ang)[:, None, None] * x + np.sin(ang)[:, None, None] * y
    return np.einsum("k,khw->hw", amp, np.cos(np.pi * f[:, None, None] * u + phase[:, None, None]))


def gaussian_bumps(
    x: np.ndarray,
    y: np.ndarray,
    rng: np.random.Generator,
    count: int,
    amp: tuple[float, float],
    sigma: tuple[float, float],
) -> np.ndarray:
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


def silhouette(
    x: np.ndarray, y: np.ndarray, rng: np.random.Generator, wobble: float
) -> tuple[np.ndarray, np.ndarray]:
    """Normalised radius rho (< 1 inside) of a star-shaped outline, and the local radius R."""
    theta = np.arctan2(y, x)
    r0 = rng.uniform(0.6, 0.92)
    radius = np.ones_like(x)
    for k in range(2, 6):
        radius += wobble * rng.uniform(0, 0.15) / k * np.cos(k * theta + rng.uniform(0, 2 * np.pi))
    radius *= r0
    cx, cy = rng.uniform(-0.05, 0.05, 2)
    return np.hypot(x - cx, y - cy) / radius, radius


def dome_profile(rho: np.ndarray, power: float = 2.0) -> np.ndarray:
    """Superquadric dome (1 - rho^p)^(1/p) over the normalised radius; p = 2 is a hemisphere.

    Above 2 the top flattens and the sides turn vertical over a wider band, which is what puts
    many pixels at grazing slant (n_z < 0.3) even at small render sizes."""
    if power == 2.0:  # the original expression, so default renders stay bit-identical
        return np.sqrt(np.clip(1.0 - rho**2, 0.0, None))
    return np.clip(1.0 - np.clip(rho, 0.0, None) ** power, 0.0, None) ** (1.0 / power)


def _trim_outline(inside: np.ndarray) -> np.ndarray:
    """Drop the outermost pixel ring: finite differences across the outline are meaningless."""
    mask = inside.copy()
    mask[1:] &= inside[:-1]
    mask[:-1] &= inside[1:]
    mask[:, 1:] &= inside[:, :-1]
    mask[:, :-1] &= inside[:, 1:]
    return mask


def cloth_folds(
    x: np.ndarray, y: np.ndarray, rng: np.random.Generator, depth: tuple[float, float] = FOLD_DEPTH
) -> np.ndarray:
    """Harvest-like cloth folds: rounded ridges between deep, narrow, curved valleys.

    Along a warped coordinate u, the height is amp * (sin^2 + eps^2)^(g/2) with g < 1: a cusp
    at each zero of the sine (a concave fold with steep walls) and a round top in between."""
    out = np.zeros_like(x)
    for family in range(int(rng.integers(1, 3))):
        ang = rng.uniform(0, np.pi)
        u = np.cos(ang) * x + np.sin(ang) * y
        v = -np.sin(ang) * x + np.cos(ang) * y
        u = u + rng.uniform(0.05, 0.25) * fourier_noise(x, y, rng, 6, 0.5, 2.0)  # curved folds
        freq = rng.uniform(1.5, 4.0)  # folds per grid unit
        s = np.sin(np.pi * freq * u + rng.uniform(0, 2 * np.pi))
        eps = rng.uniform(0.03, 0.15)
        g = rng.uniform(0.35, 0.8)
        amp = rng.uniform(*depth) / freq * (1.0 if family == 0 else 0.5)
        # Folds die out along their length, as cloth folds do.
        along = 0.6 + 0.4 * np.cos(np.pi * rng.uniform(0.3, 1.0) * v + rng.uniform(0, 2 * np.pi))
        out += amp * along * (s * s + eps * eps) ** (g / 2)
    return out


def make_shape(
    kind: str,
    size: int,
    rng: np.random.Generator,
    max_depth: float = DEFAULT_MAX_DEPTH,
    steep: bool = False,
    fold_depth: tuple[float, float] = FOLD_DEPTH,
    cup_depth: tuple[float, float] = CUP_DEPTH,
) -> tuple[np.ndarray, np.ndarray]:
    """(height (H, W) float64, mask (H, W) bool) for one random shape of ``kind``.

    ``max_depth``: the dome's height over its radius is drawn from [0.5, max_depth]; above 1 the
    sides get steeper than a sphere's, so more of the object is seen at grazing slant.
    ``steep``: draw the height / radius from ``STEEP_DEPTH`` and a superquadric profile exponent
    from ``STEEP_POWER`` instead (occluding-contour-like rims; ignored by full-frame shapes).
    ``fold_depth`` / ``cup_depth``: ranges of the folds' and the cup's depth (see ``FOLD_DEPTH``,
    ``CUP_DEPTH``); deeper ones shadow more and bounce more light between their walls."""
    x, y = grid(size)
    if kind == "relief":
        # A full-frame sculpted surface (like a bas-relief or a cloth patch): no silhouette.
        z = 0.12 * fourier_noise(x, y, rng, 24, 1.0, 6.0) + 0.5 * creases(x, y, rng, 2)
        z += gaussian_bumps(x, y, rng, 6, (0.05, 0.2), (0.06, 0.25))
        return z, np.ones_like(z, bool)
    if kind == "folds" and rng.random() < 0.4:
        # A full-frame patch of folded cloth.
        z = cloth_folds(x, y, rng, fold_depth) + 0.05 * fourier_noise(x, y, rng, 8, 0.5, 3.0)
        return z, np.ones_like(x, bool)
    if kind not in ALL_SHAPES:
        raise ValueError(f"unknown shape {kind!r}; choose from {', '.join(ALL_SHAPES)}")
    wobble = 0.0 if kind == "sphere" else 1.0
    rho, radius = silhouette(x, y, rng, wobble)
    inside = rho < 1.0
    power = 2.0
    if steep:
        depth = rng.uniform(*STEEP_DEPTH)
        power = rng.uniform(*STEEP_POWER)
    else:
        depth = 1.0 if kind == "sphere" else rng.uniform(0.5, max_depth)
    dome = dome_profile(rho, power)
    # Scale by the mean radius, not the local one: a theta-dependent height at the centre would
    # make a cone-like singular point there.
    r_mid = float(np.median(radius[inside]))
    z = depth * r_mid * dome
    # Detail fades out towards the outline so silhouettes stay clean.
    fade = np.clip(1.0 - rho**2, 0.0, None)
    if kind == "blob":
        z += fade * (0.06 * fourier_noise(x, y, rng, 8, 1.0, 3.0))
        z += fade * gaussian_bumps(x, y, rng, 3, (0.03, 0.1), (0.15, 0.35))
    elif kind == "bumps":
        z += fade * gaussian_bumps(x, y, rng, int(rng.integers(6, 20)), (0.02, 0.12), (0.04, 0.18))
    elif kind == "creases":
        z += fade * 0.5 * creases(x, y, rng, int(rng.integers(1, 4)))
    elif kind == "sculpted":
        z += fade * (0.08 * fourier_noise(x, y, rng, 32, 1.0, 10.0, slope=1.2))
        z += fade * 0.3 * creases(x, y, rng, int(rng.integers(0, 3)))
        z += fade * gaussian_bumps(x, y, rng, 5, (0.02, 0.08), (0.04, 0.12))
    elif kind == "folds":
        # A rounded bag-like object covered in folds (like DiLiGenT harvest).
        z += np.sqrt(fade) * cloth_folds(x, y, rng, fold_depth)
    elif kind == "cup":
        # A bowl: a cavity of normalised radius a sunk into the dome, with a rounded lip. Its
        # inner wall starts vertical at the lip, so it is steep, self-shadowing and concave.
        a = rng.uniform(0.45, 0.8)
        lip = depth * r_mid * float(dome_profile(np.array(a), power))
        hollow = rng.uniform(*cup_depth) * a * r_mid * max(depth, 0.8)
        bowl = lip - hollow * dome_profile(rho / a, rng.uniform(2.0, 3.0))
        z = np.where(rho < a, bowl, z)
        width = rng.uniform(0.04, 0.1)
        z += rng.uniform(0.2, 0.6) * width * r_mid * np.exp(-(((rho - a) / width) ** 2))
    return np.where(inside, z, 0.0), _trim_outline(inside)


# ----------------------------------------------------------------------------- fine relief
# Real objects carry relief at the scale of a few pixels (engraving, scratches, weave, stamped
# lettering) that a network trained on smooth renders learns to smooth away. These are built in
# *pixel* units and converted to grid units at the end, so a groove stays 1-3 px wide whatever
# the render size (a [-1, 1]-grid pattern would get finer per pixel as renders shrink and
# vanish as they grow).

RELIEF_KINDS = ("engraving", "scratches", "weave", "lettering")


def _segment_profile(
    size: int, seg: np.ndarray, width: np.ndarray, weight: np.ndarray | float = 1.0
) -> np.ndarray:
    """max over segments of weight * exp(-(d / w)^2), d = pixel distance to the segment, (H, W).

    seg (K, 4) = (r0, c0, r1, c1) in pixels, width (K,) in pixels. Each segment is evaluated
    only in its own bounding box (plus 3 widths), where its profile is not negligible: strokes
    are a few pixels long, so this is far cheaper than a (K, H, W) distance field."""
    out = np.zeros((size, size))
    weight = np.broadcast_to(np.asarray(weight, np.float64), (len(seg),))
    for (r0, c0, r1, c1), w, a in zip(seg, width, weight, strict=True):
        pad = 3.0 * w
        rlo, rhi = max(int(min(r0, r1) - pad), 0), min(int(max(r0, r1) + pad) + 2, size)
        clo, chi = max(int(min(c0, c1) - pad), 0), min(int(max(c0, c1) + pad) + 2, size)
        if rlo >= rhi or clo >= chi:
            continue  # entirely off the frame
        rr, cc = np.mgrid[rlo:rhi, clo:chi].astype(np.float64)
        dr, dc = r1 - r0, c1 - c0
        t = np.clip(((rr - r0) * dr + (cc - c0) * dc) / max(dr * dr + dc * dc, 1e-9), 0.0, 1.0)
        d2 = (rr - r0 - t * dr) ** 2 + (cc - c0 - t * dc) ** 2
        win = out[rlo:rhi, clo:chi]
        np.maximum(win, a * np.exp(-d2 / (w * w)), out=win)
    return out


def _polyline(
    rng: np.random.Generator,
    start: np.ndarray,
    heading: float,
    steps: int,
    step_px: float,
    turn: float,
) -> np.ndarray:
    """Segments (steps, 4) of a smoothly turning random walk in pixel coordinates."""
    headings = heading + np.cumsum(rng.normal(0.0, turn, steps))
    moves = step_px * np.stack([np.sin(headings), np.cos(headings)], axis=1)
    pts = start + np.concatenate([[[0.0, 0.0]], np.cumsum(moves, axis=0)])
    return np.concatenate([pts[:-1], pts[1:]], axis=1)


def _engraving(size: int, rng: np.random.Generator) -> np.ndarray:
    segs = [
        _polyline(
            rng,
            rng.uniform(0, size, 2),
            rng.uniform(0, 2 * np.pi),
            int(rng.integers(6, 20)),
            rng.uniform(2.0, 6.0),
            rng.uniform(0.1, 0.5),
        )
        for _ in range(int(rng.integers(2, 7)))
    ]
    seg = np.concatenate(segs)
    width = np.full(len(seg), rng.uniform(0.6, 1.4))
    return -rng.uniform(0.4, 1.5) * _segment_profile(size, seg, width)


def _scratches(size: int, rng: np.random.Generator) -> np.ndarray:
    k = int(rng.integers(10, 50))
    centre = rng.uniform(0, size, (k, 2))
    # Scratches share a dominant direction (wiping, brushing), with some scatter.
    ang = rng.uniform(0, np.pi) + rng.normal(0.0, rng.uniform(0.05, 0.6), k)
    half = rng.uniform(3.0, 0.25 * size + 3.0, k)[:, None]
    d = np.stack([np.sin(ang), np.cos(ang)], axis=1) * half
    seg = np.concatenate([centre - d, centre + d], axis=1)
    depth = rng.uniform(0.2, 0.8, k)
    width = rng.uniform(0.4, 0.9, k)
    return -_segment_profile(size, seg, width, depth)


def _weave(size: int, rng: np.random.Generator) -> np.ndarray:
    """Plain weave: threads along u and v that pass over and under each other every period."""
    rows, cols = np.mgrid[0:size, 0:size].astype(np.float64)
    period = rng.uniform(2.5, 6.0)  # thread spacing in pixels
    ang = rng.uniform(0, np.pi)
    u = (np.cos(ang) * cols + np.sin(ang) * rows) / period
    v = (-np.sin(ang) * cols + np.cos(ang) * rows) / period
    warp = np.abs(np.cos(np.pi * v)) ** 0.7  # cross-section of the threads running along u
    weft = np.abs(np.cos(np.pi * u)) ** 0.7
    over = 0.5 + 0.5 * np.sin(np.pi * u) * np.sin(np.pi * v)  # which thread is on top
    return rng.uniform(0.2, 0.7) * (over * warp + (1.0 - over) * weft)


def _lettering(size: int, rng: np.random.Generator) -> np.ndarray:
    """Lines of glyph-like strokes (stamped or engraved text): 2-4 strokes per glyph cell, their
    ends on a 3 x 4 lattice in the cell, cells along a baseline."""
    segs, widths = [], []
    for _ in range(int(rng.integers(1, 4))):
        height = rng.uniform(5.0, 12.0)  # glyph height in pixels
        ang = rng.uniform(-0.5, 0.5) + (np.pi / 2 if rng.random() < 0.2 else 0.0)
        along = np.array([np.sin(ang), np.cos(ang)])  # (drow, dcol) along the baseline
        up = np.array([-np.cos(ang), np.sin(ang)])
        origin = rng.uniform(0.1 * size, 0.9 * size, 2)
        w = rng.uniform(0.5, 1.2)
        for g in range(int(rng.integers(3, 12))):
            cell = origin + along * g * 0.8 * height
            ends = (
                rng.integers(0, 3, (int(rng.integers(2, 5)), 2)),
                rng.integers(0, 4, (int(rng.integers(2, 5)), 2)),
            )
            n = min(len(ends[0]), len(ends[1]))
            for (i0, i1), (j0, j1) in zip(ends[0][:n], ends[1][:n], strict=True):
                p0 = cell + along * i0 * 0.3 * height + up * j0 * height / 3
                p1 = cell + along * i1 * 0.3 * height + up * j1 * height / 3
                segs.append(np.concatenate([p0, p1]))
                widths.append(w)
    prof = _segment_profile(size, np.asarray(segs), np.asarray(widths))
    return rng.choice([-1.0, 1.0]) * rng.uniform(0.4, 1.5) * prof


def fine_relief(
    size: int, rng: np.random.Generator, kinds: tuple[str, ...] = RELIEF_KINDS
) -> np.ndarray:
    """Pixel-scale relief, (size, size) heights in grid units, over a random part of the frame.

    One to three of ``kinds`` are drawn; depths are 0.2-1.5 px and widths / periods 1-6 px, so
    the normals tilt by up to ~40 deg over 1-3 px."""
    makers = dict(zip(RELIEF_KINDS, (_engraving, _scratches, _weave, _lettering), strict=True))
    picks = rng.choice(len(kinds), size=min(len(kinds), int(rng.integers(1, 4))), replace=False)
    x, y = grid(size)
    z = np.zeros((size, size))
    for i in picks:
        part = makers[kinds[int(i)]](size, rng)
        # Each kind covers a random smooth region (a label, a worn patch), not the whole object.
        region = fourier_noise(x, y, rng, 6, 0.5, 2.0) + rng.uniform(-0.2, 1.5)
        z += part / (1.0 + np.exp(-6.0 * region))
    return z * (2.0 / (size - 1))  # pixels -> grid units


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
    r2 = (x * x + y * y) / radius**2
    mask = r2 < 1.0
    n = np.stack([x / radius, y / radius, np.sqrt(np.clip(1 - r2, 0, None))], axis=-1)
    n[~mask] = 0.0
    return n, mask
