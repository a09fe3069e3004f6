"""msf-train on bad Blobby/Sculpture data: objects with fewer images than the curriculum's most
lights, and lists naming missing images, are refused when the data is indexed (before anything
is written); what only decoding finds, in a DataLoader worker, is the same one-line error as in
the training process (review-train-synth.md 10, 11)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _runtime_helpers import QUICK_VALIDATION

pytest.importorskip("torch")

from msfnet.common.errors import InputError
from msfnet.common.imageio import write_png
from msfnet.model.data import (
    check_blobby_samples,
    find_blobby_samples,
    load_blobby_sample,
    make_sample,
)
from msfnet.model.train_cli import main as train_main
from msfnet.synth.shapes import sphere_normals

# a step and a validation take well under a second
TINY = [
    "--epochs",
    "1",
    "--steps-per-epoch",
    "2",
    "--batch",
    "2",
    "--crop",
    "8",
    *QUICK_VALIDATION,
    "--precision",
    "fp32",
    "--device",
    "cpu",
    "--no-progress",
    "-q",
]


def _blobby(root: Path, counts: dict[str, int]) -> Path:
    """A Blobby-layout root: one shape per entry, one material folder listing ``count``
    16 px images."""
    normals, mask = sphere_normals(16)
    rng = np.random.default_rng(0)
    for shape, count in counts.items():
        folder = root / "Images" / shape
        (folder / "mat").mkdir(parents=True)
        enc = np.where(mask[..., None], np.rint((normals + 1) / 2 * 255), 0).astype(np.uint8)
        write_png(folder / f"{shape}_normal.png", enc)
        lines = []
        for i in range(count):
            d = rng.normal([0, 0, 3], 0.5)
            d /= np.linalg.norm(d)
            img = np.clip(np.einsum("hwc,c->hw", normals, d), 0, 1) * 200
            name = f"{i:03d}.png"
            write_png(folder / "mat" / name, np.repeat(img[..., None], 3, 2).astype(np.uint8))
            lines.append(f"{name} {d[0]:.6f} {d[1]:.6f} {d[2]:.6f}")
        (folder / "mat" / "list.txt").write_text("\n".join(lines) + "\n")
    return root


def _refused(argv: list[str], capfd) -> str:
    assert train_main(argv) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("msf-train: error: "), err
    return err[0]


def test_objects_with_fewer_images_than_the_curriculum_are_refused_before_training(
    tmp_path: Path, capfd
) -> None:
    """One object listing 3 of the 4 lights asked for crashed a batch of 2 ("all input arrays
    must have the same shape", internal error) or, at batch 1, trained on 3 lights logged as
    4."""
    root = _blobby(tmp_path / "blob", {"a": 5, "b": 3})
    out = tmp_path / "run"
    line = _refused(["--out", str(out), "--data", str(root), "--lights", "4", *TINY], capfd)
    assert str(root / "Images" / "b" / "mat") in line
    assert "list.txt lists 3 images" in line and "up to 4 lights" in line, line
    assert not out.exists()  # nothing written: refused before the run started
    # the check itself, and the sampler's: never fewer lights than asked
    pairs = find_blobby_samples(root)
    check_blobby_samples(pairs, 3)
    with pytest.raises(InputError, match="lists 3 images"):
        check_blobby_samples(pairs, 4)
    stack = load_blobby_sample(*pairs[1])
    with pytest.raises(InputError, match="only 3"):
        make_sample(stack, 4, 8, np.random.default_rng(0))


def test_a_missing_image_is_refused_when_the_data_is_indexed(tmp_path: Path, capfd) -> None:
    root = _blobby(tmp_path / "blob", {"a": 5, "b": 5})
    missing = root / "Images" / "b" / "mat" / "002.png"
    missing.unlink()
    out = tmp_path / "run"
    argv = ["--out", str(out), "--data", str(root), "--lights", "4", "--workers", "1", *TINY]
    line = _refused(argv, capfd)
    assert line == f"msf-train: error: {missing}: image file not found (listed in list.txt)"
    assert not out.exists()


def test_bad_data_read_in_a_worker_is_one_error_line(tmp_path: Path, capfd) -> None:
    """A damaged PNG (found only by decoding it) read in a DataLoader worker: was a ~2,000
    character line holding the worker's traceback, or "internal error ... worker killed" (exit
    1) when stop_workers' SIGKILL reached torch's SIGCHLD handler first."""
    root = _blobby(tmp_path / "blob", {"a": 5})
    damaged = root / "Images" / "a" / "mat" / "001.png"
    damaged.write_bytes(b"\x89PNG\r\n\x1a\n not a png")
    for attempt in range(2):  # the race the review saw in 1 run of 3
        out = tmp_path / f"run{attempt}"
        argv = ["--out", str(out), "--data", str(root), "--lights", "5", "--workers", "1", *TINY]
        line = _refused(argv, capfd)
        prefix = f"msf-train: error: {damaged}: "
        assert line.startswith(prefix), line
        problem = line[len(prefix) :]
        assert "Traceback" not in problem and "worker" not in problem, problem
        assert len(problem) < 200, problem
        assert not out.exists()  # a fresh run failing before its first save leaves nothing
