"""The published code's way of computing MSF-Net: a Python loop over lights with a running max.

It recomputes extractor1 three times and extractor2 twice (once per stage that needs them), as
the authors' per-light loop does. Same weights as :class:`MSFNet`; used to check that the
lights-folded network gives the same normals, and as the slow baseline in benchmarks.
"""

from __future__ import annotations

import torch
from torch import Tensor

from msfnet.model.network import MSFNet


def _light_input(images: Tensor, lights: Tensor, i: int) -> Tensor:
    b, _, _, h, w = images.shape
    return torch.cat([images[:, i], lights[:, i].reshape(b, 3, 1, 1).expand(-1, -1, h, w)], 1)


def _running_max(feats) -> Tensor:
    out: Tensor | None = None
    for f in feats:
        out = f if out is None else torch.maximum(out, f)
    assert out is not None, "no lights"
    return out


@torch.no_grad()
def per_light_forward(net: MSFNet, images: Tensor, lights: Tensor) -> Tensor:
    """Deep-path normals computed light by light (B, 3, H, W)."""
    n = images.shape[1]

    def stage1(i: int) -> Tensor:
        return net.extractor1(_light_input(images, lights, i))

    m1 = _running_max(stage1(i) for i in range(n))

    def stage2(i: int) -> Tensor:
        f1 = stage1(i)  # recomputed, as the published loop does
        return net.extractor2(net.stage_input(f1, m1))

    m2 = _running_max(stage2(i) for i in range(n))

    def stage3(i: int) -> Tensor:
        f2 = stage2(i)
        return net.extractor3(net.stage_input(f2, m2))

    m3 = _running_max(stage3(i) for i in range(n))
    return net.regressor(m3)
