"""Checkpoint -> ONNX with a dynamic light count, metadata, and self-verification.

The ONNX contract (also in the README):
  inputs   images  float32 (B, N, 3, H, W)  normalised as msfnet.runtime.preprocess.normalise
           lights  float32 (B, N, 3)        unit directions, x right, y up, z to the camera
  output   normals float32 (B, 3, H, W)     unit normals, same frame
  N, H, W (and B) are dynamic unless exported --static; H and W must be multiples of 4.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
import torch

import msfnet
from msfnet.model.checkpoint import load_model, sha256_of
from msfnet.runtime.contract import METADATA_KEYS, PREPROCESSING_SPEC
from msfnet.runtime.errors import InputError
from msfnet.runtime.metrics import angular_error_deg

DEFAULT_OPSET = 17  # TorchScript exporter: GELU as Erf, runs on older runtimes (OpenVINO 2022)
TOLERANCE_DEG = 0.01
EXAMPLE_SHAPE = (2, 4, 24, 20)  # B, N, H, W of the tracing example: differs from every check


@dataclass(frozen=True)
class StaticShape:
    lights: int
    height: int
    width: int

    @classmethod
    def parse(cls, text: str) -> StaticShape:
        try:
            n, h, w = (int(v) for v in text.split(","))
        except ValueError as exc:
            raise InputError(f"--static {text!r}: expected N,H,W such as 32,128,128") from exc
        if n < 1 or h < 4 or w < 4 or h % 4 or w % 4:
            raise InputError(f"--static {text!r}: need N >= 1 and H, W positive multiples of 4")
        return cls(n, h, w)


def random_inputs(batch: int, lights: int, height: int, width: int,
                  seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Plausible network inputs: positive normalised images and upper-hemisphere unit lights."""
    rng = np.random.default_rng(seed)
    images = rng.random((batch, lights, 3, height, width), dtype=np.float32)
    images *= np.float32(np.sqrt(1.0 / 32.0))  # about the scale normalise() produces
    dirs = rng.normal(size=(batch, lights, 3))
    dirs[..., 2] = np.abs(dirs[..., 2]) + 0.5
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    return images, dirs.astype(np.float32)


