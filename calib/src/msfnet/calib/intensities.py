"""Light intensities (per light, per RGB channel) from a matte white sphere or plane.

With the light directions known, a Lambertian target of known normals gives
``I_c(p) = e_c * rho * max(n(p) . l, 0)``: per light and channel, ``e_c`` is the least-squares
fit of the (ambient-subtracted) pixel values to the shading ``s = n . l``. Saturated and
grazing pixels are left out. The result is scaled so its mean is 1 (only ratios matter).
How well the shading explains the pixels (the relative fit residual) is checked: wrong light
directions or a glossy target give plausible-looking intensities that are wrong.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from msfnet.calib.directions import Intrinsics, sphere_geometry
from msfnet.calib.sphere import Circle
from msfnet.common.errors import InputError
from msfnet.common.vocabulary import declare, opt

# msf-calib intensities' --target, --normal and --accept-poor-fit
declare("target", "--target")
declare("normal", "--normal")
declare("accept_poor_fit", "--accept-poor-fit", "store_true")

# Relative fit residual ||I - e s|| / ||I|| over the used pixels of every light. Measured:
# right lights: rendered Lambertian spheres 0.0002 (16-bit), 0.005 (8-bit), 0.04 (1 % noise);
# real psmImages/gray 0.073 (lights.txt) / 0.065 (chrome-calibrated); real DiLiGenT ballPNG,
# a somewhat glossy ball, 0.118 (0.122 without its mask). Wrong: y negated 0.31 (rendered),
# 0.34 (ballPNG), 0.45 (gray); x negated 0.36 (ballPNG), 0.25 (gray); a sphere fitted as a
# plane 0.41; a mirror sphere 0.34 (rendered) / 0.99 (psmImages/chrome).
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
    out = np.zeros((n, 3))
    black = np.zeros(n, bool)  # nothing lit on the target before any ambient subtraction
    warnings = []
    misfit = total = 0.0  # squared fit residual and squared signal, over every light
    for i in range(n):
        img = np.asarray(imgs[i], np.float64)
        if img.ndim == 2:  # grey: the same value in every channel
            img = np.repeat(img[..., None], 3, axis=2)
        unsat = np.all(img < 0.99 * white_level, axis=-1)
        s = normals @ (lights[i] / np.linalg.norm(lights[i]))
        lit = valid & (s > min_shading)
        use = lit & unsat
        if use.sum() < 30:
            if lit.sum() >= 30:  # lit pixels enough, but at the white level: not too dark
                raise InputError(
                    f"{names[i]}: the lit target is saturated ({1 - unsat[lit].mean():.0%} "
                    "of it at the white level): lower the exposure",
                    source,
                )
            why = (
                "its light points away from the camera (z <= 0; expected x right, y up, "
                "z toward the camera): flip the sign of z"
                if lights[i][2] <= 0
                else "check the mask and the light directions"
            )
            raise InputError(f"{names[i]}: fewer than 30 lit target pixels ({why})", source)
        black[i] = float(img[use].max()) < 0.02 * white_level
        if amb is not None:
            img = img - amb
        sat_share = 1.0 - unsat[valid & (s > min_shading)].mean()
        if sat_share > 0.02:
            warnings.append(f"{names[i]}: {sat_share:.0%} of the lit target is saturated")
        sv, iv = s[use], img[use]
        out[i] = (iv * sv[:, None]).sum(0) / (sv * sv).sum()
        misfit += float(((iv - sv[:, None] * out[i]) ** 2).sum())
        total += float((iv * iv).sum())
    bad = np.flatnonzero(np.any(out <= 0, axis=1))
    if len(bad):
        which = ", ".join(names[i] for i in bad[:6]) + (" ..." if len(bad) > 6 else "")
        # the cause said only where it is one: a black image was blamed on an ambient frame
        # that did not exist
        if np.all(black[bad]):
            why = "the target is black in these images: light off, or exposure far too low"
        elif amb is not None:
            why = "the ambient frame is brighter than these lit images"
        else:
            why = "check the light directions for these images"
        raise InputError(
            f"zero or negative intensity for {len(bad)} light(s): {which} ({why})", source
        )
    residual = np.sqrt(misfit / max(total, 1e-300))
    if plane:
        # a plane's shading is one value per light: the residual sees only brightness varying
        # across the image alike under every light (lens vignetting: 21 % at a 38 deg
        # half-diagonal, rendered), which cancels in the ratios, or a target that is no
        # plane; never a wrong light. So a warning, never a refusal.
        if residual > FIT_WARN:
            warnings.append(
                f"{source or 'the images'}: the plane's brightness varies across the image "
                f"more than matte shading explains (fit residual {residual:.0%}): fine if it "
                "is vignetting (the same under every light); check the target is a plane"
            )
        return out / out.mean(), warnings
    if residual > FIT_REFUSE and not accept_poor_fit:
        raise InputError(
            f"the target does not fit matte shading under these light directions (fit "
            f"residual {residual:.0%}, at most {FIT_REFUSE:.0%} accepted): check for "
            f"{_fit_hint()} ({opt('accept_poor_fit')} writes them anyway)",
            source,
        )
    if residual > FIT_WARN:
        warnings.append(
            f"{source or 'the images'}: the target fits matte shading poorly (fit residual "
            f"{residual:.0%}): check for {_fit_hint()}"
        )
    return out / out.mean(), warnings


__all__ = ["estimate_intensities", "target_normals"]
