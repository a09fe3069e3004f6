"""The option groups msf-run and msf-eval share, generated from the option dataclasses'
field metadata (ModelOptions, MapOptions, LoadOptions); built once in :func:`model_options` /
:func:`load_options`.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from msfnet.common.cli import add_flags, flag_names, options_from_args
from msfnet.common.errors import InputError
from msfnet.runtime.options import ModelOptions
from msfnet.runtime.results.maps import MAP_NAMES, MapOptions
from msfnet.runtime.results.maps.registered import Frame, check_local_size
from msfnet.runtime.results.result import SaveOptions
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


def add_map_flags(parser: argparse.ArgumentParser) -> None:
    """MapOptions' flags, --no-maps (Model(maps=None)) and --no-report (a writer switch)."""
    insp = parser.add_argument_group(
        "inspection maps (written by default: albedo, height, curvature, mesh, report.html)"
    )
    insp.add_argument("--no-maps", action="store_true", help="write the normals only")
    late = ("image_pixel_size_mm", "local_size_px", "tiff")  # --help's order, not the fields'
    add_flags(insp, MapOptions, skip=late)
    for name in late:
        add_flags(insp, MapOptions, only=(name,))
    add_flags(insp, SaveOptions, only=("report",))
    parser.set_defaults(maps=None)  # not given: --no-maps contradicts only a given --maps


def map_options(args: argparse.Namespace) -> MapOptions | None:
    """The inspection maps the flags ask for (None: normals only)."""
    given = getattr(args, "maps", None)
    if getattr(args, "no_maps", True) and given is not None:
        raise InputError("--maps and --no-maps contradict each other: give one of them")
    if getattr(args, "no_maps", True) or given == ():  # --maps none
        return None
    intr = args.intrinsics
    if intr is not None and not (intr[0] > 0 and intr[1] > 0):
        raise InputError(
            f"--intrinsics: focal lengths must be positive, got {intr[0]:g}, {intr[1]:g}"
        )
    # the maps are the --roi's, downscaled: where they sit in the stored images (maps.json)
    roi = getattr(args, "roi", None)
    frame = Frame.of_cut(roi, getattr(args, "downscale", None))
    k = frame.downscale
    overrides = {"maps": given or MAP_NAMES, "frame": frame}
    maps = options_from_args(MapOptions, args, overrides=overrides)
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
]
