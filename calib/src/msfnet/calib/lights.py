"""Light back-ends: a serial LED controller, a manual prompt, and a simulated rig.

Serial line protocol (ASCII, one command per line, ``\\n``-terminated, 1-based light index;
the controller answers every command with one line, ``OK ...`` or ``ERR <reason>``):

    PING        -> OK MSF-LED <count>     handshake; <count> = number of lights
    ON <i>      -> OK                     light i on, every other light off
    OFF         -> OK                     all lights off
    LEVEL <v>   -> OK                     optional: drive level 0..255 for later ON commands

The host waits for the reply (timeout = error) and then ``settle`` seconds before exposing.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Protocol

from msfnet.common.errors import InputError
from msfnet.common.vocabulary import opt


class Lights(Protocol):
    count: int

    def on(self, index: int) -> None: ...  # 0-based; only this light on
    def off(self) -> None: ...
    def close(self) -> None: ...


class SerialPort(Protocol):
    """What SerialLights needs of a port (a pyserial Serial, or a fake in tests)."""

    def write(self, data: bytes) -> object: ...

    def readline(self) -> bytes: ...

    def close(self) -> None: ...


class SerialLights:
    """An LED controller speaking the line protocol above (pyserial, imported lazily)."""

    def __init__(
        self,
        port: str | SerialPort,
        baud: int = 115200,
        count: int | None = None,
        timeout: float = 2.0,
        settle: float = 0.05,
        level: int | None = None,
    ) -> None:
        if isinstance(port, str):
            try:
                import serial  # pyserial: the [camera] extra
            except ImportError as exc:
                raise InputError(
                    "the serial light back-end needs pyserial: pip install 'msfnet[camera]'"
                ) from exc
            try:
                port = serial.Serial(port, baud, timeout=timeout)
            except Exception as exc:  # SerialException, OSError
                raise InputError(f"cannot open serial port ({exc})", str(port)) from exc
        self.port: SerialPort = port  # type: ignore[assignment]
        self.settle = settle
        reply = self._command("PING")
        parts = reply.split()
        reported = int(parts[2]) if len(parts) >= 3 and parts[2].isdigit() else None
        if count is not None and reported is not None and count != reported:
            raise InputError(f"controller reports {reported} lights but {count} were expected")
        self.count = count if count is not None else (reported or 0)
        if self.count <= 0:
            raise InputError(
                f"controller did not report its light count (reply {reply!r}); pass {opt('count')}"
            )
        if level is not None:
            self._command(f"LEVEL {int(level)}")

    def _command(self, line: str) -> str:
        self.port.write((line + "\n").encode("ascii"))
        raw = self.port.readline()
        reply = raw.decode("ascii", "replace").strip() if raw else ""
        if not reply:
            raise InputError(f"LED controller did not answer {line!r} (timeout)")
        if not reply.startswith("OK"):
            raise InputError(f"LED controller refused {line!r}: {reply}")
        return reply

    def on(self, index: int) -> None:
        self._command(f"ON {index + 1}")
        time.sleep(self.settle)

    def off(self) -> None:
        self._command("OFF")
        time.sleep(self.settle)

    def close(self) -> None:
        try:
            self._command("OFF")
        finally:
            close = getattr(self.port, "close", None)
            if close:
                close()


class ManualLights:
    """The operator switches lights by hand when prompted."""

    def __init__(self, count: int, ask: Callable[[str], str] = input) -> None:
        self.count = count
        self.ask = ask

    def on(self, index: int) -> None:
        self.ask(f"Switch ON light {index + 1} of {self.count} (only it), then press Enter: ")

    def off(self) -> None:
        self.ask("Switch ALL lights off (ambient frame), then press Enter: ")

    def close(self) -> None:
        pass


class SimulatedLights:
    """Lights of a simulated rig: tells the shared rig state which light is on."""

    def __init__(self, rig: SimulatedRig) -> None:
        self.rig = rig
        self.count = len(rig.lights)

    def on(self, index: int) -> None:
        self.rig.current = index

    def off(self) -> None:
        self.rig.current = None

    def close(self) -> None:
        self.rig.current = None


class SimulatedRig:
    """Known lights + a synthetic scene; pair with ``cameras.SimulatedCamera``."""

    def __init__(
        self,
        scene,
        lights,
        intensities=None,
        ambient: float = 0.05,
        gain: float = 0.8,
        bit_depth: int = 16,
        noise: float = 0.0,
        seed: int = 0,
    ):
        import numpy as np

        self.scene = scene
        self.lights = np.asarray(lights, np.float64)
        self.intensities = (
            np.ones((len(self.lights), 3))
            if intensities is None
            else np.asarray(intensities, np.float64)
        )
        self.ambient = ambient
        self.gain = gain
        self.bit_depth = bit_depth
        self.noise = noise
        self.seed = seed
        self.current: int | None = None
        self.frames = 0


__all__ = ["Lights", "ManualLights", "SerialLights", "SimulatedLights", "SimulatedRig"]
