"""``Result``: everything one run produced, as arrays, and the folder it is saved as.

The folder: normals.npy (H x W x 3 float32, camera frame, zeros outside the mask) and its
picture normals_view.png, profile.json (with ``SaveOptions(normals_png=True)`` normals.png too,
:func:`~msfnet.runtime.results.outputs.normals_png`: the same normals, 16-bit); with ground truth
metrics.json (NormalMetrics) and error.png (angular error with a colour bar, automatic range,
blank where not scored); the inspection maps and report.html when computed. Written all
together through :func:`msfnet.common.files.staged_folder`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Literal, overload

import numpy as np

from msfnet.common.errors import InputError
from msfnet.common.files import json_text, staged_folder
from msfnet.common.vocabulary import flag, options_type
from msfnet.runtime.engines.method import RunMethod
from msfnet.runtime.evaluate.metrics import NormalMetrics
from msfnet.runtime.infer.tiling import TilePlan
from msfnet.runtime.results.maps import InspectionMaps
from msfnet.runtime.results.outputs import normals_png, write_rgb_png
from msfnet.runtime.results.profile import BatchStats, Profile
from msfnet.runtime.results.provenance import Provenance
from msfnet.runtime.stack import Stack

if TYPE_CHECKING:
    from matplotlib.figure import Figure


@options_type
@dataclass(frozen=True)
class SaveOptions:
    """What a result folder holds beyond the normals (normals.npy and their picture), the
    profile and the maps: report.html, and the normals a second time as a 16-bit PNG."""

    report: bool = flag(True, "no report.html", name="--no-report", action="store_false")
    normals_png: bool = flag(
        False,
        "also write normals.png, the normals as 16-bit RGB (n + 1) / 2 (as benchmarks store "
        "them; normals.npy holds the same in float32)",
        action="store_true",
    )


@contextmanager
def _needs_matplotlib() -> Iterator[None]:
    """``plot(figure=True)`` wraps the picture in a matplotlib Figure, an optional extra: its
    absence is one InputError naming the extra (as a missing engine is), not a bare
    ModuleNotFoundError."""
    try:
        yield
    except ModuleNotFoundError as exc:
        if (exc.name or "").partition(".")[0] != "matplotlib":
            raise
        from msfnet.common.cli import install_hint

        raise InputError(
            f"plot(figure=True) needs matplotlib, which is not installed: "
            f"{install_hint('matplotlib')}"
        ) from exc


@dataclass
class Result:
    """Everything one run produced, as arrays; serialised only by :meth:`save`."""

    stack: Stack
    normals: np.ndarray  # (H, W, 3) float32 unit normals, zeros outside the mask
    method: RunMethod  # what ran (Model.describe())
    timings: Profile
    metrics: NormalMetrics | None = None  # with ground truth
    error_deg: np.ndarray | None = None  # (H, W) angular error, NaN where not scored
    plan: TilePlan | None = None
    maps: InspectionMaps | None = None  # albedo, height, curvature, ... (Model(maps=...))
    input: dict[str, object] | None = None  # how the stack was read (LoadOptions.describe())
    batch: BatchStats | None = None  # set by a batch run

    def profile(self) -> dict[str, object]:
        """Latency per stage, memory, work done and what ran: profile.json's content."""
        h, w = self.stack.shape
        info: dict[str, object] = {
            **self.method.as_json(),
            "stack": str(self.stack.source or self.stack.name),
            "lights": self.stack.num_lights,
            "height": h,
            "width": w,
            "mask_pixels": int(self.stack.mask.sum()),
        }
        if self.plan is not None:
            p = self.plan
            info["tiles"] = {
                "run": len(p.tiles),
                "skipped": p.skipped,
                "tile_px": p.tile_size,
                "halo_px": p.halo,
                "pixels_computed": p.pixels,
                "overhead_vs_image": p.pixels / float(h * w),
            }
        if self.input is not None:
            info["input"] = self.input
        if self.stack.warnings:  # a stack that loads but looks wrong: kept with the result
            info["warnings"] = list(self.stack.warnings)
        if self.batch is not None:
            info["batch"] = self.batch.as_dict()
        return {**self.timings.summary(), **info}

    @property
    def auto_mask(self) -> bool:
        """Whether the mask was computed from the images (``--auto-mask``)."""
        return self.input is not None and bool(self.input.get("auto_mask"))

    def save(
        self,
        folder: str | Path,
        *,
        overwrite: bool = False,
        inputs: tuple[Path, ...] = (),
        write_mask: bool | None = None,
        options: SaveOptions | None = None,
    ) -> list[Path]:
        """Write normals.npy, their picture, profile.json and, with ground truth, metrics.json
        and error.png into ``folder``, all at once or not at all; mask.png too when the mask was
        computed (``write_mask``: None = only then); the maps and report.html when computed
        (``options``: SaveOptions). Returns the files written."""
        from msfnet.common.files import check_output
        from msfnet.runtime.stack import linked_reads

        folder = Path(folder)
        src = tuple(p for p in (self.stack.source, *inputs) if p is not None)
        # the files given in place of the stack's own (LoadOptions lights=, intensities=,
        # mask=) were read too: an --overwrite of the folder holding one deleted it
        given = self.input or {}
        src += tuple(Path(str(given[k])) for k in ("lights", "intensities", "mask") if given.get(k))
        # and what the stack read from elsewhere, through links
        reads = linked_reads(self.stack.source) if self.stack.source is not None else []
        check_output(folder, src, overwrite=overwrite, folder=True, reads=reads)
        # an automatic mask is a result the user should be able to inspect and reuse
        mask = self.auto_mask if write_mask is None else write_mask
        return write_result(self, folder, overwrite=overwrite, options=options, write_mask=mask)

    # ------------------------------------------------------------ for a person or a log

    @property
    def name(self) -> str:
        return self.stack.name

    def _what_ran(self) -> str:
        m = self.method
        return "least squares" if m.method == "l2" else f"msf {m.engine} {m.precision}"

    def summary(self) -> str:
        """One line: what ran on which stack, the score with ground truth, and the time."""
        h, w = self.stack.shape
        parts = [
            f"{self.name}: {self.stack.num_lights} lights, {w}x{h}, "
            f"{int(self.stack.mask.sum()):,} px in the mask",
            self._what_ran(),
        ]
        if self.metrics is not None:
            m = self.metrics
            parts.append(
                f"MAE {m.mae_deg:.2f} deg (median {m.median_deg:.2f}, err15 {m.err15 * 100:.1f} %)"
            )
        parts.append(f"{self.timings.median_s('total'):.2f} s")
        if self.stack.warnings:
            parts.append(f"{len(self.stack.warnings)} warning(s)")
        return "; ".join(parts)

    def as_dict(self) -> dict[str, object]:
        """Everything but the arrays, as plain JSON types: profile.json's content, the metrics
        and the maps' summary."""
        out: dict[str, object] = {"name": self.name, **self.profile()}
        out["metrics"] = None if self.metrics is None else self.metrics.as_dict()
        if self.maps is not None:
            out["maps"] = self.maps.summary()
        return out

    def to_json(self, indent: int | None = 2) -> str:
        """:meth:`as_dict` as JSON text (one line with ``indent=None``, for a log)."""
        return json_text(self.as_dict(), indent).rstrip("\n")

    @overload
    def plot(self, what: str = ..., *, figure: Literal[False] = ...) -> np.ndarray: ...
    @overload
    def plot(self, what: str = ..., *, figure: Literal[True]) -> Figure: ...
    @overload
    def plot(self, what: str = ..., *, figure: bool) -> np.ndarray | Figure: ...
    def plot(self, what: str = "normals", *, figure: bool = False) -> np.ndarray | Figure:
        """A picture of the result: an (h, w, 3) uint8 RGB array (cropped to the object, with
        a colour bar where it has a scale), or with ``figure=True`` a matplotlib Figure
        showing it. ``what``: "normals" (with the colour-convention sphere), "error"
        (angular error; needs ground truth), or a computed map: "albedo", "height",
        "curvature". Drawn with numpy, OpenCV and Pillow (results.maps.pictures); only
        ``figure=True`` needs matplotlib (the ``[pictures]`` extra): without it, an InputError
        that says how to install it."""
        with _needs_matplotlib():
            rgb = self._picture(what)
            if not figure:
                return rgb
            from matplotlib.backends.backend_agg import FigureCanvasAgg
            from matplotlib.figure import Figure

        h, w = rgb.shape[:2]
        fig = Figure(figsize=(w / 100, h / 100), dpi=100)
        FigureCanvasAgg(fig)
        ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
        ax.imshow(rgb)
        ax.set_axis_off()
        return fig

    def _picture(self, what: str) -> np.ndarray:
        from msfnet.runtime.results.maps import pictures

        mask = self.stack.mask
        if what == "normals":
            return pictures.normals_picture(self.normals, mask)
        if what == "error":
            if self.error_deg is None:
                raise InputError(
                    f"plot('error'): {self.name} has no ground truth, so no error to show"
                )
            return pictures.error_picture(self.error_deg, mask)
        drawers: dict[str, Callable[[np.ndarray, np.ndarray], np.ndarray]] = {
            "albedo": pictures.albedo_picture,
            "height": pictures.height_picture,
            "curvature": pictures.curvature_picture,
        }
        if what not in drawers:
            raise InputError(
                f"plot({what!r}): expected one of normals, error, {', '.join(drawers)}"
            )
        values = None if self.maps is None else getattr(self.maps, what, None)
        if values is None:
            raise InputError(
                f"plot({what!r}): no {what} map was computed: Model(maps={what!r}) or "
                "Model(maps=msfnet.MapOptions(...)) chooses the maps; maps=None computes none"
            )
        return drawers[what](values, mask)

    def __repr__(self) -> str:
        # the arrays (and the stack's images) stay out: a repr is for a console line
        h, w = self.stack.shape
        score = "" if self.metrics is None else f", mae_deg={self.metrics.mae_deg:.2f}"
        maps = "" if self.maps is None else f", maps={list(self.maps.options.maps)}"
        return (
            f"Result({self.name!r}, {w}x{h}, lights={self.stack.num_lights}, "
            f"{self._what_ran()}{score}{maps}, total_s={self.timings.median_s('total'):.2f})"
        )

    def without_images(self) -> Result:
        """A copy whose stack no longer holds the images (N x H x W x 0: shape and light count
        kept), to keep or ship many results (a batch, a Ray task) without their inputs."""
        n, h, w = self.stack.images.shape[:3]
        stack = replace(self.stack, images=np.empty((n, h, w, 0), np.float32))
        return replace(self, stack=stack)


