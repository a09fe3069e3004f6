"""Rotation consistency in training: a batch turned as a whole, and the agreement term.

The augmentation (``data.rotate_flip``) makes the training *set* symmetric under the 8 turns and
mirrors of the image grid, but not the network: single turned passes of the bundled model differ
by up to ~0.4 deg on DiLiGenT ball (docs/training.md). ``msf-train --consistency W`` also runs
each batch turned one of the 7 other ways (drawn per step), trains on it as on the plain batch,
and adds W x the cosine disagreement between the plain deep prediction and the turned one mapped
back, so the network is pulled towards giving the same normals for every turn.

Same conventions as ``data.rotate_flip`` and ``runtime.infer.tta``: a quarter turn
counter-clockwise on screen (``torch.rot90`` over (rows, cols)) maps (x, y) -> (-y, x); the
mirror is left-right, x -> -x, applied after the turn.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from msfnet.model.data import Batch


def consistency_turn(seed: int, step: int) -> tuple[int, bool]:
    """The turn of step ``step``: one of the 7 that are not the identity, uniformly."""
    i = int(np.random.default_rng([seed, 4, step]).integers(1, 8))
    return i % 4, i >= 4


def turn_vectors(v: Tensor, k: int, flip: bool, dim: int) -> Tensor:
    """Direction components along ``dim`` (x, y, z) turned with the image."""
    x, y, z = v.select(dim, 0), v.select(dim, 1), v.select(dim, 2)
    for _ in range(k % 4):
        x, y = -y, x
    if flip:
        x = -x
    return torch.stack([x, y, z], dim)


def _image(t: Tensor, k: int, flip: bool) -> Tensor:
    t = torch.rot90(t, k % 4, dims=(-2, -1))
    return t.flip(-1) if flip else t


def turn_batch(batch: Batch, k: int, flip: bool) -> Batch:
    """The batch as the turned scene: images (B, N, 3, H, W), lights, normals, mask."""
    return Batch(
        _image(batch.images, k, flip),
        turn_vectors(batch.lights, k, flip, -1),
        turn_vectors(_image(batch.normals, k, flip), k, flip, 1),
        _image(batch.mask, k, flip),
    )


def turn_back(normals: Tensor, k: int, flip: bool) -> Tensor:
    """(B, 3, H, W) normals predicted on the turned batch, in the plain batch's frame."""
    n = normals.flip(-1) if flip else normals
    if flip:
        n = torch.stack([-n[:, 0], n[:, 1], n[:, 2]], 1)
    n = torch.rot90(n, -(k % 4), dims=(-2, -1))
    x, y = n[:, 0], n[:, 1]
    for _ in range(k % 4):
        x, y = y, -x  # the inverse quarter turn
    return torch.stack([x, y, n[:, 2]], 1)


__all__ = ["consistency_turn", "turn_back", "turn_batch", "turn_vectors"]
