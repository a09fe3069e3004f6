"""The option groups msf-run and msf-eval share, generated from the option dataclasses.

Model settings come from :class:`~msfnet.runtime.options.ModelOptions`' own field metadata;
:class:`~msfnet.runtime.stack.LoadOptions` declares its own by category. Each
command adds the groups it needs and builds the options once, in :func:`model_options` /
:func:`load_options`.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from msfnet.common.cli import (
    add_flags,
    flag_names,
    nonnegative_float,
    options_from_args,
    positive_float,
)
from msfnet.common.errors import InputError
from msfnet.runtime.options import ModelOptions
from msfnet.runtime.results.maps import MAP_NAMES, MAP_PRESETS, MapOptions, preset_maps
from msfnet.runtime.results.maps.integrate import METHODS as INTEGRATION_METHODS
from msfnet.runtime.results.maps.registered import Frame, check_local_size
from msfnet.runtime.stack import LoadOptions


def add_model_flags(
    parser: argparse.ArgumentParser, *, skip: Sequence[str] = ("maps",), **help_override: str
) -> None:
    """Every ModelOptions setting with a flag (maps have their own group: :func:`add_map_flags`)."""
    add_flags(parser, ModelOptions, skip=(*skip, "maps"), help_override=help_override)


def add_load_flags(
    parser: argparse.ArgumentParser, names: Sequence[str] | None = None, *, camera: bool = False
) -> None:
    """The stack-reading flags (LoadOptions' "stack" category, or only ``names`` of it);
    ``camera``: the real-camera group too (ROI -> downscale -> linearise -> auto-mask)."""
    stack = [n for n in flag_names(LoadOptions, "stack") if names is None or n in names]
    add_flags(parser, LoadOptions, only=stack)
    if camera:
        cam = parser.add_argument_group(
            "real-camera inputs (applied while loading: ROI -> downscale -> linearise -> auto-mask)"
        )
        add_flags(cam, LoadOptions, only=("roi", "downscale"))
        add_flags(cam.add_mutually_exclusive_group(), LoadOptions, only=("srgb", "gamma"))
        add_flags(cam, LoadOptions, only=("white_level", "auto_mask"))


def parse_maps(text: str) -> tuple[str, ...]:
    """Map names, or one preset word (all, inspect, none: then no map)."""
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    bad = [n for n in names if n not in MAP_NAMES]
    if len(names) == 1 and names[0] in MAP_PRESETS:
        return preset_maps(names)
    if bad or not names:
        raise argparse.ArgumentTypeError(
            f"expected names from {','.join(MAP_NAMES)} or one of {', '.join(MAP_PRESETS)}, "
            f"got {text!r}"
        )
    return names


def add_map_flags(parser: argparse.ArgumentParser) -> None:
    insp = parser.add_argument_group(
        "inspection maps (written by default: albedo, height, curvature, mesh, report.html)"
    )
    insp.add_argument("--no-maps", action="store_true", help="write the normals only")
    insp.add_argument(
        "--maps",
        type=parse_maps,
        metavar="LIST",
        help=f"which maps, comma-separated from {','.join(MAP_NAMES)}, or one of "
        f"{', '.join(MAP_PRESETS)} (inspect: what msf-inspect reads, no mesh; none: as "
        "--no-maps; default: all)",
    )
    insp.add_argument(
        "--integration",
        choices=INTEGRATION_METHODS,
        default="poisson",
        help="normal integration for the height map: poisson (masked least squares, default), "
        "bini (keeps depth discontinuities sharp, slower), fc (Frankot-Chellappa FFT, full "
        "frame)",
    )
    insp.add_argument(
        "--intrinsics",
        type=float,
        nargs=4,
        metavar=("FX", "FY", "CX", "CY"),
        help="perspective camera (pixels) for the height map; default orthographic",
    )
    insp.add_argument(
        "--curvature-sigma",
        type=nonnegative_float,
        default=MapOptions.curvature_sigma,
        metavar="PX",
        help="smoothing of the normals before curvature, px (default %(default)g; 0 = none)",
    )
    insp.add_argument(
        "--pixel-size",
        type=positive_float,
        metavar="MM",
        help="object-side size of one pixel of the stored images in mm (as --roi is in "
        "stored-image pixels; with --downscale K a map pixel is K times it): the TIFFs then "
        "hold mm and 1/mm, maps.json records both sizes",
    )
    insp.add_argument(
        "--local-size",
        type=positive_float,
        default=MapOptions.local_size_px,
        metavar="PX",
        help="characteristic size of the local-shape map (height minus its trend at this "
        "size), px of the maps (default %(default)g; at most their longer side)",
    )
    insp.add_argument(
        "--no-tiff", action="store_true", help="no pixel-registered float32 TIFF maps"
    )
    insp.add_argument("--no-report", action="store_true", help="no report.html")


def map_options(args: argparse.Namespace) -> MapOptions | None:
    """The inspection maps the flags ask for (None: normals only)."""
    if getattr(args, "no_maps", True) and getattr(args, "maps", None) is not None:
        raise InputError("--maps and --no-maps contradict each other: give one of them")
    if getattr(args, "no_maps", True) or getattr(args, "maps", None) == ():  # --maps none
        return None
    intr = tuple(args.intrinsics) if args.intrinsics else None
    if intr is not None and not (intr[0] > 0 and intr[1] > 0):
        raise InputError(
            f"--intrinsics: focal lengths must be positive, got {intr[0]:g}, {intr[1]:g}"
        )
    # the maps are the --roi's, downscaled: where they sit in the stored images (maps.json)
    roi = getattr(args, "roi", None)
    frame = Frame.of_cut(roi, getattr(args, "downscale", None))
    k = frame.downscale
    maps = MapOptions(
        maps=args.maps or MAP_NAMES,
        method=args.integration,
        intrinsics=intr,
        curvature_sigma=getattr(args, "curvature_sigma", MapOptions.curvature_sigma),
        image_pixel_size_mm=getattr(args, "pixel_size", None),
        local_size_px=getattr(args, "local_size", MapOptions.local_size_px),
        tiff=not getattr(args, "no_tiff", False),
        frame=frame,
    )
    if roi and maps.wants("height") and intr is None:
        # the maps' size is known now: refuse before loading and inference, not after
        check_local_size(maps.local_size_px, (max(roi[3] // k, 1), max(roi[2] // k, 1)))
    return maps


def model_options(args: argparse.Namespace, **overrides: object) -> ModelOptions:
    """The ModelOptions the flags describe, built once (maps from the map group)."""
    return options_from_args(ModelOptions, args, overrides={"maps": map_options(args), **overrides})


def load_options(args: argparse.Namespace) -> LoadOptions:
    """The LoadOptions the flags describe, built once."""
    linear = not (getattr(args, "srgb", False) or getattr(args, "gamma", None) is not None)
    if getattr(args, "white_level", None) is not None and linear:
        # linear images need no full scale (normals do not depend on it): refuse, not ignore
        raise InputError(
            "--white-level is the full scale for linearising: it applies with "
            "--srgb or --gamma only"
        )
    budget = {"max_memory_mb": getattr(args, "max_memory_mb", None)}
    return options_from_args(LoadOptions, args, overrides=budget)


__all__ = [
    "add_load_flags",
    "add_map_flags",
    "add_model_flags",
    "load_options",
    "map_options",
    "model_options",
    "parse_maps",
]
