"""How a model runs: one typed options object, built once and passed everywhere.

:class:`ModelOptions` is what ``Model(...)`` takes as keywords, what msf-run and msf-eval build
from their flags (the flags are generated from the fields: :func:`msfnet.common.cli.add_flags`),
what a Ray worker receives to build the same model, and what a report records. A new setting is
one new field here, with its :func:`~msfnet.common.cli.flag` spelling.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import numbers
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from msfnet.common.cli import path_arg, positive_float, thread_count
from msfnet.common.cpu import check_threads
from msfnet.common.errors import InputError
from msfnet.common.vocabulary import flag, opt, options_type, verbatim
from msfnet.runtime.contract import INPUT_MULTIPLE
from msfnet.runtime.engines.bundled import EngineRequest
from msfnet.runtime.infer.compose import Layers
from msfnet.runtime.infer.tiling import BASE_MEMORY_MB, DEFAULT_MAX_MEMORY_MB, HALO
from msfnet.runtime.results.maps.api import MAP_NAMES, MapOptions, preset_maps

METHODS = ("msf", "l2")
TTA_COUNTS = (1, 4, 8)  # infer.tta: the plain pass, + half turn and mirrors, + quarter turns


def tta_count(text: str) -> int:
    """--tta's value: 1, 4 or 8."""
    if text.strip() not in {str(k) for k in TTA_COUNTS}:
        raise argparse.ArgumentTypeError(f"expected 1, 4 or 8 copies, got {text!r}")
    return int(text)


DEFAULT_MAPS = MapOptions()  # albedo, height (Poisson), curvature, mesh
MIN_TILE = 2 * HALO + INPUT_MULTIPLE  # the smallest window with a core inside its halo


def map_options(maps: MapOptions | str | Iterable[str] | None) -> MapOptions | None:
    """``Model(maps=...)``: a MapOptions, None (normals only), or map names as msf-run's
    ``--maps`` takes them, ``"height,curvature"`` or ``("height", "curvature")``, which give
    ``MapOptions(maps=names)`` (the other map settings at their defaults), or a preset word
    (``"inspect"``, ``"all"``, ``"none"``: None). Anything else is refused here, before any
    work."""
    if maps is None or isinstance(maps, MapOptions):
        return maps
    names: tuple[str, ...] | None = None
    if isinstance(maps, str):
        names = tuple(n.strip() for n in maps.split(",") if n.strip())
    elif isinstance(maps, (list, tuple)) and all(isinstance(n, str) for n in maps):
        names = tuple(maps)
    elif isinstance(maps, (set, frozenset)) and all(isinstance(n, str) for n in maps):
        known = [n for n in MAP_NAMES if n in maps]  # a set: in the usual order
        names = (*known, *sorted(set(maps) - set(known)))  # unknown ones refused below
    if names is None:
        raise InputError(
            f"maps={maps!r}: expected map names ('height,curvature' or ('height', 'curvature'); "
            f"from {', '.join(MAP_NAMES)}), a msfnet.MapOptions, or None (normals only)"
        )
    if not names:
        raise InputError(f"maps={maps!r} names no map; maps=None computes none")
    names = preset_maps(names)
    return MapOptions(maps=names) if names else None  # unknown names refused there


