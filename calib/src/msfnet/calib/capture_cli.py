"""``msf-capture``: capture a photometric stack (one frame per light + ambient), resumable."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
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
from msfnet.calib.options import DEVICES, LINEARISE, CaptureOptions
from msfnet.common.cli import (
    Command,
    add_flags,
    command_main,
    flag_names,
    make_parser,
    options_from_args,
    path_arg,
)
from msfnet.common.errors import InputError
from msfnet.common.files import folder_lock

PROG = "msf-capture"
COMMAND = Command(PROG, extra="camera")
EXAMPLES = (
    "msf-capture calib/ --camera sim --sim-scene chrome       # no hardware: a chrome sphere",
    "msf-calib directions calib/ -o lights.txt                # ... calibrated",
    "msf-capture obj/ --camera sim --light-directions lights.txt --run   # ... an object, run",
    "msf-capture -o obj/ --camera oak --light-rig serial --port /dev/ttyUSB0 "
    "--light-directions lights.txt --mask mask.png",
    "msf-capture obj/ --camera opencv --device 0 --exposure -6 --count 12 --srgb",
    "msf-capture takes/ --camera sim --loop 5 --run --method l2   # takes/001, 002, ... + runs",
)


def add_device_arguments(p: argparse.ArgumentParser) -> None:
    """The "capture devices" group: camera, light rig and session options (CaptureOptions'
    DEVICES), the --srgb / --gamma pair among them one of two."""
    g = p.add_argument_group("capture devices")
    add_flags(g, CaptureOptions, only=flag_names(CaptureOptions, DEVICES))
    add_flags(
        g.add_mutually_exclusive_group(), CaptureOptions, only=flag_names(CaptureOptions, LINEARISE)
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
    add_flags(p, CaptureOptions, only=flag_names(CaptureOptions, ""))
    return p


class _SceneCamera(SimulatedCamera):
    """The simulated camera, its info naming the scene: session.json records it, so a resume
    with another --sim-scene is refused instead of mixing the two scenes' frames."""

    def __init__(self, rig: Any, scene: str) -> None:
        super().__init__(rig)
        self.scene = scene

    def info(self) -> dict:
        return {**super().info(), "scene": self.scene}


def _light_rig(options: CaptureOptions) -> str:
    if options.light_rig is None:
        return "sim" if options.camera == "sim" else "manual"
    return str(options.light_rig)


