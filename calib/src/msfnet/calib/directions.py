"""Light directions from the highlights on mirror (chrome) spheres.

For each image and sphere: find the highlight blob (sub-pixel, robust to saturation and bloom),
reflect the view ray about the sphere normal at every blob pixel and average those reflected
directions, weighted by brightness above the blob threshold and by each pixel's footprint on the
sphere of directions (1 / n.v), so a foreshortened highlight near the rim is not biased inwards.
Estimates from several spheres or captures are averaged by confidence.

Output frame (DiLiGenT): x right, y up, z toward the camera.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from msfnet.calib.sphere import Circle, finite_lstsq
from msfnet.common.camera import Intrinsics
from msfnet.common.errors import InputError
from msfnet.common.vocabulary import opt
from msfnet.runtime.evaluate.metrics import angular_error_deg


@dataclass
class LightEstimate:
    """One highlight on one sphere in one image."""

    direction: np.ndarray | None  # (3,) unit, or None when no highlight was found
    x: float = float("nan")  # weighted image centroid (diagnostics)
    y: float = float("nan")
    snr: float = 0.0
    saturated: float = 0.0  # share of blob pixels at the white level
    touches_rim: bool = False
    second_ratio: float = 0.0  # brightness of the strongest other blob relative to this one
    confidence: float = 0.0
    sphere: int = 0
    capture: int = 0
    peak_level: float = float("nan")  # brightest sphere pixel / white level (no highlight: why)


@dataclass
class DirectionResult:
    directions: np.ndarray  # (N, 3) float64 unit
    confidence: np.ndarray  # (N,) 0..1
    estimates: list[list[LightEstimate]]  # per light, every sphere x capture
    spread_deg: np.ndarray  # (N,) largest angle of a single estimate from the average
    warnings: list[str] = field(default_factory=list)


def sphere_geometry(
    circle: Circle, x: np.ndarray, y: np.ndarray, intrinsics: Intrinsics | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals and unit view vectors (toward the camera) at pixels on the sphere."""
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    if intrinsics is None:
        nx = (x - circle.cx) / circle.r
        ny = -(y - circle.cy) / circle.r
        nz = np.sqrt(np.clip(1.0 - nx * nx - ny * ny, 0.0, None))
        n = np.stack([nx, ny, nz], -1)
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        return n, np.broadcast_to(np.array([0.0, 0.0, 1.0]), n.shape)
    # Perspective: the silhouette is a cone of rays d with d.c = cos(alpha) around the sphere's
    # centre direction c. Fit c/cos(alpha) linearly from rays through the circle's outline.
    th = np.linspace(0, 2 * np.pi, 90, endpoint=False)
    edge = intrinsics.rays(circle.cx + circle.r * np.cos(th), circle.cy + circle.r * np.sin(th))
    cvec = finite_lstsq(edge, np.ones(len(th)), "the sphere's outline rays")
    cos_a = 1.0 / np.linalg.norm(cvec)
    c = cvec * cos_a
    dist = 1.0 / np.sqrt(max(1.0 - cos_a * cos_a, 1e-12))  # sphere radius 1
    centre = c * dist
    d = intrinsics.rays(x, y)
    b = d @ centre
    disc = np.clip(b * b - (centre @ centre - 1.0), 0.0, None)  # clip: rays grazing the rim
    t = b - np.sqrt(disc)
    n = t[..., None] * d - centre
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return n, -d


