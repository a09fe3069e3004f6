"""The inspection-maps entry point: compute every map from one run, write them all.

Wiring into a run is two lines (``stack``: the loaded Stack, ``normals``: the estimate):
    maps = stack_maps(stack, normals, MapOptions(integration="poisson"))
    files = write_maps(outdir, maps, images=stack.images, error_deg=err, profile=summary)
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from msfnet.common.cli import nonnegative_float, positive_float
from msfnet.common.errors import InputError
from msfnet.common.files import json_text, write_atomic
from msfnet.common.vocabulary import flag, options_type
from msfnet.runtime.results.maps.albedo import DEFAULT_MIN_SHADING, checked_albedo, display_level
from msfnet.runtime.results.maps.budget import MapsBudget
from msfnet.runtime.results.maps.curvature import DEFAULT_SIGMA, curvature_maps
from msfnet.runtime.results.maps.integrate import (
    DEFAULT_MIN_NZ,
    METHODS,
    Integration,
    Intrinsics,
    integrate_normals,
)
from msfnet.runtime.results.maps.registered import (
    DEFAULT_LOCAL_SIZE_PX,
    Frame,
    Units,
    check_local_size,
    described_png,
    gradients,
    grey16_view,
    local_shape,
    signed_view,
    tiff_placement,
    write_tiff,
)
from msfnet.runtime.results.maps.validate import check_normals
from msfnet.runtime.stack import Stack

MAP_NAMES = ("albedo", "height", "curvature", "mesh")
# one word for a usual set (--maps inspect, Model(maps="inspect")): "inspect" is what
# msf-inspect judges and aligns with (local shape comes with the height), no mesh
MAP_PRESETS: dict[str, tuple[str, ...]] = {
    "all": MAP_NAMES,
    "inspect": ("albedo", "height", "curvature"),
    "none": (),
}


def preset_maps(names: tuple[str, ...]) -> tuple[str, ...]:
    """``names`` with a lone preset word replaced by its maps ("none": no map)."""
    return MAP_PRESETS[names[0]] if len(names) == 1 and names[0] in MAP_PRESETS else names


def parse_maps(text: str) -> tuple[str, ...]:
    """--maps: map names, or one preset word (all, inspect, none: then no map)."""
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    if names and all(n in MAP_NAMES for n in preset_maps(names)):
        return preset_maps(names)
    raise argparse.ArgumentTypeError(
        f"expected names from {','.join(MAP_NAMES)} or one of {', '.join(MAP_PRESETS)}, "
        f"got {text!r}"
    )


PIXEL_SIZE_MM = (1e-6, 1e4)  # 1 nm (microscopes) to 10 m (aerial) a pixel
# what the registered TIFFs hold where there is no value (maps.json "outside_mask"; docs/run.md)
OUTSIDE_MASK = "NaN; albedo.tif is NaN inside the mask too where no observation was kept"


@options_type
@dataclass(frozen=True)
class MapOptions:
    """What to compute and how (the user-set fields carry their flags: msf-run's map group).

    maps: any of "albedo", "height", "curvature", "mesh" ("mesh" implies "height").
    integration: the height's, "fc" | "poisson" | "bini" (see maps.integrate).
    intrinsics: (fx, fy, cx, cy) in pixels for a perspective camera; None = orthographic.
    depth_ref: perspective only, the median object depth the unknown scale is fixed to
        (default fx: heights then read in pixels at that distance).
    min_nz: smallest nz (or |D|) used for slopes, bounding them to 1/min_nz px per px.
    min_shading, saturation: albedo observation filters (cosine; image units, None = the
        images' full scale, see maps.albedo.default_saturation).
    bini_k, bini_max_iter, bini_tol: "bini" sharpness, rounds and energy tolerance.
    mesh_max_jump: drop mesh triangles spanning a larger height step (px); None keeps all.
    pixel_size_mm: the object-side size of one pixel of the maps; with it the registered
        TIFFs hold mm (height, local shape) and 1/mm (curvature); None = pixel units.
    image_pixel_size_mm: the same for one pixel of the stored images (as --roi is in
        stored-image pixels); given, it sets ``pixel_size_mm`` to it x
        ``frame.downscale`` (a map pixel is K x K stored ones); not given, it is
        ``pixel_size_mm`` / ``frame.downscale``. Both go into maps.json.
    frame: where the maps sit in the stored images (--roi corner, --downscale K; see
        maps.registered.Frame): recorded in maps.json and the TIFFs' position tags. The
        commands set it from their flags; a caller loading with LoadOptions(roi=...,
        downscale=...) passes it here (the maps cannot know how their stack was cut).
    curvature_sigma, local_size_px (see maps.registered), tiff: as their flags say.
    """

    maps: tuple[str, ...] = flag(
        MAP_NAMES,
        f"which maps, comma-separated from {','.join(MAP_NAMES)}, or one of "
        f"{', '.join(MAP_PRESETS)} (inspect: what msf-inspect reads, no mesh; none: as "
        "--no-maps; default: all)",
        type=parse_maps,
        metavar="LIST",
    )
    integration: str = flag(
        "poisson",
        "normal integration for the height map: poisson (masked least squares, default), "
        "bini (keeps depth discontinuities sharp, slower), fc (Frankot-Chellappa FFT, full "
        "frame)",
        choices=METHODS,
    )
    intrinsics: Intrinsics | tuple[float, float, float, float] | None = flag(
        None,
        "perspective camera (pixels) for the height map; default orthographic",
        type=float,
        nargs=4,
        metavar=("FX", "FY", "CX", "CY"),
    )
    depth_ref: float | None = None
    min_nz: float = DEFAULT_MIN_NZ
    min_shading: float = DEFAULT_MIN_SHADING
    saturation: float | None = None
    curvature_sigma: float = flag(
        DEFAULT_SIGMA,
        "smoothing of the normals before curvature, px (default %(default)g; 0 = none)",
        type=nonnegative_float,
        metavar="PX",
    )
    bini_k: float = 2.0
    bini_max_iter: int = 50
    bini_tol: float = 1e-4
    mesh_max_jump: float | None = None
    pixel_size_mm: float | None = None
    local_size_px: float = flag(
        DEFAULT_LOCAL_SIZE_PX,
        "characteristic size of the local-shape map (height minus its trend at this "
        "size), px of the maps (default %(default)g; at most their longer side)",
        name="--local-size",
        type=positive_float,
        metavar="PX",
    )
    tiff: bool = flag(
        True, "no pixel-registered float32 TIFF maps", name="--no-tiff", action="store_false"
    )
    image_pixel_size_mm: float | None = flag(
        None,
        "object-side size of one pixel of the stored images in mm (as --roi is in "
        "stored-image pixels; with --downscale K a map pixel is K times it): the TIFFs then "
        "hold mm and 1/mm, maps.json records both sizes",
        name="--pixel-size",
        type=positive_float,
        metavar="MM",
    )
    frame: Frame = field(default_factory=Frame)

    def __post_init__(self) -> None:
        if not isinstance(self.frame, Frame):
            raise InputError(f"frame must be a maps.registered.Frame, got {self.frame!r}")
        given = self.image_pixel_size_mm
        if given is not None:
            if not (np.isfinite(given) and given > 0):
                raise InputError(f"image pixel size mm {given}: must be a positive number")
            size = given * self.frame.downscale
            if self.pixel_size_mm is None:
                object.__setattr__(self, "pixel_size_mm", size)
            elif not np.isclose(self.pixel_size_mm, size, rtol=1e-9, atol=0.0):
                raise InputError(
                    f"pixel size {self.pixel_size_mm:g} mm is not the image pixel size "
                    f"{given:g} mm x downscale {self.frame.downscale}: give one of them"
                )
        elif self.pixel_size_mm is not None and np.isfinite(self.pixel_size_mm):
            # only the map pixel given (the API): the stored image's follows from the frame
            object.__setattr__(
                self, "image_pixel_size_mm", self.pixel_size_mm / self.frame.downscale
            )
        for name in ("curvature_sigma", "local_size_px", "pixel_size_mm"):
            v = getattr(self, name)
            if v is None and name == "pixel_size_mm":
                continue
            if v is None or not (
                np.isfinite(v) and (v >= 0 if name == "curvature_sigma" else v > 0)
            ):
                raise InputError(f"{name.replace('_', ' ')} {v}: must be a positive number")
        lo, hi = PIXEL_SIZE_MM
        if self.pixel_size_mm is not None and not lo <= self.pixel_size_mm <= hi:
            # a subnormal size passed as positive, then divided into infinities in the maps
            raise InputError(f"pixel size {self.pixel_size_mm:g} mm: must lie in {lo:g}..{hi:g} mm")
        unknown = [m for m in self.maps if m not in MAP_NAMES]
        if unknown:
            raise InputError(
                f"unknown map(s) {', '.join(map(repr, unknown))}: expected any of "
                f"{', '.join(MAP_NAMES)}"
            )
        if self.integration not in METHODS:
            raise InputError(
                f"integration method {self.integration!r}: expected one of {', '.join(METHODS)}"
            )
        object.__setattr__(self, "maps", tuple(self.maps))
        object.__setattr__(self, "intrinsics", Intrinsics.coerce(self.intrinsics))

    def wants(self, name: str) -> bool:
        return name in self.maps or (name == "height" and "mesh" in self.maps)

    def check_shape(self, shape: tuple[int, int]) -> None:
        """Refuse settings that cannot work on (H, W) maps, before any work: a local size
        above the maps' longer side, intrinsics absurd for the image (a principal point at
        1e308 px ran the whole stack, then failed in the height solve)."""
        if self.wants("height") and self.intrinsics is None:  # the local shape's Gaussian sums
            check_local_size(self.local_size_px, shape)
        intrinsics = Intrinsics.coerce(self.intrinsics)  # __post_init__ made it one
        if intrinsics is not None:
            intrinsics.check_for(shape)


@dataclass
class InspectionMaps:
    """Every map of one run; maps not asked for are None. All (H, W[, 3]) float32.

    mask: (H, W) bool, the pixels that had a usable normal (the maps' domain).
    normals: (H, W, 3) unit normals as given (zeros outside ``mask``).
    albedo: RGB, image units per unit light intensity, NaN outside the mask and, per channel,
        where no observation was kept (all shadowed or at full scale: unknown, not black).
    height: z toward the camera in px (perspective: depth_ref units), min 0 per object part,
        NaN outside. depth: perspective only, depth along the optical axis, NaN outside.
    curvature: mean curvature in 1/px (convex toward the camera > 0), NaN outside;
    gaussian_curvature (1/px^2), shape_index ([-1, 1], NaN where planar), curvedness (1/px).
    gradient_p, gradient_q: dz/d(column), dz/d(row), dimensionless, NaN outside.
    local_shape: height minus its trend at ``options.local_size_px`` (px), NaN outside.
    integration: method, iterations, timing of the height solve. timings: seconds per map.
    """

    mask: np.ndarray
    normals: np.ndarray
    options: MapOptions
    albedo: np.ndarray | None = None
    height: np.ndarray | None = None
    depth: np.ndarray | None = None
    curvature: np.ndarray | None = None
    gaussian_curvature: np.ndarray | None = None
    shape_index: np.ndarray | None = None
    curvedness: np.ndarray | None = None
    gradient_p: np.ndarray | None = None
    gradient_q: np.ndarray | None = None
    local_shape: np.ndarray | None = None
    integration: Integration | None = None
    timings: dict[str, float] = field(default_factory=dict)
    skipped: tuple[str, ...] = ()  # maps asked for that did not fit in --max-memory
    warning: str | None = None  # the one line saying so

    def summary(self) -> dict[str, Any]:
        """JSON-ready facts: options, units, timings, integration details, value ranges."""
        # maps.json keeps the integration's key "method"
        opts = {"method" if k == "integration" else k: v for k, v in asdict(self.options).items()}
        out: dict[str, Any] = {
            "options": opts,
            # map pixel (col, row) is stored-image pixel (x0 + K col + (K-1)/2, y0 + ...)
            "frame": self.options.frame.as_dict(),
            "pixels": int(self.mask.sum()),
            "timings_s": dict(self.timings),
            "units": {
                "albedo": "image units per unit light intensity",
                "height": "px" if self.options.intrinsics is None else "depth_ref units",
                "curvature": "1/px",
                "shape_index": "dimensionless",
            },
            "registered": self.written_units(),
        }
        if self.skipped:
            out["skipped"] = {"maps": list(self.skipped), "why": self.warning}
        if self.integration is not None:
            out["integration"] = {
                "method": self.integration.method,
                "iterations": self.integration.iterations,
                "multigrid_builds": self.integration.builds,
                "seconds": self.integration.seconds,
            }
        if self.height is not None and np.isfinite(self.height).any():
            out["height_range"] = float(np.nanmax(self.height) - np.nanmin(self.height))
        return out

    def registered_units(self) -> dict[str, object]:
        """Every registered map's units and conventions (see maps.registered), computed or
        not; maps.json keeps those of the TIFFs written (:meth:`written_units`)."""
        opts = self.options
        u = Units.of(opts.pixel_size_mm)
        return {
            "pixel_size_mm": opts.pixel_size_mm,  # a map pixel: what every mm value uses
            "image_pixel_size_mm": opts.image_pixel_size_mm,  # a stored-image pixel
            "local_size_px": self.options.local_size_px,
            "curvature_sigma_px": self.options.curvature_sigma,
            "height": u.height,
            "local_shape": u.height,
            "curvature": u.curvature,
            "gaussian_curvature": u.gaussian_curvature,
            "gradient": "dz/dcolumn (p), dz/drow (q), rows down, z to the camera",
            "normals": "x right, y up, z to the camera",
            "outside_mask": OUTSIDE_MASK,
        }

    def written_units(self) -> dict[str, object]:
        """:meth:`registered_units` of the TIFFs :func:`write_maps` writes (none with
        ``tiff=False``; no height or local shape for a perspective run), with their names."""
        written = self.tiff_names()
        units = self.registered_units()
        for key, name in (
            ("height", "height"),
            ("local_shape", "local_shape"),
            ("curvature", "curvature"),
            ("gaussian_curvature", "gaussian_curvature"),
            ("gradient", "gradient_p"),
            ("normals", "normals"),
        ):
            if name not in written:
                del units[key]
        units["files"] = [f"{name}.tif" for name in written]
        return units

    def tiff_names(self) -> list[str]:
        """The maps :func:`write_maps` writes as registered TIFFs (none with ``tiff=False``):
        the physical ones but the normals, which normals.npy holds (gradient_p / gradient_q are
        their TIFF form for other tools). A map with a TIFF gets no .npy copy."""
        return [n for n in self.physical_names() if n != "normals"] if self.options.tiff else []

    def physical(self) -> dict[str, np.ndarray]:
        """The registered data maps in their TIFF units (mm with a pixel size): name -> (H, W)
        or (H, W, 3) float32. Only maps that were computed."""
        return {name: self.physical_map(name) for name in self.physical_names()}

    def physical_names(self) -> list[str]:
        """The names :meth:`physical` gives, without making any of the maps."""
        names = ["normals"]
        if self.gradient_p is not None and self.gradient_q is not None:
            names += ["gradient_p", "gradient_q"]
        if self.height is not None and self.options.intrinsics is None:
            names.append("height")
        for name in ("local_shape", "curvature", "gaussian_curvature", "albedo"):
            if getattr(self, name) is not None:
                names.append(name)
        return names

    def physical_map(self, name: str) -> np.ndarray:
        """One map of :meth:`physical` (made on demand: the writer holds one at a time)."""
        k = self.options.pixel_size_mm or 1.0
        scale = {
            "height": np.float32(k),
            "local_shape": np.float32(k),
            "curvature": np.float32(1.0 / k),
            "gaussian_curvature": np.float32(1.0 / (k * k)),
        }
        values = self.normals if name == "normals" else getattr(self, name)
        if name in scale and scale[name] != 1:
            return np.asarray(values * scale[name], np.float32)
        return np.asarray(values, np.float32)


def compute_maps(
    images: np.ndarray | None,
    lights: np.ndarray | None,
    intensities: np.ndarray | None,
    mask: np.ndarray,
    normals: np.ndarray,
    options: MapOptions | None = None,
    *,
    max_memory_mb: float | None = None,
) -> InspectionMaps:
    """Compute the maps ``options.maps`` asks for.

    images (N, H, W, 3), lights (N, 3), intensities (N, 3): only needed for the albedo.
    mask (H, W) bool; normals (H, W, 3) unit, camera frame (x right, y up, z to the camera).
    Bad input raises InputError (NaN normals in the mask, shape mismatches, missing images for
    the albedo). An empty mask is not an error: albedo, height and curvature all NaN.
    A local size above the maps' longer side is refused before any map is made.
    ``max_memory_mb``: the whole process's budget (see maps.budget): a map whose working set
    does not fit beside what the process holds is skipped before its work starts, named in
    ``skipped`` and in the one-line ``warning``.
    """
    opts = options or MapOptions()
    if opts.wants("albedo") and (images is None or lights is None or intensities is None):
        raise InputError("the albedo needs the images, lights and intensities")
    m = np.asarray(mask, bool)
    opts.check_shape((int(m.shape[0]), int(m.shape[1])))
    lights_n = 0 if images is None else int(images.shape[0])
    budget = MapsBudget(max_memory_mb, int(m.size), int(np.count_nonzero(m)), lights_n)
    wanted = [n for n in ("albedo", "height", "curvature", "mesh") if opts.wants(n)]
    skipped: list[str] = []
    needs: dict[str, float] = {}

    def fits(name: str) -> bool:
        if budget.fits(name, opts.integration):
            return True
        spare = (budget.spare_mb() or 0.0) - budget.write_reserve_mb()
        needs[name] = budget.need_mb(name, opts.integration) - spare
        skipped.append(name)
        return False

    if not fits("base"):  # not even the checked normals: no map at all
        needs.update({n: needs["base"] for n in wanted})
        skipped[:] = wanted
        shape = np.asarray(normals).shape
        maps = InspectionMaps(m, np.asarray(normals, np.float32).reshape(shape), opts)
        maps.skipped = tuple(skipped)
        maps.warning = budget.skipped_line(skipped, needs, every=True)
        return maps
    unit, valid = check_normals(normals, m)
    maps = InspectionMaps(mask=valid, normals=unit.astype(np.float32), options=opts)
    maps.gradient_p, maps.gradient_q = gradients(unit, valid, opts.min_nz)
    if opts.wants("albedo") and fits("albedo"):
        assert images is not None and lights is not None and intensities is not None
        start = time.perf_counter()
        args = (np.asarray(images), lights, intensities, valid, unit)
        chunk = budget.albedo_chunk()
        maps.albedo = checked_albedo(*args, opts.min_shading, opts.saturation, chunk)
        maps.timings["albedo"] = time.perf_counter() - start
    if opts.wants("height") and fits("height"):
        _height_maps(maps, unit, valid)
    elif "mesh" in wanted and "height" in skipped:
        skipped.append("mesh")  # a mesh is the height's
        needs["mesh"] = needs["height"]
    if opts.wants("curvature") and fits("curvature"):
        start = time.perf_counter()
        curv = curvature_maps(unit, valid, sigma=opts.curvature_sigma)
        maps.curvature, maps.gaussian_curvature = curv.mean, curv.gaussian
        maps.shape_index, maps.curvedness = curv.shape_index, curv.curvedness
        maps.timings["curvature"] = time.perf_counter() - start
        del curv
    del unit  # the float64 copy: the writes that follow need room
    if "mesh" in wanted and maps.height is not None:
        fits("mesh")
    if skipped:
        maps.skipped = tuple(skipped)
        maps.warning = budget.skipped_line(skipped, needs, every=False)
    return maps


def _height_maps(maps: InspectionMaps, unit: np.ndarray, valid: np.ndarray) -> None:
    """The height (and depth with intrinsics) and the local shape, into ``maps``."""
    opts = maps.options
    start = time.perf_counter()
    integ = integrate_normals(
        unit,
        valid,
        opts.integration,
        intrinsics=opts.intrinsics,
        depth_ref=opts.depth_ref,
        min_nz=opts.min_nz,
        k=opts.bini_k,
        max_iter=opts.bini_max_iter,
        tol=opts.bini_tol,
    )
    maps.integration, maps.height, maps.depth = integ, integ.height, integ.depth
    maps.timings[f"height ({opts.integration})"] = time.perf_counter() - start
    if opts.intrinsics is None:  # a perspective height is log-depth based: no local shape
        maps.local_shape = local_shape(integ.height, valid, opts.local_size_px)


def stack_maps(
    stack: Stack,
    normals: np.ndarray,
    options: MapOptions | None = None,
    *,
    max_memory_mb: float | None = None,
) -> InspectionMaps:
    """:func:`compute_maps` for a ``msfnet.runtime.stack.Stack`` and its estimated normals."""
    arrays = (stack.images, stack.lights, stack.intensities, stack.mask, normals)
    return compute_maps(*arrays, options, max_memory_mb=max_memory_mb)


ALBEDO_PNG_PERCENTILE = 99.5


def albedo_png(
    albedo: np.ndarray, mask: np.ndarray, percentile: float = ALBEDO_PNG_PERCENTILE
) -> np.ndarray:
    """(H, W, 3) albedo -> 16-bit linear RGB with the ``percentile`` of each pixel's
    brightest channel in the mask at 65535, brighter values clipped (relative; the absolute
    values are in albedo.npy): scaled to the one brightest pixel, a specular speck, the rest
    would be black in a viewer. Zeros outside the mask and where the albedo is unknown (NaN:
    no observation kept), so black there."""
    top = display_level(albedo, mask, percentile)
    scale = 65535.0 / top if top > 0 else 0.0
    img = np.clip(np.rint(np.nan_to_num(albedo) * scale), 0, 65535).astype(np.uint16)
    img[~mask] = 0
    return img


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    import zlib

    return len(data).to_bytes(4, "big") + kind + data + zlib.crc32(kind + data).to_bytes(4, "big")


_AFTER_IHDR = 8 + 25  # the PNG signature, then IHDR: length, type, 13 bytes, CRC


def png_with_text(png: bytes, key: str, text: str) -> bytes:
    """PNG bytes with a tEXt chunk after the header (what a viewer's image properties show)."""
    chunk = _png_chunk(b"tEXt", key.encode("latin-1") + b"\0" + text.encode("latin-1"))
    return png[:_AFTER_IHDR] + chunk + png[_AFTER_IHDR:]


def linear_png(png: bytes, note: str) -> bytes:
    """PNG bytes marked as linear (a gAMA chunk of 1.0: viewers that honour it, browsers
    among them, show the values as light, not as sRGB codes, which look near-black) and
    carrying ``note`` as its Description text."""
    gamma = _png_chunk(b"gAMA", (100000).to_bytes(4, "big"))  # 1 / gamma x 100000
    marked = png[:_AFTER_IHDR] + gamma + png[_AFTER_IHDR:]
    return png_with_text(marked, "Description", note)


ALBEDO_PNG_NOTE = (
    f"relative linear albedo (gamma 1.0): the {ALBEDO_PNG_PERCENTILE:g}th percentile of the "
    "brightest channel in the mask is 65535, brighter pixels clipped; absolute values in "
    "albedo.tif (albedo.npy without TIFFs)"
)


def provenance(profile: Mapping[str, object] | None) -> dict[str, object]:
    """The report header's facts: model, engine, lights file, command and time (from the run's
    profile.json summary where it says)."""
    import sys
    from datetime import datetime, timezone

    p = dict(profile or {})
    inp = p.get("input")
    lights = inp.get("lights") if isinstance(inp, Mapping) else None
    recorded = p.get("provenance")
    if isinstance(recorded, Mapping):  # the run's own record (results/provenance.py)
        from msfnet.runtime.results.provenance import Provenance

        facts: dict[str, object] = dict(Provenance.from_dict(recorded).facts())
        if lights:
            facts["lights"] = lights
        return facts
    engine = " ".join(str(p[k]) for k in ("engine", "precision") if p.get(k))
    return {
        "model": p.get("model") or ("none (least squares)" if p.get("method") == "l2" else "-"),
        "engine": engine or "-",
        "lights": lights or p.get("stack") or "-",
        "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]) if sys.argv else "-",
        "time": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC"),
    }


def height_range_text(value: float, options: MapOptions) -> str:
    """The report's height range with its unit: px (and mm with a pixel size), or the
    perspective height's depth_ref units."""
    if options.intrinsics is not None:
        return f"{value:.4g} depth_ref units"
    text = f"{value:.4g} px"
    if options.pixel_size_mm is not None:
        text += f" ({value * options.pixel_size_mm:.4g} mm)"
    return text


def _npy_writer(arr: np.ndarray) -> Any:
    return lambda tmp: np.save(tmp, np.ascontiguousarray(arr, np.float32))


def _bytes_writer(data: bytes) -> Any:
    return lambda tmp: tmp.write_bytes(data)


Job = tuple[str, Any]  # an output's name and its writer (bytes, or a function of the path)


def write_maps(
    folder: str | Path,
    maps: InspectionMaps,
    *,
    images: np.ndarray | None = None,
    error_deg: np.ndarray | None = None,
    profile: Mapping[str, object] | None = None,
    report: bool = True,
    title: str | None = None,
    rendered: Mapping[str, bytes] | None = None,
) -> list[Path]:
    """Write the computed maps into ``folder`` (created if needed; it may already hold the
    run's normals.npy etc., which are left alone); returns the written paths.

    albedo.png (16-bit linear RGB, relative: see :func:`albedo_png`), height.png (16-bit grey
    view), local_shape.png and curvature.png (signed views); the data once each
    (:meth:`InspectionMaps.tiff_names`): as registered float32 TIFFs, or as .npy (float32, NaN
    outside) without TIFFs or for a perspective height [+ depth.npy]; shape_index.npy;
    mesh.ply; maps.json (options, units, timings) and, with
    ``report``, report.html (inputs from ``images``, normals, maps, ``error_deg`` (H, W) in
    degrees, and the latency table from ``profile``, a profile.json summary).
    ``rendered``: pictures the caller already drew ("normals", "error" PNG bytes), reused
    instead of drawn twice.
    The pictures are rendered in memory first; the data files (TIFFs, mesh) are made one at
    a time as each is written (held one at a time within --max-memory); each goes through
    ``msfnet.common.files.write_atomic``: a failure while drawing writes nothing, and no file
    is ever left half-written.
    """
    import msfnet.runtime.results.maps.pictures as pictures

    folder = Path(folder)
    m = maps.mask
    draw = pictures.can_draw()  # without Pillow no figures, all else written
    figures: list[tuple[str, bytes]] = []
    if images is not None and draw:
        inputs = pictures.png_bytes(pictures.inputs_picture(images, m))
        figures.append(("wide: inputs: maximum over all images and a few of them", inputs))
    done = dict(rendered or {})
    if draw:
        normals = done.get("normals")
        normals = normals or pictures.png_bytes(pictures.normals_picture(maps.normals, m))
        figures.append(("normals", normals))
    jobs, views = _view_jobs(maps, draw)
    figures += views
    jobs += _data_jobs(maps)
    if error_deg is not None and draw:
        error = done.get("error") or pictures.png_bytes(pictures.error_picture(error_deg, m))
        figures.append(("angular error vs ground truth", error))
    summary = maps.summary()
    jobs.append(("maps.json", _bytes_writer(json_text(summary).encode())))
    if report:
        heading = title or f"inspection maps: {folder.name}"
        text = _report_text(maps, summary, figures, profile, draw, heading)
        jobs.append(("report.html", _bytes_writer(text.encode("utf-8"))))
    written = []
    for name, writer in jobs:
        path = folder / name
        if name == "mesh.ply":
            writer(path)  # write_ply goes through write_atomic itself
        else:
            write_atomic(path, writer)
        written.append(path)
    return written


def _view_jobs(maps: InspectionMaps, draw: bool) -> tuple[list[Job], list[tuple[str, bytes]]]:
    """The maps' registered views and data (albedo, height, local shape, curvature) and their
    report figures (with axes and colour bars: only in the report)."""
    import msfnet.runtime.results.maps.pictures as pictures

    m = maps.mask
    jobs: list[Job] = []
    figures: list[tuple[str, bytes]] = []
    tiffs = maps.tiff_names()  # each map's data once: its TIFF, else a .npy
    if maps.albedo is not None:
        png = linear_png(pictures.png_bytes(albedo_png(maps.albedo, m)), ALBEDO_PNG_NOTE)
        jobs.append(("albedo.png", _bytes_writer(png)))
        if "albedo" not in tiffs:
            jobs.append(("albedo.npy", _npy_writer(maps.albedo)))
        if draw:
            figures.append(("albedo", pictures.png_bytes(pictures.albedo_picture(maps.albedo, m))))
    if maps.height is not None:
        units = "px" if maps.options.intrinsics is None else "depth_ref units"
        if draw:
            figure = pictures.png_bytes(pictures.height_picture(maps.height, m, units=units))
            figures.append((f"height ({maps.options.integration})", figure))
        view = described_png(
            pictures.png_bytes(grey16_view(maps.height, m)),
            "height, min..max in the mask stretched to 1..65535, 0 outside; values in height.tif",
        )
        jobs.append(("height.png", _bytes_writer(view)))
        if "height" not in tiffs:
            jobs.append(("height.npy", _npy_writer(maps.height)))
        if maps.depth is not None:
            jobs.append(("depth.npy", _npy_writer(maps.depth)))
    if maps.local_shape is not None:
        if draw:  # the map msf-inspect judges, with its colour bar
            size = maps.options.local_size_px
            drawn = pictures.local_shape_picture(maps.local_shape, m, size)
            figures.append(("local shape", pictures.png_bytes(drawn)))
        rgb, top = signed_view(maps.local_shape, m)
        note = f"local shape, red up / blue down, +-{top:.4g} px full colour; values in .tif"
        jobs.append(
            ("local_shape.png", _bytes_writer(described_png(pictures.png_bytes(rgb), note)))
        )
    if maps.curvature is not None:
        if draw:
            figure = pictures.png_bytes(pictures.curvature_picture(maps.curvature, m))
            figures.append(("mean curvature", figure))
        rgb, top = signed_view(maps.curvature, m)
        note = f"mean curvature, red convex / blue concave, +-{top:.4g} 1/px full colour"
        jobs.append(("curvature.png", _bytes_writer(described_png(pictures.png_bytes(rgb), note))))
        if "curvature" not in tiffs:
            jobs.append(("curvature.npy", _npy_writer(maps.curvature)))
        if maps.shape_index is not None:
            jobs.append(("shape_index.npy", _npy_writer(maps.shape_index)))
    return jobs, figures


def _data_jobs(maps: InspectionMaps) -> list[Job]:
    """The registered TIFFs and the mesh, each made only when its turn to be written comes."""
    from msfnet.runtime.results.maps.mesh import albedo_colors, height_mesh, write_ply

    jobs: list[Job] = []
    reg_units = maps.registered_units()
    placement = tiff_placement(maps.options.frame, maps.options.image_pixel_size_mm)
    for name in maps.tiff_names():
        text = f"msfnet {name} ({reg_units.get(name, 'see maps.json')}), float32, registered"

        def write(tmp: Path, n: str = name, t: str = text) -> None:
            write_tiff(tmp, maps.physical_map(n), t, placement)

        jobs.append((f"{name}.tif", write))
    if "mesh" in maps.options.maps and maps.height is not None and "mesh" not in maps.skipped:
        m = maps.mask

        def mesh_writer(tmp: Path) -> None:
            # built when its turn comes and dropped after: one output held at a time
            assert maps.height is not None
            colors = None if maps.albedo is None else albedo_colors(maps.albedo, m)
            mesh = height_mesh(
                maps.height,
                m,
                normals=maps.normals,
                colors=colors,
                intrinsics=Intrinsics.coerce(maps.options.intrinsics),
                depth=maps.depth,
                max_jump=maps.options.mesh_max_jump,
            )
            write_ply(tmp, mesh)

        jobs.append(("mesh.ply", mesh_writer))
    return jobs


def _report_text(
    maps: InspectionMaps,
    summary: dict[str, Any],
    figures: list[tuple[str, bytes]],
    profile: Mapping[str, object] | None,
    draw: bool,
    title: str,
) -> str:
    import msfnet.runtime.results.maps.pictures as pictures
    from msfnet.runtime.results.maps.report import build_report

    meta: dict[str, object] = {**provenance(profile), "pixels": summary["pixels"]}
    meta["height integration"] = maps.options.integration
    if not draw:
        meta["figures"] = pictures.missing_note()
    if maps.integration is not None:
        meta["integration iterations"] = maps.integration.iterations
    if "height_range" in summary:
        meta["height range"] = height_range_text(summary["height_range"], maps.options)
    return build_report(title, figures, meta=meta, profile=profile, map_seconds=maps.timings)


__all__ = [
    "MAP_NAMES",
    "InspectionMaps",
    "MapOptions",
    "albedo_png",
    "compute_maps",
    "linear_png",
    "png_with_text",
    "stack_maps",
    "write_maps",
]
