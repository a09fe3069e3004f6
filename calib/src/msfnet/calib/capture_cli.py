"""``msf-capture``: capture a photometric stack (one frame per light + ambient), resumable."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from msfnet.calib.cameras import Camera, SimulatedCamera
from msfnet.calib.capture import (
    Linearisation,
    capture_loop,
    capture_stack,
    check_folder,
    check_inputs,
)
from msfnet.calib.lights import Lights
from msfnet.common.cli import (
    Command,
    command_main,
    finite_float,
    float_range,
    int_range,
    make_parser,
    nonnegative_float,
    nonnegative_int,
    path_arg,
    positive_float,
    positive_int,
)
from msfnet.common.errors import InputError
from msfnet.common.files import folder_lock
from msfnet.runtime.stack import MIN_LIGHTS
from msfnet.runtime.stack.readers import MAX_LIGHTS

PROG = "msf-capture"
COMMAND = Command(PROG, extra="camera")
MAX_INTERVAL = 7 * 24 * 3600.0  # seconds
EXAMPLES = (
    "msf-capture calib/ --camera sim --sim-scene chrome       # no hardware: a chrome sphere",
    "msf-calib directions calib/ -o lights.txt                # ... calibrated",
    "msf-capture obj/ --camera sim --light-directions lights.txt --run   # ... an object, run",
    "msf-capture -o obj/ --camera oak --light-rig serial --port /dev/ttyUSB0 "
    "--light-directions lights.txt --mask mask.png",
    "msf-capture obj/ --camera opencv --device 0 --exposure -6 --count 12 --srgb",
    "msf-capture takes/ --camera sim --loop 5 --run --method l2   # takes/001, 002, ... + runs",
)


def add_device_arguments(
    p: argparse.ArgumentParser,
    lights_flag: str = "--light-rig",
    camera_default: str | None = "opencv",
) -> None:
    """Camera, light-rig and session options.

    ``lights_flag`` names the light back-end option (msf-run uses --lights for files). The
    caller adds --mask and --overwrite, whose meaning it owns.
    """
    g = p.add_argument_group("capture devices")
    _add_camera_arguments(g, camera_default)
    _add_light_rig_arguments(g, lights_flag)
    _add_session_arguments(g)
    _add_linearisation_arguments(g)


def _add_camera_arguments(g: argparse._ArgumentGroup, camera_default: str | None) -> None:
    """The camera back-end and its settings (exposure, gain, white balance, focus ...)."""
    g.add_argument(
        "--camera",
        choices=("oak", "opencv", "sim"),
        default=camera_default,
        help="camera back-end"
        + (
            f" (default {camera_default}); sim: a rendered sphere, no hardware"
            if camera_default
            else ""
        ),
    )
    g.add_argument("--device", default="0", help="OpenCV device index or URL; OAK device id")
    g.add_argument(
        "--exposure",
        type=finite_float,
        help="OpenCV: exposure in the driver's units, passed as given (V4L2 and DirectShow "
        "drivers often take negative log2 seconds, e.g. -6); OAK: microseconds, positive "
        "(default 10000)",
    )
    g.add_argument("--iso", type=int, default=100, help="OAK ISO (default 100)")
    g.add_argument("--gain", type=finite_float, help="OpenCV gain")
    g.add_argument("--wb-kelvin", type=int, default=5500, help="locked white balance")
    g.add_argument("--focus", type=finite_float, help="locked focus (OAK lens position 0..255)")
    g.add_argument(
        "--oak-mode",
        choices=("raw", "isp"),
        default="raw",
        help="raw: linear Bayer demosaiced on host (default); isp: tone-mapped RGB",
    )
    g.add_argument("--bayer", default="RGGB", help="OAK raw Bayer pattern (default RGGB)")
    g.add_argument(
        "--average", type=positive_int, default=1, help="OpenCV: frames averaged per light"
    )


def _add_light_rig_arguments(g: argparse._ArgumentGroup, lights_flag: str) -> None:
    """The light back-end (named by ``lights_flag``) and its settings."""
    g.add_argument(
        lights_flag,
        dest="light_rig",
        choices=("serial", "manual", "sim"),
        default=None,
        help="light back-end (default: sim with --camera sim, "
        "otherwise manual: an operator prompt per light)",
    )
    g.add_argument("--port", help="serial port of the LED controller, e.g. /dev/ttyUSB0")
    g.add_argument(
        "--baud", type=positive_int, default=115200, help="serial speed of --port (default 115200)"
    )
    g.add_argument(
        "--count",
        # fewer than MIN_LIGHTS photos cannot give a normal: refused before the first frame
        type=int_range(MIN_LIGHTS, MAX_LIGHTS),
        help=f"number of lights, at least {MIN_LIGHTS} (manual; checks serial; sim default 12)",
    )
    g.add_argument(
        "--settle",
        type=nonnegative_float,
        default=0.05,
        help="--light-rig serial: seconds to wait after switching a light (default 0.05; "
        "the manual and sim rigs do not wait)",
    )


def _add_session_arguments(g: argparse._ArgumentGroup) -> None:
    """The simulated scene, the light files put in the stack, and how frames are kept
    (ambient frame, exposure checks)."""
    g.add_argument(
        "--sim-scene",
        choices=("chrome", "matte"),
        default="matte",
        help="simulated scene: a chrome sphere (light calibration) or a matte one",
    )
    g.add_argument(
        "--light-directions",
        type=path_arg,
        help="light_directions.txt to put in the "
        "stack (from msf-calib directions); checked before capturing",
    )
    g.add_argument("--light-intensities", type=path_arg, help="light_intensities.txt for the stack")
    g.add_argument("--no-ambient", action="store_true", help="skip the ambient (dark) frame")
    g.add_argument(
        "--keep-ambient",
        action="store_true",
        help="do not subtract the ambient frame from the stack images",
    )
    g.add_argument("--strict", action="store_true", help="fail on saturated/under-exposed frames")


def _add_linearisation_arguments(g: argparse._ArgumentGroup) -> None:
    """The camera's encoding, undone when the stack is built: --srgb or --gamma, not both."""
    lin = g.add_mutually_exclusive_group()
    lin.add_argument(
        "--srgb",
        action="store_true",
        help="the camera delivers sRGB-encoded frames (webcams, OAK isp): the "
        "stack is written linear, 16-bit; recorded in session.json",
    )
    lin.add_argument(
        "--gamma",
        type=positive_float,
        metavar="G",
        help="the camera's frames are power-law encoded: linear = value ** G",
    )


