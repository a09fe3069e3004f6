"""Training: stage losses, the selective update strategy, ablations, loss falls, CLI resume."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="needs torch: the [train] extra")

from msfnet.model.data import collate, make_sample, rotate_flip  # noqa: E402
from msfnet.model.network import MSFNet, max_over_lights  # noqa: E402
from msfnet.model.train import backward_losses, cosine_loss, gradient_loss, stage_losses  # noqa: E402
from msfnet.model.train_cli import main as train_main  # noqa: E402
from msfnet.runtime.infer.normalise import normalise  # noqa: E402
from msfnet.synth import RenderOptions, render_stack  # noqa: E402
from msfnet.synth.shapes import sphere_normals  # noqa: E402

torch.set_num_threads(2)


def _batch(seed=0, b=2, lights=4, crop=16):
    rng = np.random.default_rng(seed)
    stacks = [render_stack(seed + i, RenderOptions(size=32, lights=8)) for i in range(b)]
    return collate([make_sample(s, lights, crop, rng) for s in stacks])


def _grads(model):
    return {n: (None if p.grad is None else p.grad.clone()) for n, p in model.named_parameters()}


@pytest.mark.slow
def test_middle_loss_sends_no_gradient_into_extractor1():
    torch.manual_seed(0)
    model = MSFNet()
    bt = _batch()
    losses = stage_losses(model, bt.images, bt.lights, bt.normals, bt.mask)
    assert len(losses) == 3
    backward_losses(model, losses, sus=True, weights=(0.0, 1.0, 0.0))
    g = _grads(model)
    for name, grad in g.items():
        if name.startswith("extractor1."):
            assert grad is None or torch.count_nonzero(grad) == 0, name
    for prefix in ("extractor2.", "fusion.", "regressor."):
        assert any(
            grad is not None and grad.abs().sum() > 0
            for n, grad in g.items()
            if n.startswith(prefix)
        ), prefix
    # extractor3 plays no part in the middle stage
    assert all(
        grad is None or torch.count_nonzero(grad) == 0
        for n, grad in g.items()
        if n.startswith("extractor3.")
    )
    # without SUS the same loss does reach extractor1
    model.zero_grad(set_to_none=True)
    losses = stage_losses(model, bt.images, bt.lights, bt.normals, bt.mask)
    backward_losses(model, losses, sus=False, weights=(0.0, 1.0, 0.0))
    assert model.extractor1.conv1[0].weight.grad.abs().sum() > 0


@pytest.mark.slow
def test_selective_update_equals_detaching_extractor1_for_the_middle_loss():
    torch.manual_seed(1)
    model = MSFNet().double()
    bt = _batch(seed=3)
    x, lt, n, m = bt.images.double(), bt.lights.double(), bt.normals.double(), bt.mask
    losses = stage_losses(model, x, lt, n, m)
    backward_losses(model, losses, sus=True)
    ours = _grads(model)

    # Reference: an explicit second pass whose stage-2 input is extractor1's detached output.
    model.zero_grad(set_to_none=True)
    b, k, _, h, w = x.shape
    inp = torch.cat([x.flatten(0, 1), lt.reshape(b * k, 3, 1, 1).expand(-1, -1, h, w)], 1)
    f1 = model.extractor1(inp)
    m1 = max_over_lights(f1, b)
    f2 = model.extractor2(model.stage_input(f1, m1))
    m2 = max_over_lights(f2, b)
    f3 = model.extractor3(model.stage_input(f2, m2))
    m3 = max_over_lights(f3, b)
    f1d = f1.detach()
    f2d = model.extractor2(model.stage_input(f1d, max_over_lights(f1d, b)))
    loss = (
        0.5 * cosine_loss(model.regressor(m1), n, m)
        + 0.5 * cosine_loss(model.regressor(max_over_lights(f2d, b)), n, m)
        + cosine_loss(model.regressor(m3), n, m)
    )
    loss.backward()
    for name, p in model.named_parameters():
        ref = p.grad if p.grad is not None else torch.zeros_like(p)
        got = ours[name] if ours[name] is not None else torch.zeros_like(p)
        torch.testing.assert_close(got, ref, rtol=1e-9, atol=1e-12, msg=name)
    assert model.extractor1.conv1[0].weight.grad.abs().sum() > 0  # shallow + deep reach it


@pytest.mark.slow
def test_ablation_switches_change_the_graph():
    full, no_mff, no_mfe = MSFNet(), MSFNet(mff=False), MSFNet(mfe=False)
    bt = _batch(b=1)
    prefixes = lambda mdl: {n.split(".")[0] for n, _ in mdl.named_parameters()}  # noqa: E731
    assert prefixes(full) == {"extractor1", "extractor2", "extractor3", "fusion", "regressor"}
    assert prefixes(no_mff) == {"extractor1", "extractor2", "extractor3", "regressor"}
    assert prefixes(no_mfe) == {"extractor1", "regressor"}
    assert len(stage_losses(full, bt.images, bt.lights, bt.normals, bt.mask)) == 3
    assert len(stage_losses(no_mff, bt.images, bt.lights, bt.normals, bt.mask)) == 3
    losses = stage_losses(no_mfe, bt.images, bt.lights, bt.normals, bt.mask)
    assert len(losses) == 1
    backward_losses(no_mfe, losses, sus=True)
    assert no_mfe.extractor1.conv1[0].weight.grad.abs().sum() > 0


@pytest.mark.slow
def test_loss_falls_in_a_few_steps():
    torch.manual_seed(0)
    model = MSFNet()
    opt = torch.optim.Adam(model.parameters(), lr=1e-3, betas=(0.9, 0.999))
    bt = _batch(seed=5, b=2, lights=4, crop=12)
    history = []
    for _ in range(10):
        opt.zero_grad(set_to_none=True)
        losses = stage_losses(model, bt.images, bt.lights, bt.normals, bt.mask)
        history.append(float(backward_losses(model, losses, sus=True)))
        opt.step()
    assert history[-1] < 0.6 * history[0], history


def test_gradient_loss_scores_smoothed_relief_and_ignores_an_offset():
    # A 1 px groove across a flat patch: the prediction without it loses the pixel-to-pixel
    # changes; a constant offset of the whole map changes no difference between neighbours.
    gt = torch.zeros(1, 3, 8, 8)
    gt[:, 2] = 1.0
    gt[0, 0, :, 4] = 0.6  # the groove's wall tilts the normal along x
    mask = torch.ones(1, 8, 8, dtype=torch.bool)
    flat = torch.zeros_like(gt)
    flat[:, 2] = 1.0
    assert float(gradient_loss(gt, gt, mask)) == 0.0
    assert float(gradient_loss(gt + 0.1, gt, mask)) == pytest.approx(0.0, abs=1e-7)
    # 8 rows x 2 column pairs differ by 0.6 in x, over 2 x 56 neighbour pairs
    assert float(gradient_loss(flat, gt, mask)) == pytest.approx(8 * 2 * 0.6 / 112, rel=1e-6)
    # pairs that leave the mask do not count
    mask[:, :, 4] = False
    assert float(gradient_loss(flat, gt, mask)) == 0.0


@pytest.mark.slow
def test_stage_losses_add_the_weighted_gradient_term():
    torch.manual_seed(0)
    model = MSFNet()
    bt = _batch()
    with torch.no_grad():
        plain = stage_losses(model, bt.images, bt.lights, bt.normals, bt.mask)
        both = stage_losses(model, bt.images, bt.lights, bt.normals, bt.mask, grad_weight=0.5)
        feats = model.pooled_features(bt.images, bt.lights)
        extras = [0.5 * gradient_loss(model.regressor(f), bt.normals, bt.mask) for f in feats]
    for p, b, extra in zip(plain, both, extras, strict=True):
        assert float(extra) > 0
        assert float(b) == pytest.approx(float(p + extra), rel=1e-5)


def test_rotate_flip_keeps_a_sphere_a_sphere():
    n, mask = sphere_normals(24)
    lights = np.array([[0.3, -0.2, 0.93], [-0.5, 0.1, 0.86]], np.float32)
    imgs = np.clip(np.einsum("hwc,kc->khw", n, lights), 0, None)[..., None].repeat(3, 3)
    for k in range(4):
        for flip in (False, True):
            im2, n2, m2, l2 = rotate_flip(imgs, n, mask, lights, k, flip)
            np.testing.assert_allclose(n2, n, atol=1e-12)  # sphere is symmetric
            np.testing.assert_array_equal(m2, mask)
            # shading is consistent with the transformed normals and lights
            shade = np.clip(np.einsum("hwc,kc->khw", n2, l2), 0, None)
            np.testing.assert_allclose(im2[..., 0], shade, atol=1e-6)


def test_sample_input_is_runtime_normalise_of_the_crop():
    s = render_stack(2, RenderOptions(size=32, lights=10))
    rng = np.random.default_rng(9)
    x, _lt, _nrm, _m = make_sample(s, 10, 32, rng, noise=0.0, calib_jitter=0.0)
    # full crop, all lights: equal to runtime normalise up to the light order and rotation
    ref = normalise(s.images, s.intensities, s.mask)
    assert x.shape == (10, 3, 32, 32)
    np.testing.assert_allclose(
        np.sort(np.abs(x).ravel()), np.sort(np.abs(ref).ravel()), rtol=1e-5, atol=1e-7
    )


@pytest.mark.slow
def test_cli_trains_saves_and_resumes(tmp_path, capsys):
    out = tmp_path / "run"
    common = [
        "--batch",
        "2",
        "--lights",
        "4",
        "--crop",
        "16",
        "--pool",
        "3",
        "--render-size",
        "32",
        "--val-objects",
        "1",
        "--log-every",
        "1",
        "--no-progress",
        "--precision",
        "fp32",
    ]
    assert train_main(["--out", str(out), "--epochs", "1", "--steps-per-epoch", "2", *common]) == 0
    ckpt = torch.load(out / "last.pth", weights_only=True)
    assert set(ckpt) >= {"state_dict", "model"} and ckpt["step"] == 2
    MSFNet().load_state_dict(ckpt["state_dict"], strict=True)
    assert train_main(["--out", str(out), "--epochs", "1", *common]) == 2  # refuses non-empty
    # a kill after the last save: rows past the saved step, the last one torn in mid-append
    with open(out / "log.jsonl", "a") as f:
        f.write('{"step": 3, "loss": 9.0}\n{"step": 4, "lo')
    capsys.readouterr()
    assert train_main(["--out", str(out), "--resume", "--epochs", "2", "-q"]) == 0
    assert capsys.readouterr().out == ""  # -q: errors only
    rows = [json.loads(r) for r in (out / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows if "loss" in r] == [1, 2, 3, 4]
    assert 9.0 not in [r["loss"] for r in rows if "loss" in r]
    assert sum("val_mae" in r for r in rows) == 2
    assert torch.load(out / "last_state.pth", weights_only=True)["step"] == 4


@pytest.mark.slow
def test_cli_starts_from_given_weights(tmp_path):
    from msfnet.model.checkpoint import save_checkpoint

    torch.manual_seed(7)
    start = MSFNet()
    ckpt = save_checkpoint(start, tmp_path / "start.pth", fp16=True)
    out = tmp_path / "run"
    assert (
        train_main(
            [
                "--out",
                str(out),
                "--epochs",
                "1",
                "--steps-per-epoch",
                "1",
                "--batch",
                "1",
                "--lights",
                "3",
                "--crop",
                "16",
                "--pool",
                "1",
                "--render-size",
                "32",
                "--val-objects",
                "1",
                "--no-progress",
                "--precision",
                "fp32",
                "--lr",
                "1e-12",
                "--init",
                str(ckpt),
                "--grad-loss",
                "0.2",
            ]
        )
        == 0
    )
    assert json.loads((out / "config.json").read_text())["grad_loss"] == 0.2
    trained = torch.load(out / "last.pth", weights_only=True)["state_dict"]
    want = start.state_dict()["regressor.est_normal.0.weight"].half().float()
    assert torch.allclose(trained["regressor.est_normal.0.weight"], want, atol=1e-6)


def test_synth_source_draws_object_sizes_from_the_range():
    from msfnet.model.data import SynthSource

    opts = RenderOptions(size=24, lights=4)
    src = SynthSource(3, opts, pool=6, refresh=1, max_size=40)
    sizes = {s.shape[0] for s in src.pool}
    assert all(24 <= v <= 40 for v in sizes) and len(sizes) > 1
    again = SynthSource(3, opts, pool=6, refresh=1, max_size=40)  # deterministic per seed
    assert [s.shape for s in again.pool] == [s.shape for s in src.pool]
    fixed = SynthSource(3, opts, pool=3, refresh=1)
    assert {s.shape[0] for s in fixed.pool} == {24}


def test_gpu_render_workers_follow_the_usable_cores(monkeypatch):
    from msfnet.model import train

    monkeypatch.setattr(train, "usable_cores", lambda: 8)
    assert train.default_workers(torch.device("cuda")) == 6
    assert train.default_workers(torch.device("cpu")) == 0


@pytest.mark.slow
def test_resume_with_a_damaged_state_or_config_is_one_line(tmp_path, capfd):
    """A damaged Adam state failed at the first step, and a bad config.json value (lr NaN)
    when the optimiser was made: both as internal errors, exit 1."""
    import shutil

    out = tmp_path / "run"
    small = ["--batch", "2", "--lights", "4", "--crop", "16", "--pool", "3"]
    small += ["--render-size", "32", "--val-objects", "1", "--no-progress", "--precision", "fp32"]
    assert train_main(["--out", str(out), "--epochs", "1", "--steps-per-epoch", "2", *small]) == 0
    moments = tmp_path / "moments"
    shutil.copytree(out, moments)
    st = torch.load(moments / "last_state.pth", weights_only=True)
    first = next(iter(st["optimizer"]["state"].values()))
    first["exp_avg"] = torch.zeros(2, 2)
    torch.save(st, moments / "last_state.pth")
    config = tmp_path / "config"
    shutil.copytree(out, config)
    text = (config / "config.json").read_text()
    cfg = json.loads(text)
    cfg["lr"] = float("nan")
    (config / "config.json").write_text(json.dumps(cfg))
    capfd.readouterr()
    for run, word in ((moments, "last_state.pth"), (config, "config.json")):
        assert train_main(["--out", str(run), "--resume", "--epochs", "2", "-q"]) == 2
        err = capfd.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("msf-train: error:") and word in err[0], err


@pytest.mark.parametrize("workers", ["0", "2"])
def test_a_resumed_run_ends_with_the_weights_of_an_unbroken_one(tmp_path, workers: str) -> None:
    """On the numpy renderer a resume restarted the object pool and the batch streams at the
    resume step: the weights ended up to 0.003 away from an unbroken run's (a review)."""
    tiny = [
        "--batch", "1", "--lights", "4", "--crop", "8", "--render-size", "16",
        "--render-lights", "4", "--pool", "2", "--refresh", "1", "--val-objects", "1",
        "--val-size", "16", "--threads", "1", "--precision", "fp32", "--device", "cpu",
        "--workers", workers, "--steps-per-epoch", "3", "--no-progress", "-q",
    ]  # fmt: skip
    whole, parts = tmp_path / "whole", tmp_path / "parts"
    assert train_main(["--out", str(whole), "--epochs", "2", *tiny]) == 0
    assert train_main(["--out", str(parts), "--epochs", "1", *tiny]) == 0
    assert train_main(["--out", str(parts), "--resume", "--epochs", "2", *tiny]) == 0
    a = torch.load(whole / "last.pth", weights_only=True)["state_dict"]
    b = torch.load(parts / "last.pth", weights_only=True)["state_dict"]
    assert a.keys() == b.keys()
    assert all(torch.equal(a[k], b[k]) for k in a), max(
        float((a[k].float() - b[k].float()).abs().max()) for k in a
    )
