"""Renders the sample behind ``msf-run --demo`` into the runtime's data folder.

``python -m msfnet.synth.demo`` rewrites runtime/src/msfnet/runtime/data/demo_stack.npz; a test
checks that the shipped file equals a fresh render, so the two never drift apart.
"""

from __future__ import annotations

import io
import sys
from pathlib import Path

import numpy as np

from msfnet.common.files import write_atomic
from msfnet.synth.render import RenderOptions, render_stack

DEMO_SEED = 20261122
DEMO_OPTIONS = RenderOptions(size=128, lights=32)


def demo_arrays() -> dict[str, np.ndarray]:
    """The demo stack as the arrays of its .npz file (images as 16-bit counts)."""
    stack = render_stack(DEMO_SEED, DEMO_OPTIONS, name="demo")
    return {
        "images": np.rint(stack.images).astype(np.uint16),
        "lights": stack.lights,
        "intensities": stack.intensities,
        "mask": stack.mask,
        "normals": np.asarray(stack.normals_gt, np.float32),
    }


def write_demo(path: Path) -> Path:
    buf = io.BytesIO()
    np.savez_compressed(buf, **demo_arrays())  # type: ignore[arg-type]
    return write_atomic(path, lambda t: t.write_bytes(buf.getvalue()))


def main() -> int:
    from msfnet.runtime.demo import DEMO_FILE

    print(f"wrote {write_demo(DEMO_FILE)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
