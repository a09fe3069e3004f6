"""The network's input normalisation, exactly as the published evaluation did it.

1. divide each image by its light's RGB intensity;
2. per pixel and colour channel, divide the N values by their L2 norm over the lights (+1e-10);
3. multiply by sqrt(N / train_lights), so the value scale does not depend on N;
4. multiply by the mask.
Every step is per pixel, so normalising a tile equals cropping the normalised image: the tiled
runtime relies on that.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from msfnet.runtime.contract import INPUT_MULTIPLE, TRAIN_LIGHTS

if TYPE_CHECKING:
    from msfnet.runtime.stack import Stack


def normalise(
    images: np.ndarray, intensities: np.ndarray, mask: np.ndarray, train_lights: int = TRAIN_LIGHTS
) -> np.ndarray:
    """(N, H, W, 3) raw images (float, or a stack's uint8/uint16) -> (N, 3, H, W) float32
    network input."""
    n = images.shape[0]
    # cast first, once per tile: integer values are exact in float32 (so a uint16 stack gives
    # the numbers its float32 copy would) and must never meet the squares below (overflow)
    x = images.astype(np.float32)
    x /= intensities.astype(np.float32)[:, None, None, :]
    norm = np.sqrt(np.einsum("nhwc,nhwc->hwc", x, x, dtype=np.float64)).astype(np.float32)
    scale = np.float32(np.sqrt(n / train_lights))
    x *= (scale / (norm + np.float32(1e-10)))[None]
    x *= mask[None, :, :, None].astype(np.float32)
    return np.ascontiguousarray(x.transpose(0, 3, 1, 2))


def padded_size(size: int, multiple: int = INPUT_MULTIPLE) -> int:
    return -(-size // multiple) * multiple


def network_lights(lights: np.ndarray) -> np.ndarray:
    """Unit light directions as float32, (N, 3)."""
    lights = np.asarray(lights, np.float64)
    return (lights / np.linalg.norm(lights, axis=1, keepdims=True)).astype(np.float32)


def network_input(
    stack: Stack,
    rows: slice = slice(None),
    cols: slice = slice(None),
    *,
    lights: Sequence[int] | np.ndarray | None = None,
    train_lights: int = TRAIN_LIGHTS,
    shape: tuple[int, int] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The network's two inputs for a crop of ``stack``: images (1, N, 3, h, w) normalised as
    above and lights (1, N, 3) unit directions. ``lights``: indices of a light subset;
    ``shape``: zero-pad the crop to this (h, w), e.g. a tile reaching past the image. Only the
    crop is gathered and cast, never all N full images."""
    pick = slice(None) if lights is None else np.asarray(lights)
    x = normalise(
        stack.images[pick, rows, cols],
        stack.intensities[pick],
        stack.mask[rows, cols],
        train_lights,
    )
    if shape is not None and tuple(shape) != x.shape[2:]:
        padded = np.zeros((*x.shape[:2], *shape), np.float32)
        padded[:, :, : x.shape[2], : x.shape[3]] = x
        x = padded
    return x[None], network_lights(stack.lights[pick])[None]
