"""msf-train --consistency: batches turned as a whole (model.equivariance) agree with the
augmentation's own transform, turn back exactly, and a training step with the term runs."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from msfnet.model.data import Batch, rotate_flip  # noqa: E402
from msfnet.model.equivariance import (  # noqa: E402
    consistency_turn,
    turn_back,
    turn_batch,
)

TURNS = [(k, f) for f in (False, True) for k in range(4)]


def _batch(seed: int = 0) -> Batch:
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(2, 3, 6, 5)).astype(np.float32)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return Batch(
        torch.from_numpy(rng.random((2, 4, 3, 6, 5), np.float32)),
        torch.from_numpy(rng.normal(size=(2, 4, 3)).astype(np.float32)),
        torch.from_numpy(n),
        torch.from_numpy(rng.random((2, 6, 5)) > 0.3),
    )


@pytest.mark.parametrize(("k", "flip"), TURNS)
def test_turn_matches_the_augmentation(k: int, flip: bool) -> None:
    b = _batch()
    t = turn_batch(b, k, flip)
    imgs, normals, mask, lights = rotate_flip(
        b.images[0].numpy().transpose(0, 2, 3, 1),
        b.normals[0].numpy().transpose(1, 2, 0),
        b.mask[0].numpy(),
        b.lights[0].numpy(),
        k,
        flip,
    )
    np.testing.assert_allclose(t.images[0].numpy(), imgs.transpose(0, 3, 1, 2), atol=0)
    np.testing.assert_allclose(t.normals[0].numpy(), normals.transpose(2, 0, 1), atol=1e-7)
    np.testing.assert_array_equal(t.mask[0].numpy(), mask)
    np.testing.assert_allclose(t.lights[0].numpy(), lights, atol=1e-7)


@pytest.mark.parametrize(("k", "flip"), TURNS)
def test_turn_back_inverts(k: int, flip: bool) -> None:
    b = _batch(1)
    back = turn_back(turn_batch(b, k, flip).normals, k, flip)
    torch.testing.assert_close(back, b.normals, atol=1e-7, rtol=0)


def test_turns_drawn_per_step() -> None:
    turns = {consistency_turn(0, s) for s in range(200)}
    assert (0, False) not in turns and len(turns) == 7
    assert consistency_turn(3, 5) == consistency_turn(3, 5)


def test_step_with_consistency(tmp_path) -> None:
    from msfnet.model.train import Trainer
    from msfnet.model.train_config import TrainConfig

    cfg = TrainConfig(
        out=str(tmp_path),
        batch=2,
        curriculum="0:4-4:16",
        val_objects=1,
        val_size=16,
        threads=1,
        device="cpu",
        render_on="device",
        precision="fp32",
        consistency=0.5,
    )
    t = Trainer(cfg)
    batch = next(t._device_batches(1))[0]
    loss, parts = t.train_step(batch)
    assert np.isfinite(loss) and len(parts) == 3
