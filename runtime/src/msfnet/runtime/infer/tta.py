"""Test-time augmentation: average an estimator over rotated and mirrored copies of the stack.

Orthographic photometric stereo with isotropic materials is symmetric under the dihedral group
of the image grid (quarter turns about the view axis and mirrors), provided the light directions
turn with the image. Camera frame as everywhere in msfnet: x right, y up, z towards the camera;
rows run downwards. A quarter turn counter-clockwise *as seen on screen* is ``np.rot90`` over
(rows, cols) and maps a direction (x, y) -> (-y, x); a left-right mirror maps x -> -x.

Each copy is estimated, its normals are mapped back to the original frame (image and vectors),
summed, and renormalised to unit length. The network is not exactly equivariant (stride-2
sampling and the bottom/right padding differ between copies), so the average is a small
ensemble; for an exactly equivariant estimator (least squares) it equals the plain estimate.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from msfnet.runtime.engines.method import RunMethod
from msfnet.runtime.infer.estimators import Estimate, Estimator, TilingOptions
from msfnet.runtime.instrument import StageTimer
from msfnet.runtime.stack import Stack

TTA_COUNTS = (1, 4, 8)


@dataclass(frozen=True)
class Dihedral:
    """``k`` quarter turns counter-clockwise, then (if ``mirror``) a left-right mirror."""

    k: int = 0
    mirror: bool = False

    def matrix(self) -> np.ndarray:
        """The 2 x 2 map of (x, y) direction components (an orthogonal matrix)."""
        turn = np.array([[0.0, -1.0], [1.0, 0.0]])  # (x, y) -> (-y, x)
        m = np.linalg.matrix_power(turn, self.k % 4)
        if self.mirror:
            m = np.diag([-1.0, 1.0]) @ m
        return m

    def image(self, arr: np.ndarray, axes: tuple[int, int]) -> np.ndarray:
        """Rotate / mirror an array whose (rows, cols) are ``axes`` (a view, no copy)."""
        out = np.rot90(arr, self.k % 4, axes=axes)
        return np.flip(out, axis=axes[1]) if self.mirror else out

    def image_back(self, arr: np.ndarray, axes: tuple[int, int]) -> np.ndarray:
        """The inverse of :meth:`image`."""
        out = np.flip(arr, axis=axes[1]) if self.mirror else arr
        return np.rot90(out, -(self.k % 4), axes=axes)

    def vectors(self, v: np.ndarray) -> np.ndarray:
        """Directions (..., 3) turned with the image (z unchanged)."""
        out = np.array(v, dtype=np.float32, copy=True)
        out[..., :2] = v[..., :2] @ self.matrix().T.astype(np.float32)
        return out

    def vectors_back(self, v: np.ndarray) -> np.ndarray:
        out = np.array(v, dtype=np.float32, copy=True)
        out[..., :2] = v[..., :2] @ self.matrix().astype(np.float32)  # inverse = transpose
        return out


def tta_transforms(count: int) -> tuple[Dihedral, ...]:
    """The copies averaged for ``count`` = 1, 4 or 8.

    4 is the subgroup that keeps the image's shape (identity, half turn, both mirrors), so
    every copy tiles and pads like the plain pass; 8 adds the quarter turns (H and W swap)."""
    if count not in TTA_COUNTS:
        raise ValueError(f"tta must be one of {TTA_COUNTS}, got {count}")
    if count == 1:
        return (Dihedral(),)
    same_shape = (Dihedral(0), Dihedral(2), Dihedral(0, True), Dihedral(2, True))
    if count == 4:
        return same_shape
    return (*same_shape, Dihedral(1), Dihedral(3), Dihedral(1, True), Dihedral(3, True))


def transform_stack(stack: Stack, t: Dihedral) -> Stack:
    """The stack as the rotated / mirrored scene (images, mask, lights, ground truth)."""
    if t == Dihedral():
        return stack
    gt = stack.normals_gt
    return replace(
        stack,
        images=np.ascontiguousarray(t.image(stack.images, (1, 2))),
        mask=np.ascontiguousarray(t.image(stack.mask, (0, 1))),
        lights=t.vectors(stack.lights),
        normals_gt=None if gt is None else np.ascontiguousarray(t.vectors(t.image(gt, (0, 1)))),
    )


def normals_back(normals: np.ndarray, t: Dihedral) -> np.ndarray:
    """(H', W', 3) normals estimated on the transformed stack, in the original frame."""
    return np.ascontiguousarray(t.vectors_back(t.image_back(normals, (0, 1))))


class TTAEstimator:
    """Wraps an estimator: the mean of its normals over ``count`` dihedral copies, unit length."""

    def __init__(self, inner: Estimator, count: int) -> None:
        self.transforms = tta_transforms(count)
        self.inner, self.count = inner, count
        self.method = inner.method

    def describe(self) -> RunMethod:
        return replace(self.inner.describe(), tta=self.count)

    def estimate(
        self, stack: Stack, tiling: TilingOptions, timer: StageTimer, progress: bool = False
    ) -> Estimate:
        total = np.zeros((*stack.shape, 3), np.float64)
        flops, plan = 0.0, None
        for t in self.transforms:
            est = self.inner.estimate(transform_stack(stack, t), tiling, timer, progress)
            total += normals_back(est.normals, t)
            flops += est.flops
            plan = plan or est.plan  # the plain pass's plan (the first copy is the identity)
        norm = np.linalg.norm(total, axis=2, keepdims=True)
        normals = np.where(norm > 1e-12, total / np.maximum(norm, 1e-12), 0.0)
        normals[~stack.mask] = 0.0
        return Estimate(normals.astype(np.float32), plan, flops)


__all__ = [
    "TTA_COUNTS",
    "Dihedral",
    "TTAEstimator",
    "normals_back",
    "transform_stack",
    "tta_transforms",
]
