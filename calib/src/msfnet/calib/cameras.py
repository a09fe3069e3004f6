"""Camera back-ends: any OpenCV camera, Luxonis OAK (depthai 3.x, imported lazily), simulated.

Every back-end returns RGB frames (H, W, 3) as uint8 or uint16 with ``white_level`` the largest
value the sensor can report, and locks exposure, gain/ISO, white balance and focus so that
frames differ only by the light.
"""

from __future__ import annotations

from typing import Protocol

import cv2
import numpy as np

from msfnet.common.errors import InputError


class Camera(Protocol):
    """``frame_shape`` (H, W), where a back-end can tell before capturing, is optional."""

    white_level: float

    def capture(self) -> np.ndarray: ...
    def info(self) -> dict: ...
    def close(self) -> None: ...


class OpenCVCamera:
    """A cv2.VideoCapture device (index or URL) with automatic controls switched off."""

    def __init__(
        self,
        device: int | str = 0,
        width: int | None = None,
        height: int | None = None,
        exposure: float | None = None,
        gain: float | None = None,
        wb_kelvin: float | None = None,
        focus: float | None = None,
        flush: int = 4,
        average: int = 1,
    ) -> None:
        self.cap = cv2.VideoCapture(device)
        if not self.cap.isOpened():
            raise InputError(f"cannot open OpenCV camera {device!r}")
        c = self.cap
        if width:
            c.set(cv2.CAP_PROP_FRAME_WIDTH, width)
        if height:
            c.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
        c.set(cv2.CAP_PROP_CONVERT_RGB, 1)
        # V4L2 takes 1 (= manual) for auto-exposure off; other back-ends take 0.25.
        if exposure is not None:
            c.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1) or c.set(cv2.CAP_PROP_AUTO_EXPOSURE, 0.25)
            c.set(cv2.CAP_PROP_EXPOSURE, exposure)
        if gain is not None:
            c.set(cv2.CAP_PROP_GAIN, gain)
        c.set(cv2.CAP_PROP_AUTO_WB, 0)
        if wb_kelvin is not None:
            c.set(cv2.CAP_PROP_WB_TEMPERATURE, wb_kelvin)
        c.set(cv2.CAP_PROP_AUTOFOCUS, 0)
        if focus is not None:
            c.set(cv2.CAP_PROP_FOCUS, focus)
        self.device, self.flush, self.average = device, flush, max(1, average)
        self.white_level = 255.0 if self.average == 1 else 65535.0

    def _read(self) -> np.ndarray:
        ok, frame = self.cap.read()
        if not ok or frame is None:
            raise InputError(f"OpenCV camera {self.device!r} returned no frame")
        return frame[:, :, ::-1] if frame.ndim == 3 else np.repeat(frame[..., None], 3, 2)

    def capture(self) -> np.ndarray:
        for _ in range(self.flush):  # drivers queue frames exposed before the light changed
            self.cap.grab()
        frames = [self._read() for _ in range(self.average)]
        if self.average == 1:
            return np.ascontiguousarray(frames[0])
        # Averaging 8-bit frames gains precision: keep it in a 16-bit container.
        mean = np.mean([f.astype(np.float64) for f in frames], axis=0)
        return np.clip(np.rint(mean * 257.0), 0, 65535).astype(np.uint16)

    def info(self) -> dict:
        props = {
            k: self.cap.get(getattr(cv2, f"CAP_PROP_{k.upper()}"))
            for k in ("frame_width", "frame_height", "exposure", "gain", "wb_temperature", "focus")
        }
        return {"backend": "opencv", "device": str(self.device), "average": self.average, **props}

    def close(self) -> None:
        self.cap.release()


def oak_devices(dai=None) -> list:
    """Attached OAK devices; ~0.5 s, never the ~12 s wait of opening a pipeline blindly."""
    if dai is None:
        import depthai as dai
    return list(dai.Device.getAllAvailableDevices())