def _open(options: CaptureOptions) -> tuple[Camera, Lights, dict[str, Any]]:
    """The devices, and what a simulated rig knows (true lights, mask, normals) as defaults."""
    rig_name = _light_rig(options)
    if options.camera == "sim" or rig_name == "sim":
        if options.camera != "sim" or rig_name != "sim":
            raise InputError("--camera sim and --light-rig sim go together")
        # calib -> synth, the simulated rig only (see the msfnet package docstring): lazy
        from msfnet.calib.lights import SimulatedLights, SimulatedRig
        from msfnet.synth.spheres import mirror_scene, ring_lights, sphere_masks, sphere_normals

        kind = "mirror" if options.sim_scene == "chrome" else "matte"
        rig = SimulatedRig(
            mirror_scene(160, 128, 56, kind=kind),
            ring_lights(options.count or 12),
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
        return _SceneCamera(rig, options.sim_scene), SimulatedLights(rig), known
    if rig_name == "serial":
        if not options.port:
            raise InputError("--light-rig serial needs --port")
        from msfnet.calib.lights import SerialLights

        lights: Lights = SerialLights(
            options.port, options.baud, options.count, settle=options.settle
        )
    else:
        if not options.count:
            raise InputError("--light-rig manual needs --count")
        from msfnet.calib.lights import ManualLights

        lights = ManualLights(options.count)
    if options.camera == "oak":
        from msfnet.calib.cameras import OakCamera

        if options.exposure is not None and options.exposure <= 0:
            raise InputError(
                f"--exposure: an OAK takes microseconds (> 0), got {options.exposure:g}"
            )

        cam: Camera = OakCamera(
            int(options.exposure or 10000),
            options.iso,
            options.wb_kelvin,
            int(options.focus if options.focus is not None else 120),
            options.oak_mode,
            options.bayer,
            device_id=None if options.device == "0" else options.device,
        )
    else:
        from msfnet.calib.cameras import OpenCVCamera

        dev = int(options.device) if options.device.isdigit() else options.device
        cam = OpenCVCamera(
            dev,
            exposure=options.exposure,
            gain=options.gain,
            wb_kelvin=options.wb_kelvin,
            focus=options.focus,
            average=options.average,
        )
    return cam, lights, {}


def _capture_options(
    options: CaptureOptions, known: dict[str, Any], log: Callable[[str], None]
) -> dict[str, Any]:
    """capture_stack's keyword options: the user's files first, then what the rig knows."""
    dirs, ints = options.light_directions, options.light_intensities
    if dirs is None:  # the rig's intensities belong to its true directions only
        dirs, ints = known.get("light_directions"), ints or known.get("light_intensities")
    return {
        "light_directions": dirs,
        "light_intensities": ints,
        "mask": options.mask if options.mask is not None else known.get("mask"),
        "normals_gt": known.get("normals_gt"),
        "min_level": known.get("min_level", 0.1),
        "ambient": not options.no_ambient,
        "subtract_ambient": not options.keep_ambient,
        "overwrite": options.overwrite,
        "strict": options.strict,
        "log": log,
        "linearisation": Linearisation(options.srgb, options.gamma),
        "progress": None if not options.quiet else False,
    }


def run_capture(options: CaptureOptions, out_dir: Path) -> Path:
    """Open the devices ``options`` name, capture (or resume) a session into ``out_dir``."""
    cam = lights = None
    log = _logger(options)
    # held from before the devices open (an OAK takes seconds) to the end: a second capture
    # into the folder is refused at once
    with folder_lock(out_dir, PROG):
        try:
            check_inputs(
                out_dir, (options.light_directions, options.light_intensities, options.mask)
            )
            check_folder(out_dir, options.overwrite)
            cam, lights, known = _open(options)
            kwargs = _capture_options(options, known, log)
            return capture_stack(cam, lights, out_dir, **kwargs)
        finally:
            _close(lights, cam)


def _close(*devices: Any) -> None:
    for dev in devices:
        if dev is not None:
            dev.close()


def _made(stack: Path, hint: str = "") -> str:
    """What a take left: a stack, or images awaiting their light directions."""
    if (stack / "light_directions.txt").exists():
        return "stack"
    return f"images (no light directions yet{hint})"


def _logger(options: CaptureOptions) -> Callable[[str], None]:
    def log(msg: str) -> None:
        if not options.quiet or msg.startswith("warning"):
            print(msg, file=sys.stderr if msg.startswith("warning") else sys.stdout)

    return log


def _run_args(argv: Sequence[str]) -> argparse.Namespace:
    """msf-run's options parsed before the first frame: a typo must not cost a capture."""
    from msfnet.runtime.cli.run import build_parser as run_parser

    return run_parser().parse_args(list(argv))


def _run_loop(options: CaptureOptions, root: Path) -> int:
    model = load = out_root = None
    if options.run is not None:
        from msfnet.runtime.api import Model
        from msfnet.runtime.cli.flags import load_options, model_options

        run_args = _run_args(options.run)
        if run_args.stacks or run_args.demo:
            raise InputError(
                "--loop --run: the stacks are the captured takes; give msf-run options only"
            )
        model = Model(options=model_options(run_args))
        load, out_root = load_options(run_args), run_args.output
    log = _logger(options)
    cam = lights = None
    try:
        cam, lights, known = _open(options)
        opts = {
            **_capture_options(options, known, log),
            "overwrite": False,  # each take is a new folder (--loop --overwrite is refused)
            "overwrite_allowed": False,
        }
        steps = capture_loop(
            cam,
            lights,
            root,
            iterations=options.loop or None,
            model=model,
            load=load,
            out_root=out_root,
            interval=options.interval,
            **opts,
        )
        for step in steps:
            line = f"take {step.index:03d}: {step.stack} ({_made(step.stack)})"
            if step.result is not None:
                m = step.result.metrics
                line += f"; normals -> {step.output}" + (f" (MAE {m.mae_deg:.2f} deg)" if m else "")
            if not options.quiet:
                print(line, flush=True)
    except KeyboardInterrupt:
        print(
            f"{PROG}: loop stopped; finished takes are kept, an unfinished one is resumed "
            "by the next run",
            file=sys.stderr,
        )
        return 130
    finally:
        _close(lights, cam)
    return 0


def _out_folder(out_dir: Path | None, output: Path | None) -> Path:
    """The session folder, given as OUT or -o OUT (once)."""
    if out_dir is not None and output is not None and out_dir != output:
        raise InputError("give the output folder once: OUT or -o OUT")
    out = output or out_dir
    if out is None:
        raise InputError("no output folder: give OUT (or -o OUT)")
    return out


def _main(args: argparse.Namespace) -> int:
    """The body: the folder and the options, built once from the flags, then the capture."""
    out = _out_folder(args.out_dir, args.output)
    return _capture(options_from_args(CaptureOptions, args, overrides={"quiet": args.quiet}), out)


def _capture(options: CaptureOptions, out: Path) -> int:
    """One session into ``out`` (then msf-run on it with --run), or with --loop take after
    take into its sub-folders."""
    if options.loop is not None:
        if options.overwrite:
            raise InputError("--loop never overwrites: each take goes to a new folder")
        return _run_loop(options, out)
    if options.run is not None:
        _run_args([str(out), *options.run])
    try:
        out = run_capture(options, out)
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted; run the same command again to resume", file=sys.stderr)
        return 130
    if not options.quiet:
        # on stderr: with --run --json, stdout carries msf-run's JSON alone
        print(f"frames -> {out} ({_made(out, ': run msf-calib directions')})", file=sys.stderr)
    if options.run is not None:
        from msfnet.runtime.cli.run import main as run_main

        return run_main([str(out), *options.run])
    return 0


def main(argv: list[str] | None = None) -> int:
    return command_main(COMMAND, build_parser(), _main, argv)


if __name__ == "__main__":
    sys.exit(main())
