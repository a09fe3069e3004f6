"""Draw docs/img/inspection.png: the inspection flow on a rendered matte plate.

    python scripts/inspection_figure.py [OUT.png]

Panels (each the input's size, shown 2x): the brightest input per pixel, the default path's
normals (mask cut at the right: the surface goes on), its local shape (registered
local_shape.png), and msf-inspect's overlay (regions outlined and numbered; the printed marks,
dark, are not flagged). Deterministic: the plate is seed 0.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from msfnet.common.files import write_atomic
from msfnet.common.imageio import encode_png
from msfnet.runtime.api import Model
from msfnet.runtime.inspection.defects import (
    DefectOptions,
    find_defects,
    from_maps,
    overlay_picture,
)
from msfnet.runtime.results.maps import MapOptions
from msfnet.runtime.results.maps.registered import signed_view
from msfnet.synth.plates import PlateOptions, render_plate

SCALE = 2


def _panel(rgb: np.ndarray, title: str) -> np.ndarray:
    big = cv2.resize(rgb, None, fx=SCALE, fy=SCALE, interpolation=cv2.INTER_NEAREST)
    head = np.full((22, big.shape[1], 3), 255, np.uint8)
    cv2.putText(head, title, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([head, big], axis=0)


def main(out: Path) -> None:
    plate = render_plate(PlateOptions(seed=0))
    st = plate.stack
    result = Model(threads=2, maps=MapOptions(maps=("albedo", "height", "curvature")))(st)
    assert result.maps is not None
    part = from_maps(result.maps, "plate")
    verdict, labels = find_defects(part, DefectOptions(depth=0.06))
    peak = st.images.max(axis=0).astype(np.float32)
    peak = np.clip(peak / np.percentile(peak, 99.5) * 255, 0, 255).astype(np.uint8)
    normals = np.where(st.mask[..., None], (result.normals + 1) * 127.5, 40).astype(np.uint8)
    local, top = signed_view(part.local_shape, part.mask)
    panels = [
        _panel(peak, "input (max over 12 lights)"),
        _panel(normals, "normals (mask cut at right)"),
        _panel(local, f"local shape +-{top:.2f} px"),
        _panel(overlay_picture(part, labels), f"msf-inspect: {len(verdict.regions)} defects"),
    ]
    gap = np.full((panels[0].shape[0], 6, 3), 255, np.uint8)
    spaced = [p for pair in zip(panels, [gap] * 4, strict=True) for p in pair][:-1]
    row = np.concatenate(spaced, axis=1)
    write_atomic(out, lambda tmp: encode_png(tmp, row))
    print(f"{out}: {row.shape[1]}x{row.shape[0]}, {len(verdict.regions)} regions")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("docs/img/inspection.png"))
