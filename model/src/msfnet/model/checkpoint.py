"""Checkpoint I/O in the published format: ``{'state_dict': ..., 'model': ...}``.

Loading never unpickles arbitrary objects (``weights_only=True``), maps GPU tensors to the CPU,
reads both the zip and the legacy serialisation, strips DataParallel's ``module.`` prefixes, and
checks every key and shape against the network before anything is loaded.
"""

from __future__ import annotations

import hashlib
import io
import pickle
import pickletools
import re
import zipfile
from collections.abc import Mapping
from pathlib import Path

import torch

from msfnet.common.errors import InputError, first_line
from msfnet.common.files import write_atomic
from msfnet.common.vocabulary import declare, opt
from msfnet.model.network import MSFNet

# msf-average's --fp16 (save_checkpoint's fp16)
declare("fp16", "--fp16", "store_true")


def default_checkpoint_path() -> Path:
    """The bundled model's weights in the published format (kept beside this module in a
    checkout; the edge wheel ships only the ONNX file)."""
    return Path(__file__).resolve().parent / "weights" / "msfnet_default.pth"


class CheckpointError(InputError):
    """A file that is not an MSF-Net checkpoint, or one that does not fit the network."""


# what torch.load raises on a file it cannot read (beyond refusing a pickle)
_UNREADABLE: tuple[type[Exception], ...] = (RuntimeError, EOFError, OSError, ValueError)
_UNREADABLE += (zipfile.BadZipFile, KeyError, AttributeError, TypeError, IndexError)


