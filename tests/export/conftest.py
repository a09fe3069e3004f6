"""Fixtures for the export tests: small checkpoints written once per session."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _runtime_helpers import sphere_stack

torch = pytest.importorskip("torch")


def _he_net(seed: int = 0) -> torch.nn.Module:
    """Random weights that keep the signal alive through all layers (PyTorch's default init
    shrinks it until the output hardly depends on the input, which makes parity checks weak)."""
    from msfnet.model.network import MSFNet

    torch.manual_seed(seed)
    net = MSFNet()
    for module in net.modules():
        if isinstance(module, torch.nn.Conv2d | torch.nn.ConvTranspose2d):
            torch.nn.init.kaiming_normal_(module.weight, a=0.1, nonlinearity="leaky_relu")
    return net.eval()


@pytest.fixture(scope="session")
def he_ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from msfnet.model.checkpoint import save_checkpoint

    return save_checkpoint(_he_net(), tmp_path_factory.mktemp("ckpt") / "he.pth")


@pytest.fixture(scope="session")
def zero_ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Every weight and buffer zero: a degenerate network whose normals are all (0, 0, 0)."""
    from msfnet.model.checkpoint import save_checkpoint

    net = _he_net()
    with torch.no_grad():
        for tensor in net.state_dict().values():
            if tensor.is_floating_point():
                tensor.zero_()
    return save_checkpoint(net, tmp_path_factory.mktemp("ckpt") / "zero.pth")


@pytest.fixture(scope="session")
def calib_npz(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small rendered stack (96 lights, 64 px sphere) as an .npz, for int8 calibration. With
    96 lights no rendered many-light objects are added (quantize.with_many_light_stacks, tested
    on its own): an int8 export of the bundled model takes ~25 s instead of ~2 min (AMD EPYC,
    2 cores), 0.18 deg mean from its fp32 graph."""
    stack = sphere_stack(n=96, h=64, w=64, seed=3)
    path = tmp_path_factory.mktemp("calib") / "sphere.npz"
    np.savez(
        path,
        images=stack.images,
        lights=stack.lights,
        intensities=stack.intensities,
        mask=stack.mask,
    )
    return path
