"""Per-pixel RGB albedo from the images, the lights and the estimated normals.

Lambertian model per colour channel c and light i: I_ic = rho_c * e_ic * max(n . l_i, 0), with
e_ic the light's RGB intensity. Given n, the least-squares albedo over a set K of lights is
    rho_c = sum_K I_ic s_ic / sum_K s_ic^2,    s_ic = max(n . l_i, 0) * e_ic,
(the closed form of min_rho sum_K (I_ic - rho_c s_ic)^2, as in Woodham's photometric stereo,
Optical Engineering 19(1), 1980, once the normal is known). K keeps only observations the model
can explain: lit (n . l_i above ``min_shading``, which drops attached shadows and grazing light
where the cosine is least reliable) and unsaturated (value below ``saturation`` in that channel;
by default the image's full scale, :func:`default_saturation`). Where K is empty the albedo is
unknown: NaN, as outside the mask (0 would read as a black surface).
Units: image units per unit light intensity (the images' raw scale, e.g. 0..65535 for 16-bit).
"""

from __future__ import annotations

import numpy as np

from msfnet.common.errors import InputError
from msfnet.runtime.stack.types import float_full_scale, full_scale

DEFAULT_MIN_SHADING = 0.1
CHUNK_PIXELS = 32768  # bounds the (N, chunk, 3) temporaries to a few tens of MB
MIN_CHUNK_PIXELS = 256
# working set per (pixel x light) of one chunk: the float64 gather, shading, kept-mask and the
# masked products (measured ~110 B; maps.budget sizes chunks with it)
BYTES_PER_PIXEL_LIGHT = 128


def default_saturation(images: np.ndarray) -> float:
    """The clipping level assumed when none is given (values at or above it are dropped).

    Integer images: the type's full scale, 255 / 65535 (:func:`full_scale`, the robust fit's
    rule too). Float images carry no range in their type: their largest value when it is a
    full scale float images are held at (1.0, 255, 65535, ...:
    :func:`~msfnet.runtime.stack.types.float_full_scale`, the stack check's rule; an 8-bit
    stack after --downscale or --srgb clips at 255.0), else none (inf).
    Never a fraction of the largest value: a flat, evenly lit part reads that value in every
    image, and dropping it left no observation (albedo 0 on the brightest area)."""
    full = full_scale(images.dtype)
    if full is None and images.size:
        full = float_full_scale(float(np.max(images)))
    return np.inf if full is None else full


def display_level(albedo: np.ndarray, mask: np.ndarray, percentile: float) -> float:
    """The ``percentile`` of the brightest channel over the mask's known albedos (NaN: no
    observation kept), the level a picture puts at full scale; 0 when none is known."""
    vals = albedo[mask].max(axis=1) if mask.any() else np.zeros(0)
    vals = vals[np.isfinite(vals)]
    return float(np.percentile(vals, percentile)) if vals.size else 0.0


def checked_albedo(
    imgs: np.ndarray,
    lights: np.ndarray,
    intensities: np.ndarray,
    valid: np.ndarray,
    unit: np.ndarray,
    min_shading: float = DEFAULT_MIN_SHADING,
    saturation: float | None = None,
    chunk_pixels: int = CHUNK_PIXELS,
) -> np.ndarray:
    """Least-squares RGB albedo, (H, W, 3) float32.

    imgs: (N, H, W, 3) linear values as stored; lights: (N, 3) directions (normalised here);
    intensities: (N, 3) RGB light intensities; ``valid`` and ``unit``: what
    ``validate.check_normals`` makes of the normals and the mask (no second copy of them).
    min_shading: smallest n . l kept (dimensionless cosine).
    saturation: values at or above it are dropped (default: :func:`default_saturation`, the
    images' full scale).
    Pixels outside ``valid`` get NaN, and so does a channel with no kept observation (its
    albedo is unknown).
    chunk_pixels: pixels solved at once (the working set is about
    ``chunk_pixels * N * BYTES_PER_PIXEL_LIGHT`` bytes; maps.budget sizes it to --max-memory).
    """
    if imgs.ndim != 4 or imgs.shape[3] != 3:
        raise InputError(f"images must be N x H x W x 3, got shape {imgs.shape}")
    n_lights, h, w = imgs.shape[:3]
    if unit.shape[:2] != (h, w):
        raise InputError(f"normals are {unit.shape[:2]} but images are {(h, w)}")
    dirs = np.asarray(lights, np.float64)
    ints = np.asarray(intensities, np.float64)
    if dirs.shape != (n_lights, 3) or ints.shape != (n_lights, 3):
        raise InputError(
            f"{n_lights} images need ({n_lights}, 3) lights and intensities, got "
            f"{dirs.shape} and {ints.shape}"
        )
    norms = np.linalg.norm(dirs, axis=1, keepdims=True)
    if not (np.all(np.isfinite(dirs)) and np.all(norms > 0) and np.all(np.isfinite(ints))):
        raise InputError("light directions and intensities must be finite, directions non-zero")
    dirs = dirs / norms
    sat = default_saturation(imgs) if saturation is None else float(saturation)
    out = np.full((h, w, 3), np.nan, np.float32)
    pix = np.flatnonzero(valid.ravel())
    flat = imgs.reshape(n_lights, h * w, 3)
    chunk = max(int(chunk_pixels), MIN_CHUNK_PIXELS)
    for start in range(0, pix.size, chunk):
        sel = pix[start : start + chunk]
        obs = flat[:, sel, :].astype(np.float64)  # (N, P, 3)
        cos = dirs @ unit.reshape(-1, 3)[sel].T  # (N, P)
        s = np.where(cos > min_shading, cos, 0.0)[:, :, None] * ints[:, None, :]
        keep = (s > 0) & (obs < sat) & np.isfinite(obs)
        s = np.where(keep, s, 0.0)
        num = np.einsum("npc,npc->pc", np.where(keep, obs, 0.0), s)
        den = np.einsum("npc,npc->pc", s, s)
        rho = np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)
        out.reshape(-1, 3)[sel] = rho  # written as it comes: no (P, 3) float64 beside it
    return out


__all__ = [
    "DEFAULT_MIN_SHADING",
    "checked_albedo",
    "default_saturation",
    "display_level",
]
