"""The defect step: registered maps -> connected defect regions -> a verdict.

A pixel is a candidate where |local shape| >= depth or |mean curvature| >= curvature (the maps'
units); candidates grow by hysteresis (half the thresholds), regions under ``min_area_px`` are
dropped. With a reference (mapped alike), its maps, aligned by phase correlation, are
subtracted first. docs/run.md, "Inspection: mask and ROI edges, ..., msf-inspect".
"""

from __future__ import annotations

import json
import math
from collections import Counter
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import cv2
import numpy as np

from msfnet.common.cli import nonnegative_float, positive_float, positive_int
from msfnet.common.errors import InputError, first_line
from msfnet.common.files import json_text
from msfnet.common.imageio import image_header
from msfnet.common.vocabulary import flag, opt, options_type, verbatim
from msfnet.runtime.engines.method import RunMethod
from msfnet.runtime.inspection.zones import Zones
from msfnet.runtime.results.maps.api import InspectionMaps
from msfnet.runtime.results.maps.registered import Frame, read_tiff

POLARITIES = ("both", "down", "up")
EXIT_MISMATCH = 4
# a region over this share of the inspected pixels: not the reference's part, or not in its place
MISMATCH_FRACTION = 0.8
MAX_SHIFT_PX = 32  # a reference further off than this is not "the same fixture"
# the phase correlation's peak below which two maps share no feature to align on
MIN_ALIGN_RESPONSE = 0.3


@options_type
@dataclass(frozen=True)
class DefectOptions:
    """The rule, in the maps' units (mm with a pixel size, else px); each field's help says
    what it does (depth or curvature None: not used; one of them is needed)."""

    depth: float | None = flag(
        None, "|local shape| at or above this is a defect", type=positive_float
    )
    curvature: float | None = flag(
        None, "|mean curvature| at or above this is a defect", type=positive_float
    )
    min_area_px: int = flag(
        4, "smallest region (px)", name="--min-area", type=positive_int, metavar="PX"
    )
    polarity: str = flag(
        "both",
        "down: dents and scratches only; up: bumps only (default both)",
        choices=("both", "down", "up"),
    )
    keep_out_px: float = flag(
        0.0,
        "leave out the pixels within PX of the mask's edge (map px): where the mask ends on "
        "the part's own edge its normals there draw a rim; 6 is a start (default 0)",
        name="--keep-out",
        type=nonnegative_float,
        metavar="PX",
    )
    sigmas: float = flag(
        4.0,
        "with a variation model as --reference (--train-good): a pixel is a defect where it "
        "leaves the good parts' centre by more than K of their robust standard deviations "
        "and by --depth (default 4)",
        type=positive_float,
        metavar="K",
    )

    def __post_init__(self) -> None:
        if self.depth is None and self.curvature is None:
            raise InputError(
                f"give a depth threshold ({opt('depth')}) or a curvature one ({opt('curvature')})"
            )
        for name in ("depth", "curvature", "sigmas"):
            v = getattr(self, name)
            if v is not None and not (np.isfinite(v) and v > 0):
                raise InputError(
                    f"{opt(name, verbatim(f'{v}'))}: must be a positive, finite number"
                )
        if not (np.isfinite(self.keep_out_px) and self.keep_out_px >= 0):
            keep_out = opt("keep_out_px", verbatim(f"{self.keep_out_px}"))
            raise InputError(f"{keep_out}: must be 0 or more px")
        if self.min_area_px < 1:
            raise InputError(
                f"{opt('min_area_px', self.min_area_px)}: must be at least 1 px",
                option="min_area_px",
            )
        if self.polarity not in POLARITIES:
            polarity = opt("polarity", self.polarity, quote=True)
            raise InputError(f"{polarity}: expected one of {POLARITIES}")


@dataclass(frozen=True)
class Region:
    """One defect: ``depth`` the largest |local shape| (height units; signed_depth < 0 for a
    dent or scratch) at ``peak``; ``area_px`` (and area_mm2 with a pixel size); ``peak``,
    ``centroid`` (x, y) and ``bbox`` (x, y, w, h) in map pixels (overlay.png's); the same
    in the camera image's pixels (``image_*``, see :class:`Frame`); the largest |mean
    curvature|. Shape (:func:`region_shape`): ``length_px`` and ``width_px`` of the region's
    smallest rotated rectangle, ``orientation_deg`` of its long axis (0 along x, 90 along y,
    rows down), ``mean_depth`` (mean |local shape|), and ``kind``: scratch, dent, pit or
    bump."""

    label: int
    area_px: int
    area_mm2: float | None
    depth: float
    signed_depth: float
    curvature: float
    centroid: tuple[float, float]
    bbox: tuple[int, int, int, int]
    peak: tuple[int, int] = (0, 0)
    image_peak: tuple[float, float] = (0.0, 0.0)
    image_centroid: tuple[float, float] = (0.0, 0.0)
    image_bbox: tuple[int, int, int, int] = (0, 0, 0, 0)
    kind: str = ""
    length_px: float = 0.0
    width_px: float = 0.0
    orientation_deg: float = 0.0
    mean_depth: float = 0.0
    zone: str = ""  # the zone of its peak (--zones), "" outside every zone


# A region at least this many times longer than wide is a scratch (a dent seen at an angle
# stays under 2); a sunk one at most PIT_WIDTH_PX wide, a pit.
SCRATCH_ELONGATION = 3.0
PIT_WIDTH_PX = 3.0
KINDS = ("scratch", "dent", "pit", "bump")


