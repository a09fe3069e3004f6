"""The contract between an exported msfnet model and the runtime: shapes, constants, metadata.

One place for what the exporter writes and the runtime checks: the input multiple, the light
count the weights were trained with, the ONNX metadata keys and how they are read back.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from msfnet.common.errors import InputError

FORMAT = "msfnet-normals-v1"
INPUT_MULTIPLE = 4  # the network halves H and W once and doubles back: multiples of 4
TRAIN_LIGHTS = 32  # light count of the published weights (sqrt(N / train_lights) scaling)
GRAPHS = ("monolithic", "staged")  # staged: cut at the max-over-lights steps (--staged)

METADATA_KEYS = {
    "format": "msfnet.format",
    "train_lights": "msfnet.train_lights",
    "preprocessing": "msfnet.preprocessing",
    "checkpoint_sha256": "msfnet.checkpoint_sha256",
    "version": "msfnet.version",
    "input_multiple": "msfnet.input_multiple",
    "static_shape": "msfnet.static_shape",
    "precision": "msfnet.precision",
    "graph": "msfnet.graph",
    # written by msf-export for people and tools; the runtime does not read these two
    "variant": "msfnet.variant",  # the export variant's name (msf-export --list-variants)
    "quantization": "msfnet.quantization",  # int8 only: the calibration summary, JSON
}

PREPROCESSING_SPEC = {
    "steps": [
        "images / light_intensity (per light, per RGB channel)",
        "per pixel and channel: divide the N values by their L2 norm over lights (+1e-10)",
        "multiply by sqrt(N / train_lights)",
        "multiply by the object mask; zero-pad H and W to multiples of 4 (bottom/right)",
    ],
    "layout": {
        "images": "float32 (B, N, 3, H, W) RGB",
        "lights": "float32 (B, N, 3) unit, x right, y up, z to the camera",
        "normals": "float32 (B, 3, H, W) unit",
    },
}


@dataclass(frozen=True)
class ModelInfo:
    """What an msfnet model file declares about itself."""

    path: Path
    train_lights: int
    input_multiple: int
    static_shape: tuple[int, int, int] | None  # (N, H, W) for fixed-shape exports
    precision: str
    metadata: dict[str, str]
    staged: bool = False  # cut at the max-over-lights reductions (runtime/engines/staged_loop.py)

    def quantization(self) -> dict[str, object]:
        """An int8 export's calibration summary (msf-export's ``quantise-int8`` pass); empty
        where the file has none or it is unreadable (not JSON, not an object, or nested
        deeper than the JSON reader goes)."""
        text = self.metadata.get(METADATA_KEYS["quantization"], "")
        try:
            summary = json.loads(text) if text else {}
        except (ValueError, RecursionError):
            return {}
        return summary if isinstance(summary, dict) else {}


MAX_TRAIN_LIGHTS = 10_000  # far beyond any rig; a bigger value is a corrupt or crafted file
MAX_STATIC_SIDE = 16_384  # px; a static window beyond this would not fit in memory anyway


def _positive(
    meta: Mapping[str, str], key: str, default: int, path: Path, top: int | None = None
) -> int:
    text = meta.get(METADATA_KEYS[key], str(default))
    try:
        value = int(text)
    except ValueError as exc:
        raise InputError(f"malformed {METADATA_KEYS[key]} metadata {text[:40]!r}", path) from exc
    if value < 1:
        raise InputError(f"{METADATA_KEYS[key]} metadata must be positive, got {value}", path)
    if top is not None and value > top:
        raise InputError(
            f"{METADATA_KEYS[key]} metadata {value} is beyond any msfnet export (at most {top})",
            path,
        )
    return value


def read_model_info(path: Path, meta: Mapping[str, str]) -> ModelInfo:
    """Validate a model's metadata; raise InputError if it is not a (sane) msfnet model."""
    if meta.get(METADATA_KEYS["format"]) != FORMAT:
        raise InputError(
            "not an msfnet model (missing msfnet.format metadata; export it with msf-export)", path
        )
    train_lights = _positive(meta, "train_lights", TRAIN_LIGHTS, path, MAX_TRAIN_LIGHTS)
    multiple = _positive(meta, "input_multiple", INPUT_MULTIPLE, path)
    if INPUT_MULTIPLE % multiple:  # the runtime pads inputs to multiples of INPUT_MULTIPLE
        raise InputError(
            f"model needs inputs padded to multiples of {multiple}; this runtime "
            f"pads to {INPUT_MULTIPLE}",
            path,
        )
    static_text = meta.get(METADATA_KEYS["static_shape"], "")
    try:
        static = tuple(int(v) for v in static_text.split(",")) if static_text else None
    except ValueError as exc:
        raise InputError(f"malformed msfnet.static_shape metadata {static_text!r}", path) from exc
    if static is not None and (
        len(static) != 3
        or min(static) < 1
        or max(static[1:]) > MAX_STATIC_SIDE
        or static[1] % INPUT_MULTIPLE
        or static[2] % INPUT_MULTIPLE
    ):
        raise InputError(
            f"malformed msfnet.static_shape metadata {static_text[:40]!r} (expected "
            f"N,H,W with H and W multiples of {INPUT_MULTIPLE})",
            path,
        )
    graph = meta.get(METADATA_KEYS["graph"], "monolithic")
    if graph not in GRAPHS:
        raise InputError(
            f"unknown msfnet.graph {graph!r} (this msfnet reads "
            f"{' and '.join(GRAPHS)} exports; upgrade msfnet?)",
            path,
        )
    return ModelInfo(
        path,
        train_lights,
        multiple,
        static,  # type: ignore[arg-type]
        meta.get(METADATA_KEYS["precision"], "fp32"),
        dict(meta),
        staged=graph == "staged",
    )


def model_metadata(
    *,
    train_lights: int,
    checkpoint_sha256: str,
    version: str,
    static_shape: tuple[int, int, int] | None,
    precision: str,
    staged: bool,
    variant: str | None = None,
) -> dict[str, str]:
    """The metadata_props an export writes (the inverse of :func:`read_model_info`), in the
    order msf-export writes them. ``variant``: the export variant's name, written last as
    ``msfnet.variant`` when given (every msf-export file has it; the runtime does not need it).
    """
    meta = {
        METADATA_KEYS["format"]: FORMAT,
        METADATA_KEYS["train_lights"]: str(train_lights),
        METADATA_KEYS["preprocessing"]: json.dumps(PREPROCESSING_SPEC),
        METADATA_KEYS["checkpoint_sha256"]: checkpoint_sha256,
        METADATA_KEYS["version"]: version,
        METADATA_KEYS["input_multiple"]: str(INPUT_MULTIPLE),
        METADATA_KEYS["static_shape"]: ""
        if static_shape is None
        else ",".join(str(v) for v in static_shape),
        METADATA_KEYS["precision"]: precision,
        METADATA_KEYS["graph"]: "staged" if staged else "monolithic",
    }
    if variant is not None:
        meta[METADATA_KEYS["variant"]] = variant
    return meta
