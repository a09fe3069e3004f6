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