def rendered_inputs(batch: int, lights: int, height: int, width: int,
                    seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Network inputs from rendered non-Lambertian objects, normalised exactly as the runtime
    does, and their object masks (B, H, W): what a real stack looks like to the network.

    Only object pixels are compared: in the empty background a trained network's raw output is
    a near-zero vector whose direction is ill-conditioned (measured: ~0.5 against a median of
    ~100 before normalisation), and the runtime zeroes those pixels anyway."""
    from msfnet.runtime.preprocess import normalise
    from msfnet.synth.render import RenderOptions, render_stack

    images = np.empty((batch, lights, 3, height, width), np.float32)
    dirs = np.empty((batch, lights, 3), np.float32)
    masks = np.empty((batch, height, width), bool)
    options = RenderOptions(size=max(height, width), lights=lights)
    for b in range(batch):
        stack = render_stack(np.random.default_rng([seed, b]), options)
        crop = stack.images[:, :height, :width]
        images[b] = normalise(crop, stack.intensities, stack.mask[:height, :width])
        dirs[b] = stack.lights
        masks[b] = stack.mask[:height, :width]
    return images, dirs, masks


def _torch_export_staged(model: torch.nn.Module, path: Path, opset: int) -> None:
    """The staged graph (see ``staged.py``): each entry point with its own dynamic axes, so a
    call can feed small placeholders to the entry points it does not use."""
    from msfnet.runtime.chunked import FEATURES, STAGE_INPUTS, STAGE_OUTPUTS

    from .staged import StagedGraph

    _, n, h, w = EXAMPLE_SHAPE
    images, lights = (torch.from_numpy(a) for a in random_inputs(1, n, h, w))
    # Tracing example: every light count > 1 and every size distinct, or the exporter
    # specialises size-1 axes (measured: a placeholder-sized example broke the fusion reshape).
    gen = torch.Generator().manual_seed(0)
    example = {"images": images, "lights": lights}
    c = FEATURES
    for name, shape in (("feat1_in", (3, c, 6, 5)), ("max1", (1, c, 6, 5)),
                        ("feat2_in", (2, c, 5, 7)), ("max2", (1, c, 5, 7)),
                        ("max3", (1, c, 6, 4))):
        example[name] = torch.rand(shape, generator=gen)
    feat = {0: "lights", 2: "half_height", 3: "half_width"}
    pooled = {2: "half_height", 3: "half_width"}
    dynamic = {
        "images": {1: "lights1", 3: "height", 4: "width"}, "lights": {1: "lights1"},
        "feat1": {0: "lights1", 2: "height_2", 3: "width_2"},
        "feat1_in": {k: f"{v}_s2" for k, v in feat.items()},
        "max1": {k: f"{v}_s2" for k, v in pooled.items()},
        "feat2": {k: f"{v}_s2" for k, v in feat.items()},
        "feat2_in": {k: f"{v}_s3" for k, v in feat.items()},
        "max2": {k: f"{v}_s3" for k, v in pooled.items()},
        "feat3": {k: f"{v}_s3" for k, v in feat.items()},
        "max3": {2: "half_height_r", 3: "half_width_r"},
        "normals": {2: "out_height", 3: "out_width"},
    }
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        # eval() first: export restores the wrapper's mode afterwards, and a fresh module is in
        # training mode, which would leave the network's BatchNorms training for verification
        torch.onnx.export(StagedGraph(model).eval(), tuple(example[k] for k in STAGE_INPUTS),
                          str(path),
                          input_names=list(STAGE_INPUTS), output_names=list(STAGE_OUTPUTS),
                          dynamic_axes=dynamic, opset_version=opset, do_constant_folding=True,
                          dynamo=False)


def _torch_export(model: torch.nn.Module, path: Path, opset: int,
                  static: StaticShape | None) -> None:
    if static is None:
        b, n, h, w = EXAMPLE_SHAPE
        dynamic = {
            "images": {0: "batch", 1: "lights", 3: "height", 4: "width"},
            "lights": {0: "batch", 1: "lights"},
            "normals": {0: "batch", 2: "height", 3: "width"},
        }
    else:
        b, n, h, w = 1, static.lights, static.height, static.width
        dynamic = None
    images, lights = (torch.from_numpy(a) for a in random_inputs(b, n, h, w))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # TorchScript exporter deprecation chatter
        torch.onnx.export(model, (images, lights), str(path), input_names=["images", "lights"],
                          output_names=["normals"], dynamic_axes=dynamic, opset_version=opset,
                          do_constant_folding=True, dynamo=False)


def _finalise(path: Path, meta: dict[str, str], static: StaticShape | None,
              staged: bool = False) -> None:
    """Declare the output's axes plainly (the exporter names the 3 'Divnormals_dim_1') and
    attach the metadata the runtime reads."""
    proto = onnx.load(str(path))
    if not staged:
        out_dims = proto.graph.output[0].type.tensor_type.shape.dim
        names = ["batch", 3, "height", "width"] if static is None else [
            1, 3, static.height, static.width]
        for dim, value in zip(out_dims, names, strict=True):
            if isinstance(value, int):
                dim.dim_value = value
            else:
                dim.dim_param = value
    del proto.metadata_props[:]
    for key, value in meta.items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    proto.doc_string = "MSF-Net photometric stereo (msfnet): images + lights -> unit normals"
    onnx.save(proto, str(path))


def store_weights_fp16(path: Path) -> None:
    """Store float32 weights as float16 (half the file), each followed by a Cast back to float32.

    ONNX Runtime folds the Casts when it loads the model, so it computes in float32 exactly as a
    float32 file holding the fp16-rounded weights would. Pair it with a checkpoint whose weights
    are fp16-rounded (``save_checkpoint(..., fp16=True)``) and parity is exact.
    """
    from onnx import TensorProto, helper, numpy_helper

    proto = onnx.load(str(path))
    casts = []
    for init in proto.graph.initializer:
        if init.data_type != TensorProto.FLOAT or int(np.prod(init.dims)) < 16:
            continue  # keep scalars and shape constants as they are
        half = numpy_helper.from_array(numpy_helper.to_array(init).astype(np.float16),
                                       f"{init.name}__fp16")
        casts.append(helper.make_node("Cast", [half.name], [init.name], to=TensorProto.FLOAT,
                                      name=f"{init.name}__to_fp32"))
        init.CopyFrom(half)
    nodes = [*casts, *proto.graph.node]
    del proto.graph.node[:]
    proto.graph.node.extend(nodes)
    onnx.save(proto, str(path))


def _dims(proto: onnx.ModelProto) -> dict[str, list[str | int]]:
    return {v.name: [d.dim_param or d.dim_value for d in v.type.tensor_type.shape.dim]
            for v in [*proto.graph.input, *proto.graph.output]}


def simplify(path: Path) -> None:
    """Simplify the graph in place with onnxslim; refuse if any declared axis changed."""
    try:
        import onnxslim
    except ImportError as exc:
        raise InputError("--simplify needs the onnxslim package: pip install onnxslim") from exc
    proto = onnx.load(str(path))
    simplified = onnxslim.slim(proto)
    if _dims(simplified) != _dims(proto):
        raise InputError(f"simplification changed the input/output axes {_dims(proto)} -> "
                         f"{_dims(simplified)}", path)
    onnx.save(simplified, str(path))


def verify(model: torch.nn.Module, path: Path, checks: list[tuple[int, int, int]],
           batch: int = 1, threads: int = 0, staged_chunk: int | None = None
           ) -> list[dict[str, float]]:
    """ONNX Runtime vs PyTorch at each (N, H, W) on rendered objects: max/mean angular
    difference in degrees over the objects' pixels. ``staged_chunk``: the file is a staged
    export, run by the runtime's light-chunked loop with that many lights per call."""
    import onnxruntime as ort

    from msfnet.runtime.chunked import run_staged

    try:
        onnx.checker.check_model(str(path), full_check=True)
    except onnx.checker.ValidationError as exc:
        raise InputError(f"exported graph fails onnx.checker: {str(exc).splitlines()[0]}") from exc
    opts = ort.SessionOptions()
    if threads:
        opts.intra_op_num_threads = threads
    session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    results = []
    for i, (n, h, w) in enumerate(checks):
        images, lights, masks = rendered_inputs(batch, n, h, w, seed=100 + i)
        try:
            if staged_chunk:
                onnx_out = np.concatenate([run_staged(session, images[b:b + 1],
                                                      lights[b:b + 1], staged_chunk)
                                           for b in range(batch)])
            else:
                (onnx_out,) = session.run(["normals"], {"images": images, "lights": lights})
        except Exception as exc:  # ORT raises its own Fail/InvalidArgument types
            raise InputError(f"verification failed: ONNX Runtime cannot run N={n} {w}x{h} "
                             f"({str(exc).splitlines()[0][:200]})") from exc
        with torch.no_grad():
            torch_out = model(torch.from_numpy(images), torch.from_numpy(lights)).numpy()
        diff = angular_error_deg(onnx_out.transpose(0, 2, 3, 1),
                                 torch_out.transpose(0, 2, 3, 1))[masks]
        results.append({"lights": n, "height": h, "width": w, "pixels": int(diff.size),
                        "max_deg": float(diff.max()), "mean_deg": float(diff.mean())})
    return results


STAGED_CHECK_CHUNK = 3  # verification chunk: uneven splits of every checked light count


def default_checks(static: StaticShape | None) -> list[tuple[int, int, int]]:
    """Light counts unlike the tracing example, one of them at a non-square size."""
    if static is not None:
        return [(static.lights, static.height, static.width)]
    return [(3, 32, 32), (7, 28, 44), (32, 16, 24)]


def export_checkpoint(checkpoint: str | Path, output: str | Path, *, opset: int = DEFAULT_OPSET,
                      train_lights: int = 32, static: StaticShape | None = None,
                      do_simplify: bool = False, checks: list[tuple[int, int, int]] | None = None,
                      tolerance_deg: float = TOLERANCE_DEG, fp16_weights: bool = False,
                      staged: bool = False) -> list[dict[str, float]]:
    """Export, verify and only then move the file into place; nothing is left on failure.

    ``staged``: write the staged graph (``staged.py``) for light-chunked runs; verified through
    the runtime's chunked loop against the monolithic PyTorch network.

    ``fp16_weights``: store weights in half precision (computed in float32); the reference for
    verification is then the network with its weights rounded to float16 likewise.
    """
    checkpoint, output = Path(checkpoint), Path(output)
    if staged and static is not None:
        raise InputError("--staged and --static do not combine (the staged graph's entry "
                         "points need dynamic shapes)")
    model = load_model(checkpoint)
    if fp16_weights:
        with torch.no_grad():
            for tensor in model.state_dict().values():
                if tensor.is_floating_point():
                    tensor.copy_(tensor.half().float())
    output.parent.mkdir(parents=True, exist_ok=True)
    tmp = output.with_name(f".{output.name}.partial.onnx")
    try:
        if staged:
            _torch_export_staged(model, tmp, opset)
        else:
            _torch_export(model, tmp, opset, static)
        meta = {
            METADATA_KEYS["format"]: "msfnet-normals-v1",
            METADATA_KEYS["train_lights"]: str(train_lights),
            METADATA_KEYS["preprocessing"]: json.dumps(PREPROCESSING_SPEC),
            METADATA_KEYS["checkpoint_sha256"]: sha256_of(checkpoint),
            METADATA_KEYS["version"]: msfnet.__version__,
            METADATA_KEYS["input_multiple"]: "4",
            METADATA_KEYS["static_shape"]: "" if static is None else
            f"{static.lights},{static.height},{static.width}",
            METADATA_KEYS["precision"]: "fp32 (fp16-stored weights)" if fp16_weights else "fp32",
            METADATA_KEYS["graph"]: "staged" if staged else "monolithic",
        }
        _finalise(tmp, meta, static, staged)
        if do_simplify:
            simplify(tmp)
        if fp16_weights:
            store_weights_fp16(tmp)
        results = verify(model, tmp, checks or default_checks(static),
                         staged_chunk=STAGED_CHECK_CHUNK if staged else None)
        worst = max(r["max_deg"] for r in results)
        if not np.isfinite(worst) or worst > tolerance_deg:
            raise InputError(f"verification failed: ONNX Runtime differs from PyTorch by "
                             f"{worst:.4g} deg (> {tolerance_deg} deg)", output)
        tmp.replace(output)
        return results
    finally:
        tmp.unlink(missing_ok=True)
