"""The demo sample shipped with the runtime is exactly what the renderer makes today."""

from __future__ import annotations

import numpy as np

from msfnet.runtime.demo import DEMO_FILE, demo_stack
from msfnet.synth.demo import demo_arrays


def test_shipped_demo_equals_a_fresh_render() -> None:
    shipped = np.load(DEMO_FILE)
    fresh = demo_arrays()
    assert set(shipped.files) == set(fresh)
    for key, value in fresh.items():
        np.testing.assert_array_equal(shipped[key], value, err_msg=key)
    stack = demo_stack()
    assert stack.num_lights == 32 and stack.shape == (128, 128)
    assert stack.normals_gt is not None
