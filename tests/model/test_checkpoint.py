"""The one checkpoint reader: files that are no checkpoint at all are named as such, not as
pickled objects it refuses to run (a text file, a Git LFS pointer from a clone without LFS)."""

from __future__ import annotations

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
    path.write_text("version https://git-lfs.github.com/spec/v1\n"
                    "oid sha256:" + "0" * 64 + "\nsize 123456\n")
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
def test_a_pickle_the_safe_reader_refuses_is_not_called_no_pickle(tmp_path: Path,
                                                                   protocol: int) -> None:
    """torch's weights-only reader says "Unsupported operand" both for bytes that are no pickle
    and for pickle opcodes it lacks (protocol 0; FRAME of protocols 4-5)."""
    import torch

    path = tmp_path / "p.pth"
    torch.save({"state_dict": {"w": torch.zeros(2)}}, path, pickle_protocol=protocol)
    with pytest.raises(CheckpointError, match="a pickle that PyTorch's safe reader refuses "
                                              r"\(Unsupported operand \d+\); refusing"):
        read_state_dict(path)
