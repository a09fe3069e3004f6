"""The sample behind ``msf-run --demo``: a rendered 128 x 128, 32-light object with ground truth.

Shipped as a small file (rendered once by ``python -m msfnet.synth.demo``, which a test keeps in
step with the renderer), so the runtime needs no renderer.
"""

from __future__ import annotations

from pathlib import Path

from msfnet.runtime.stack import Stack, load_stack

DEMO_FILE = Path(__file__).resolve().parent / "data" / "demo_stack.npz"


# the sample's name, and so its default output folder (msf-out/msfnet-sample): not "demo", which
# a user's own capture folder may well be called (it then landed in msf-out/demo-2)
DEMO_NAME = "msfnet-sample"


def demo_stack() -> Stack:
    stack = load_stack(DEMO_FILE)
    stack.name = DEMO_NAME
    return stack
