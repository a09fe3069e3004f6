"""The one checkpoint reader: files that are no checkpoint at all are named as such, not as
pickled objects it refuses to run (a text file, a Git LFS pointer from a clone without LFS)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

pytest.importorskip("torch")

from msfnet.model.checkpoint import CheckpointError, read_state_dict


@pytest.mark.parametrize("content", [b"not a checkpoint\n", b"<!DOCTYPE html><html>404</html>"])
def test_a_text_file_is_not_a_checkpoint(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "model.pth"
    path.write_bytes(content)
    with pytest.raises(CheckpointError, match="not a PyTorch checkpoint") as exc:
        read_state_dict(path)
    assert "pickled" not in str(exc.value) and str(path) in str(exc.value)


def test_a_git_lfs_pointer_says_so(tmp_path: Path) -> None:
    path = tmp_path / "checkp_30.pth.tar"
    path.write_text(
        "version https://git-lfs.github.com/spec/v1\noid sha256:" + "0" * 64 + "\nsize 123456\n"
    )
    with pytest.raises(CheckpointError, match="Git LFS pointer"):
        read_state_dict(path)


def test_a_folder_is_named_as_one(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match="is a folder"):
        read_state_dict(tmp_path)


def test_pickled_objects_are_still_called_so(tmp_path: Path) -> None:
    import pickle

    path = tmp_path / "objects.pth"
    path.write_bytes(pickle.dumps({"state_dict": {"w": Path("x")}}, protocol=2))
    with pytest.raises(CheckpointError, match="pickled Python objects"):
        read_state_dict(path)


@pytest.mark.filterwarnings("ignore:Detected pickle protocol")
@pytest.mark.parametrize("protocol", [0, 4, 5])
def test_a_pickle_the_safe_reader_refuses_is_not_called_no_pickle(
    tmp_path: Path, protocol: int
) -> None:
    """torch's weights-only reader says "Unsupported operand" both for bytes that are no pickle
    and for pickle opcodes it lacks (protocol 0; FRAME of protocols 4-5)."""
    import torch

    path = tmp_path / "p.pth"
    torch.save({"state_dict": {"w": torch.zeros(2)}}, path, pickle_protocol=protocol)
    with pytest.raises(
        CheckpointError,
        match="a pickle that PyTorch's safe reader refuses "
        r"\(Unsupported operand \d+\); refusing",
    ):
        read_state_dict(path)


class _RunsACommand:
    """Unpickling this would run a shell command (what a hostile checkpoint does)."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[object, tuple[str]]:
        import os

        return os.system, (f"touch {self.marker}",)


def test_a_pickle_that_would_run_code_is_refused_as_objects(tmp_path: Path) -> None:
    import pickle

    path = tmp_path / "evil.pth"
    path.write_bytes(
        pickle.dumps({"state_dict": {"w": _RunsACommand(tmp_path / "ran")}}, protocol=2)
    )
    with pytest.raises(CheckpointError, match="pickled Python objects"):
        read_state_dict(path)
    assert not (tmp_path / "ran").exists()


@pytest.mark.parametrize("spoil", ["int64", "complex", "sparse"])
def test_weights_of_the_wrong_kind_are_named(spoil: str) -> None:
    import torch

    from msfnet.model.checkpoint import check_state_dict
    from msfnet.model.network import MSFNet

    model = MSFNet()
    state = dict(model.state_dict())
    key = "regressor.est_normal.0.weight"
    state[key] = {
        "int64": state[key].long(),
        "complex": state[key].to(torch.complex64),
        "sparse": state[key].to_sparse(),
    }[spoil]
    with pytest.raises(CheckpointError, match=f"1 mis-typed key\\(s\\): {key}"):
        check_state_dict(model, state, "x.pth")
    check_state_dict(model, dict(model.state_dict()), "x.pth")  # the real thing passes


def _saved(tmp_path: Path, state: dict, name: str = "c.pth") -> Path:
    import torch

    path = tmp_path / name
    torch.save({"state_dict": state, "model": "MSF_Net"}, path)
    return path


