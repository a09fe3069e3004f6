"""The options of ``msf-calib directions``, ``msf-calib intensities`` and ``msf-capture``, each
user-set one declared once on its field with its flag (common.vocabulary), as msf-run's are:
the parsers are built from these types, and each command builds its options object once from
the parsed flags and hands it down typed.

What is no flag here: the positional folders, ``-o`` and ``-q`` (the parser adds them by hand:
``-o`` is spelled differently by other commands, ``-q`` is every command's); a command fills
them in when it builds the options.
"""

from __future__ import annotations

import argparse
from dataclasses import MISSING, dataclass
from pathlib import Path

from msfnet.common.cli import (
    finite_float,
    float_range,
    int_range,
    nonnegative_float,
    nonnegative_int,
    path_arg,
    positive_float,
    positive_int,
)
from msfnet.common.vocabulary import flag, options_type
from msfnet.runtime.stack import MIN_LIGHTS
from msfnet.runtime.stack.readers import MAX_LIGHTS

MAX_SPHERES = 16
MAX_INTERVAL = 7 * 24 * 3600.0  # seconds: a week at most, time.sleep overflows on inf and huge
SHARED = "shared"  # the category of the options both msf-calib sub-commands take
DEVICES = "devices"  # msf-capture's "capture devices" group ...
LINEARISE = "linearise"  # ... and its --srgb / --gamma pair within it (one of them)


# ---------------------------------------------------------------- msf-calib


@options_type
@dataclass(frozen=True, kw_only=True)
class CalibOptions:
    """What both msf-calib sub-commands take (their help lists it after their own options)."""

    output: Path  # -o: the output text file
    mask: Path | None = flag(
        None,
        "target mask image (default: a file in the "
        "folder with 'mask' in its name; else the sphere is fitted from images)",
        type=path_arg,
        category=SHARED,
    )
    ambient: Path | None = flag(
        None,
        "dark/ambient frame to subtract (default: a file with 'ambient' or 'dark' in its name)",
        type=path_arg,
        category=SHARED,
    )
    no_ambient: bool = flag(
        False, "do not subtract any frame", action="store_true", category=SHARED
    )
    focal: float | None = flag(
        None,
        "perspective: focal length in "
        "pixels, principal point at the image centre (default: orthographic)",
        type=positive_float,
        category=SHARED,
    )
    intrinsics: tuple[float, float, float, float] | None = flag(
        None,
        "perspective: full pinhole intrinsics in pixels (FX, FY > 0)",
        type=finite_float,
        nargs=4,
        metavar=("FX", "FY", "CX", "CY"),
        category=SHARED,
    )
    overwrite: bool = flag(
        False,
        "replace existing outputs (lights, confidence, diagnostic files)",
        action="store_true",
        category=SHARED,
    )
    quiet: bool = False  # -q: errors only


@options_type
@dataclass(frozen=True, kw_only=True)
class DirectionsOptions(CalibOptions):
    """``msf-calib directions``: mirror-sphere folders, spheres, diagnostic image."""

    images_dir: tuple[Path, ...]  # the folders of mirror-sphere images (positional)
    spheres: int = flag(
        1, "spheres to find when there is no mask (default 1)", type=int_range(1, MAX_SPHERES)
    )
    diagnostic: Path | None = flag(
        None,
        "diagnostic PNG path (default "
        "<output>_diagnostic.png; with several captures, _1, _2, ... are appended)",
        type=path_arg,
    )
    no_diagnostic: bool = flag(False, "write no diagnostic image", action="store_true")


@options_type
@dataclass(frozen=True, kw_only=True)
class IntensitiesOptions(CalibOptions):
    """``msf-calib intensities``: white-target folder, lights file, target shape."""

    images_dir: Path  # the folder of images of the white target (positional)
    lights: Path = flag(
        MISSING, "light_directions.txt for these images", type=path_arg, required=True
    )
    target: str = flag(
        "sphere",
        "the white target's shape (default sphere; plane: see --normal)",
        choices=("sphere", "plane"),
    )
    normal: tuple[float, float, float] | None = flag(
        None,
        "plane normal, with --target plane (default 0 0 1, facing the camera)",
        type=finite_float,
        nargs=3,
        metavar=("X", "Y", "Z"),
    )
    accept_poor_fit: bool = flag(
        False,
        "write the intensities even when the target fits matte shading poorly (fit "
        "residual above 20%%: usually wrong light directions or a glossy target); a warning "
        "says so",
        action="store_true",
    )


# ---------------------------------------------------------------- msf-capture


