"""What an msfnet ONNX file declares about itself (metadata_props), read without torch."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from .errors import InputError

METADATA_KEYS = {
    "format": "msfnet.format",
    "train_lights": "msfnet.train_lights",
    "preprocessing": "msfnet.preprocessing",
    "checkpoint_sha256": "msfnet.checkpoint_sha256",
    "version": "msfnet.version",
    "input_multiple": "msfnet.input_multiple",
    "static_shape": "msfnet.static_shape",
    "precision": "msfnet.precision",
    "graph": "msfnet.graph",  # "staged" for msf-export --staged, absent/"monolithic" otherwise
}

PREPROCESSING_SPEC = {
    "steps": [
        "images / light_intensity (per light, per RGB channel)",
        "per pixel and channel: divide the N values by their L2 norm over lights (+1e-10)",
        "multiply by sqrt(N / train_lights)",
        "multiply by the object mask; zero-pad H and W to multiples of 4 (bottom/right)",
    ],
    "layout": {"images": "float32 (B, N, 3, H, W) RGB", "lights": "float32 (B, N, 3) unit, "
               "x right, y up, z to the camera", "normals": "float32 (B, 3, H, W) unit"},
}


@dataclass(frozen=True)
class ModelInfo:
    path: Path
    train_lights: int
    input_multiple: int
    static_shape: tuple[int, int, int] | None  # (N, H, W) for fixed-shape exports
    precision: str
    metadata: dict[str, str]
    staged: bool = False  # cut at the max-over-lights reductions (runtime/staged.py)


def model_info_from_metadata(path: Path, meta: dict[str, str]) -> ModelInfo:
    """Validate the metadata of a loaded session; raise InputError if not an msfnet model."""
    if meta.get(METADATA_KEYS["format"]) != "msfnet-normals-v1":
        raise InputError("not an msfnet model (missing msfnet.format metadata; export it with "
                         "msf-export)", path)
    try:
        train_lights = int(meta.get(METADATA_KEYS["train_lights"], "32"))
        multiple = int(meta.get(METADATA_KEYS["input_multiple"], "4"))
        static_text = meta.get(METADATA_KEYS["static_shape"], "")
        static = tuple(int(v) for v in static_text.split(",")) if static_text else None
    except ValueError as exc:
        raise InputError(f"malformed msfnet metadata ({exc})", path) from exc
    graph = meta.get(METADATA_KEYS["graph"], "monolithic")
    if graph not in ("monolithic", "staged"):
        raise InputError(f"unknown msfnet.graph {graph!r} (this msfnet reads monolithic and "
                         "staged exports; upgrade msfnet?)", path)
    return ModelInfo(path, train_lights, multiple, static,  # type: ignore[arg-type]
                     meta.get(METADATA_KEYS["precision"], "fp32"), dict(meta),
                     staged=graph == "staged")

