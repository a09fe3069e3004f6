"""Single rotated / mirrored passes and their TTA averages on DiLiGenT, with their cost.

    python scripts/tta_measure.py ../shared/data/DiLiGenT --lights 8 16 [--objects ...] [--onnx M]

For each object and light count (evenly spaced; bear from images 21-96) the bundled model runs
once per dihedral copy (msfnet.runtime.infer.tta order); TTA-4 and TTA-8 are the unit mean of the
first 4 / all 8 copies mapped back, exactly what TTAEstimator computes. Prints one JSON line per
object and light count.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from msfnet.runtime.api import Model
from msfnet.runtime.evaluate.metrics import normal_metrics
from msfnet.runtime.infer.tta import normals_back, transform_stack, tta_transforms
from msfnet.runtime.instrument import StageTimer
from msfnet.runtime.stack.load import LoadOptions, load_stack

OBJECTS = {"ball": ("ballPNG", None), "bear": ("bearPNG", "21-96"), "harvest": ("harvestPNG", None)}


def unit_mean(parts: list[np.ndarray], mask: np.ndarray) -> np.ndarray:
    total = np.sum(parts, axis=0)
    out = total / np.maximum(np.linalg.norm(total, axis=2, keepdims=True), 1e-12)
    out[~mask] = 0.0
    return out.astype(np.float32)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("root", type=Path)
    ap.add_argument("--lights", type=int, nargs="+", default=[8, 16])
    ap.add_argument("--objects", nargs="+", default=list(OBJECTS))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--onnx", type=Path, default=None, help="another export (default: bundled)")
    args = ap.parse_args()
    # the network alone (no detail fusion): what TTA averages
    model = Model(args.onnx, threads=args.threads, maps=None, detail_fusion=False)
    for obj in args.objects:
        folder, select = OBJECTS[obj]
        for n in args.lights:
            stack = load_stack(args.root / folder, LoadOptions(select=select, max_lights=n))
            assert stack.normals_gt is not None
            passes, maes, secs = [], [], []
            for t in tta_transforms(8):
                t0 = time.perf_counter()
                moved = transform_stack(stack, t)
                est = model.estimator.estimate(moved, model.tiling, StageTimer())
                secs.append(time.perf_counter() - t0)
                back = normals_back(est.normals, t)
                passes.append(back)
                maes.append(normal_metrics(back, stack.normals_gt, stack.mask).mae_deg)

            mask, gt = stack.mask, stack.normals_gt
            tta = {k: normal_metrics(unit_mean(passes[:k], mask), gt, mask).mae_deg for k in (4, 8)}

            row = {
                "object": obj,
                "lights": n,
                "engine": model.describe().engine,
                "precision": model.describe().precision,
                "single_mae": [round(m, 3) for m in maes],
                "spread": round(max(maes) - min(maes), 3),
                "tta4": round(tta[4], 3),
                "tta8": round(tta[8], 3),
                "s_per_pass_median": round(float(np.median(secs)), 2),
            }
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