@options_type
@dataclass(frozen=True)
class CaptureOptions:
    """``msf-capture``: the camera, the light rig, the session's files and how frames are
    kept (category DEVICES, the help's "capture devices"), then the folder's own options."""

    # the camera back-end and its settings (exposure, gain, white balance, focus ...)
    camera: str = flag(
        "opencv",
        "camera back-end (default opencv); sim: a rendered sphere, no hardware",
        choices=("oak", "opencv", "sim"),
        category=DEVICES,
    )
    device: str = flag("0", "OpenCV device index or URL; OAK device id", category=DEVICES)
    exposure: float | None = flag(
        None,
        "OpenCV: exposure in the driver's units, passed as given (V4L2 and DirectShow "
        "drivers often take negative log2 seconds, e.g. -6); OAK: microseconds, positive "
        "(default 10000)",
        type=finite_float,
        category=DEVICES,
    )
    iso: int = flag(100, "OAK ISO (default 100)", type=int, category=DEVICES)
    gain: float | None = flag(None, "OpenCV gain", type=finite_float, category=DEVICES)
    wb_kelvin: int = flag(5500, "locked white balance", type=int, category=DEVICES)
    focus: float | None = flag(
        None, "locked focus (OAK lens position 0..255)", type=finite_float, category=DEVICES
    )
    oak_mode: str = flag(
        "raw",
        "raw: linear Bayer demosaiced on host (default); isp: tone-mapped RGB",
        choices=("raw", "isp"),
        category=DEVICES,
    )
    bayer: str = flag("RGGB", "OAK raw Bayer pattern (default RGGB)", category=DEVICES)
    average: int = flag(1, "OpenCV: frames averaged per light", type=positive_int, category=DEVICES)
    # the light back-end and its settings
    light_rig: str | None = flag(
        None,
        "light back-end (default: sim with --camera sim, "
        "otherwise manual: an operator prompt per light)",
        choices=("serial", "manual", "sim"),
        category=DEVICES,
    )
    port: str | None = flag(
        None, "serial port of the LED controller, e.g. /dev/ttyUSB0", category=DEVICES
    )
    baud: int = flag(
        115200, "serial speed of --port (default 115200)", type=positive_int, category=DEVICES
    )
    count: int | None = flag(
        None,
        f"number of lights, at least {MIN_LIGHTS} (manual; checks serial; sim default 12)",
        # fewer than MIN_LIGHTS photos cannot give a normal: refused before the first frame
        type=int_range(MIN_LIGHTS, MAX_LIGHTS),
        category=DEVICES,
    )
    settle: float = flag(
        0.05,
        "--light-rig serial: seconds to wait after switching a light (default 0.05; "
        "the manual and sim rigs do not wait)",
        type=nonnegative_float,
        category=DEVICES,
    )
    # the simulated scene, the light files put in the stack, and how frames are kept
    sim_scene: str = flag(
        "matte",
        "simulated scene: a chrome sphere (light calibration) or a matte one",
        choices=("chrome", "matte"),
        category=DEVICES,
    )
    light_directions: Path | None = flag(
        None,
        "light_directions.txt to put in the "
        "stack (from msf-calib directions); checked before capturing",
        type=path_arg,
        category=DEVICES,
    )
    light_intensities: Path | None = flag(
        None, "light_intensities.txt for the stack", type=path_arg, category=DEVICES
    )
    no_ambient: bool = flag(
        False, "skip the ambient (dark) frame", action="store_true", category=DEVICES
    )
    keep_ambient: bool = flag(
        False,
        "do not subtract the ambient frame from the stack images",
        action="store_true",
        category=DEVICES,
    )
    strict: bool = flag(
        False, "fail on saturated/under-exposed frames", action="store_true", category=DEVICES
    )
    # the camera's encoding, undone when the stack is built: --srgb or --gamma, not both
    srgb: bool = flag(
        False,
        "the camera delivers sRGB-encoded frames (webcams, OAK isp): the "
        "stack is written linear, 16-bit; recorded in session.json",
        action="store_true",
        category=LINEARISE,
    )
    gamma: float | None = flag(
        None,
        "the camera's frames are power-law encoded: linear = value ** G",
        type=positive_float,
        metavar="G",
        category=LINEARISE,
    )
    # the session folder's own options
    mask: Path | None = flag(
        None,
        "object mask for the stack and exposure checks "
        "(checked before capturing; the simulated camera writes its own)",
        type=path_arg,
    )
    overwrite: bool = flag(
        False,
        "discard the session already captured (its frames, session.json and "
        "the stack built from them; other images stay), or capture into a folder "
        "holding other images",
        action="store_true",
    )
    loop: int | None = flag(  # --loop alone: 0, until Ctrl-C
        None,
        "capture stack after stack into OUT/001, OUT/002, ... "
        "(K takes; none or 0: until Ctrl-C); with --run each is run as soon as "
        "it is captured, with the model loaded once (results in OUT/NNN-normals, "
        "or -o of msf-run's options as their parent)",
        nargs="?",
        const=0,
        type=nonnegative_int,
        metavar="K",
    )
    interval: float = flag(
        0.0,
        "--loop: seconds to wait between takes (to move the object; at most a week)",
        type=float_range(0.0, MAX_INTERVAL),
        metavar="S",
    )
    run: tuple[str, ...] | None = flag(
        None,
        "after capturing, run msf-run on the stack; the rest of the command "
        "line goes to msf-run (e.g. --run --method l2 -o out/)",
        nargs=argparse.REMAINDER,
        metavar="MSF_RUN_ARGS",
    )
    quiet: bool = False  # -q: errors only (warnings still print)


__all__ = ["CalibOptions", "CaptureOptions", "DirectionsOptions", "IntensitiesOptions"]
