"""Light intensities (per light, per RGB channel) from a matte white sphere or plane.

With the light directions known, a Lambertian target of known normals gives
``I_c(p) = e_c * rho * max(n(p) . l, 0)``: per light and channel, ``e_c`` is the least-squares
fit of the (ambient-subtracted) pixel values to the shading ``s = n . l``. Saturated and
grazing pixels are left out. The result is scaled so its mean is 1 (only ratios matter).
How well the shading explains the pixels (the relative fit residual) is checked: wrong light
directions or a glossy target give plausible-looking intensities that are wrong.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from msfnet.calib.directions import Intrinsics, sphere_geometry
from msfnet.calib.sphere import Circle
from msfnet.common.errors import InputError
from msfnet.common.vocabulary import declare, opt

# IntensitiesOptions' switch, named by the fit's refusal
declare("accept_poor_fit", "--accept-poor-fit", "store_true")

# Relative fit residual ||I - e s|| / ||I|| over the used pixels of every light: right lights
# stay below ~0.12 even on a somewhat glossy real ball, wrong ones (an axis negated, a sphere
# fitted as a plane, a mirror sphere) reach 0.25 and more (docs/benchmark.md, "Measurements
# behind the code's rules").
FIT_WARN = 0.15
FIT_REFUSE = 0.20


def _fit_hint() -> str:
    return (
        "a wrong lights file, axis convention (x right, y up, z toward the camera) or target "
        f"shape ({opt('target')}, {opt('normal')}), or a glossy / non-matte target"
    )


def target_normals(
    shape: tuple[int, int],
    *,
    circle: Circle | None = None,
    plane_normal: np.ndarray | None = None,
    mask: np.ndarray | None = None,
    intrinsics: Intrinsics | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Normals (H, W, 3) and valid-pixel mask of a sphere (``circle``) or a plane."""
    h, w = shape
    if circle is not None:
        inside = circle.contains(h, w, shrink=0.97)  # the rim is dominated by edge blur
        if mask is not None:
            inside &= mask
        ys, xs = np.nonzero(inside)
        n = np.zeros((h, w, 3))
        n[ys, xs] = sphere_geometry(circle, xs.astype(float), ys.astype(float), intrinsics)[0]
        return n, inside
    pn = np.asarray(plane_normal if plane_normal is not None else (0, 0, 1), np.float64)
    pn = pn / np.linalg.norm(pn)
    valid = np.ones((h, w), bool) if mask is None else mask.astype(bool)
    return np.broadcast_to(pn, (h, w, 3)).copy(), valid


@dataclass(frozen=True)
class _Target:
    """What every light's fit shares: the target's geometry, the ambient frame, the limits."""

    normals: np.ndarray  # (H, W, 3)
    valid: np.ndarray  # (H, W) bool
    ambient: np.ndarray | None  # (H, W, 1 or 3) float64
    white_level: float
    min_shading: float
    source: str | Path | None


@dataclass(frozen=True)
class _LightFit:
    """One light's least-squares fit of its pixels to the shading ``s = n . l``."""

    rgb: np.ndarray  # (3,) the light's intensity e_c
    black: bool  # nothing lit on the target before any ambient subtraction
    saturated: float  # share of the lit target at the white level
    misfit: float  # squared fit residual over the used pixels
    total: float  # squared signal over the used pixels


def _fit_light(target: _Target, image: np.ndarray, light: np.ndarray, name: str) -> _LightFit:
    """Fit one image (cast to float64 here) to its light's shading; refuse an image with too
    few usable (lit, unsaturated) target pixels, naming the likely cause."""
    img = np.asarray(image, np.float64)
    if img.ndim == 2:  # grey: the same value in every channel
        img = np.repeat(img[..., None], 3, axis=2)
    white_level = target.white_level
    unsat = np.all(img < 0.99 * white_level, axis=-1)
    s = target.normals @ (light / np.linalg.norm(light))
    lit = target.valid & (s > target.min_shading)
    use = lit & unsat
    if use.sum() < 30:
        if lit.sum() >= 30:  # lit pixels enough, but at the white level: not too dark
            raise InputError(
                f"{name}: the lit target is saturated ({1 - unsat[lit].mean():.0%} "
                "of it at the white level): lower the exposure",
                target.source,
            )
        why = (
            "its light points away from the camera (z <= 0; expected x right, y up, "
            "z toward the camera): flip the sign of z"
            if light[2] <= 0
            else "check the mask and the light directions"
        )
        raise InputError(f"{name}: fewer than 30 lit target pixels ({why})", target.source)
    black = float(img[use].max()) < 0.02 * white_level
    if target.ambient is not None:
        img = img - target.ambient
    sat_share = 1.0 - unsat[target.valid & (s > target.min_shading)].mean()
    sv, iv = s[use], img[use]
    rgb = (iv * sv[:, None]).sum(0) / (sv * sv).sum()
    misfit = float(((iv - sv[:, None] * rgb) ** 2).sum())
    return _LightFit(rgb, black, sat_share, misfit, float((iv * iv).sum()))


