"""The inspection station: the model, the rule and the reference loaded once, then one verdict
per part, computing only the maps the rule reads (docs/run.md, "Inspection station").
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from msfnet.common.errors import InputError
from msfnet.common.vocabulary import opt
from msfnet.runtime.api import Model
from msfnet.runtime.inspection.defects import (
    DefectOptions,
    InspectionInput,
    Verdict,
    find_defects,
    from_maps,
    is_run,
    overlay_picture,
    read_run,
)
from msfnet.runtime.inspection.zones import Zones, read_zones
from msfnet.runtime.options import ModelOptions
from msfnet.runtime.results.maps import MapOptions
from msfnet.runtime.stack import LoadOptions, Stack, load_stack

STAGES = ("decode", "normals", "maps", "judge")


@dataclass(frozen=True)
class StageTimes:
    """Seconds one part spent in each stage (decode is 0 for a Stack given in memory)."""

    decode: float
    normals: float
    maps: float
    judge: float

    @property
    def total(self) -> float:
        return self.decode + self.normals + self.maps + self.judge

    def milliseconds(self) -> dict[str, float]:
        times = {s: getattr(self, s) for s in STAGES} | {"total": self.total}
        return {s: round(t * 1e3, 2) for s, t in times.items()}


@dataclass
class Inspection:
    """One part's verdict, its regions' label image (0 = none), the maps judged and the time
    each stage took."""

    name: str
    verdict: Verdict
    labels: np.ndarray
    part: InspectionInput
    times: StageTimes

    @property
    def passed(self) -> bool:
        return self.verdict.passed

    def overlay(self) -> np.ndarray:
        """(H, W, 3) uint8 RGB: the part with each region outlined and numbered."""
        return overlay_picture(self.part, self.labels, self.verdict.regions)

    def __repr__(self) -> str:
        word = "PASS" if self.passed else f"FAIL ({len(self.verdict.regions)} defects)"
        return f"Inspection({self.name}: {word}, {self.times.total * 1e3:.0f} ms)"


def rule_maps(rule: DefectOptions, pictures: bool) -> tuple[str, ...]:
    """The maps a rule reads: the height (whose local shape a depth threshold judges), the
    curvature, and the albedo for the overlay's grey base when pictures are wanted."""
    wanted = (rule.depth is not None, rule.curvature is not None, pictures)
    return tuple(n for n, w in zip(("height", "curvature", "albedo"), wanted, strict=True) if w)


def _given_maps(reference: Stack | InspectionInput | str | Path | None) -> InspectionInput | None:
    """A reference whose maps are given (in memory, or an msf-run output folder); None for a
    stack (mapped by the station) or none. InputError for a path that is not there."""
    if reference is None or isinstance(reference, Stack):
        return None
    if isinstance(reference, InspectionInput):  # e.g. a VariationModel's centre
        return reference
    path = Path(reference)
    if not path.exists():
        raise InputError("no such file or folder", path)
    return read_run(path) if is_run(path) else None


def _check_reference(reference: InspectionInput, rule: DefectOptions) -> None:
    """The reference holds the maps the rule judges (else every part would fail alike)."""
    if rule.depth is not None and reference.local_shape is None:
        raise InputError(
            f"the reference has no local shape map for {opt('depth')}", reference.source
        )
    if rule.curvature is not None and reference.curvature is None:
        raise InputError(
            f"the reference has no curvature map for {opt('curvature')}", reference.source
        )