@dataclass(frozen=True)
class RegionShape:
    length_px: float
    width_px: float
    orientation_deg: float
    kind: str


def region_shape(rows: np.ndarray, cols: np.ndarray, sunk: bool) -> RegionShape:
    """The shape of a region given its pixels: length and width of the smallest rotated
    rectangle holding the pixel squares, the long axis' direction (second moments: steadier
    than the rectangle's on a blob), and its kind: raised -> bump; sunk and elongated ->
    scratch; sunk, compact and narrow -> pit; else dent."""
    points = np.column_stack([cols, rows]).astype(np.float32)
    (_, _), (w, h), _ = cv2.minAreaRect(points)
    length, width = max(w, h) + 1.0, min(w, h) + 1.0
    x, y = cols - cols.mean(), rows - rows.mean()
    sxx, syy, sxy = float((x * x).mean()), float((y * y).mean()), float((x * y).mean())
    angle = 0.5 * math.degrees(math.atan2(2 * sxy, sxx - syy)) % 180.0
    if not sunk:
        kind = "bump"
    elif length >= SCRATCH_ELONGATION * width:
        kind = "scratch"
    else:
        kind = "pit" if width <= PIT_WIDTH_PX else "dent"
    return RegionShape(round(float(length), 2), round(float(width), 2), round(angle, 1), kind)


def kinds_text(kinds: Iterable[str]) -> str:
    """Regions counted by kind, most first: "3 scratch, 2 dent"."""
    return ", ".join(f"{n} {k}" for k, n in Counter(kinds).most_common())


_PAIRS = {
    "centroid": 2,
    "bbox": 4,
    "peak": 2,
    "image_peak": 2,
    "image_centroid": 2,
    "image_bbox": 4,
}


@dataclass(frozen=True)
class JudgedStatistics:
    """One judged map inside the inspected pixels, toward the rule's polarity (what a
    threshold is chosen from): its median, 99th percentile and maximum, in ``units``."""

    map: str  # "local shape" or "curvature"
    units: str
    threshold: float
    p50: float
    p99: float
    max: float

    def line(self) -> str:
        return (
            f"{self.map}: p50 {self.p50:.3g}, p99 {self.p99:.3g}, max {self.max:.3g} "
            f"{self.units} (threshold {self.threshold:g} {self.units})"
        )


@dataclass(frozen=True)
class Verdict:
    """``passed``: no region found. ``units``: of depth and curvature. ``shift``: the
    reference's alignment (x, y px) when one was used. ``statistics``: of each judged map."""

    passed: bool
    regions: tuple[Region, ...]
    options: DefectOptions
    units: dict[str, str]
    pixels: int
    reference: str | None = None
    shift: tuple[float, float] | None = None
    source: str | None = None
    notes: tuple[str, ...] = field(default_factory=tuple)
    frame: Frame = field(default_factory=Frame)
    aligned_on: str | None = None  # "albedo" or "local shape": what the shift came from
    provenance: dict[str, str | None] | None = None  # what produced the maps (Provenance)
    statistics: tuple[JudgedStatistics, ...] = ()
    # (H, W) the judged map over its threshold (signed: < 0 sunk or concave), NaN where not
    # inspected: what deviation.png draws (not written to verdict.json)
    deviation: np.ndarray | None = field(default=None, repr=False, compare=False)
    # why the part is not the reference's (one region covers more than MISMATCH_FRACTION of
    # it, or it lies more than MAX_SHIFT_PX off): another part, or not in its place
    mismatch: str | None = None

    @property
    def word(self) -> str:
        return "mismatch" if self.mismatch is not None else "pass" if self.passed else "fail"

    @property
    def exit_code(self) -> int:
        """What a PLC script reads: 0 pass, 1 defects found, 4 the part does not match its
        reference or model (2, bad input, is raised)."""
        return EXIT_MISMATCH if self.mismatch is not None else 0 if self.passed else 1

    def as_dict(self) -> dict[str, object]:
        return {
            "verdict": self.word,
            "mismatch": self.mismatch,
            "exit_code": self.exit_code,
            "defects": len(self.regions),
            "regions": [asdict(r) for r in self.regions],
            "options": asdict(self.options),
            "units": dict(self.units),
            "pixels_inspected": self.pixels,
            "reference": self.reference,
            "reference_shift_px": None if self.shift is None else list(self.shift),
            "reference_aligned_on": self.aligned_on,
            "source": self.source,
            "frame": self.frame.as_dict(),
            "notes": list(self.notes),
            "provenance": self.provenance,
            "statistics": [asdict(st) for st in self.statistics],
        }

    def json_text(self) -> str:
        return json_text(self.as_dict())

    def kinds(self) -> str:
        """The regions by kind, most first: "3 scratch, 2 dent"."""
        return kinds_text(r.kind for r in self.regions)

    def csv_text(self) -> str:
        """regions.csv: one row per region (the fields of :class:`Region`; pairs and boxes as
        their x / y / w / h columns), for a spreadsheet or a line's database."""
        import csv
        import io

        columns = [f.name for f in fields(Region)]
        out = io.StringIO()
        writer = csv.writer(out, lineterminator="\n")
        header: list[str] = []
        for name in columns:
            axes = "xywh"[: _PAIRS[name]] if name in _PAIRS else ""
            header += [f"{name}_{a}" for a in axes] if axes else [name]
        writer.writerow(header)
        for region in self.regions:
            row: list[object] = []
            for name in columns:
                value = getattr(region, name)
                row += list(value) if isinstance(value, tuple) else [value]
            writer.writerow(row)
        return out.getvalue()


