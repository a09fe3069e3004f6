"""runtime.contract: the metadata an export writes (``model_metadata``, which msf-export's
metadata pass calls) and how the runtime reads it back (``read_model_info``)."""

from __future__ import annotations

from pathlib import Path

import pytest

from msfnet.runtime.api import default_model_path
from msfnet.runtime.contract import (
    FORMAT,
    INPUT_MULTIPLE,
    METADATA_KEYS,
    model_metadata,
    read_model_info,
)


@pytest.mark.parametrize(("static", "staged"), [(None, False), (None, True), ((5, 16, 20), False)])
def test_read_model_info_inverts_model_metadata(static, staged) -> None:
    meta = model_metadata(
        train_lights=16,
        checkpoint_sha256="ab" * 32,
        version="9.9",
        static_shape=static,
        precision="int8-qdq",
        staged=staged,
        variant="some-variant",
    )
    info = read_model_info(Path("m.onnx"), meta)
    assert (
        info.train_lights,
        info.input_multiple,
        info.static_shape,
        info.precision,
        info.staged,
    ) == (16, INPUT_MULTIPLE, static, "int8-qdq", staged)
    assert info.metadata == meta
    assert meta[METADATA_KEYS["format"]] == FORMAT
    assert meta[METADATA_KEYS["static_shape"]] == ("" if static is None else "5,16,20")
    assert list(meta)[-1] == "msfnet.variant" and meta["msfnet.variant"] == "some-variant"


def test_variant_key_only_when_given() -> None:
    meta = model_metadata(
        train_lights=32,
        checkpoint_sha256="0" * 64,
        version="test",
        static_shape=None,
        precision="fp32",
        staged=False,
    )
    assert "msfnet.variant" not in meta
    assert list(meta) == [
        METADATA_KEYS[k]
        for k in (
            "format",
            "train_lights",
            "preprocessing",
            "checkpoint_sha256",
            "version",
            "input_multiple",
            "static_shape",
            "precision",
            "graph",
        )
    ]


def test_bundled_model_carries_exactly_what_model_metadata_builds() -> None:
    """The bundled file was written before the exporter called model_metadata: the builder must
    reproduce its keys, order and values, and read the same."""
    onnx = pytest.importorskip("onnx")
    path = default_model_path()
    proto = onnx.load(str(path), load_external_data=False)
    meta = {p.key: p.value for p in proto.metadata_props}
    built = model_metadata(
        train_lights=32,
        checkpoint_sha256=meta["msfnet.checkpoint_sha256"],
        version=meta["msfnet.version"],
        static_shape=None,
        precision="fp32 (fp16-stored weights)",
        staged=True,
        variant="staged-fp16",
    )
    assert list(built.items()) == list(meta.items())
    assert read_model_info(path, built) == read_model_info(path, meta)


@pytest.mark.parametrize(
    ("text", "want"),
    [
        ('{"reduce_range": true, "ranges_from_percentiles": 24}', {"reduce_range": True}),
        ("", {}),  # an fp32 export: no summary
        ("{not json", {}),
        ("[1, 2]", {}),  # JSON, but not an object
        ("[" * 100_000, {}),  # deeper than the JSON reader goes (RecursionError)
    ],
)
def test_quantization_summary_is_read_once_for_every_reader(text: str, want: dict) -> None:
    from msfnet.runtime.contract import ModelInfo

    meta = {METADATA_KEYS["quantization"]: text} if text else {}
    got = ModelInfo(Path("m.onnx"), 32, 4, None, "int8-qdq", meta).quantization()
    assert {k: got[k] for k in want} == want and (want or got == {})
