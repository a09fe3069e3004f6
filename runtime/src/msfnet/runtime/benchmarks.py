"""Public benchmarks: their evaluation protocol and the published figures to compare against.

DiLiGenT (Shi et al., CVPR 2016): 96 lights per object; bear's first 20 images are corrupted and
the standard protocol (the MSF-Net paper's too) uses images 21-96. Published mean angular errors
(deg) for the objects we validate on, as listed in the data's SOURCE.md.
"""

from __future__ import annotations

PROTOCOL_SELECT = {"bearPNG": "21-96"}  # object folder -> the images the benchmark uses

PUBLISHED_MAE: dict[str, dict[str, float]] = {
    "ballPNG": {"L2 (paper)": 4.10, "PS-FCN": 2.67, "MSF-Net (paper)": 2.27},
    "bearPNG": {"L2 (paper)": 8.39, "PS-FCN": 7.72, "MSF-Net (paper)": 4.60},
    "harvestPNG": {"L2 (paper)": 30.62, "PS-FCN": 12.39, "MSF-Net (paper)": 10.80},
}
PUBLISHED_METHODS = ("PS-FCN", "MSF-Net (paper)")


__all__ = ["PROTOCOL_SELECT", "PUBLISHED_MAE", "PUBLISHED_METHODS"]