@dataclass
class InspectionInput:
    """The registered maps the step reads (height units per ``units``): local_shape and
    curvature (H, W) float32 with NaN outside the mask (either may be missing, not both:
    a perspective run has no local shape); albedo (H, W, 3) or None."""

    local_shape: np.ndarray | None
    curvature: np.ndarray | None
    albedo: np.ndarray | None
    units: dict[str, str]
    pixel_size_mm: float | None
    source: str
    local_size_px: float | None = None
    frame: Frame = field(default_factory=Frame)
    perspective: bool = False
    method: RunMethod | None = None  # the Model's describe() when run in process
    # a variation model's centre (inspection.variation) carries the good parts' spreads
    local_shape_spread: np.ndarray | None = None
    curvature_spread: np.ndarray | None = None

    @property
    def _any_map(self) -> np.ndarray:
        found = self.local_shape if self.local_shape is not None else self.curvature
        assert found is not None, "an InspectionInput holds a local shape or a curvature"
        return found

    @property
    def mask(self) -> np.ndarray:
        return np.isfinite(self._any_map)

    @property
    def shape(self) -> tuple[int, int]:
        h, w = self._any_map.shape[:2]
        return int(h), int(w)


def from_maps(maps: InspectionMaps, source: str) -> InspectionInput:
    """The step's input straight from computed maps (a run in this process)."""
    phys = maps.physical()
    if "local_shape" not in phys and "curvature" not in phys:
        raise InputError("the defect step needs the height or curvature map", source)
    units = maps.registered_units()
    return InspectionInput(
        local_shape=phys.get("local_shape"),
        curvature=phys.get("curvature"),
        albedo=phys.get("albedo"),
        units={"depth": str(units["local_shape"]), "curvature": str(units["curvature"])},
        pixel_size_mm=maps.options.pixel_size_mm,
        source=source,
        local_size_px=float(maps.options.local_size_px),
        frame=maps.options.frame,
        perspective=maps.options.intrinsics is not None,
    )


DEPTH_UNITS = ("px", "mm")
CURVATURE_UNITS = ("1/px", "1/mm")


# msf-inspect's peak beyond its interpreter and imports (~55 MB), per pixel of a run folder's
# maps: 50 B a part alone, 115 B against a reference (measured on 1-4 MP maps, AMD EPYC)
INSPECT_BYTES_PER_PX = 64
INSPECT_BYTES_PER_PX_REFERENCE = 128
INSPECT_BASE_MB = 100


def check_run_memory(folder: Path, max_memory_mb: float, reference: bool) -> None:
    """Refuse a run folder whose maps' headers say the inspection would not fit
    ``max_memory_mb``, before any map is decoded (msf-run refuses its stacks the same way)."""
    maps = [folder / n for n in ("local_shape.tif", "curvature.tif") if (folder / n).is_file()]
    header = image_header(maps[0]) if maps else None  # read_run names a folder without maps
    if header is None:
        return
    per_px = INSPECT_BYTES_PER_PX_REFERENCE if reference else INSPECT_BYTES_PER_PX
    need = INSPECT_BASE_MB + header.pixels * per_px / 2**20
    if need > max_memory_mb:
        raise InputError(
            f"maps of {header.width}x{header.height} need about {need:.0f} MB to inspect"
            f"{' against a reference' if reference else ''}, above "
            f"{opt('max_memory_mb', max_memory_mb)} MB",
            maps[0],
        )


def is_run(path: Path) -> bool:
    """An msf-run output folder with maps (or a variation model): what :func:`read_run` reads."""
    return path.is_dir() and (path / "maps.json").is_file()