def sha256_of(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_torch_file(path: str | Path) -> object:
    """What a torch.save file holds, read with torch's weights-only reader (never unpickling
    objects); any failure is one CheckpointError naming the file."""
    path = Path(path)
    if path.is_dir():
        raise CheckpointError("is a folder, not a checkpoint file", path)
    if not path.exists():
        raise CheckpointError("checkpoint file not found", path)
    if not path.is_file():  # /dev/null, a pipe: torch would read nothing or block
        raise CheckpointError("not a regular file, so not a checkpoint", path)
    try:
        with path.open("rb") as f:
            head = f.read(1 << 20)  # a legacy checkpoint's first pickle is far smaller
    except OSError as exc:
        raise CheckpointError(f"cannot be read ({first_line(exc)})", path) from exc
    problem = not_a_checkpoint(head)
    if problem:  # said from the bytes: torch fails on these with e.g. "KeyError: 101"
        raise CheckpointError(problem, path)
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        raise CheckpointError(_refusal(path, exc), path) from exc
    except _UNREADABLE as exc:
        raise CheckpointError(f"not a readable PyTorch checkpoint ({_reason(exc)})", path) from exc


def _reason(exc: BaseException) -> str:
    """Why torch could not read the file, short and complete: torch's first sentence (its
    zip reader adds a paragraph of advice), a damaged zip archive said plainly."""
    text = first_line(exc, 10_000)
    damaged = ("failed reading zip archive", "central directory")
    if isinstance(exc, zipfile.BadZipFile) or any(s in text for s in damaged):
        return "a truncated or damaged zip archive"
    sentence = text.split(". ")[0].rstrip(".")
    if len(sentence) > 160:
        sentence = sentence[:160].rsplit(" ", 1)[0] + " ..."
    return sentence


def read_checkpoint(path: str | Path) -> tuple[dict[str, torch.Tensor], int | None]:
    """The tensors of a checkpoint file and the training step msf-train recorded in it (None:
    not recorded), from one read."""
    obj = read_torch_file(path)
    step = obj.get("step") if isinstance(obj, Mapping) else None
    return _tensors(obj, Path(path)), step if isinstance(step, int) else None


def read_state_dict(path: str | Path) -> dict[str, torch.Tensor]:
    """The tensors of a checkpoint file, keys without ``module.`` prefixes."""
    return _tensors(read_torch_file(path), Path(path))


def _tensors(obj: object, path: Path) -> dict[str, torch.Tensor]:
    if isinstance(obj, Mapping) and isinstance(obj.get("state_dict"), Mapping):
        obj = obj["state_dict"]
    if not isinstance(obj, Mapping) or not obj or not all(map(torch.is_tensor, obj.values())):
        raise CheckpointError(
            "does not hold a state_dict of tensors (expected "
            "{'state_dict': {...}} or a bare state_dict)",
            path,
        )
    tensors: dict[str, torch.Tensor] = {}
    given: dict[str, str] = {}
    for k, v in obj.items():
        key = _strip_prefix(str(k))
        if key in tensors:
            # DataParallel's module.X next to X: which of the two is meant cannot be told
            raise CheckpointError(
                f"holds both {given[key]} and {k}, one weight under two names; keep one of "
                "them (re-save the state_dict)",
                path,
            )
        tensors[key], given[key] = v, str(k)
    return tensors


def _refusal(path: Path, exc: pickle.UnpicklingError) -> str:
    """Why torch's weights-only reader refused the file, told from the file's own bytes: its
    messages do not separate "no pickle at all" from "a pickle it does not support"."""
    text = str(exc)
    with open(path, "rb") as f:
        head = f.read(1 << 20)
    problem = not_a_checkpoint(head)
    if problem:
        return problem
    if not zipfile.is_zipfile(path) and not _is_a_pickle(head):
        return "not a PyTorch checkpoint (neither a zip archive nor a pickle)"
    if re.search(r"unsupported global", text, re.IGNORECASE):  # wording varies by torch
        return (
            "holds pickled Python objects, not only tensors; refusing to unpickle it "
            "(re-save it as a plain state_dict)"
        )
    reason = re.search(r"WeightsUnpickler error:\s*(\S[^\n]*)", text)
    detail = reason.group(1).strip()[:120] if reason else first_line(exc, 120)
    return (
        f"a pickle that PyTorch's safe reader refuses ({detail}); refusing to unpickle it "
        "(re-save the state_dict with torch.save's defaults)"
    )


def not_a_checkpoint(head: bytes) -> str | None:
    """What a file is instead, when its first bytes already show it is no torch.save file
    (a zip archive, "PK"; before torch 1.6 a pickle); None when it may be one."""
    if not head:
        return "an empty file, not a checkpoint"
    if head.startswith(b"version https://git-lfs"):
        return "a Git LFS pointer, not the checkpoint itself (fetch it with `git lfs pull`)"
    if not head.startswith(b"PK") and not _is_a_pickle(head):
        return "not a PyTorch checkpoint (neither a zip archive nor a pickle)"
    return None


def _is_a_pickle(head: bytes) -> bool:
    """Whether ``head`` opens with a complete pickle; pickletools only parses the opcodes,
    nothing is built or run."""
    try:
        for _ in pickletools.genops(head):
            pass
    except Exception:  # any parse failure means: not a pickle (truncated ones included)
        return False
    return True


def _strip_prefix(key: str) -> str:
    while key.startswith("module."):
        key = key[len("module.") :]
    return key


def check_state_dict(
    model: torch.nn.Module, state: Mapping[str, torch.Tensor], source: str | Path
) -> None:
    """Raise CheckpointError listing missing, unexpected and mis-shaped keys."""
    expected = model.state_dict()
    # BatchNorm's num_batches_tracked counter is not used in inference, and checkpoints of
    # PyTorch < 0.4.1 (or converted ones) lack it: load_state_dict(strict=True) fills it in
    missing = sorted(k for k in set(expected) - set(state) if not _optional_key(k))
    unexpected = sorted(set(state) - set(expected))
    shapes = sorted(
        f"{k} {tuple(state[k].shape)} != {tuple(v.shape)}"
        for k, v in expected.items()
        if k in state and state[k].shape != v.shape
    )
    # weights must be real floating-point dense tensors (an integer one would load truncated)
    kinds = sorted(
        f"{k} {state[k].dtype}{'' if state[k].layout == torch.strided else ' sparse'}"
        for k, v in expected.items()
        if k in state and not _same_kind(state[k], v)
    )
    problems = []
    labels = ("missing", "unexpected", "mis-shaped", "mis-typed")
    for label, keys in zip(labels, (missing, unexpected, shapes, kinds), strict=True):
        if keys:
            shown = ", ".join(keys[:6]) + (f", ... (+{len(keys) - 6})" if len(keys) > 6 else "")
            problems.append(f"{len(keys)} {label} key(s): {shown}")
    if problems:
        raise CheckpointError("not an MSF-Net checkpoint: " + "; ".join(problems), source)
    # a diverged run's weights: training would go on at loss nan, an export score nothing
    broken = sorted(
        k for k, v in state.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())
    )
    if broken:
        raise CheckpointError(
            f"{broken[0]} holds NaN or infinite values"
            + (f" (and {len(broken) - 1} more weights)" if len(broken) > 1 else "")
            + ": a diverged run's weights?",
            source,
        )


