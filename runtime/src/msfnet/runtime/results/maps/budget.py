"""The inspection maps within ``--max-memory``: the whole process's peak, as least squares.

Before each map is computed, what the process holds now (resident memory) plus that map's
working set, estimated from the image size and the mask, must fit in the budget; a map that
does not fit is skipped before any of its work, and the run says so in one warning line (the
normals and the maps that fit are still written). The albedo is solved in chunks of pixels
sized to what is left.

The working sets below bound the peak resident growth measured per stage (docs/benchmark.md).
"""

from __future__ import annotations

from dataclasses import dataclass

from msfnet.common.vocabulary import declare, opt, verbatim
from msfnet.runtime.instrument import memory_in_use_mb
from msfnet.runtime.results.maps.albedo import BYTES_PER_PIXEL_LIGHT, CHUNK_PIXELS, MIN_CHUNK_PIXELS

# --no-maps: Model(maps=None) from Python (that text is its keyword)
declare("maps=None", "--no-maps")
# ModelOptions' --max-memory (this module sees no options type that holds it)
declare("max_memory_mb", "--max-memory")

MB = 2**20
# bytes per image pixel (H x W) and per mask pixel of each stage's working set
BASE_PER_PIXEL = 64  # check_normals (float64 unit normals, norms) + float32 normals, p, q
HEIGHT_FIXED_MB = 100
HEIGHT_PER_PIXEL = {"poisson": 40, "bini": 40, "fc": 560}
HEIGHT_PER_MASK_PIXEL = {"poisson": 560, "bini": 620, "fc": 0}
CURVATURE_PER_PIXEL = 150
MESH_PER_MASK_PIXEL = 120
ALBEDO_OUT_PER_PIXEL = 12
# what writing the results takes after the maps: Pillow's drawing, its font and the first
# pictures, and the largest one-at-a-time output's temporaries (the 16-bit normals picture)
WRITE_RESERVE_MB = 20
WRITE_PER_PIXEL = 32


@dataclass(frozen=True)
class MapsBudget:
    """The process budget in MB (None: no limit) and the stack's size."""

    max_memory_mb: float | None
    pixels: int  # H x W
    mask_pixels: int
    lights: int

    def need_mb(self, name: str, integration: str = "poisson") -> float:
        """The working set of one map (or "base": the checks all maps share) in MB."""
        p, m = self.pixels, self.mask_pixels
        if name == "base":
            return BASE_PER_PIXEL * p / MB
        if name == "albedo":
            return (
                ALBEDO_OUT_PER_PIXEL * p + MIN_CHUNK_PIXELS * self.lights * BYTES_PER_PIXEL_LIGHT
            ) / MB
        if name == "height":
            need = HEIGHT_PER_PIXEL[integration] * p + HEIGHT_PER_MASK_PIXEL[integration] * m
            return HEIGHT_FIXED_MB + need / MB
        if name == "curvature":
            return CURVATURE_PER_PIXEL * p / MB
        if name == "mesh":
            return MESH_PER_MASK_PIXEL * m / MB
        raise ValueError(name)

    def write_reserve_mb(self) -> float:
        """Kept free for writing the results once the maps are computed."""
        import sys

        drawn = "PIL.ImageDraw" in sys.modules  # imported by the first picture drawn
        return (0.0 if drawn else WRITE_RESERVE_MB) + WRITE_PER_PIXEL * self.pixels / MB

    def spare_mb(self) -> float | None:
        """What the budget leaves beside what the process holds now (None: no limit, or the
        resident memory cannot be read)."""
        if self.max_memory_mb is None:
            return None
        rss = memory_in_use_mb()
        return None if rss is None else self.max_memory_mb - rss

    def fits(self, name: str, integration: str = "poisson") -> bool:
        spare = self.spare_mb()
        return spare is None or self.need_mb(name, integration) + self.write_reserve_mb() <= spare

    def albedo_chunk(self) -> int:
        """Pixels per albedo chunk: as many as the spare budget allows, at most CHUNK_PIXELS."""
        spare = self.spare_mb()
        if spare is None:
            return CHUNK_PIXELS
        room = (spare - self.write_reserve_mb()) * MB - ALBEDO_OUT_PER_PIXEL * self.pixels
        room /= max(self.lights * BYTES_PER_PIXEL_LIGHT, 1)
        return int(min(max(room, MIN_CHUNK_PIXELS), CHUNK_PIXELS))

    def skipped_line(self, names: list[str], needs: dict[str, float], every: bool) -> str:
        """The one warning line naming what was skipped, how much more it needed and the
        budget (``every``: not even the maps' shared start fitted)."""
        budget = opt("max_memory_mb", verbatim(f"{self.max_memory_mb:g}"))
        if every:
            return (
                f"{budget} MB leaves too little for the inspection maps: "
                f"skipped {', '.join(names)} (~{max(needs.values()):.0f} MB more needed); "
                f"the normals are written (raise {opt('max_memory_mb')}, or use {opt('maps=None')})"
            )
        said = ", ".join(f"{n} (~{needs[n]:.0f} MB more needed)" for n in names)
        return (
            f"{budget} MB: skipped the {said}; the normals and the other maps are written "
            f"(raise {opt('max_memory_mb')}, or choose {opt('maps')})"
        )


__all__ = ["MapsBudget"]
