"""The sample stack behind ``msf-run --demo``: rendered on the spot, so nothing large is shipped.

A non-Lambertian synthetic object with ground truth (msfnet.synth, numpy only), so the demo can
print the bundled model's error next to least squares on the same data.
"""

from __future__ import annotations

from msfnet.synth.render import RenderOptions, render_stack

from .stack import Stack

DEMO_SEED = 20261122
DEMO_OPTIONS = RenderOptions(size=128, lights=32)


def demo_stack() -> Stack:
    """A fixed 128 x 128, 32-light synthetic object (same every run)."""
    stack = render_stack(DEMO_SEED, DEMO_OPTIONS, name="demo")
    stack.name = "demo"
    return stack