def reflect(n: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Mirror direction of v about n (both unit): the light that makes a highlight there."""
    r = 2.0 * np.sum(n * v, -1, keepdims=True) * n - v
    return r / np.linalg.norm(r, axis=-1, keepdims=True)


def _grey(img: np.ndarray) -> np.ndarray:
    a = np.asarray(img, np.float64)
    return a.mean(axis=-1) if a.ndim == 3 else a


def find_highlight(
    img: np.ndarray,
    circle: Circle,
    white_level: float,
    intrinsics: Intrinsics | None = None,
    min_snr: float = 8.0,
    level: float = 0.5,
) -> LightEstimate:
    """The brightest blob on the sphere and the light direction it implies."""
    g = _grey(img)
    h, w = g.shape
    inside = circle.contains(h, w)
    if inside.sum() < 20:
        return LightEstimate(None)
    vals = g[inside]
    bg = float(np.median(vals))
    noise = 1.4826 * float(np.median(np.abs(vals - bg))) + 0.5 * white_level / 255.0
    smooth = cv2.GaussianBlur(g.astype(np.float32), (0, 0), 1.0)
    smooth[~inside] = -np.inf
    py, px = np.unravel_index(int(np.argmax(smooth)), smooth.shape)
    peak = float(g[inside].max())
    snr = (peak - bg) / noise
    if snr < min_snr:
        # why there is none: a sphere at the white level is over-exposed, not dark
        return LightEstimate(
            None,
            snr=snr,
            saturated=float(np.mean(vals >= 0.99 * white_level)),
            peak_level=peak / white_level,
        )
    thr = bg + level * (peak - bg)
    count, labels = cv2.connectedComponents(((g > thr) & inside).astype(np.uint8), connectivity=8)
    blob = labels == labels[py, px]
    if labels[py, px] == 0:  # smoothed peak fell between pixels above threshold
        sums = np.bincount(labels.ravel(), weights=np.clip(g - thr, 0, None).ravel())
        sums[0] = 0
        blob = labels == int(np.argmax(sums))
    # The strongest other blob (two similar highlights make the answer ambiguous).
    others = [
        float(g[labels == k].max())
        for k in range(1, count)
        if not blob[labels == k].any() and (labels == k).sum() >= 2
    ]
    second = (max(others) - bg) / (peak - bg) if others else 0.0
    ys, xs = np.nonzero(blob)
    wts = g[ys, xs] - thr
    n, v = sphere_geometry(circle, xs.astype(np.float64), ys.astype(np.float64), intrinsics)
    ndotv = np.sum(n * v, -1)
    r = reflect(n, v)
    # Footprint of a pixel on the sphere of directions grows as 1/(n.v): weighting by it gives
    # the centre of the light source itself, not of its foreshortened image.
    wr = wts / np.maximum(ndotv, 0.05)
    d = (r * wr[:, None]).sum(0)
    d /= np.linalg.norm(d)
    dist = np.hypot(xs - circle.cx, ys - circle.cy)
    rim = bool(np.any(dist > circle.r - 1.5))
    sat = float(np.mean(g[ys, xs] >= 0.99 * white_level))
    est = LightEstimate(
        d,
        float((xs * wts).sum() / wts.sum()),
        float((ys * wts).sum() / wts.sum()),
        float(snr),
        sat,
        rim,
        float(second),
    )
    nz = float(np.sum((wts[:, None] * n).sum(0) / wts.sum() * np.array([0, 0, 1.0])))
    c_snr = float(np.clip(np.log10(snr / min_snr), 0.0, 1.0))
    c_rim = 0.2 if rim else float(np.clip(nz / 0.25, 0.0, 1.0))
    c_unique = float(np.clip(1.0 - second, 0.0, 1.0))
    est.confidence = c_snr * c_rim * c_unique
    return est


def white_level_of(arr: np.ndarray) -> float:
    if arr.dtype == np.uint8:
        return 255.0
    if arr.dtype == np.uint16:
        return 65535.0
    return float(np.max(arr))


def estimate_directions(
    captures: list[np.ndarray],
    circles: list[list[Circle]],
    intrinsics: Intrinsics | None = None,
    ambient: list[np.ndarray | None] | None = None,
    white_level: float | None = None,
    names: list[str] | None = None,
    min_snr: float = 8.0,
    source: str | Path | None = None,
    fitted: list[bool] | None = None,
) -> DirectionResult:
    """Light directions from one or more captures (each (N, H, W[, 3])) of mirror spheres.

    ``circles[k]`` lists the spheres of capture k. All captures must have the same N lights.
    ``source``: the file or folder an error names (the first capture's folder).
    ``fitted[k]``: capture k's spheres were fitted from the images (no mask), so a missing
    highlight may be a wrong circle.
    """
    if not captures:
        raise InputError("no images given")
    nlights = len(captures[0])
    if any(len(c) != nlights for c in captures):
        raise InputError(
            f"captures have different image counts: {[len(c) for c in captures]}", source
        )
    names = names or [f"image {i + 1}" for i in range(nlights)]
    per_light: list[list[LightEstimate]] = [[] for _ in range(nlights)]
    for k, cap in enumerate(captures):
        wl = white_level if white_level is not None else white_level_of(np.asarray(cap))
        amb = ambient[k] if ambient else None
        for i in range(nlights):
            img = np.asarray(cap[i], np.float64)
            if amb is not None:
                img = np.clip(img - np.asarray(amb, np.float64), 0.0, None)
            for s, circ in enumerate(circles[k]):
                est = find_highlight(img, circ, wl, intrinsics, min_snr)
                est.sphere, est.capture = s, k
                per_light[i].append(est)
    dirs = np.zeros((nlights, 3))
    conf = np.zeros(nlights)
    spread = np.zeros(nlights)
    warnings: list[str] = []
    missing = []
    for i, ests in enumerate(per_light):
        where = lambda e: (  # noqa: E731
            f"sphere {e.sphere + 1}" + (f", capture {e.capture + 1}" if len(captures) > 1 else "")
        )
        for e in ests:
            if e.direction is None:
                warnings.append(
                    f"{names[i]}: no highlight on {where(e)} "
                    f"(peak only {e.snr:.1f} noise levels above the sphere)"
                )
            else:
                if e.touches_rim:
                    warnings.append(
                        f"{names[i]}: highlight clipped at the rim of {where(e)}; "
                        "direction unreliable"
                    )
                if e.second_ratio > 0.5:
                    warnings.append(
                        f"{names[i]}: a second highlight {e.second_ratio:.0%} as "
                        f"bright on {where(e)}; check for stray light"
                    )
        good = [e for e in ests if e.direction is not None]
        if not good:
            missing.append(names[i])
            continue
        wts = np.array([max(e.confidence, 1e-3) for e in good])
        d = (np.array([e.direction for e in good]) * wts[:, None]).sum(0)
        d /= np.linalg.norm(d)
        dirs[i] = d
        spread[i] = max(float(angular_error_deg(np.asarray(e.direction), d)) for e in good)
        agree = float(np.clip(1.0 - spread[i] / 5.0, 0.0, 1.0))
        conf[i] = float(np.mean([e.confidence for e in good])) * agree * len(good) / len(ests)
        if spread[i] > 2.0:
            warnings.append(f"{names[i]}: spheres/captures disagree by up to {spread[i]:.1f} deg")
    if missing:
        failed = [per_light[names.index(m)] for m in missing]
        guessed = any(fitted[e.capture] for ests in failed for e in ests) if fitted else False
        raise InputError(
            f"no highlight found for {len(missing)} light(s): "
            f"{', '.join(missing[:6])}{' ...' if len(missing) > 6 else ''} "
            f"({_why_none(failed, guessed)})",
            source,
        )
    return DirectionResult(dirs, conf, per_light, spread, warnings)


def light_labels(names: list[str]) -> list[str]:
    """The number each light goes by in its file name (``chrome.0.tga`` -> ``0``, ``007.png``
    -> ``7``), so the diagnostic, the printout and the files agree; 1-based positions when
    the names carry no distinct numbers."""
    found = [re.search(r"(\d+)\D*$", Path(n).stem) for n in names]
    numbers = [str(int(m.group(1))) for m in found if m]
    if len(numbers) == len(names) and len(set(numbers)) == len(numbers):
        return numbers
    return [str(i + 1) for i in range(len(names))]


Box = tuple[int, int, int, int]  # x0, y0, x1, y1 in pixels, exclusive ends


def _overlap(a: Box, b: Box) -> int:
    return max(0, min(a[2], b[2]) - max(a[0], b[0])) * max(0, min(a[3], b[3]) - max(a[1], b[1]))


def _clamped(cx: float, cy: float, w: int, h: int, shape: tuple[int, int]) -> Box:
    """The w x h box centred on (cx, cy), moved inside a picture of ``shape``."""
    x0 = min(max(round(cx - w / 2), 0), shape[1] - w)
    y0 = min(max(round(cy - h / 2), 0), shape[0] - h)
    return x0, y0, x0 + w, y0 + h


def place_labels(
    points: list[tuple[int, int]],
    sizes: list[tuple[int, int]],
    shape: tuple[int, int],
    marker: int = 5,
) -> list[Box]:
    """Boxes for text labels of ``sizes`` (w, h) for marks at ``points``, none covering
    another label or a mark (``marker`` px either way), in a picture of ``shape``.

    A label goes right beside its mark where that spot is free and nearer its own mark than
    any other (so it cannot be read as another's); otherwise it is called out to a ring
    around the whole group, at the mark's own bearing where free (the caller draws a leader
    line). A cluster of highlights on a chrome sphere otherwise stacks its numbers on one
    another."""
    if not points:
        return []
    pts = np.asarray(points, np.float64)
    centre = pts.mean(axis=0)
    spread = float(np.linalg.norm(pts - centre, axis=1).max())
    markers: list[Box] = [
        (int(x) - marker, int(y) - marker, int(x) + marker + 1, int(y) + marker + 1)
        for x, y in points
    ]
    placed: list[Box] = []

    def free(box: Box) -> bool:
        return all(_overlap(box, o) == 0 for o in placed + markers)

    def own(box: Box, i: int) -> bool:
        mid = np.array([(box[0] + box[2]) / 2, (box[1] + box[3]) / 2])
        dist = np.linalg.norm(pts - mid, axis=1)
        return bool(np.all(dist[i] * 1.5 < np.delete(dist, i)))

    def crosses(p: tuple[int, int], box: Box) -> bool:
        """Whether the leader line from mark p to box runs through a placed label."""
        near = (min(max(p[0], box[0]), box[2]), min(max(p[1], box[1]), box[3]))
        steps = np.linspace(0, 1, 24)[:, None]
        line = np.asarray(p) + steps * (np.asarray(near) - np.asarray(p))
        xs, ys = line[:, 0], line[:, 1]
        return any(((xs > o[0]) & (xs < o[2]) & (ys > o[1]) & (ys < o[3])).any() for o in placed)

    bearing = np.arctan2(pts[:, 1] - centre[1], pts[:, 0] - centre[0])
    boxes: list[Box | None] = [None] * len(points)
    # first every label that fits beside its own mark, then the others called out
    for i in range(len(points)):
        (x, y), (w, h) = points[i], sizes[i]
        away = float(bearing[i]) if spread > 0 else -np.pi / 4
        for t in np.radians([0, 45, -45, 90, -90, 135, -135, 180]):
            r = marker + 2 + max(w, h) / 2
            box = _clamped(x + r * np.cos(away + t), y + r * np.sin(away + t), w, h, shape)
            if free(box) and own(box, i):
                placed.append(box)
                boxes[i] = box
                break
    # callouts round the ring in bearing order, so their leader lines do not cross
    for i in (int(j) for j in np.argsort(bearing) if boxes[j] is None):
        (w, h), away = sizes[i], float(bearing[i]) if spread > 0 else -np.pi / 4
        ring = spread + marker + 10 + max(w, h)

        def at(dist: float, angle: float, w: int = w, h: int = h) -> Box:
            return _clamped(
                centre[0] + dist * np.cos(angle), centre[1] + dist * np.sin(angle), w, h, shape
            )

        turns = [sign * a for a in np.radians(np.arange(0, 181, 6)) for sign in (1, -1)]
        candidates = (
            (strict, at(ring + extra, away + t))
            for strict in (True, False)  # a leader line through a label only if nothing else
            for extra in (0, max(w, h) + 4, 2 * (max(w, h) + 4))
            for t in turns
        )
        ok = (c for strict, c in candidates if free(c) and not (strict and crosses(points[i], c)))
        # nowhere free (a crowded, tiny picture): the preferred spot
        found = next(ok, None) or at(ring, away)
        placed.append(found)
        boxes[i] = found
    return [b for b in boxes if b is not None]


def _why_none(failed: list[list[LightEstimate]], fitted: bool = False) -> str:
    """The likely cause when lights have no highlight: a saturated sphere was blamed on too
    low an exposure. ``fitted``: the sphere was fitted from the images, where a ring of
    highlights can pass for its outline; a wrong circle was blamed on the exposure."""
    ests = [e for ests in failed for e in ests]
    if ests and all(e.saturated > 0.5 for e in ests):
        cause = "the sphere is saturated in these images: lower the exposure"
    elif ests and all(e.peak_level < 0.02 for e in ests):
        cause = "the sphere is black in these images: light off, or exposure far too low"
    else:
        cause = "light off, sphere mask wrong, or exposure too low"
    if fitted:
        return (
            f"the sphere fitted from the images may be wrong: pass a mask ({opt('mask')}); "
            f"else {cause}"
        )
    return cause


def diagnostic_image(
    images: np.ndarray,
    circles: list[Circle],
    estimates: list[list[LightEstimate]],
    capture: int = 0,
    labels: list[str] | None = None,
) -> np.ndarray:
    """8-bit RGB: brightest-over-lights image, sphere outlines, highlight marks labelled with
    ``labels`` (default: :func:`light_labels` of nothing, 1-based positions) beside them,
    decluttered, with a leader line where a label had to move away (green = confident,
    orange = doubtful, red = rim-clipped or low confidence)."""
    g = _grey(np.max(images, axis=0))  # the max is exact as stored: no float64 stack
    lo, hi = np.percentile(g, [1, 99.9])
    base = np.clip((g - lo) / max(hi - lo, 1e-9), 0, 1) ** 0.5 * 255
    up = 2 if max(g.shape) < 800 else 1
    vis = cv2.cvtColor(base.astype(np.uint8), cv2.COLOR_GRAY2RGB)
    vis = cv2.resize(vis, None, fx=up, fy=up, interpolation=cv2.INTER_NEAREST)
    sh = 4  # sub-pixel drawing
    one = 1 << sh
    labels = labels or [str(i + 1) for i in range(len(estimates))]
    font, scale = cv2.FONT_HERSHEY_SIMPLEX, 0.35 * up

    def pt(x: float, y: float) -> tuple[int, int]:
        # pixel centre x of the original lands at (x + 0.5) * up - 0.5 after upscaling
        return round(((x + 0.5) * up - 0.5) * one), round(((y + 0.5) * up - 0.5) * one)

    for c in circles:
        cv2.circle(vis, pt(c.cx, c.cy), round(c.r * up * one), (60, 140, 255), 1, cv2.LINE_AA, sh)
    marks: list[tuple[tuple[int, int], str, tuple[int, int, int]]] = []
    for i, ests in enumerate(estimates):
        for e in ests:
            if e.capture != capture or e.direction is None:
                continue
            col = (0, 220, 0) if e.confidence >= 0.5 else (255, 160, 0)
            if e.touches_rim or e.confidence < 0.2:
                col = (255, 40, 40)
            p = pt(e.x, e.y)
            marks.append(((p[0] >> sh, p[1] >> sh), labels[i], col))
    sizes = [cv2.getTextSize(text, font, scale, 1)[0] for _, text, _ in marks]
    boxes = place_labels([m[0] for m in marks], [(int(w), int(h)) for w, h in sizes], vis.shape[:2])
    for (p, text, col), box in zip(marks, boxes, strict=True):
        cv2.drawMarker(vis, p, col, cv2.MARKER_CROSS, 10, 1, cv2.LINE_AA)
        near = (min(max(p[0], box[0]), box[2]), min(max(p[1], box[1]), box[3]))
        if np.hypot(near[0] - p[0], near[1] - p[1]) > 8:  # moved away: say whose it is
            cv2.line(vis, p, near, col, 1, cv2.LINE_AA)
        origin = (box[0], box[3] - 1)
        cv2.putText(vis, text, origin, font, scale, (0, 0, 0), 3, cv2.LINE_AA)  # legible
        cv2.putText(vis, text, origin, font, scale, col, 1, cv2.LINE_AA)
    return vis


__all__ = [
    "DirectionResult",
    "Intrinsics",
    "LightEstimate",
    "diagnostic_image",
    "estimate_directions",
    "find_highlight",
    "light_labels",
    "place_labels",
    "reflect",
    "sphere_geometry",
]