def build_parser() -> argparse.ArgumentParser:
    p = make_parser(
        PROG,
        "Capture a photometric stack: one frame per light plus an ambient frame, each written "
        "to OUT/raw as it arrives (run the same command again to resume an interrupted "
        "session), then the DiLiGenT-layout stack in OUT that msf-run reads.",
        EXAMPLES,
    )
    p.add_argument(
        "out_dir",
        type=path_arg,
        nargs="?",
        metavar="OUT",
        help="session / stack folder (or -o OUT)",
    )
    p.add_argument(
        "-o",
        "--output",
        type=path_arg,
        metavar="OUT",
        help="session / stack folder (same as the positional OUT)",
    )
    add_device_arguments(p)
    p.add_argument(
        "--mask",
        type=path_arg,
        help="object mask for the stack and exposure checks "
        "(checked before capturing; the simulated camera writes its own)",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="discard the session already captured (its frames, session.json and "
        "the stack built from them; other images stay), or capture into a folder "
        "holding other images",
    )
    p.add_argument(
        "--loop",
        nargs="?",
        type=nonnegative_int,
        const=0,
        default=None,
        metavar="K",
        help="capture stack after stack into OUT/001, OUT/002, ... "
        "(K takes; none or 0: until Ctrl-C); with --run each is run as soon as "
        "it is captured, with the model loaded once (results in OUT/NNN-normals, "
        "or -o of msf-run's options as their parent)",
    )
    p.add_argument(
        "--interval",
        # a week at most: time.sleep overflows on inf and on huge values
        type=float_range(0.0, MAX_INTERVAL),
        default=0.0,
        metavar="S",
        help="--loop: seconds to wait between takes (to move the object; at most a week)",
    )
    p.add_argument(
        "--run",
        nargs=argparse.REMAINDER,
        metavar="MSF_RUN_ARGS",
        help="after capturing, run msf-run on the stack; the rest of the command "
        "line goes to msf-run (e.g. --run --method l2 -o out/)",
    )
    return p


