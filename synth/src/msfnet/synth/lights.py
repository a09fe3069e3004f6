"""Light rigs: directions in a cone around the view axis and per-light RGB intensities.

Real rigs (DiLiGenT: 96 LEDs, 4-43 deg from the view axis, mean 27 deg) put every light in front
of the object, mostly within ~50 deg of the camera axis. Directions: x right, y up, z to camera.
"""

from __future__ import annotations

import numpy as np


def cone_lights(
    n: int, rng: np.random.Generator, max_angle_deg: float = 50.0, min_angle_deg: float = 0.0
) -> np.ndarray:
    """n unit directions uniform over the spherical cap [min, max] deg from +z, (n, 3) float32."""
    cmin, cmax = np.cos(np.radians(min_angle_deg)), np.cos(np.radians(max_angle_deg))
    cz = rng.uniform(cmax, cmin, n)  # uniform in cos(theta) = uniform area on the cap
    phi = rng.uniform(0, 2 * np.pi, n)
    s = np.sqrt(1 - cz**2)
    return np.stack([s * np.cos(phi), s * np.sin(phi), cz], axis=1).astype(np.float32)


def grid_lights(n: int, rng: np.random.Generator, max_angle_deg: float = 45.0) -> np.ndarray:
    """A jittered square LED board (like DiLiGenT's) seen from the object, (n, 3) float32."""
    side = int(np.ceil(np.sqrt(n)))
    half = np.tan(np.radians(max_angle_deg)) / np.sqrt(2)
    t = np.linspace(-half, half, side)
    gx, gy = np.meshgrid(t, t)
    pts = np.stack([gx.ravel(), gy.ravel()], axis=1)
    pts = pts[rng.permutation(len(pts))[:n]] + rng.normal(0, 0.15 * half / side, (n, 2))
    v = np.concatenate([pts, np.ones((n, 1))], axis=1)
    return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


def rig_lights(n: int, rng: np.random.Generator) -> np.ndarray:
    """A random real-rig-like layout: a cone of random width, or a jittered LED board."""
    if rng.random() < 0.35:
        return grid_lights(n, rng, rng.uniform(35.0, 50.0))
    # Mostly within ~50 deg; a few rigs reach 65 deg for harder, more shadowed cases.
    max_angle = rng.uniform(35.0, 55.0) if rng.random() < 0.8 else rng.uniform(55.0, 65.0)
    return cone_lights(n, rng, max_angle)


def led_ring_lights(
    n: int,
    rng: np.random.Generator,
    angles_deg: tuple[float, ...] = (30.0,),
    jitter_deg: float = 1.0,
) -> np.ndarray:
    """LED ring(s) around the lens: n lights split as evenly as possible over rings at the given
    angles from the view axis (the first rings take the remainder), evenly spaced in azimuth
    with a random rotation per ring and up to ``jitter_deg`` of mounting error. (n, 3) float32.

    A ring "at 30 deg" means every LED is 30 deg off the camera axis (the object sees the ring
    at 60 deg elevation above its base plane)."""
    if n < 1 or not angles_deg:
        raise ValueError("need n >= 1 and at least one ring angle")
    per = np.full(len(angles_deg), n // len(angles_deg))
    per[: n % len(angles_deg)] += 1
    polar, azim = [], []
    for count, angle in zip(per, angles_deg, strict=True):
        if count == 0:
            continue
        az = np.arange(count) * (2 * np.pi / count) + rng.uniform(0, 2 * np.pi)
        polar.append(angle + rng.uniform(-jitter_deg, jitter_deg, count))
        azim.append(az + np.radians(rng.uniform(-jitter_deg, jitter_deg, count)))
    th, ph = np.radians(np.concatenate(polar)), np.concatenate(azim)
    dirs = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=1)
    return dirs.astype(np.float32)


def ring_rig(n: int, rng: np.random.Generator) -> np.ndarray:
    """A random LED-ring rig with n lights: one ring (15-55 deg) or two (10-30 and 35-60 deg);
    more rings when n > 32, so no ring holds more than 16 LEDs (rings sold carry 8-16)."""
    rings = 1 if rng.random() < 0.5 else 2
    rings = max(rings, int(np.ceil(n / 16)))
    if rings == 1:
        angles: tuple[float, ...] = (rng.uniform(15.0, 55.0),)
    elif rings == 2:
        angles = (rng.uniform(10.0, 30.0), rng.uniform(35.0, 60.0))
    else:
        angles = tuple(np.sort(rng.uniform(10.0, 60.0, rings)))
    return led_ring_lights(n, rng, angles)


def rig_intensities(n: int, rng: np.random.Generator) -> np.ndarray:
    """Per-light RGB intensities: a rig-wide colour cast plus per-LED brightness scatter."""
    cast = np.exp(rng.normal(0, 0.25, 3))
    per_light = np.exp(rng.normal(0, rng.uniform(0.05, 0.5), (n, 1)))
    per_channel = np.exp(rng.normal(0, 0.05, (n, 3)))
    return (cast * per_light * per_channel).astype(np.float32)
