"""How the normals' error grows with what a real rig gets wrong, for each path (issue #47, 1).

    python scripts/rig_errors.py [--seeds 3] [--methods l2,fast,full]

Rendered inspection plates (synth.plates: 128 x 192, 12 LEDs on a 35 deg ring, the user's mask
cut at column 144 where the surface goes on, a background strip below), matte and glossy, each
under one error the tool is not told about at a time, then all together:

- ``lights 0.5deg``: each light direction the tool reads is 0.5 deg off the one that lit it
  (a random direction per light);
- ``LED +-2%``: each light 2 % brighter or dimmer (uniform) than the intensities say;
- ``8-bit``: the images quantised to 8 bits (the brightest pixel at 250);
- ``rig``: all three.

Printed: the mean angular error (deg) inside (more than 4 px from the mask's edge) / within 4
px of the mask's edge, per path, as a markdown table; each cell the mean over ``--seeds``
plates. Deterministic for a given seed list.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import replace

import cv2
import numpy as np

from msfnet.runtime.api import Model
from msfnet.runtime.evaluate.metrics import error_map
from msfnet.runtime.options import ModelOptions
from msfnet.runtime.stack import Stack
from msfnet.synth.plates import PlateOptions, render_plate

EDGE_PX = 4
PATHS = {
    "l2": ModelOptions(method="l2", maps=None),
    "fast": ModelOptions(speed="fast", maps=None),
    "full": ModelOptions(maps=None),
}


def _tilted(lights: np.ndarray, deg: float, rng: np.random.Generator) -> np.ndarray:
    """Each unit direction turned by ``deg`` about a random axis perpendicular to it."""
    out = []
    for v in lights.astype(np.float64):
        axis = np.cross(v, rng.normal(size=3))
        axis /= np.linalg.norm(axis)
        t = np.radians(deg)
        out.append(v * np.cos(t) + np.cross(axis, v) * np.sin(t))
    return np.asarray(out, np.float32)


def _lights_off(stack: Stack, rng: np.random.Generator) -> Stack:
    return replace(stack, lights=_tilted(stack.lights, 0.5, rng))


def _leds_off(stack: Stack, rng: np.random.Generator) -> Stack:
    gain = 1.0 + rng.uniform(-0.02, 0.02, stack.num_lights)
    images = stack.images.astype(np.float32) * gain[:, None, None, None].astype(np.float32)
    return replace(stack, images=images)


def _eight_bit(stack: Stack, rng: np.random.Generator) -> Stack:
    images = stack.images.astype(np.float32)
    scale = 250.0 / max(float(images.max()), 1e-12)
    return replace(stack, images=np.round(images * scale).astype(np.uint8))


def _rig(stack: Stack, rng: np.random.Generator) -> Stack:
    return _eight_bit(_leds_off(_lights_off(stack, rng), rng), rng)


ERRORS: dict[str, Callable[[Stack, np.random.Generator], Stack]] = {
    "clean": lambda stack, rng: stack,
    "lights 0.5deg": _lights_off,
    "LED +-2%": _leds_off,
    "8-bit": _eight_bit,
    "rig": _rig,
}


def _scores(normals: np.ndarray, stack: Stack) -> tuple[float, float]:
    err = error_map(normals, stack.normals_gt, stack.mask)  # type: ignore[arg-type]
    inside = cv2.distanceTransform(stack.mask.astype(np.uint8), cv2.DIST_L2, 5) > EDGE_PX
    edge = stack.mask & ~inside
    return float(np.nanmean(err[inside])), float(np.nanmean(err[edge]))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--methods", default="l2,fast,full")
    args = p.parse_args()
    paths = args.methods.split(",")
    models = {name: Model(options=PATHS[name]) for name in paths}
    print("| part | error | " + " | ".join(f"{m} in / edge" for m in paths) + " |")
    print("|---|---|" + "---|" * len(paths))
    for glossy in (False, True):
        plates = [render_plate(PlateOptions(seed=s, glossy=glossy)) for s in range(args.seeds)]
        for error, spoil in ERRORS.items():
            cells = []
            for name in paths:
                pairs = []
                for s, plate in enumerate(plates):
                    stack = spoil(plate.stack, np.random.default_rng([s, 47]))
                    pairs.append(_scores(models[name](stack).normals, stack))
                inside, edge = np.mean(pairs, axis=0)
                cells.append(f"{inside:.2f} / {edge:.2f}")
            part = "glossy plate" if glossy else "matte plate"
            print(f"| {part} | {error} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
