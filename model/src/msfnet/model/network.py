"""MSF-Net, exactly as specified in docs/network-spec.md (state-dict names and shapes included).

Read it against the layer table: every attribute name below is a state-dict prefix.
Lights are folded into the batch axis, (B*N, C, H, W), and "max over lights" is a tensor
reduction, so each stage is computed once per light and the exported graph has a truly dynamic
light count (a Python loop over lights would be unrolled at export).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

FEATURES = 96  # channels of every stage's per-light feature


def conv(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    """3x3 convolution with bias + LeakyReLU(0.1); keys <name>.0.weight, <name>.0.bias."""
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, padding=1, bias=True), nn.LeakyReLU(0.1))


def deconv(cin: int, cout: int) -> nn.Sequential:
    """4x4 stride-2 transposed convolution, no bias, + LeakyReLU(0.1): doubles H and W."""
    return nn.Sequential(
        nn.ConvTranspose2d(cin, cout, 4, stride=2, padding=1, bias=False), nn.LeakyReLU(0.1)
    )


class Extractor1(nn.Module):
    """Shallow stage: per-light image + light (6 ch) -> 96 ch at half resolution."""

    def __init__(self) -> None:
        super().__init__()
        self.conv1 = conv(6, 64)
        self.conv2 = conv(64, 128)
        self.conv3 = conv(128, 96, stride=2)
        self.conv4 = conv(96, 96)

    def forward(self, x: Tensor) -> Tensor:
        return self.conv4(self.conv3(self.conv2(self.conv1(x))))


class StageExtractor(nn.Module):
    """Middle and deep stages: [raw, fused] (192 ch, half res) -> 96 ch at half resolution."""

    def __init__(self) -> None:
        super().__init__()
        self.conv1 = conv(2 * FEATURES, 192)
        self.conv2 = deconv(192, 128)
        self.conv3 = conv(128, FEATURES, stride=2)

    def forward(self, x: Tensor) -> Tensor:
        return self.conv3(self.conv2(self.conv1(x)))


class Regressor(nn.Module):
    """Max-pooled feature (96 ch, half res) -> unit normal map (3 ch, full res)."""

    def __init__(self) -> None:
        super().__init__()
        self.deconv1 = conv(FEATURES, 128)  # a convolution, despite the published name
        self.deconv2 = deconv(128, 64)
        self.deconv3 = conv(64, 32)
        self.est_normal = nn.Sequential(nn.Conv2d(32, 3, 3, 1, 1, bias=False))

    def forward(self, x: Tensor) -> Tensor:
        n = self.est_normal(self.deconv3(self.deconv2(self.deconv1(x))))
        return F.normalize(n, p=2, dim=1)


class Fusion(nn.Module):
    """Blend each light's feature with the max over lights, gated by a learned similarity.

    As the released weights were trained: both inputs pass through GELU first, and the blend uses
    the GELU'd features: out = (1 - s) * gelu(x) + s * gelu(y),
    with s = sigmoid(<f_x(gelu x), f_y(gelu y)>) summed over channels.
    """

    def __init__(self) -> None:
        super().__init__()
        self.f_x, self.f_y = (
            nn.Sequential(nn.Conv2d(FEATURES, FEATURES, 1, bias=False), nn.BatchNorm2d(FEATURES))
            for _ in range(2)
        )

    def forward(self, feats: Tensor, pooled: Tensor) -> Tensor:
        """feats (B*N, C, h, w) per light, pooled (B, C, h, w) max over lights -> (B*N, C, h, w)."""
        b = pooled.shape[0]
        x = F.gelu(feats)
        y = F.gelu(pooled)
        per_sample = (b, -1, *x.shape[1:])  # reshape, not unflatten: keeps B dynamic at export
        k = self.f_x(x).reshape(per_sample)  # (B, N, C, h, w)
        q = self.f_y(y).unsqueeze(1)  # (B, 1, C, h, w)
        sim = torch.sigmoid((k * q).sum(dim=2, keepdim=True))  # (B, N, 1, h, w)
        out = (1 - sim) * x.reshape(per_sample) + sim * y.unsqueeze(1)
        return out.flatten(0, 1)


def max_over_lights(feats: Tensor, batch: int) -> Tensor:
    """(B*N, C, h, w) -> (B, C, h, w), element-wise max over each sample's lights."""
    return feats.reshape(batch, -1, *feats.shape[1:]).amax(dim=1)


class MSFNet(nn.Module):
    """Calibrated photometric stereo: (images, lights) -> unit normals.

    Options (the paper's ablations; the released network has all three on):
      mfe: multi-stage feature extraction (off: extractor1 -> max -> regressor only);
      mff: the fusion module (off: a stage's input is concat(raw, max));
      sus: selective update, used by training (see ``model.train``).
    """

    def __init__(self, mfe: bool = True, mff: bool = True) -> None:
        super().__init__()
        self.mfe = mfe
        self.mff = mff
        self.extractor1 = Extractor1()
        if mfe:
            self.extractor2 = StageExtractor()
            self.extractor3 = StageExtractor()
            if mff:
                self.fusion = Fusion()
        self.regressor = Regressor()

    def stage_input(self, feats: Tensor, pooled: Tensor) -> Tensor:
        """What a later stage sees per light: raw feature first, fused (or max) second."""
        if self.mff:
            fused = self.fusion(feats, pooled)
        else:
            fused = pooled.unsqueeze(1).expand(-1, feats.shape[0] // pooled.shape[0], -1, -1, -1)
            fused = fused.flatten(0, 1)
        return torch.cat([feats, fused], dim=1)

    def pooled_features(self, images: Tensor, lights: Tensor) -> list[Tensor]:
        """Max-pooled features after each stage: [m1] or [m1, m2, m3], each (B, 96, H/2, W/2).

        images (B, N, 3, H, W) normalised, lights (B, N, 3) unit; H, W multiples of 4.
        """
        b, n, _, h, w = images.shape
        light_maps = lights.reshape(b * n, 3, 1, 1).expand(-1, -1, h, w)
        x = torch.cat([images.flatten(0, 1), light_maps], dim=1)  # image first, light second
        f = self.extractor1(x)
        pooled = [max_over_lights(f, b)]
        if self.mfe:
            for extractor in (self.extractor2, self.extractor3):
                f = extractor(self.stage_input(f, pooled[-1]))
                pooled.append(max_over_lights(f, b))
        return pooled

    def forward(self, images: Tensor, lights: Tensor) -> Tensor:
        """Deep-path normals (B, 3, H, W)."""
        return self.regressor(self.pooled_features(images, lights)[-1])
