"""Light-chunked inference through a staged msfnet graph (``msf-export --staged``).

The network takes a max over all lights after each of its three stages. A staged export cuts the
graph there, so this loop can run a few lights at a time per stage and keep only each light's
stage output (96 channels at half resolution) between stages: 96 B per pixel and light instead
of the KBs of activations a monolithic graph holds at once, so tiles can be several times
larger for the same memory and less of the work goes into halos.
The result equals the monolithic graph's: the max is exact and every other op is per light.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

STAGE_INPUTS = ("images", "lights", "feat1_in", "max1", "feat2_in", "max2", "max3")
STAGE_OUTPUTS = ("feat1", "feat2", "feat3", "normals")
FEATURES = 96  # channels of each stage's per-light output (half resolution)
# lights per call. Each call's activations are the working set that grows with it (OpenVINO
# keeps one arena per stage model), while a call of 4 lights on a real window is still large
# enough work: a lower peak than 8 at the same time, 2 ran slower (docs/benchmark.md).
DEFAULT_CHUNK = 4
# kept for the whole tile: one float32 stage output (96 ch on 1/4 of the pixels) + the input
STORED_BYTES_PER_PIXEL_LIGHT = FEATURES * 4 // 4 + 3 * 4


def placeholders() -> dict[str, np.ndarray]:
    """The cheapest feeds every entry point accepts: ONNX Runtime evaluates the whole graph on
    every call, so the entry points a call does not use get these."""
    feat = np.zeros((1, FEATURES, 2, 2), np.float32)
    return {
        "images": np.zeros((1, 1, 3, 4, 4), np.float32),
        "lights": np.array([[[0.0, 0.0, 1.0]]], np.float32),
        "feat1_in": feat,
        "max1": feat,
        "feat2_in": feat,
        "max2": feat,
        "max3": feat,
    }


# A stage call: compute ``output`` for one chunk of lights from ``feeds``, write the chunk's
# per-light result into ``out`` (chunk, 96, h, w), and return its max over those lights
# (1, 96, h, w), valid until the next call.
StageCall = Callable[[str, dict[str, np.ndarray], np.ndarray], np.ndarray]
# the regressor: the last stage's max over all lights -> normals (1, 3, H, W)
FinalCall = Callable[[np.ndarray], np.ndarray]


def run_stages(
    stage: StageCall,
    final: FinalCall,
    images: np.ndarray,
    lights: np.ndarray,
    chunk: int = DEFAULT_CHUNK,
    keep: dict[str, np.ndarray] | None = None,
) -> np.ndarray:
    """images (1, N, 3, H, W), lights (1, N, 3) -> normals (1, 3, H, W), ``chunk`` lights a
    stage call, through any engine's ``stage`` and ``final`` calls.

    The per-light outputs live in one buffer of N + min(chunk, N) lights, and each chunk's
    next-stage output is written where the chunk before it (in the stage's order) has just been
    read: one stage runs upwards, shifting every chunk by min(chunk, N) lights into the spare
    room, the next downwards, back. So an engine that can write into a given array (OpenVINO)
    writes straight into the buffer: no copy of the 0.3-1 GB a stage that a buffer of N lights
    would need at 96 lights (OpenVINO bf16: 1.19-1.25x faster, engines.openvino). Each stage's
    max over lights is gathered chunk by chunk.
    ``keep``: if given, filled with the real input of every entry point (all lights, in light
    order), as int8 calibration needs them.
    """
    if images.shape[0] != 1:
        raise ValueError("staged inference runs one stack at a time (batch 1)")
    n = images.shape[1]
    spans = [(i, min(chunk, n - i)) for i in range(0, n, chunk)]
    step = min(chunk, n)  # the largest span: the spare room a shift needs (tiling budgets it)
    # the stages run at half resolution (stride-2 convolutions, padding 1: ceil(H / 2)); an
    # engine given another shape fails loudly (its result does not fit ``out``)
    feats = np.empty((n + step, FEATURES, *_half(images.shape[-2:])), np.float32)
    pooled: np.ndarray | None = None
    for start, size in spans:
        s = slice(start, start + size)
        m = stage("feat1", {"images": images[:, s], "lights": lights[:, s]}, feats[s])
        pooled = _running_max(pooled, m)
    assert pooled is not None
    offset = 0  # where light 0's features are now: 0 or ``step``
    for output, feat_in, max_in in (("feat2", "feat1_in", "max1"), ("feat3", "feat2_in", "max2")):
        if keep is not None:
            keep.update({feat_in: feats[offset : offset + n].copy(), max_in: pooled})
        shift = step if offset == 0 else -step
        order = spans[::-1] if shift > 0 else spans  # never write over a chunk not yet read
        new: np.ndarray | None = None
        for start, size in order:
            src = feats[offset + start : offset + start + size]
            dst = feats[offset + shift + start : offset + shift + start + size]
            new = _running_max(new, stage(output, {feat_in: src, max_in: pooled}, dst))
        assert new is not None
        pooled, offset = new, offset + shift
    if keep is not None:
        keep.update(images=images, lights=lights, max3=pooled)
    return final(pooled)


def _half(hw: tuple[int, ...]) -> tuple[int, int]:
    return (hw[0] + 1) // 2, (hw[1] + 1) // 2


def _running_max(acc: np.ndarray | None, m: np.ndarray) -> np.ndarray:
    if acc is None:
        return np.array(m, dtype=np.float32, copy=True)  # ``m`` may be the engine's buffer
    return np.maximum(acc, m, out=acc)


def run_staged(
    session,
    images: np.ndarray,
    lights: np.ndarray,
    chunk: int = DEFAULT_CHUNK,
    keep: dict[str, np.ndarray] | None = None,
) -> np.ndarray:
    """:func:`run_stages` through an onnxruntime.InferenceSession of a staged export, or any
    object with its ``run`` (a stage output it returns only has to stay valid until the next
    call: it is copied at once)."""
    base = placeholders()

    def stage(output: str, feeds: dict[str, np.ndarray], out: np.ndarray) -> np.ndarray:
        out[...] = session.run([output], {**base, **feeds})[0]
        return out.max(axis=0, keepdims=True)

    def final(pooled: np.ndarray) -> np.ndarray:
        return session.run(["normals"], {**base, "max3": pooled})[0]

    return run_stages(stage, final, images, lights, chunk, keep)


__all__ = [
    "DEFAULT_CHUNK",
    "STAGE_INPUTS",
    "STAGE_OUTPUTS",
    "FinalCall",
    "StageCall",
    "placeholders",
    "run_staged",
    "run_stages",
]
