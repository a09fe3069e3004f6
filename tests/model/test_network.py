"""The torch network matches network-spec.md: names, shapes, fusion, invariances, reference."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from msfnet.model.network import MSFNet  # noqa: E402
from msfnet.model.reference import per_light_forward  # noqa: E402

# (key, shape) straight from the layer table in docs/network-spec.md
EXPECTED = {
    "extractor1.conv1.0.weight": (64, 6, 3, 3),
    "extractor1.conv1.0.bias": (64,),
    "extractor1.conv2.0.weight": (128, 64, 3, 3),
    "extractor1.conv2.0.bias": (128,),
    "extractor1.conv3.0.weight": (96, 128, 3, 3),
    "extractor1.conv3.0.bias": (96,),
    "extractor1.conv4.0.weight": (96, 96, 3, 3),
    "extractor1.conv4.0.bias": (96,),
    "regressor.deconv1.0.weight": (128, 96, 3, 3),
    "regressor.deconv1.0.bias": (128,),
    "regressor.deconv2.0.weight": (128, 64, 4, 4),
    "regressor.deconv3.0.weight": (32, 64, 3, 3),
    "regressor.deconv3.0.bias": (32,),
    "regressor.est_normal.0.weight": (3, 32, 3, 3),
}
for stage in ("extractor2", "extractor3"):
    EXPECTED |= {
        f"{stage}.conv1.0.weight": (192, 192, 3, 3),
        f"{stage}.conv1.0.bias": (192,),
        f"{stage}.conv2.0.weight": (192, 128, 4, 4),
        f"{stage}.conv3.0.weight": (96, 128, 3, 3),
        f"{stage}.conv3.0.bias": (96,),
    }
for branch in ("f_x", "f_y"):
    EXPECTED |= {
        f"fusion.{branch}.0.weight": (96, 96, 1, 1),
        f"fusion.{branch}.1.weight": (96,),
        f"fusion.{branch}.1.bias": (96,),
        f"fusion.{branch}.1.running_mean": (96,),
        f"fusion.{branch}.1.running_var": (96,),
        f"fusion.{branch}.1.num_batches_tracked": (),
    }


def _inputs(b: int, n: int, h: int, w: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    images = torch.rand(b, n, 3, h, w, generator=g)
    lights = torch.nn.functional.normalize(torch.randn(b, n, 3, generator=g), dim=-1)
    return images, lights


def _randomise_bn(net: MSFNet, seed: int = 0) -> None:
    """Non-trivial batch-norm statistics, so fusion is exercised as in a trained network."""
    g = torch.Generator().manual_seed(seed)
    for bn in (net.fusion.f_x[1], net.fusion.f_y[1]):
        bn.running_mean.copy_(torch.randn(96, generator=g) * 0.1)
        bn.running_var.copy_(torch.rand(96, generator=g) + 0.5)
        bn.weight.data.copy_(torch.rand(96, generator=g) + 0.5)
        bn.bias.data.copy_(torch.randn(96, generator=g) * 0.1)


def test_state_dict_names_and_shapes_match_the_spec() -> None:
    got = {k: tuple(v.shape) for k, v in MSFNet().state_dict().items()}
    assert got == EXPECTED
    params = sum(p.numel() for p in MSFNet().parameters() if p.requires_grad)
    assert 2.1e6 < params < 2.3e6  # "about 2.2 M learnable parameters"


def test_output_is_unit_normals_at_input_resolution() -> None:
    net = MSFNet().eval()
    images, lights = _inputs(2, 5, 16, 24)
    with torch.no_grad():
        out = net(images, lights)
    assert out.shape == (2, 3, 16, 24)
    assert torch.allclose(out.norm(dim=1), torch.ones(2, 16, 24), atol=1e-5)


def test_light_order_does_not_matter() -> None:
    net = MSFNet().eval()
    _randomise_bn(net)
    images, lights = _inputs(1, 6, 16, 16)
    perm = torch.tensor([3, 0, 5, 1, 4, 2])
    with torch.no_grad():
        a = net(images, lights)
        b = net(images[:, perm], lights[:, perm])
    assert torch.allclose(a, b, atol=1e-6)


def test_batch_samples_are_independent() -> None:
    net = MSFNet().eval()
    images, lights = _inputs(2, 4, 12, 16)
    with torch.no_grad():  # features, not normals: normalising tiny random outputs amplifies noise
        both = net.pooled_features(images, lights)[-1]
        first = net.pooled_features(images[:1], lights[:1])[-1]
    assert torch.allclose(both[:1], first, rtol=1e-4, atol=1e-6)


def test_folded_network_equals_the_published_per_light_loop() -> None:
    torch.manual_seed(3)
    net = MSFNet().eval()
    _randomise_bn(net)
    images, lights = _inputs(2, 5, 16, 20, seed=4)
    with torch.no_grad():
        folded = net(images, lights)
    looped = per_light_forward(net, images, lights)
    assert torch.allclose(folded, looped, atol=1e-5)


def test_fusion_follows_the_released_formula() -> None:
    """(1 - s) * gelu(x) + s * gelu(m), s = sigmoid(sum_c f_x(gelu x) * f_y(gelu m))."""
    torch.manual_seed(5)
    net = MSFNet().eval()
    _randomise_bn(net)
    feats = torch.randn(3, 96, 4, 5)  # one sample, 3 lights
    pooled = feats.amax(dim=0, keepdim=True)
    with torch.no_grad():
        got = net.fusion(feats, pooled)
        gx, gy = torch.nn.functional.gelu(feats), torch.nn.functional.gelu(pooled)
        s = torch.sigmoid((net.fusion.f_x(gx) * net.fusion.f_y(gy)).sum(1, keepdim=True))
        want = (1 - s) * gx + s * gy
    assert torch.allclose(got, want, atol=1e-6)


def test_stage_input_puts_raw_feature_first() -> None:
    net = MSFNet().eval()
    feats = torch.randn(2, 96, 4, 4)
    pooled = feats.amax(0, keepdim=True)
    with torch.no_grad():
        x = net.stage_input(feats, pooled)
    assert x.shape == (2, 192, 4, 4)
    assert torch.equal(x[:, :96], feats)


def test_pooled_features_give_three_stages() -> None:
    net = MSFNet().eval()
    images, lights = _inputs(1, 3, 8, 8)
    with torch.no_grad():
        pooled = net.pooled_features(images, lights)
    assert [tuple(p.shape) for p in pooled] == [(1, 96, 4, 4)] * 3
