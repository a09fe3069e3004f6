"""The staged graph: MSF-Net cut at its three max-over-lights reductions, for light-chunked runs.

Every stage needs the max over *all* lights of the previous stage, so a monolithic graph holds
every light's intermediate activations at once (about 1.3-3 KB per pixel and light). Cut at the
reductions, the runtime can push a few lights at a time through each stage, keep only the
per-light stage outputs (96 channels at half resolution: 96 B per pixel and light) and take the
running max itself (``msfnet.runtime.engines.staged_loop``).

One ONNX file holds four independent entry points sharing one set of weights:
  images (1, n, 3, H, W), lights (1, n, 3)  -> feat1 (n, 96, H/2, W/2)   extractor1
  feat1_in (n, 96, h, w), max1 (1, 96, h, w) -> feat2                      fusion + extractor2
  feat2_in (n, 96, h, w), max2 (1, 96, h, w) -> feat3                      fusion + extractor3
  max3 (1, 96, h, w)                         -> normals (1, 3, H, W)       regressor
ONNX Runtime evaluates the whole graph on every call, so a call feeds tiny placeholders
(``msfnet.runtime.engines.staged_loop.placeholders``) to the entry points it does not use.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from msfnet.model.network import MSFNet


class StagedGraph(nn.Module):
    """The four entry points of the staged graph (batch 1, lights folded into the batch)."""

    def __init__(self, model: MSFNet) -> None:
        super().__init__()
        if not (model.mfe and model.mff):
            raise ValueError("the staged graph needs the full network (mfe and mff on)")
        self.model = model

    def forward(
        self,
        images: Tensor,
        lights: Tensor,
        feat1_in: Tensor,
        max1: Tensor,
        feat2_in: Tensor,
        max2: Tensor,
        max3: Tensor,
    ) -> tuple[Tensor, ...]:
        m = self.model
        n, h, w = images.shape[1], images.shape[3], images.shape[4]
        light_maps = lights.reshape(n, 3, 1, 1).expand(-1, -1, h, w)
        feat1 = m.extractor1(torch.cat([images.flatten(0, 1), light_maps], dim=1))
        feat2 = m.extractor2(m.stage_input(feat1_in, max1))
        feat3 = m.extractor3(m.stage_input(feat2_in, max2))
        return feat1, feat2, feat3, m.regressor(max3)


__all__ = ["StagedGraph"]