@options_type
@dataclass(frozen=True)
class ModelOptions:
    """Every setting of a :class:`~msfnet.runtime.api.Model`, checked once on creation.

    ``model``: an msfnet ONNX file (None: the bundled model). ``method``: "msf" the network,
    "l2" per-pixel least squares. ``engine`` / ``precision``: None = chosen for this CPU.
    ``maps``: inspection maps computed after the normals (None: normals only; map names
    ``"height,curvature"`` are taken too, see :func:`map_options`).
    """

    model: Path | None = flag(
        None,
        "msfnet ONNX model (default: the bundled model)",
        name="--onnx",
        type=path_arg,
        metavar="MODEL",
    )
    method: str = flag(
        "msf", "msf: the network (default); l2: per-pixel least squares, no model", choices=METHODS
    )
    engine: str | None = flag(
        None,
        "inference engine (default: chosen for this CPU and the installed engines; the "
        "choice and its reason are printed and kept in profile.json)",
        choices=("onnxruntime", "openvino"),
        category="resources",
    )
    precision: str | None = flag(
        None,
        "compute precision (default: the fastest one measured within 0.5 deg of fp32 on "
        "real data for this CPU: the bundled model's int8 twin where it was measured "
        "faster (AVX2 and AVX-512 VNNI CPUs without native bf16; AMD Zen 4), else bf16 "
        "through OpenVINO where the CPU has it natively, else fp32; int8 with --onnx needs "
        "an int8 export)",
        choices=("fp32", "bf16", "int8"),
        category="resources",
    )
    threads: int | None = flag(
        None,
        "inference threads (default: all available cores; msf-run --ray: 1 per worker)",
        type=thread_count,
        metavar="T",
        category="resources",
    )
    provider: str | None = flag(
        None,
        "ONNX Runtime execution provider: cpu (default), cuda, ... when installed",
        metavar="P",
        category="resources",
    )
    tile: int | None = flag(
        None,
        f"tile edge in px including the {HALO} px halo (multiple of 4); 0 = no tiling; "
        "default: the largest tile that fits --max-memory",
        type=int,
        metavar="S",
        category="resources",
    )
    max_memory_mb: float = flag(
        DEFAULT_MAX_MEMORY_MB,
        "peak memory target in MB (loaded stack + working set), least squares included "
        f"(default {DEFAULT_MAX_MEMORY_MB})",
        name="--max-memory",
        type=positive_float,
        metavar="MB",
        category="resources",
    )
    fine_detail: bool = flag(
        False,
        "keep relief of a few pixels (engravings, scratches, fabric): also run the network "
        "on the stack enlarged 2x and take the fine detail from that run (about 5x the time; "
        "the stack and its enlargement, 5x its memory, must fit --max-memory beside the "
        f"runtime's {BASE_MEMORY_MB} MB; docs/run.md)",
        action="store_true",
    )
    detail_fusion: bool = flag(
        True,
        "network only, no least-squares detail: by default the network's shape is fused with "
        "least squares' fine detail (and shape) where the Lambertian fit holds "
        "(infer.detail_fusion; docs/run.md, Inspection)",
        name="--no-detail-fusion",
        action="store_false",
    )
    edge_context: bool = flag(
        True,
        "zeros beyond the mask everywhere (the published protocol's input): by default the "
        "network also sees lit surface that continues past a mask edge (infer.tiled)",
        name="--no-edge-context",
        action="store_false",
    )
    speed: str = flag(
        "full",
        "speed ladder (infer.ladder): full = the network on every pixel and light (default); "
        "balanced = the network at 2/5 of the resolution, least-squares detail at full resolution; "
        "fast = a third of the resolution on at most 8 lights (time and accuracy per rung: "
        "docs/benchmark.md)",
        choices=("full", "balanced", "fast"),
    )
    device: str | None = flag(
        None,
        "run on an accelerator instead of the CPU: cuda or tensorrt (ONNX Runtime), gpu, "
        "gpu.N or npu (OpenVINO); refused in one line where it is absent",
        metavar="D",
        category="resources",
    )
    tta: int = flag(
        1,
        "test-time augmentation: the mean of the network's normals over 4 (half turn and "
        "mirrors) or 8 (also quarter turns) rotated / mirrored copies of the stack, lights "
        "turned with it (4x / 8x the inference time; infer.tta, docs/training.md); default 1: off",
        type=tta_count,
        metavar="K",
    )
    timeout_s: float | None = flag(
        None,
        "stop a model compile or a stack's inference still running after S seconds (exit 2; "
        "a model that never ends, e.g. an endless Loop); default: no limit",
        name="--timeout",
        type=positive_float,
        metavar="S",
    )
    maps: MapOptions | None = DEFAULT_MAPS  # msf-run builds it from its map flags

    def __post_init__(self) -> None:
        if self.model is not None and not isinstance(self.model, Path):
            object.__setattr__(self, "model", Path(self.model))
        if self.provider == "cpu":
            object.__setattr__(self, "provider", None)  # the default, spelled out
        object.__setattr__(self, "maps", map_options(self.maps))
        if isinstance(self.tile, numbers.Integral) and not isinstance(self.tile, bool):
            object.__setattr__(self, "tile", int(self.tile))  # numpy's integers too
        self.check()

    def check(self) -> None:
        """Refuse settings that contradict each other (before any work, also for a Ray
        batch): one line each, in the words of the options."""
        if self.method not in METHODS:
            raise InputError(f"method {self.method!r}: expected 'msf' (the network) or 'l2'")
        if self.method == "l2":
            if self.model is not None:
                raise InputError(
                    f"least squares ({opt('method', 'l2')}) needs no model; drop {opt('model')}"
                )
            if self.engine or self.precision:
                raise InputError(
                    f"{opt('engine')} / {opt('precision')} choose how the network runs; "
                    f"{opt('method', 'l2')} has no network",
                    option="engine",
                )
            if self.fine_detail:
                raise InputError(
                    f"fine detail ({opt('fine_detail')}) runs the network a second time; "
                    f"{opt('method', 'l2')} has no network (least squares keeps all detail, "
                    "and its noise)"
                )
        if self.method == "l2" and (self.speed != "full" or self.device):
            raise InputError(
                f"{opt('speed')} / {opt('device')} choose how the network runs; "
                f"{opt('method', 'l2')} has no network",
                option="speed",
            )
        if self.speed not in ("full", "balanced", "fast"):
            raise InputError(f"speed {self.speed!r}: expected full, balanced or fast")
        if self.speed != "full" and self.fine_detail:
            raise InputError(
                f"{opt('speed', self.speed)} runs the network at a reduced resolution, "
                f"{opt('fine_detail')} at twice the full one: choose one",
                option="speed",
            )
        if self.device and self.provider:
            raise InputError(
                f"{opt('device')} and {opt('provider')} both pick where ONNX Runtime runs: "
                f"use {opt('device')}",
                option="device",
            )
        if self.tta not in TTA_COUNTS:
            raise InputError(f"tta {self.tta!r}: expected 1 (off), 4 or 8 copies")
        if self.tta > 1 and self.method == "l2":
            raise InputError(
                f"test-time augmentation ({opt('tta')}) averages the network over turned "
                f"copies; least squares ({opt('method', 'l2')}) gives the same normals for "
                "every copy"
            )
        if self.timeout_s is not None and not (
            math.isfinite(self.timeout_s) and self.timeout_s > 0
        ):
            raise InputError(f"timeout {self.timeout_s}: must be a positive number of seconds")
        if not self.max_memory_mb > 0:
            raise InputError(f"max memory {self.max_memory_mb}: must be a positive number of MB")
        if self.threads is not None:
            check_threads(self.threads)
        tile = self.tile
        if tile is not None and (
            isinstance(tile, bool)
            or not isinstance(tile, int)
            or (tile != 0 and (tile < MIN_TILE or tile % INPUT_MULTIPLE))
        ):
            raise InputError(
                f"{opt('tile', verbatim(repr(tile)))}: expected 0 (no tiling) or a window "
                "edge in px, a multiple "
                f"of {INPUT_MULTIPLE} and at least {MIN_TILE} (2 x {HALO} px halo + "
                f"{INPUT_MULTIPLE})",
                option="tile",
            )

    @property
    def is_network(self) -> bool:
        return self.method == "msf"

    def engine_request(self) -> EngineRequest:
        """What is asked of the engine (engines.bundled)."""
        return EngineRequest(self.engine, self.precision, self.provider, self.device, self.threads)

    def layers(self) -> Layers:
        """What wraps the base estimator (infer.compose)."""
        return Layers(self.edge_context, self.speed, self.fine_detail, self.tta, self.detail_fusion)

    def replace(self, **changes: object) -> ModelOptions:
        return dataclasses.replace(self, **changes)  # type: ignore[arg-type]

    @classmethod
    def of(cls, base: ModelOptions | None = None, **settings: object) -> ModelOptions:
        """``base`` (or the defaults) with ``settings`` changed; unknown names refused in the
        API's words."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(settings) - names)
        if unknown:
            raise InputError(
                f"unknown model setting(s) {', '.join(unknown)}; the settings are "
                f"{', '.join(sorted(names))} (msfnet.runtime.options.ModelOptions)"
            )
        return (base or cls()).replace(**settings) if settings else (base or cls())

    def describe(self) -> dict[str, object]:
        """The settings a report records (the model path as given)."""
        out: dict[str, object] = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name == "maps":
                value = None if value is None else list(value.maps)
            elif isinstance(value, Path):
                value = str(value)
            out[f.name] = value
        return out


__all__ = [
    "DEFAULT_MAPS",
    "METHODS",
    "MIN_TILE",
    "TTA_COUNTS",
    "ModelOptions",
    "map_options",
    "tta_count",
]
