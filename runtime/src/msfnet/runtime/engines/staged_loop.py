"""Light-chunked inference through a staged msfnet graph (``msf-export --staged``).

The network takes a max over all lights after each of its three stages. A staged export cuts the
graph there, so this loop can run a few lights at a time per stage and keep only each light's
stage output (96 channels at half resolution) between stages: per pixel and light that is 96 B
instead of the 1.3-3 KB of activations a monolithic graph holds at once, so tiles can be several
times larger for the same memory and less of the work goes into halos.
The result equals the monolithic graph's: the max is exact and every other op is per light.
"""

from __future__ import annotations

import numpy as np

STAGE_INPUTS = ("images", "lights", "feat1_in", "max1", "feat2_in", "max2", "max3")
STAGE_OUTPUTS = ("feat1", "feat2", "feat3", "normals")
FEATURES = 96  # channels of each stage's per-light output (half resolution)
DEFAULT_CHUNK = 8  # lights per call: enough work per call, a small activation working set
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


def run_staged(
    session,
    images: np.ndarray,
    lights: np.ndarray,
    chunk: int = DEFAULT_CHUNK,
    keep: dict[str, np.ndarray] | None = None,
) -> np.ndarray:
    """images (1, N, 3, H, W), lights (1, N, 3) -> normals (1, 3, H, W), ``chunk`` lights a call.

    ``session``: an onnxruntime.InferenceSession of a staged export, or any object with its
    ``run``; a stage output it returns only has to stay valid until the next call (it is copied
    at once). ``keep``: if given, filled with the real input of every entry point (all lights),
    as int8 calibration needs them.
    """
    if images.shape[0] != 1:
        raise ValueError("staged inference runs one stack at a time (batch 1)")
    n = images.shape[1]
    parts = [slice(i, min(i + chunk, n)) for i in range(0, n, chunk)]
    base = placeholders()

    def call(output: str, **feeds: np.ndarray) -> np.ndarray:
        return session.run([output], {**base, **feeds})[0]

    feats: np.ndarray | None = None
    for s in parts:
        f = call("feat1", images=images[:, s], lights=lights[:, s])
        if feats is None:
            feats = np.empty((n, *f.shape[1:]), np.float32)
        feats[s] = f
    assert feats is not None
    pooled = feats.max(axis=0, keepdims=True)
    for output, feat_in, max_in in (("feat2", "feat1_in", "max1"), ("feat3", "feat2_in", "max2")):
        if keep is not None:
            keep.update({feat_in: feats.copy(), max_in: pooled})
        for s in parts:  # in place: stage k's chunk is not needed once stage k+1 has it
            feats[s] = call(output, **{feat_in: feats[s], max_in: pooled})
        pooled = feats.max(axis=0, keepdims=True)
    if keep is not None:
        keep.update(images=images, lights=lights, max3=pooled)
    return call("normals", max3=pooled)


__all__ = ["DEFAULT_CHUNK", "STAGE_INPUTS", "STAGE_OUTPUTS", "placeholders", "run_staged"]