def _optional_key(key: str) -> bool:
    return key.endswith(".num_batches_tracked")


def _same_kind(got: torch.Tensor, want: torch.Tensor) -> bool:
    if got.layout != torch.strided or got.is_complex():
        return False
    return got.is_floating_point() == want.is_floating_point()


def network_for(state: Mapping[str, torch.Tensor]) -> MSFNet:
    """An untrained MSFNet of the variant whose keys ``state`` has (the paper's ablations drop
    the later stages, ``--no-mfe``, or the fusion module, ``--no-mff``)."""
    return MSFNet(
        mfe=any(k.startswith("extractor2.") for k in state),
        mff=any(k.startswith("fusion.") for k in state),
    )


def load_model(path: str | Path, **options: bool) -> MSFNet:
    """An MSFNet in eval mode with the checkpoint's weights (strict); without ``options``, the
    variant the checkpoint's keys describe (msf-train's ablation runs included)."""
    state = read_state_dict(path)
    model = MSFNet(**options) if options else network_for(state)
    check_state_dict(model, state, path)
    model.load_state_dict(state, strict=True)
    return model.eval()


def save_checkpoint(
    model: torch.nn.Module, path: str | Path, fp16: bool = False, **extra: object
) -> Path:
    """Write ``{'state_dict': ..., 'model': 'MSF_Net', ...}`` atomically (the published layout).

    ``fp16``: store floating-point tensors in half precision (half the size; load_state_dict
    casts them back to float32 on load, here and in the authors' code).
    """
    content = checkpoint_content(model, fp16, **extra)
    return write_atomic(path, lambda tmp: torch_save(content, tmp))


def torch_save(obj: object, path: str | Path) -> None:
    """``torch.save`` through memory: torch's own writer turns a full disk (ENOSPC) into a
    RuntimeError ("unexpected pos ...", also when given a Python file) that no caller can tell
    from a bug. Serialised first (a checkpoint is a few MB), the bytes are written by Python,
    whose OSError keeps its errno: the command says "No space left on device" in one line."""
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    try:
        with open(path, "wb") as f:
            f.write(buffer.getbuffer())
    except OSError as exc:
        if exc.filename is not None or exc.errno is None:
            raise
        raise OSError(exc.errno, exc.strerror, str(path)) from exc


def checkpoint_content(
    model: torch.nn.Module, fp16: bool = False, **extra: object
) -> dict[str, object]:
    """What :func:`save_checkpoint` writes, for a caller that writes it itself."""
    state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    if fp16:
        # fp16 holds magnitudes up to 65504: beyond it a weight would be written as inf
        big = [k for k, v in state.items() if v.is_floating_point() and v.abs().max() > 65504]
        if big:
            raise CheckpointError(
                f"{big[0]} holds values beyond fp16's range (65504); write it without {opt('fp16')}"
            )
        state = {k: v.half() if v.is_floating_point() else v for k, v in state.items()}
    return {"state_dict": state, "model": "MSF_Net", **extra}