class Station:
    """A warm per-part inspection: ``Station(rule, options).inspect(stack)``.

    ``rule``: the thresholds (:class:`DefectOptions`). ``options``: how a part is run (the
    model, ``method="l2"`` for least squares, ``speed``, the maps' units and local size: only
    the maps the rule needs are computed, whatever ``options.maps`` lists). ``load``: how a
    part's folder is read. ``reference``: a good part (a stack, a stack folder or an msf-run
    output folder) mapped once with these settings, or a variation model (its folder, or
    ``VariationModel.centre``); each part is then judged on what differs from it. ``zones``:
    areas with their own thresholds or left out (a JSON file, :mod:`.zones`).
    ``pictures``: compute the albedo too, for the overlay's grey base.
    """

    def __init__(
        self,
        rule: DefectOptions,
        options: ModelOptions | None = None,
        *,
        load: LoadOptions | None = None,
        reference: Stack | InspectionInput | str | Path | None = None,
        zones: Zones | str | Path | None = None,
        pictures: bool = False,
    ) -> None:
        opts = options or ModelOptions()
        self.rule = rule
        self.zones = read_zones(Path(zones)) if isinstance(zones, (str, Path)) else zones
        self.load = load or LoadOptions()
        given = _given_maps(reference)
        # the albedo is what alignment to a reference uses first: computed for every part
        # when the reference has one (a stack mapped here gets one)
        albedo = pictures or (reference is not None and (given is None or given.albedo is not None))
        maps = replace(opts.maps or MapOptions(), maps=rule_maps(rule, albedo))
        self.model = Model(options=opts.replace(maps=maps))
        self.reference: InspectionInput | None = given
        if reference is not None and given is None:
            assert not isinstance(reference, InspectionInput)  # those are given maps
            stack = reference if isinstance(reference, Stack) else self.read(Path(reference))[0]
            self.reference = self._maps(stack, str(stack.source or reference))[0]
        if self.reference is not None:
            _check_reference(self.reference, rule)

    def settings(self) -> dict[str, object]:
        """What decides a verdict, for a station folder to hold: the rule, the reference and
        zones, how parts are run and mapped, and how they are read (resource settings such as
        threads, engine or memory left out: they change times, not verdicts)."""
        o = self.model.options  # the station's settings, with the maps the rule reads
        kept = ("model", "method", "speed", "fine_detail", "detail_fusion", "edge_context", "tta")
        run = {k: v for k, v in o.describe().items() if k in kept}
        maps = o.maps or MapOptions()
        return {
            "rule": asdict(self.rule),
            "reference": None if self.reference is None else self.reference.source,
            "zones": None if self.zones is None else self.zones.source,
            "run": run,
            "maps": {"local_size_px": maps.local_size_px, "pixel_size_mm": maps.pixel_size_mm},
            "load": self.load.describe(),
        }

    def read(self, path: str | Path) -> tuple[Stack, float]:
        """A part's stack decoded with the station's load options, and the seconds it took
        (safe to call from another thread: the station decodes the next part meanwhile)."""
        start = time.perf_counter()
        stack = load_stack(Path(path), self.load)
        return stack, time.perf_counter() - start

    def _maps(self, stack: Stack, source: str) -> tuple[InspectionInput, float, float]:
        result = self.model(stack)
        assert result.maps is not None
        maps_s = result.timings.median_s("maps")
        normals_s = result.timings.median_s("total") - maps_s
        part = from_maps(result.maps, source)
        part.method = result.method  # what ran (least squares where too few lights for the net)
        return part, normals_s, maps_s

    def inspect(self, part: Stack | str | Path, name: str | None = None) -> Inspection:
        """Judge one part (a Stack, or a stack folder read with the station's load options)."""
        decode_s = 0.0
        if not isinstance(part, Stack):
            name = name or Path(part).name
            part, decode_s = self.read(part)
        return self.judge(part, name or "part", decode_s)

    def judge(self, stack: Stack, name: str, decode_s: float = 0.0) -> Inspection:
        """Judge a decoded part; ``decode_s``: what decoding it took, for its times."""
        if stack.normals_gt is not None:  # a rendered part's: scoring it is not the station's job
            stack = replace(stack, normals_gt=None)
        maps, normals_s, maps_s = self._maps(stack, name)
        start = time.perf_counter()
        verdict, labels = find_defects(maps, self.rule, self.reference, self.zones)
        judge_s = time.perf_counter() - start
        times = StageTimes(decode_s, normals_s, maps_s, judge_s)
        return Inspection(name, verdict, labels, maps, times)

    def __repr__(self) -> str:
        ref = "" if self.reference is None else f", reference={self.reference.source}"
        return f"Station({self.model!r}, {self.rule}{ref})"


__all__ = ["STAGES", "Inspection", "StageTimes", "Station", "rule_maps"]