def test_one_weight_under_two_names_is_refused_as_ambiguous(tmp_path: Path) -> None:
    """X and DataParallel's module.X were merged silently (the last one won): the exported
    weights depended on key order."""
    import torch

    from msfnet.model.checkpoint import load_model
    from msfnet.model.network import MSFNet

    state = dict(MSFNet().state_dict())
    key = "extractor1.conv1.0.bias"
    state["module." + key] = torch.zeros_like(state[key])
    with pytest.raises(CheckpointError) as exc:
        load_model(_saved(tmp_path, state))
    message = str(exc.value)
    assert f"both {key} and module.{key}" in message and "\n" not in message


def test_a_state_dict_without_num_batches_tracked_loads_exactly(tmp_path: Path) -> None:
    """Checkpoints of PyTorch < 0.4.1 lack BatchNorm's num_batches_tracked, which strict
    load_state_dict accepts: they were refused as "missing key(s)"."""
    import torch

    from msfnet.model.checkpoint import check_state_dict, load_model
    from msfnet.model.network import MSFNet

    torch.manual_seed(0)
    source = MSFNet()
    state = {k: v for k, v in source.state_dict().items() if "num_batches_tracked" not in k}
    assert len(state) < len(source.state_dict())  # the network has BatchNorm layers
    loaded = load_model(_saved(tmp_path, state)).state_dict()
    for key, value in state.items():
        assert torch.equal(loaded[key], value), key
    # any other missing key is still refused
    del state["regressor.est_normal.0.weight"]
    with pytest.raises(CheckpointError, match="1 missing key"):
        check_state_dict(MSFNet(), state, "x.pth")


def test_a_truncated_zip_checkpoint_is_said_in_a_complete_sentence(tmp_path: Path) -> None:
    """torch's zip reader appends advice that the 200-character cut left mid-sentence."""
    import torch

    path = tmp_path / "whole.pth"
    torch.save({"state_dict": {"w": torch.zeros(1000)}}, path)
    cut = tmp_path / "trunc.pth"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(CheckpointError) as exc:
        read_state_dict(cut)
    assert exc.value.message == (
        "not a readable PyTorch checkpoint (a truncated or damaged zip archive)"
    )


@pytest.mark.parametrize(
    ("content", "words"),
    [
        (b"hello\n", "not a PyTorch checkpoint (neither a zip archive nor a pickle)"),
        (b"", "an empty file, not a checkpoint"),
        (None, "not a regular file"),  # /dev/null: exists, reads as nothing
    ],
)
def test_a_file_that_is_no_checkpoint_is_said_plainly(
    tmp_path: Path, content: bytes | None, words: str
) -> None:
    """A text file read "not a readable PyTorch checkpoint (101)" (its first byte's value),
    /dev/null "checkpoint file not found"."""
    path = Path(os.devnull) if content is None else tmp_path / "x.pth"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(CheckpointError) as exc:
        read_state_dict(path)
    assert words in exc.value.message
    assert not any(ch.isdigit() for ch in exc.value.message)


def test_weights_that_are_not_finite_are_refused() -> None:
    """msf-train --init / --resume trained on at loss nan from a diverged run's weights."""

    from msfnet.model.checkpoint import check_state_dict
    from msfnet.model.network import MSFNet

    model = MSFNet()
    state = dict(model.state_dict())
    key = next(k for k, v in state.items() if v.is_floating_point())
    state[key] = state[key].clone().fill_(float("nan"))
    with pytest.raises(CheckpointError, match=f"{key} holds NaN"):
        check_state_dict(model, state, "run/last.pth")


def test_fp16_refuses_weights_beyond_its_range() -> None:
    """msf-average --fp16 wrote inf for them, exit 0, and then refused its own file."""
    import torch

    from msfnet.model.checkpoint import checkpoint_content
    from msfnet.model.network import MSFNet

    model = MSFNet()
    with torch.no_grad():
        next(p for p in model.parameters()).view(-1)[0] = 1e6
    with pytest.raises(CheckpointError, match="beyond fp16's range"):
        checkpoint_content(model, fp16=True)
    assert checkpoint_content(model)["state_dict"]  # fp32 keeps it
