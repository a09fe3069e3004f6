"""OAK (depthai) back-end: host-only paths always; the device path only when one is attached."""

from __future__ import annotations

import subprocess
import sys
import time

import numpy as np
import pytest

from msfnet.calib import cameras
from msfnet.common.errors import InputError

dai = pytest.importorskip("depthai")


@pytest.fixture(scope="module")
def devices():
    t = time.time()
    found = cameras.oak_devices()
    assert time.time() - t < 5.0  # discovery answers fast; never the ~12 s pipeline wait
    return found


def pack_raw10(img: np.ndarray) -> np.ndarray:
    h, w = img.shape
    g = img.reshape(h, w // 4, 4).astype(np.uint16)
    out = np.empty((h, w // 4, 5), np.uint8)
    out[..., :4] = g >> 2
    out[..., 4] = sum(((g[..., k] & 3) << (2 * k)) for k in range(4)).astype(np.uint8)
    return out.reshape(h, w * 5 // 4)


def test_raw10_frame_to_linear_rgb(rng):
    raw = rng.integers(64, 1024, (8, 16)).astype(np.uint16)
    assert np.array_equal(cameras.unpack_raw10(pack_raw10(raw), 16, 8), raw)
    frame = dai.ImgFrame()  # a host-side frame: no device involved
    frame.setType(dai.ImgFrame.Type.RAW10)
    frame.setWidth(16)
    frame.setHeight(8)
    frame.setStride(20)
    frame.setData(pack_raw10(raw).ravel())
    rgb = cameras.oak_frame_to_rgb(frame, "RGGB", black_level=64)
    assert rgb.shape == (8, 16, 3) and rgb.dtype == np.uint16
    flat = np.full((8, 16), 64 + 480, np.uint16)  # uniform grey stays uniform and linear
    assert np.allclose(cameras.raw_to_rgb(flat, "RGGB", 64), round(480 * 65535 / 959), atol=1)


def test_locked_control_is_host_constructible():
    ctrl = cameras.oak_control(8000, 200, 5000, 130)
    assert isinstance(ctrl, dai.CameraControl)
    assert dai.Pipeline(False) is not None  # host-only pipeline builds without a device


def test_no_device_fails_fast_and_cleanly(devices):
    if devices:
        pytest.skip("an OAK is attached; this checks the no-device path")
    t = time.time()
    with pytest.raises(InputError, match="no OAK device"):
        cameras.OakCamera()
    assert time.time() - t < 5.0


def test_capture_from_real_oak(devices):
    if not devices:
        pytest.skip("no OAK device attached")
    cam = cameras.OakCamera(exposure_us=5000, iso=100)
    try:
        frame = cam.capture()
        assert frame.ndim == 3 and frame.shape[2] == 3 and frame.dtype == np.uint16
    finally:
        cam.close()


def test_calib_never_imports_torch_depthai_or_serial():
    code = (
        "import sys; import msfnet.calib.cli, msfnet.calib.capture_cli, msfnet.calib.capture, "
        "msfnet.calib.cameras, msfnet.calib.lights; "
        "print(sorted(m for m in ('torch', 'depthai', 'serial') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