class _SceneCamera(SimulatedCamera):
    """The simulated camera, its info naming the scene: session.json records it, so a resume
    with another --sim-scene is refused instead of mixing the two scenes' frames."""

    def __init__(self, rig: Any, scene: str) -> None:
        super().__init__(rig)
        self.scene = scene

    def info(self) -> dict:
        return {**super().info(), "scene": self.scene}


def _light_rig(args: argparse.Namespace) -> str:
    if args.light_rig is None:
        return "sim" if args.camera == "sim" else "manual"
    return str(args.light_rig)


def _open(args: argparse.Namespace) -> tuple[Camera, Lights, dict[str, Any]]:
    """The devices, and what a simulated rig knows (true lights, mask, normals) as defaults."""
    rig_name = _light_rig(args)
    if args.camera == "sim" or rig_name == "sim":
        if args.camera != "sim" or rig_name != "sim":
            raise InputError("--camera sim and --light-rig sim go together")
        # calib -> synth, the simulated rig only (see the msfnet package docstring): lazy
        from msfnet.calib.lights import SimulatedLights, SimulatedRig
        from msfnet.synth.spheres import mirror_scene, ring_lights, sphere_masks, sphere_normals

        kind = "mirror" if args.sim_scene == "chrome" else "matte"
        rig = SimulatedRig(
            mirror_scene(160, 128, 56, kind=kind),
            ring_lights(args.count or 12),
            gain=0.8 if kind == "matte" else 0.02,
        )
        known = {
            "light_directions": rig.lights,
            "light_intensities": rig.intensities,
            "mask": np.any(sphere_masks(rig.scene), axis=0),
            "normals_gt": sphere_normals(rig.scene),
            # a mirror sphere is dark but for a highlight of a few pixels: the
            # under-exposure check (99.5th percentile) would fire on every frame
            "min_level": 0.0 if kind == "mirror" else 0.1,
        }
        return _SceneCamera(rig, args.sim_scene), SimulatedLights(rig), known
    if rig_name == "serial":
        if not args.port:
            raise InputError("--light-rig serial needs --port")
        from msfnet.calib.lights import SerialLights

        lights: Lights = SerialLights(args.port, args.baud, args.count, settle=args.settle)
    else:
        if not args.count:
            raise InputError("--light-rig manual needs --count")
        from msfnet.calib.lights import ManualLights

        lights = ManualLights(args.count)
    if args.camera == "oak":
        from msfnet.calib.cameras import OakCamera

        if args.exposure is not None and args.exposure <= 0:
            raise InputError(f"--exposure: an OAK takes microseconds (> 0), got {args.exposure:g}")

        cam: Camera = OakCamera(
            int(args.exposure or 10000),
            args.iso,
            args.wb_kelvin,
            int(args.focus if args.focus is not None else 120),
            args.oak_mode,
            args.bayer,
            device_id=None if args.device == "0" else args.device,
        )
    else:
        from msfnet.calib.cameras import OpenCVCamera

        dev = int(args.device) if args.device.isdigit() else args.device
        cam = OpenCVCamera(
            dev,
            exposure=args.exposure,
            gain=args.gain,
            wb_kelvin=args.wb_kelvin,
            focus=args.focus,
            average=args.average,
        )
    return cam, lights, {}


def _capture_options(
    args: argparse.Namespace, known: dict[str, Any], log: Callable[[str], None], overwrite: bool
) -> dict[str, Any]:
    """capture_stack's keyword options: the user's files first, then what the rig knows."""
    dirs = args.light_directions
    given_dirs = dirs is not None
    return {
        "light_directions": dirs if given_dirs else known.get("light_directions"),
        # the rig's intensities belong to its true directions only
        "light_intensities": args.light_intensities
        if args.light_intensities is not None
        else (None if given_dirs else known.get("light_intensities")),
        "mask": args.mask if args.mask is not None else known.get("mask"),
        "normals_gt": known.get("normals_gt"),
        "min_level": known.get("min_level", 0.1),
        "ambient": not args.no_ambient,
        "subtract_ambient": not args.keep_ambient,
        "overwrite": overwrite,
        "strict": args.strict,
        "log": log,
        "linearisation": Linearisation(args.srgb, args.gamma),
        "progress": None if not args.quiet else False,
    }


