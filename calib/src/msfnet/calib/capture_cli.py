"""``msf-capture``: capture a photometric stack (one frame per light + ambient), resumable."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from msfnet.runtime.errors import InputError

from .cameras import Camera
from .capture import capture_stack
from .lights import Lights


def add_device_arguments(p: argparse.ArgumentParser, lights_flag: str = "--light-rig",
                         camera_default: str | None = "opencv") -> None:
    """Camera, light-rig and session options, shared by msf-capture and ``msf-run --camera``.

    ``lights_flag`` names the light back-end option (msf-run already uses --lights for files).
    The caller adds --mask and --overwrite, whose meaning it owns.
    """
    g = p.add_argument_group("capture devices")
    g.add_argument("--camera", choices=("oak", "opencv", "sim"), default=camera_default,
                   help="camera back-end" + (f" (default {camera_default})" if camera_default
                                             else ": capture the stack first, then run"))
    g.add_argument("--device", default="0", help="OpenCV device index or URL; OAK device id")
    g.add_argument("--exposure", type=float, help="OpenCV: exposure (driver units); "
                   "OAK: microseconds (default 10000)")
    g.add_argument("--iso", type=int, default=100, help="OAK ISO (default 100)")
    g.add_argument("--gain", type=float, help="OpenCV gain")
    g.add_argument("--wb-kelvin", type=int, default=5500, help="locked white balance")
    g.add_argument("--focus", type=float, help="locked focus (OAK lens position 0..255)")
    g.add_argument("--oak-mode", choices=("raw", "isp"), default="raw",
                   help="raw: linear Bayer demosaiced on host (default); isp: tone-mapped RGB")
    g.add_argument("--bayer", default="RGGB", help="OAK raw Bayer pattern (default RGGB)")
    g.add_argument("--average", type=int, default=1, help="OpenCV: frames averaged per light")
    g.add_argument(lights_flag, dest="light_rig", choices=("serial", "manual", "sim"),
                   default="manual", help="light back-end (default manual: operator prompt)")
    g.add_argument("--port", help="serial port of the LED controller, e.g. /dev/ttyUSB0")
    g.add_argument("--baud", type=int, default=115200)
    g.add_argument("--count", type=int, help="number of lights (manual; checks serial)")
    g.add_argument("--settle", type=float, default=0.05, help="seconds after switching a light")
    g.add_argument("--sim-scene", choices=("chrome", "matte"), default="matte")
    g.add_argument("--light-directions", type=Path, help="light_directions.txt to put in the "
                   "stack (from msf-calib directions)")
    g.add_argument("--light-intensities", type=Path, help="light_intensities.txt for the stack")
    g.add_argument("--no-ambient", action="store_true", help="skip the ambient (dark) frame")
    g.add_argument("--keep-ambient", action="store_true",
                   help="do not subtract the ambient frame from the stack images")
    g.add_argument("--strict", action="store_true", help="fail on saturated/under-exposed frames")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="msf-capture", description=__doc__ + " Frames are written "
                                "to OUT_DIR/raw as they arrive; run the same command again to "
                                "resume an interrupted session.")
    p.add_argument("out_dir", type=Path, help="session / stack folder")
    add_device_arguments(p)
    p.add_argument("--mask", type=Path, help="object mask for the stack and exposure checks")
    p.add_argument("--overwrite", action="store_true", help="discard frames already captured")
    p.add_argument("--run", nargs=argparse.REMAINDER, metavar="MSF_RUN_ARGS",
                   help="after capturing, run msf-run on the stack; the rest of the command "
                   "line goes to msf-run (e.g. --run --method l2 -o out/)")
    return p


def _open(args: argparse.Namespace) -> tuple[Camera, Lights]:
    if args.camera == "sim" or args.light_rig == "sim":
        if args.camera != "sim" or args.light_rig != "sim":
            raise InputError("--camera sim and --lights sim go together")
        from msfnet.synth.spheres import mirror_scene, ring_lights

        from .cameras import SimulatedCamera
        from .lights import SimulatedLights, SimulatedRig

        kind = "mirror" if args.sim_scene == "chrome" else "matte"
        rig = SimulatedRig(mirror_scene(160, 128, 56, kind=kind), ring_lights(args.count or 12),
                           gain=0.8 if kind == "matte" else 0.02)
        return SimulatedCamera(rig), SimulatedLights(rig)
    if args.light_rig == "serial":
        if not args.port:
            raise InputError("--lights serial needs --port")
        from .lights import SerialLights

        lights: Lights = SerialLights(args.port, args.baud, args.count, settle=args.settle)
    else:
        if not args.count:
            raise InputError("--lights manual needs --count")
        from .lights import ManualLights

        lights = ManualLights(args.count)
    if args.camera == "oak":
        from .cameras import OakCamera

        cam: Camera = OakCamera(int(args.exposure or 10000), args.iso, args.wb_kelvin,
                        int(args.focus if args.focus is not None else 120), args.oak_mode,
                        args.bayer, device_id=None if args.device == "0" else args.device)
    else:
        from .cameras import OpenCVCamera

        dev = int(args.device) if args.device.isdigit() else args.device
        cam = OpenCVCamera(dev, exposure=args.exposure, gain=args.gain,
                           wb_kelvin=args.wb_kelvin, focus=args.focus, average=args.average)
    return cam, lights


def run_capture(args: argparse.Namespace, out_dir: Path, overwrite: bool = False) -> Path:
    """Open the devices named by ``args``, capture (or resume) a session into ``out_dir``."""
    cam = lights = None
    try:
        if (out_dir / "filenames.txt").exists() and not overwrite and \
                not (out_dir / "session.json").exists():
            raise InputError("folder holds a stack not made by msf-capture (use --overwrite "
                             "or another folder)", out_dir)
        cam, lights = _open(args)
        dirs, ints = args.light_directions, args.light_intensities
        rig = getattr(lights, "rig", None)
        if rig is not None and dirs is None:  # the simulated rig knows its true lights
            dirs, ints = rig.lights, rig.intensities
        return capture_stack(cam, lights, out_dir, light_directions=dirs,
                             light_intensities=ints, mask=args.mask,
                             ambient=not args.no_ambient,
                             subtract_ambient=not args.keep_ambient,
                             overwrite=overwrite, strict=args.strict)
    finally:
        for dev in (lights, cam):
            if dev is not None:
                dev.close()


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        out = run_capture(args, args.out_dir, args.overwrite)
        done = "stack" if (out / "light_directions.txt").exists() else \
            "images (no light directions yet: run msf-calib directions)"
        print(f"frames -> {out} ({done})")
        if args.run is not None:
            from msfnet.runtime.run_cli import main as run_main

            return run_main([str(out), *args.run])
    except InputError as exc:
        print(f"msf-capture: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("msf-capture: interrupted; run the same command again to resume",
              file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