def read_run(folder: Path) -> InspectionInput:
    """The maps of an msf-run output folder (local_shape.tif and/or curvature.tif, albedo.tif,
    maps.json's units, local size and frame); InputError naming what is missing."""
    folder = Path(folder)
    info_path = folder / "maps.json"
    if not info_path.is_file():
        raise InputError("no maps.json: not an msf-run output folder with maps", folder)
    try:
        info = json.loads(info_path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise InputError(f"not valid JSON ({first_line(exc)})", info_path) from exc
    try:
        reg = dict(info["registered"])
        options = dict(info.get("options") or {})
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(
            "maps.json has no registered-map units (older msf-run?)", info_path
        ) from exc
    perspective = options.get("intrinsics") is not None
    local = folder / "local_shape.tif"
    curv = folder / "curvature.tif"
    alb = folder / "albedo.tif"
    if not local.is_file() and not curv.is_file():
        why = (
            f"a perspective run ({opt('intrinsics')}) has no local shape; run msf-run with "
            f"curvature in {opt('maps')} and inspect with {opt('curvature')}"
            if perspective
            else "run msf-run with the height or curvature map and TIFF output"
        )
        raise InputError(f"no local_shape.tif or curvature.tif: {why}", folder)
    # a map not written has no unit entry (a curvature-only run): it follows the pixel size
    mm = reg.get("pixel_size_mm") is not None
    units = {
        "depth": str(reg.get("local_shape", "mm" if mm else "px")),
        "curvature": str(reg.get("curvature", "1/mm" if mm else "1/px")),
    }
    if units["depth"] not in DEPTH_UNITS or units["curvature"] not in CURVATURE_UNITS:
        raise InputError(
            f"unknown units {units['depth']!r} / {units['curvature']!r} (expected "
            f"{'/'.join(DEPTH_UNITS)} and {'/'.join(CURVATURE_UNITS)})",
            info_path,
        )
    size = _positive(reg.get("pixel_size_mm"), "pixel_size_mm", info_path)
    local_size = _positive(reg.get("local_size_px"), "local_size_px", info_path)
    first = _read(local, 2) if local.is_file() else _read(curv, 2)
    return InspectionInput(
        local_shape=first if local.is_file() else None,
        curvature=(_read(curv, 2, first.shape) if curv.is_file() else None)
        if local.is_file()
        else first,
        albedo=_read(alb, 3, first.shape) if alb.is_file() else None,
        local_shape_spread=_spread(folder, "local_shape", first.shape),
        curvature_spread=_spread(folder, "curvature", first.shape),
        units=units,
        pixel_size_mm=size,
        source=str(folder),
        local_size_px=local_size,
        frame=_frame(info.get("frame"), info_path)
        if "frame" in info
        else _frame_of_older_run(folder),
        perspective=perspective,
    )


def _spread(folder: Path, name: str, size: tuple[int, ...]) -> np.ndarray | None:
    """A variation model's spread map (inspection.variation), None in a plain run."""
    path = folder / f"spread_{name}.tif"
    return _read(path, 2, size) if path.is_file() else None


def _positive(value: object, name: str, where: Path) -> float | None:
    """A positive number of maps.json, or None when absent."""
    if value is None:
        return None
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float))
        or not math.isfinite(value)
        or value <= 0
    ):
        raise InputError(f"{name} must be a positive number, got {value!r}", where)
    return float(value)


def _frame_of_older_run(folder: Path) -> Frame:
    """A run written before maps.json had "frame": its ROI and downscale from profile.json's
    load options (identity when it has none, as such runs then had)."""
    try:
        load = json.loads((folder / "profile.json").read_text(encoding="utf-8"))["input"]
        return Frame.of_cut(load.get("roi"), load.get("downscale"))
    except (OSError, ValueError, KeyError, TypeError, IndexError, AttributeError, InputError):
        return Frame()


def _frame(value: object, where: Path) -> Frame:
    """maps.json's "frame" ({"origin_xy": [x, y], "downscale": K}); absent (a run of an
    earlier version): the whole image."""
    if value is None:
        return Frame()
    try:
        return Frame(tuple(value["origin_xy"]), value["downscale"])  # type: ignore[index,arg-type]
    except (InputError, KeyError, TypeError, ValueError) as exc:
        raise InputError(
            f'"frame" must be {{"origin_xy": [x, y], "downscale": K}}, got {value!r}', where
        ) from exc


def _read(path: Path, ndim: int, size: tuple[int, ...] | None = None) -> np.ndarray:
    """A map of the run: real numbers, ``ndim`` dimensions (albedo: H x W x 3), and the local
    shape's H x W; a TIFF edited or from another run is bad input, not a crash."""
    try:
        data = read_tiff(path)
    except InputError:
        raise
    except Exception as exc:  # tifffile raises its own types for damaged files
        raise InputError(f"cannot read the TIFF ({type(exc).__name__}: {exc})", path) from exc
    want = "H x W x 3" if ndim == 3 else "H x W"
    if data.ndim != ndim or (ndim == 3 and data.shape[2] != 3):
        raise InputError(f"expected a {want} map, found shape {data.shape}", path)
    if size is not None and data.shape[:2] != size[:2]:
        raise InputError(
            f"{data.shape[1]}x{data.shape[0]} but local_shape.tif is {size[1]}x{size[0]}: "
            "maps of different runs?",
            path,
        )
    return data


def _align(moving: np.ndarray, fixed: np.ndarray) -> tuple[float, float, float]:
    """(dx, dy) such that ``moving`` shifted by it matches ``fixed``, and the phase
    correlation's peak (0..1): how much the two maps had in common to align on (a featureless
    map's peak is noise, low). Phase correlation (NaN as 0, Hann-windowed) for the coarse
    shift, refined by OpenCV's ECC (translation only) over the pixels both maps hold."""
    # each map less its mean: a constant (a uniform albedo) correlates perfectly at zero shift
    # and would outvote the features
    a = np.nan_to_num(fixed.astype(np.float32) - np.float32(np.nanmean(fixed)))
    b = np.nan_to_num(moving.astype(np.float32) - np.float32(np.nanmean(moving)))
    window = cv2.createHanningWindow((a.shape[1], a.shape[0]), cv2.CV_32F)
    (dx, dy), response = cv2.phaseCorrelate(b, a, window)
    start = np.array([[1, 0, -dx], [0, 1, -dy]], np.float32)  # ECC maps fixed -> moving
    both = (np.isfinite(fixed) & np.isfinite(moving)).astype(np.uint8)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-5)
    try:
        _, warp = cv2.findTransformECC(a, b, start, cv2.MOTION_TRANSLATION, criteria, both, 5)
        dx, dy = -float(warp[0, 2]), -float(warp[1, 2])
    except cv2.error:
        pass  # ECC did not converge (a featureless map): the phase correlation's shift stands
    return float(dx), float(dy), float(response)