def run_capture(args: argparse.Namespace, out_dir: Path, overwrite: bool = False) -> Path:
    """Open the devices named by ``args``, capture (or resume) a session into ``out_dir``."""
    cam = lights = None
    log = _logger(args)
    # held from before the devices open (an OAK takes seconds) to the end: a second capture
    # into the folder is refused at once
    with folder_lock(out_dir, PROG):
        try:
            check_inputs(out_dir, (args.light_directions, args.light_intensities, args.mask))
            check_folder(out_dir, overwrite)
            cam, lights, known = _open(args)
            options = _capture_options(args, known, log, overwrite)
            return capture_stack(cam, lights, out_dir, **options)
        finally:
            for dev in (lights, cam):
                if dev is not None:
                    dev.close()


def _logger(args: argparse.Namespace) -> Callable[[str], None]:
    def log(msg: str) -> None:
        if not args.quiet or msg.startswith("warning"):
            print(msg, file=sys.stderr if msg.startswith("warning") else sys.stdout)

    return log


def _run_args(argv: list[str]) -> argparse.Namespace:
    """msf-run's options parsed before the first frame: a typo must not cost a capture."""
    from msfnet.runtime.cli.run import build_parser as run_parser

    return run_parser().parse_args(argv)


def _run_loop(args: argparse.Namespace, root: Path) -> int:
    model = load = out_root = None
    if args.run is not None:
        from msfnet.runtime.api import Model
        from msfnet.runtime.cli.flags import load_options, model_options

        run_args = _run_args(args.run)
        if run_args.stacks or run_args.demo:
            raise InputError(
                "--loop --run: the stacks are the captured takes; give msf-run options only"
            )
        model = Model(options=model_options(run_args))
        load, out_root = load_options(run_args), run_args.output
    log = _logger(args)
    cam = lights = None
    try:
        cam, lights, known = _open(args)
        opts = {**_capture_options(args, known, log, overwrite=False), "overwrite_allowed": False}
        steps = capture_loop(
            cam,
            lights,
            root,
            iterations=args.loop or None,
            model=model,
            load=load,
            out_root=out_root,
            interval=args.interval,
            **opts,
        )
        for step in steps:
            done = (
                "stack"
                if (step.stack / "light_directions.txt").exists()
                else "images (no light directions yet)"
            )
            line = f"take {step.index:03d}: {step.stack} ({done})"
            if step.result is not None:
                m = step.result.metrics
                line += f"; normals -> {step.output}" + (f" (MAE {m.mae_deg:.2f} deg)" if m else "")
            if not args.quiet:
                print(line, flush=True)
    except KeyboardInterrupt:
        print(
            f"{PROG}: loop stopped; finished takes are kept, an unfinished one is resumed "
            "by the next run",
            file=sys.stderr,
        )
        return 130
    finally:
        for dev in (lights, cam):
            if dev is not None:
                dev.close()
    return 0


def _main(args: argparse.Namespace) -> int:
    if args.out_dir is not None and args.output is not None and args.out_dir != args.output:
        raise InputError("give the output folder once: OUT or -o OUT")
    out = args.output or args.out_dir
    if out is None:
        raise InputError("no output folder: give OUT (or -o OUT)")
    if args.loop is not None:
        if args.overwrite:
            raise InputError("--loop never overwrites: each take goes to a new folder")
        return _run_loop(args, out)
    if args.run is not None:
        _run_args([str(out), *args.run])
    try:
        out = run_capture(args, out, args.overwrite)
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted; run the same command again to resume", file=sys.stderr)
        return 130
    if not args.quiet:
        done = (
            "stack"
            if (out / "light_directions.txt").exists()
            else "images (no light directions yet: run msf-calib directions)"
        )
        # on stderr: with --run --json, stdout carries msf-run's JSON alone
        print(f"frames -> {out} ({done})", file=sys.stderr)
    if args.run is not None:
        from msfnet.runtime.cli.run import main as run_main

        return run_main([str(out), *args.run])
    return 0


def main(argv: list[str] | None = None) -> int:
    return command_main(COMMAND, build_parser(), _main, argv)


if __name__ == "__main__":
    sys.exit(main())