def unpack_raw10(
    data: np.ndarray, width: int, height: int, stride: int | None = None
) -> np.ndarray:
    """MIPI RAW10 packed (4 pixels in 5 bytes, low bits in the 5th) -> uint16 (H, W)."""
    buf = np.frombuffer(np.asarray(data, np.uint8).tobytes(), np.uint8)
    stride = stride or width * 5 // 4
    rows = buf[: stride * height].reshape(height, stride)[:, : width * 5 // 4]
    g = rows.reshape(height, width // 4, 5).astype(np.uint16)
    out = np.empty((height, width // 4, 4), np.uint16)
    for k in range(4):
        out[..., k] = (g[..., k] << 2) | ((g[..., 4] >> (2 * k)) & 3)
    return out.reshape(height, width)


BAYER = {
    "RGGB": cv2.COLOR_BayerBG2RGB,
    "BGGR": cv2.COLOR_BayerRG2RGB,
    "GRBG": cv2.COLOR_BayerGB2RGB,
    "GBRG": cv2.COLOR_BayerGR2RGB,
}


def raw_to_rgb(
    raw: np.ndarray, pattern: str = "RGGB", black_level: int = 64, bits: int = 10
) -> np.ndarray:
    """Linear camera RGB (uint16, scaled to 16 bits) from a Bayer mosaic: the photometric
    choice, since ISP outputs are tone-mapped."""
    top = (1 << bits) - 1
    lin = np.clip(raw.astype(np.int32) - black_level, 0, None)
    lin = (lin * (65535.0 / max(top - black_level, 1))).astype(np.uint16)
    return cv2.cvtColor(lin, BAYER[pattern.upper()])


def oak_frame_to_rgb(frame, pattern: str = "RGGB", black_level: int = 64) -> np.ndarray:
    """A depthai ImgFrame (RAW10 packed, RAW16, RGB888i/BGR888i) -> RGB array."""
    import depthai as dai

    t = frame.getType()
    w, h = frame.getWidth(), frame.getHeight()
    if t == dai.ImgFrame.Type.RAW10:
        return raw_to_rgb(
            unpack_raw10(frame.getData(), w, h, frame.getStride()), pattern, black_level, 10
        )
    if t == dai.ImgFrame.Type.RAW16:
        raw = np.frombuffer(np.asarray(frame.getData()).tobytes(), np.uint16)[: w * h]
        return raw_to_rgb(raw.reshape(h, w), pattern, black_level, 16)
    if t in (dai.ImgFrame.Type.RGB888i, dai.ImgFrame.Type.BGR888i):
        arr = np.asarray(frame.getData(), np.uint8)[: w * h * 3].reshape(h, w, 3)
        return arr[:, :, ::-1].copy() if t == dai.ImgFrame.Type.BGR888i else arr.copy()
    return frame.getCvFrame()[:, :, ::-1].copy()  # anything else through depthai's converter


def oak_control(exposure_us: int, iso: int, wb_kelvin: int, lens_position: int):
    """A CameraControl with every automatic loop locked (host-side object, no device needed)."""
    import depthai as dai

    return _lock_controls(dai.CameraControl(), exposure_us, iso, wb_kelvin, lens_position)


def _lock_controls(ctrl, exposure_us: int, iso: int, wb_kelvin: int, lens_position: int):  # type: ignore[no-untyped-def]
    """``ctrl`` (a depthai CameraControl) with exposure, white balance and focus set."""
    ctrl.setManualExposure(int(exposure_us), int(iso))
    ctrl.setManualWhiteBalance(int(wb_kelvin))
    ctrl.setManualFocus(int(lens_position))
    return ctrl


class OakCamera:
    """Luxonis OAK through depthai 3.x with locked controls.

    ``mode="raw"`` (default): the full-resolution Bayer stream, black-level corrected and
    demosaiced on the host to linear 16-bit RGB. ``mode="isp"``: full-resolution RGB888 from the
    ISP (tone-mapped, not linear: intensity calibration then absorbs only part of it).
    """

    def __init__(
        self,
        exposure_us: int = 10000,
        iso: int = 100,
        wb_kelvin: int = 5500,
        lens_position: int = 120,
        mode: str = "raw",
        bayer: str = "RGGB",
        black_level: int = 64,
        device_id: str | None = None,
        flush: int = 3,
    ) -> None:
        try:
            import depthai as dai
        except ImportError as exc:
            raise InputError(
                "the OAK back-end needs depthai: pip install 'msfnet[camera]'"
            ) from exc
        devices = oak_devices(dai)
        if not devices:
            raise InputError("no OAK device found (USB connection, udev rules, container flags)")
        if device_id is not None and device_id not in [d.getDeviceId() for d in devices]:
            raise InputError(f"OAK device {device_id} not found")
        self.mode, self.bayer, self.black_level, self.flush = mode, bayer, black_level, flush
        self.settings = dict(
            exposure_us=exposure_us, iso=iso, wb_kelvin=wb_kelvin, lens_position=lens_position
        )
        info = next(d for d in devices if device_id in (None, d.getDeviceId()))
        self.device = dai.Device(info)
        self.pipeline = dai.Pipeline(self.device)
        cam = self.pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_A)
        _lock_controls(cam.initialControl, **self.settings)
        full = cam.requestFullResolutionOutput(dai.ImgFrame.Type.RGB888i)
        out = cam.raw if mode == "raw" else full
        self.queue = out.createOutputQueue(maxSize=2, blocking=False)
        self.control = cam.inputControl.createInputQueue()
        self.pipeline.start()
        self.control.send(oak_control(**self.settings))
        self.white_level = 65535.0 if mode == "raw" else 255.0

    def capture(self) -> np.ndarray:
        for _ in range(self.flush):  # frames already in flight were exposed under the old light
            self.queue.get()
        if self.mode == "raw":
            return oak_frame_to_rgb(self.queue.get(), self.bayer, self.black_level)
        return oak_frame_to_rgb(self.queue.get())

    def info(self) -> dict:
        return {"backend": "oak", "mode": self.mode, **self.settings}

    def close(self) -> None:
        try:
            self.pipeline.stop()
        finally:
            self.device.close()


class SimulatedCamera:
    """Renders the simulated rig's scene under whichever light is on."""

    def __init__(self, rig) -> None:
        self.rig = rig
        self.white_level = 255.0 if rig.bit_depth == 8 else 65535.0

    @property
    def frame_shape(self) -> tuple[int, int]:
        """(H, W) of every frame, known before capturing (lets a mask be checked first)."""
        cam = self.rig.scene.camera
        return cam.height, cam.width

    def capture(self) -> np.ndarray:
        # calib -> synth, the simulated rig only (see the msfnet package docstring): lazy
        from msfnet.synth.spheres import expose, render

        r = self.rig
        i = r.current
        light = None if i is None else r.lights[i]
        inten = None if i is None else r.intensities[i]
        rad = render(r.scene, light, inten, ambient=r.ambient)
        r.frames += 1
        rng = np.random.default_rng([r.seed, 0 if i is None else i + 1])
        return expose(rad, r.gain, r.bit_depth, r.noise, rng)

    def info(self) -> dict:
        return {"backend": "simulated", "bit_depth": self.rig.bit_depth}

    def close(self) -> None:
        pass


__all__ = [
    "BAYER",
    "OakCamera",
    "OpenCVCamera",
    "SimulatedCamera",
    "oak_control",
    "oak_devices",
    "oak_frame_to_rgb",
    "raw_to_rgb",
    "unpack_raw10",
]