def fill_result_folder(folder: Path, result: Result, options: SaveOptions | None = None) -> None:
    """Write a result's files into an (empty, staging) folder: the normals as data and as a
    picture with a colour-convention sphere, metrics and an error picture with a colour bar
    (automatic range) when there is ground truth, the profile, and the inspection maps with
    report.html when they were computed."""
    from msfnet.runtime.results.maps import pictures, write_maps

    o = options or SaveOptions()
    mask = result.stack.mask
    profile = result.profile()  # and where it came from, for profile.json and report.html
    src = result.stack.source or result.stack.name
    profile["provenance"] = Provenance.of(src, result.method).as_dict()
    np.save(folder / "normals.npy", np.ascontiguousarray(result.normals, np.float32))
    # the figures need Pillow (their text); without it everything else is written, and the
    # 16-bit normals.png is the normals' picture
    draw = pictures.can_draw()
    if o.normals_png or not draw:
        write_rgb_png(folder / "normals.png", normals_png(result.normals, mask))
    rendered: dict[str, bytes] = {}
    if draw:
        rendered["normals"] = pictures.png_bytes(pictures.normals_picture(result.normals, mask))
        (folder / "normals_view.png").write_bytes(rendered["normals"])
    if result.metrics is not None and result.error_deg is not None:
        metrics: dict[str, object] = dict(result.metrics.as_dict())
        if draw:
            vmax = pictures.error_range(result.error_deg, mask)
            metrics["error_png_max_deg"] = vmax
            drawn = pictures.error_picture(result.error_deg, mask, vmax=vmax)
            rendered["error"] = pictures.png_bytes(drawn)
            (folder / "error.png").write_bytes(rendered["error"])
        (folder / "metrics.json").write_text(json_text(metrics))
    (folder / "profile.json").write_text(json_text(profile))
    if result.maps is not None:
        images = result.stack.images if result.stack.images.shape[-1] == 3 else None
        # the report shows the same two pictures: drawn once (a map's mask equals the stack's)
        write_maps(
            folder,
            result.maps,
            images=images,
            error_deg=result.error_deg,
            profile=profile,
            report=o.report,
            title=f"msfnet: {result.stack.name}",
            rendered=rendered,
        )


def write_result(
    result: Result,
    outdir: Path,
    *,
    overwrite: bool = False,
    options: SaveOptions | None = None,
    write_mask: bool = False,
) -> list[Path]:
    """Write every result file (``write_mask``: mask.png too), or none of them. Returns the
    final paths."""
    with staged_folder(outdir, overwrite=overwrite) as tmp:
        fill_result_folder(tmp, result, options=options)
        if write_mask:
            write_rgb_png(tmp / "mask.png", result.stack.mask.astype(np.uint8) * 255)
        names = sorted(p.name for p in tmp.iterdir())
    return [outdir / n for n in names]


__all__ = ["Result", "SaveOptions", "fill_result_folder", "write_result"]
