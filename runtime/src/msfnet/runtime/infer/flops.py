"""Analytic cost and receptive field of MSF-Net, from the layer table of docs/network-spec.md.

One table serves both: the FLOP counter (profile, benchmark) and the halo the tiler needs.
Counts are multiply-accumulates (MAC) of the convolutions, per full-resolution pixel; element-wise
work (activations, the fusion's similarity sum, max over lights) is left out, as is customary.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Layer:
    name: str
    kind: str  # "conv" (k x k, zero padding k // 2) or "deconv" (4x4 stride-2 transposed, pad 1)
    cin: int
    cout: int
    kernel: int
    stride: int
    res_in: str  # "full" or "half": resolution of the layer's input
    per_light: bool  # computed once per light (True) or once per stack (False)


def _stage(prefix: str) -> list[Layer]:
    """extractor2 / extractor3: conv 192->192 (half), deconv 192->128 (-> full), conv s2 -> half."""
    return [
        Layer(f"{prefix}.conv1", "conv", 192, 192, 3, 1, "half", True),
        Layer(f"{prefix}.conv2", "deconv", 192, 128, 4, 2, "half", True),
        Layer(f"{prefix}.conv3", "conv", 128, 96, 3, 2, "full", True),
    ]


def _fusion(prefix: str) -> list[Layer]:
    """f_x runs on every light's feature, f_y once on the max over lights (both 1x1, half res)."""
    return [
        Layer(f"{prefix}.f_x", "conv", 96, 96, 1, 1, "half", True),
        Layer(f"{prefix}.f_y", "conv", 96, 96, 1, 1, "half", False),
    ]


# Execution order of the inference ("deep") path.
LAYERS: tuple[Layer, ...] = (
    Layer("extractor1.conv1", "conv", 6, 64, 3, 1, "full", True),
    Layer("extractor1.conv2", "conv", 64, 128, 3, 1, "full", True),
    Layer("extractor1.conv3", "conv", 128, 96, 3, 2, "full", True),
    Layer("extractor1.conv4", "conv", 96, 96, 3, 1, "half", True),
    *_fusion("fusion(stage2)"),
    *_stage("extractor2"),
    *_fusion("fusion(stage3)"),
    *_stage("extractor3"),
    Layer("regressor.deconv1", "conv", 96, 128, 3, 1, "half", False),
    Layer("regressor.deconv2", "deconv", 128, 64, 4, 2, "half", False),
    Layer("regressor.deconv3", "conv", 64, 32, 3, 1, "full", False),
    Layer("regressor.est_normal", "conv", 32, 3, 3, 1, "full", False),
)

_AREA = {"full": 1.0, "half": 0.25}


def layer_macs(layer: Layer) -> int:
    """MAC per full-resolution pixel."""
    k2 = layer.kernel * layer.kernel
    if layer.kind == "deconv":  # every input pixel scatters a k x k x cout patch
        area = _AREA[layer.res_in]
    else:  # every output pixel gathers a k x k x cin patch
        area = _AREA[layer.res_in] / (layer.stride * layer.stride)
    return round(layer.cin * layer.cout * k2 * area)


MACS_PER_LIGHT_PIXEL = sum(layer_macs(x) for x in LAYERS if x.per_light)  # 547,968
MACS_PER_PIXEL = sum(layer_macs(x) for x in LAYERS if not x.per_light)  # 84,320


def inference_flops(lights: int, pixels: int) -> float:
    """FLOPs (2 per MAC) of one forward pass over ``pixels`` network-input pixels."""
    return 2.0 * pixels * (lights * MACS_PER_LIGHT_PIXEL + MACS_PER_PIXEL)


def receptive_field() -> tuple[int, int]:
    """How far (full-res pixels) before and after an output pixel its inputs can lie.

    Walks the spatial layers backwards from one output pixel, mapping the index interval through
    each layer exactly (stride-2 grids anchored at 0, which tile origins that are multiples of 4
    preserve). The extent depends on the pixel's phase modulo 4, so the worst of the four is
    returned as (before, after): (19, 18) for the released network.
    """
    before = after = 0
    for phase in range(4):
        lo, hi = phase, phase
        for layer in reversed(LAYERS):
            if layer.kernel == 1:
                continue
            if layer.kind == "deconv":  # out o = 2*i - 1 + k, k in 0..3 -> i in [(o-2)/2, (o+1)/2]
                lo, hi = -((2 - lo) // 2), (hi + 1) // 2
            else:  # in i = s*o - pad + k, k in 0..kernel-1
                pad = layer.kernel // 2
                lo, hi = layer.stride * lo - pad, layer.stride * hi - pad + layer.kernel - 1
        before, after = max(before, phase - lo), max(after, hi - phase)
    return before, after


__all__ = [
    "LAYERS",
    "MACS_PER_LIGHT_PIXEL",
    "MACS_PER_PIXEL",
    "Layer",
    "inference_flops",
    "layer_macs",
    "receptive_field",
]
