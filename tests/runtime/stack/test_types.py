"""Stack.validate on integer stacks: the checks that matter for them, exact and cheap."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from _runtime_helpers import sphere_stack

from msfnet.runtime.errors import InputError
from msfnet.runtime.stack import Stack, as_held, held_dtype


def _int_stack(dtype: type, scale: float = 1.0) -> Stack:
    ref = sphere_stack(n=5)
    top = np.iinfo(dtype).max
    images = np.clip(np.rint(ref.images * np.float32(scale)), 0, top).astype(dtype)
    return replace(ref, images=images)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_integer_stacks_validate(dtype: type) -> None:
    scale = 255 / 65535 if dtype == np.uint8 else 1.0
    stack = _int_stack(dtype, scale)
    assert stack.validate() is stack and stack.images.dtype == dtype


def test_signal_range_uses_the_integer_maximum_without_overflow() -> None:
    """Every pixel at 65535: the peak is read in uint16 (a max cannot overflow) and the
    ratio to the intensity is taken in float64."""
    stack = _int_stack(np.uint16)
    full = replace(stack, images=np.full_like(stack.images, 65535))
    full.validate()
    tiny = np.full_like(stack.intensities, 65535 / 2e15)  # brightest / intensity = 2e15
    with pytest.raises(InputError, match=r"brightest pixel / light intensity is 2e\+15"):
        replace(full, intensities=tiny).validate()
    dim = np.full_like(stack.intensities, 1e7)  # 65535 / 1e7 = 6.55e-3: inside the range
    replace(full, intensities=dim).validate()


def test_black_integer_stack_is_refused() -> None:
    stack = _int_stack(np.uint8)
    with pytest.raises(InputError, match="every image is black"):
        replace(stack, images=np.zeros_like(stack.images)).validate()


def test_held_types() -> None:
    assert held_dtype(np.uint8) == np.uint8 and held_dtype(np.uint16) == np.uint16
    for other in (np.float16, np.float32, np.float64, np.int8, np.int16, np.int32, np.uint32,
                  np.bool_):
        assert held_dtype(other) == np.float32
    a = np.zeros((2, 2), np.uint16)
    assert as_held(a) is a  # no copy
    assert as_held(a.astype(np.float64)).dtype == np.float32