def _refuse_nonpositive(
    out: np.ndarray,
    black: np.ndarray,
    names: list[str],
    has_ambient: bool,
    source: str | Path | None,
) -> None:
    """Refuse zero or negative intensities, naming the lights and the likely cause."""
    bad = np.flatnonzero(np.any(out <= 0, axis=1))
    if len(bad):
        which = ", ".join(names[i] for i in bad[:6]) + (" ..." if len(bad) > 6 else "")
        # the cause said only where it is one: a black image was blamed on an ambient frame
        # that did not exist
        if np.all(black[bad]):
            why = "the target is black in these images: light off, or exposure far too low"
        elif has_ambient:
            why = "the ambient frame is brighter than these lit images"
        else:
            why = "check the light directions for these images"
        raise InputError(
            f"zero or negative intensity for {len(bad)} light(s): {which} ({why})", source
        )


def _judge_fit(
    residual: float, plane: bool, accept_poor_fit: bool, source: str | Path | None
) -> str | None:
    """The warning the relative fit residual calls for (None: none), or the refusal of a
    target that matte shading under these lights does not explain."""
    if plane:
        # a plane's shading is one value per light: the residual sees only brightness varying
        # across the image alike under every light (lens vignetting: 21 % at a 38 deg
        # half-diagonal, rendered), which cancels in the ratios, or a target that is no
        # plane; never a wrong light. So a warning, never a refusal.
        if residual > FIT_WARN:
            return (
                f"{source or 'the images'}: the plane's brightness varies across the image "
                f"more than matte shading explains (fit residual {residual:.0%}): fine if it "
                "is vignetting (the same under every light); check the target is a plane"
            )
        return None
    if residual > FIT_REFUSE and not accept_poor_fit:
        raise InputError(
            f"the target does not fit matte shading under these light directions (fit "
            f"residual {residual:.0%}, at most {FIT_REFUSE:.0%} accepted): check for "
            f"{_fit_hint()} ({opt('accept_poor_fit')} writes them anyway)",
            source,
        )
    if residual > FIT_WARN:
        return (
            f"{source or 'the images'}: the target fits matte shading poorly (fit residual "
            f"{residual:.0%}): check for {_fit_hint()}"
        )
    return None


def estimate_intensities(
    images: np.ndarray,
    lights: np.ndarray,
    normals: np.ndarray,
    valid: np.ndarray,
    ambient: np.ndarray | None = None,
    white_level: float | None = None,
    min_shading: float = 0.15,
    names: list[str] | None = None,
    source: str | Path | None = None,
    accept_poor_fit: bool = False,
    plane: bool = False,
) -> tuple[np.ndarray, list[str]]:
    """(N, 3) relative RGB intensities, mean 1, plus warnings. ``source``: the images'
    folder, named by every error (with the image's name). ``accept_poor_fit``: a fit residual
    above FIT_REFUSE warns instead of refusing (a target known to be imperfect)."""
    imgs = np.asarray(images)  # as stored: cast to float64 one light at a time below
    n = len(imgs)
    if len(lights) != n:
        raise InputError(f"{len(lights)} light directions for {n} images", source)
    if white_level is None:
        white_level = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(
            imgs.dtype, float(np.max(imgs))
        )
    names = names or [f"image {i + 1}" for i in range(n)]
    amb = None if ambient is None else np.asarray(ambient, np.float64)
    if amb is not None and amb.ndim == 2:
        amb = amb[..., None]
    target = _Target(normals, valid, amb, white_level, min_shading, source)
    out = np.zeros((n, 3))
    black = np.zeros(n, bool)  # nothing lit on the target before any ambient subtraction
    warnings = []
    misfit = total = 0.0  # squared fit residual and squared signal, over every light
    for i in range(n):
        fit = _fit_light(target, imgs[i], lights[i], names[i])
        black[i] = fit.black
        if fit.saturated > 0.02:
            warnings.append(f"{names[i]}: {fit.saturated:.0%} of the lit target is saturated")
        out[i] = fit.rgb
        misfit += fit.misfit
        total += fit.total
    _refuse_nonpositive(out, black, names, amb is not None, source)
    residual = np.sqrt(misfit / max(total, 1e-300))
    warning = _judge_fit(residual, plane, accept_poor_fit, source)
    if warning is not None:
        warnings.append(warning)
    return out / out.mean(), warnings


__all__ = ["estimate_intensities", "target_normals"]