def shift_map(values: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """``values`` moved by (dx, dy) px (bilinear; NaN where nothing moved in)."""
    m = np.array([[1, 0, dx], [0, 1, dy]], np.float32)
    h, w = values.shape[:2]
    valid = np.isfinite(values).astype(np.float32)
    moved = cv2.warpAffine(
        np.nan_to_num(values).astype(np.float32), m, (w, h), flags=cv2.INTER_LINEAR
    )
    ok = cv2.warpAffine(valid, m, (w, h), flags=cv2.INTER_LINEAR) > 0.999
    return np.where(ok, moved, np.nan).astype(np.float32)


@dataclass(frozen=True)
class Aligned:
    """The reference's maps moved onto the part's pixels (spreads: a variation model's)."""

    local_shape: np.ndarray | None
    curvature: np.ndarray | None
    shift: tuple[float, float]
    aligned_on: str
    local_shape_spread: np.ndarray | None = None
    curvature_spread: np.ndarray | None = None


def _check_alike(part: InspectionInput, reference: InspectionInput) -> None:
    """The reference was mapped as the part was, else subtracting it means nothing (a mm
    part minus a px reference failed a part compared with itself)."""
    if reference.shape != part.shape:
        h, w = part.shape
        rh, rw = reference.shape
        raise InputError(
            f"the reference is {rw}x{rh} but the part is {w}x{h}: capture it with the same "
            "camera, ROI and downscale",
            reference.source,
        )
    differ = []
    if reference.units != part.units:
        differ.append(f"units: reference {reference.units['depth']}, part {part.units['depth']}")
    ps, rs = part.pixel_size_mm, reference.pixel_size_mm
    if (ps is None) != (rs is None) or (
        ps is not None and rs is not None and not math.isclose(ps, rs, rel_tol=1e-6)
    ):
        differ.append(f"pixel size: reference {rs} mm, part {ps} mm")
    pl, rl = part.local_size_px, reference.local_size_px
    if pl is not None and rl is not None and not math.isclose(pl, rl, rel_tol=1e-6):
        differ.append(f"local size: reference {rl:g} px, part {pl:g} px")
    if reference.frame != part.frame:
        differ.append(
            f"ROI corner / downscale: reference {reference.frame.origin_xy} / "
            f"{reference.frame.downscale}, part {part.frame.origin_xy} / {part.frame.downscale}"
        )
    if differ:
        raise InputError(
            f"the reference was mapped differently from the part ({'; '.join(differ)}): "
            f"map both with the same {opt('image_pixel_size_mm')}, {opt('local_size_px')}, "
            f"{opt('roi')} and {opt('downscale')}",
            reference.source,
        )


def align_to(part: InspectionInput, reference: InspectionInput, *, limit: bool = True) -> Aligned:
    """The reference's maps aligned to the part's, on whichever they share most of: the
    albedo (print, texture) or the local shape (a uniform part's albedo is only noise, and
    aligning on it kept a 2 px misplacement)."""
    _check_alike(part, reference)
    candidates = []
    if part.albedo is not None and reference.albedo is not None:
        candidates.append(("albedo", reference.albedo.mean(axis=2), part.albedo.mean(axis=2)))
    for name in ("local_shape", "curvature"):
        mine, theirs = getattr(part, name), getattr(reference, name)
        if mine is not None and theirs is not None:
            candidates.append((name.replace("_", " "), theirs, mine))
            break
    if not candidates:
        raise InputError(
            "the reference shares no map with the part to align on (albedo, local shape or "
            "curvature): map it with the rule's maps",
            reference.source,
        )
    best = max(
        ((name, *_align(moving, fixed)) for name, moving, fixed in candidates), key=lambda c: c[3]
    )
    name, dx, dy, response = best
    if response < MIN_ALIGN_RESPONSE:
        # nothing to align on (a plain part): the fixture's place, not a peak of noise (one
        # put a 0.34 px dent 13 px outside the compared area and passed the part)
        name, dx, dy = "none (no features: taken as in place)", 0.0, 0.0
    if limit:
        _check_shift(dx, dy, reference.source)

    def moved(values: np.ndarray | None) -> np.ndarray | None:
        return None if values is None else shift_map(values, dx, dy)

    r = reference
    return Aligned(
        moved(r.local_shape),
        moved(r.curvature),
        (dx, dy),
        name,
        moved(r.local_shape_spread),
        moved(r.curvature_spread),
    )


def _check_shift(dx: float, dy: float, source: str | None = None) -> None:
    if max(abs(dx), abs(dy)) > MAX_SHIFT_PX:
        raise InputError(
            f"the reference is {dx:+.1f}, {dy:+.1f} px off this part (more than "
            f"{MAX_SHIFT_PX} px): not captured in the same fixture?",
            source,
        )


def _toward(signed: np.ndarray, polarity: str) -> np.ndarray:
    """How far each pixel goes in the direction ``polarity`` inspects (bumps and convex
    curvature are positive, dents and scratches negative)."""
    if polarity == "down":
        return np.maximum(-signed, 0.0)
    if polarity == "up":
        return np.maximum(signed, 0.0)
    return np.abs(signed)


@dataclass
class _Judged:
    """What the rule compares: the part's maps less the aligned reference's (if any), the
    pixels both hold, and each map's threshold (a number, or per pixel with a variation
    model's spreads)."""

    mask: np.ndarray
    local: np.ndarray | None
    curv: np.ndarray | None
    depth: float | np.ndarray | None
    bend: float | np.ndarray | None
    aligned: Aligned | None = None
    mismatch: str | None = None  # not the reference's part: nothing to compare
    zone_of: np.ndarray | None = None  # each pixel's zone (Zones.labels), -1 none


def _kept_in(mask: np.ndarray, keep_out_px: float) -> np.ndarray:
    """The mask less its pixels within ``keep_out_px`` of where it ends (the image's own
    border is not an edge of the part: the surface may go on beyond it)."""
    if keep_out_px <= 0:
        return mask
    padded = cv2.copyMakeBorder(mask.astype(np.uint8), 1, 1, 1, 1, cv2.BORDER_REPLICATE)
    distance = cv2.distanceTransform(padded, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[1:-1, 1:-1]
    return mask & (distance > keep_out_px)


def _floors(
    part: InspectionInput, options: DefectOptions, zones: Zones | None
) -> tuple[np.ndarray, float | np.ndarray | None, float | np.ndarray | None, np.ndarray | None]:
    """The pixels judged (the mask less the keep-out and ignored zones) and the thresholds
    before any variation model: the rule's, or a zone's own inside it; the zone labels."""
    mask = _kept_in(part.mask, options.keep_out_px)
    depth: float | np.ndarray | None = options.depth
    bend: float | np.ndarray | None = options.curvature
    zone_of = None
    if zones is not None:
        zone_of = zones.labels(part.shape, part.frame)
        for i, zone in enumerate(zones.zones):
            inside = zone_of == i
            if zone.ignore:
                mask = mask & ~inside
            if zone.depth is not None and depth is not None:
                depth = np.where(inside, zone.depth, depth)
            if zone.curvature is not None and bend is not None:
                bend = np.where(inside, zone.curvature, bend)
    if not mask.any():
        keep_out = opt("keep_out_px")
        what = f"{keep_out} and the ignored zones leave" if zones else f"{keep_out} leaves"
        raise InputError(f"{what} nothing of the mask to inspect", part.source)
    return mask, depth, bend, zone_of


def _against_reference(
    part: InspectionInput,
    options: DefectOptions,
    reference: InspectionInput | None,
    zones: Zones | None = None,
) -> _Judged:
    mask, depth, bend, zone_of = _floors(part, options, zones)
    local, curv = part.local_shape, part.curvature
    judged = _Judged(mask, local, curv, depth, bend, zone_of=zone_of)
    if reference is None:
        return judged
    ref = align_to(part, reference, limit=False)
    dx, dy = ref.shift
    if max(abs(dx), abs(dy)) > MAX_SHIFT_PX:
        judged.aligned = ref
        judged.mismatch = f"it lies {dx:+.1f}, {dy:+.1f} px off the reference (over {MAX_SHIFT_PX})"
        return judged
    for name, ref_map in (("local_shape", ref.local_shape), ("curvature", ref.curvature)):
        wanted = options.depth if name == "local_shape" else options.curvature
        if wanted is not None and getattr(part, name) is not None and ref_map is None:
            raise InputError(f"the reference has no {name.replace('_', ' ')} map", reference.source)
    if ref.local_shape is not None and local is not None:
        mask = mask & np.isfinite(ref.local_shape)
        local = local - ref.local_shape
    if ref.curvature is not None and curv is not None:
        mask = mask & np.isfinite(ref.curvature)
        curv = curv - ref.curvature
    if not mask.any():
        raise InputError("the part and the aligned reference share no pixel", part.source)
    judged = _Judged(mask, local, curv, depth, bend, ref, zone_of=zone_of)
    # a variation model: the threshold is K spreads where the good parts varied more than
    # the floor allows (pixels fewer than 3 good parts held have no centre: left out above)
    if ref.local_shape_spread is not None and depth is not None:
        judged.depth = np.fmax(depth, options.sigmas * ref.local_shape_spread)
    if ref.curvature_spread is not None and bend is not None:
        judged.bend = np.fmax(bend, options.sigmas * ref.curvature_spread)
    return judged


def find_defects(
    part: InspectionInput,
    options: DefectOptions,
    reference: InspectionInput | None = None,
    zones: Zones | None = None,
) -> tuple[Verdict, np.ndarray]:
    """The verdict and an (H, W) int32 label image of the regions (0 = none). ``reference``:
    a good part, or a variation model's centre (with spreads: per-pixel thresholds);
    ``zones``: areas with their own thresholds, or left out."""
    if not part.mask.any():
        raise InputError("the mask is empty: nothing to inspect", part.source)
    if options.depth is not None and part.local_shape is None:
        why = f" (a perspective run has none: use {opt('curvature')})" if part.perspective else ""
        raise InputError(f"{opt('depth')} needs local_shape.tif{why}", part.source, option="depth")
    if options.curvature is not None and part.curvature is None:
        raise InputError(
            f"{opt('curvature')} needs curvature.tif in the run folder",
            part.source,
            option="curvature",
        )
    j = _against_reference(part, options, reference, zones)
    mask = j.mask
    signed = np.zeros(mask.shape, np.float32) if j.local is None else np.nan_to_num(j.local)
    signed_curv = None if j.curv is None else np.nan_to_num(j.curv)
    high = np.zeros(mask.shape, bool)
    low = np.zeros(mask.shape, bool)
    judged: list[JudgedStatistics] = []
    if options.depth is not None and j.depth is not None:
        size = _toward(signed, options.polarity)
        high |= size >= j.depth
        low |= size >= 0.5 * j.depth
        judged.append(_statistics("local shape", part.units["depth"], options.depth, size, mask))
    if options.curvature is not None and signed_curv is not None and j.bend is not None:
        bend = _toward(signed_curv, options.polarity)
        high |= bend >= j.bend
        low |= bend >= 0.5 * j.bend
        unit = part.units["curvature"]
        judged.append(_statistics("curvature", unit, options.curvature, bend, mask))
    high &= mask
    low &= mask
    if options.depth is not None and j.depth is not None:
        ratio = signed / j.depth
    else:
        ratio = (np.zeros(mask.shape) if signed_curv is None else signed_curv) / (j.bend or 1.0)
    deviation = np.where(mask, ratio, np.nan).astype(np.float32)
    regions: list[Region] = []
    out = np.zeros(mask.shape, np.int32)
    if j.mismatch is None:  # aligned: the regions (too far off, nothing is compared)
        # the peak: the deepest point, or with curvature alone the most bent one
        score = np.abs(signed if signed_curv is None or options.depth is not None else signed_curv)
        regions, out = _regions(part, options, high, low, signed, signed_curv, score)
        if zones is not None and j.zone_of is not None:
            names = ["", *(z.name for z in zones.zones)]  # label -1 (no zone) -> ""
            zone_of = j.zone_of
            regions = [replace(r, zone=names[int(zone_of[r.peak[::-1]]) + 1]) for r in regions]
    mismatch = j.mismatch
    inspected = max(int(np.count_nonzero(mask)), 1)
    largest = max((r.area_px for r in regions), default=0) / inspected
    if mismatch is None and reference is not None and largest > MISMATCH_FRACTION:
        mismatch = (
            f"one region covers {100 * largest:.0f} % of it (over {100 * MISMATCH_FRACTION:.0f} %)"
        )
    verdict = Verdict(
        passed=not regions and mismatch is None,
        regions=tuple(regions),
        options=options,
        units=dict(part.units),
        pixels=int(mask.sum()),
        reference=None if reference is None else reference.source,
        shift=None if j.aligned is None else j.aligned.shift,
        source=part.source,
        frame=part.frame,
        aligned_on=None if j.aligned is None else j.aligned.aligned_on,
        statistics=tuple(judged),
        mismatch=mismatch,
        deviation=deviation,
    )
    return verdict, out


def _regions(
    part: InspectionInput,
    options: DefectOptions,
    high: np.ndarray,
    low: np.ndarray,
    signed: np.ndarray,
    signed_curv: np.ndarray | None,
    score: np.ndarray,
) -> tuple[list[Region], np.ndarray]:
    """Hysteresis: the connected regions of ``low`` that hold a ``high`` pixel, at least
    min_area_px each; their records and label image."""
    _, labels, stats, cents = cv2.connectedComponentsWithStats(low.astype(np.uint8), connectivity=8)
    out = np.zeros(low.shape, np.int32)
    regions: list[Region] = []
    seeded = np.unique(labels[high])
    frame = part.frame
    for lab in seeded[seeded > 0]:
        area = int(stats[lab, cv2.CC_STAT_AREA])
        if area < options.min_area_px:
            continue
        sel = labels == lab
        k = len(regions) + 1
        out[sel] = k
        i = int(np.argmax(np.where(sel, score, -1.0)))
        py, px_ = divmod(i, low.shape[1])
        peak = float(signed.flat[i])
        px = part.pixel_size_mm
        x, y, w, h = (int(v) for v in stats[lab, :4])
        cx, cy = float(cents[lab][0]), float(cents[lab][1])
        (x0, y0), kk = frame.origin_xy, frame.downscale
        rows, cols = np.nonzero(sel)
        # sunk or raised: the local shape's sign, or with curvature alone the curvature's
        # (concave, a dent's or a scratch's, is negative)
        sign = peak if part.local_shape is not None or signed_curv is None else signed_curv.flat[i]
        shape = region_shape(rows, cols, sunk=float(sign) < 0)
        regions.append(
            Region(
                label=k,
                area_px=area,
                area_mm2=None if px is None else area * px * px,
                depth=abs(peak),
                signed_depth=peak,
                curvature=0.0 if signed_curv is None else float(np.abs(signed_curv[sel]).max()),
                centroid=(cx, cy),
                bbox=(x, y, w, h),
                peak=(px_, py),
                image_peak=frame.image_xy(px_, py),
                image_centroid=frame.image_xy(cx, cy),
                image_bbox=(x0 + kk * x, y0 + kk * y, kk * w, kk * h),
                kind=shape.kind,
                length_px=shape.length_px,
                width_px=shape.width_px,
                orientation_deg=shape.orientation_deg,
                mean_depth=float(np.abs(signed[sel]).mean()),
            )
        )
    return regions, out


def _statistics(
    name: str, units: str, threshold: float, values: np.ndarray, mask: np.ndarray
) -> JudgedStatistics:
    inside = values[mask]
    p50, p99 = (float(v) for v in np.percentile(inside, (50, 99)))
    return JudgedStatistics(name, units, threshold, p50, p99, float(inside.max()))


# outline colours by kind (RGB), told apart also by people who do not see red and green well
KIND_COLOURS = {
    "scratch": (255, 60, 60),
    "dent": (255, 170, 0),
    "pit": (230, 80, 255),
    "bump": (0, 200, 255),
    "": (255, 60, 60),
}


DEVIATION_RANGE = 2.0  # deviation.png's scale ends at twice the threshold
BAR_PX = 26  # its colour bar's height


def deviation_picture(verdict: Verdict) -> np.ndarray:
    """(H + BAR_PX, W, 3) uint8 RGB: the judged map over its threshold at one fixed scale, so a
    good part looks calm whatever its own range: grey at 0, full colour at the threshold (red
    sunk or concave, blue raised or convex), darker up to DEVIATION_RANGE thresholds; dark
    where not inspected; a colour bar below, in thresholds (t: the rule's, or a pixel's own
    spread limit against a variation model)."""
    dev = verdict.deviation
    assert dev is not None, "a verdict from find_defects carries its deviation"
    w = dev.shape[1]
    t = np.clip(np.nan_to_num(dev) / DEVIATION_RANGE, -1.0, 1.0)
    rgb = _diverging(t)
    rgb[~np.isfinite(dev)] = (25, 25, 25)
    bar = np.zeros((BAR_PX, w, 3), np.uint8)
    bar[:8] = _diverging(np.linspace(-1.0, 1.0, w))[None]
    for value in (-2, -1, 0, 1, 2):
        x = round((value / DEVIATION_RANGE + 1) / 2 * (w - 1))
        label = "0" if value == 0 else f"{value:+d}t"
        (tw, _), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_PLAIN, 0.8, 1)
        x0 = min(max(0, x - tw // 2), w - tw)
        bar[8:11, max(0, x - 1) : x + 1] = 200
        cv2.putText(bar, label, (x0, BAR_PX - 3), cv2.FONT_HERSHEY_PLAIN, 0.8, (220, 220, 220), 1)
    return np.concatenate([rgb, bar], axis=0)


def _diverging(t: np.ndarray) -> np.ndarray:
    """t in [-1, 1] (a deviation over DEVIATION_RANGE thresholds) -> RGB: grey at 0, full red
    (sunk) or blue (raised) at the threshold, darker beyond it, half as bright at the end."""
    grey = np.array([150.0, 150.0, 150.0])
    a = np.abs(t)[..., None] * DEVIATION_RANGE  # in thresholds
    colour = np.where((t < 0)[..., None], [230.0, 40.0, 40.0], [40.0, 90.0, 235.0])
    rgb = grey + (colour - grey) * np.minimum(a, 1.0)
    rgb *= 1.0 - 0.5 * np.clip((a - 1.0) / (DEVIATION_RANGE - 1.0), 0.0, 1.0)
    return np.clip(rgb, 0, 255).astype(np.uint8)


def overlay_picture(
    part: InspectionInput, labels: np.ndarray, regions: tuple[Region, ...] = ()
) -> np.ndarray:
    """(H, W, 3) uint8 RGB at the maps' size: the albedo (or the local shape) in grey, the
    mask's outside darkened, each region outlined in its kind's colour (KIND_COLOURS) and
    labelled beside it: its number, and with ``regions`` (the verdict's) its kind and depth."""
    mask = part.mask
    if part.albedo is not None:
        base = np.nan_to_num(part.albedo.mean(axis=2))
    else:
        base = np.nan_to_num(part._any_map)
    vals = base[mask]
    if part.albedo is not None:  # from black: a uniform part stays uniform, not its noise
        lo, hi = 0.0, float(np.percentile(vals, 99)) if vals.size else 1.0
    else:
        lo, hi = (
            (float(np.percentile(vals, 1)), float(np.percentile(vals, 99)))
            if vals.size
            else (0.0, 1.0)
        )
    grey = np.clip((base - lo) / (hi - lo if hi > lo else 1.0), 0, 1) * 200 + 30
    grey = np.where(mask, grey, grey * 0.3).astype(np.uint8)
    rgb = np.ascontiguousarray(np.repeat(grey[..., None], 3, axis=2))
    by_label = {r.label: r for r in regions}
    h, w = labels.shape
    for k in range(1, int(labels.max()) + 1):
        sel = (labels == k).astype(np.uint8)
        region = by_label.get(k)
        colour = KIND_COLOURS.get(region.kind if region else "", KIND_COLOURS[""])
        contours, _ = cv2.findContours(sel, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(rgb, contours, -1, colour, 1)
        text = str(k) if region is None else f"{k} {region.kind} {region.depth:.2g}"
        ys, xs = np.nonzero(sel)
        (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_PLAIN, 0.8, 1)
        # beside the region, kept inside the picture (a region at the right edge: left of it)
        x = int(xs.max()) + 3 if int(xs.max()) + 3 + tw < w else max(0, int(xs.min()) - 3 - tw)
        y = min(max(th + 1, int(ys.min()) + th), h - 2)
        for at, ink in (((x + 1, y + 1), (0, 0, 0)), ((x, y), colour)):  # a shadow, then the text
            cv2.putText(rgb, text, at, cv2.FONT_HERSHEY_PLAIN, 0.8, ink, 1, cv2.LINE_AA)
    return rgb


__all__ = [
    "EXIT_MISMATCH",
    "KINDS",
    "MISMATCH_FRACTION",
    "POLARITIES",
    "Aligned",
    "DefectOptions",
    "InspectionInput",
    "JudgedStatistics",
    "Region",
    "Verdict",
    "align_to",
    "check_run_memory",
    "deviation_picture",
    "find_defects",
    "from_maps",
    "is_run",
    "overlay_picture",
    "read_run",
    "shift_map",
]
