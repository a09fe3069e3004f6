"""Fine-detail mode: the network at 2x for relief of a few pixels, fused with the normal run."""

from __future__ import annotations

import numpy as np
import pytest
from _runtime_helpers import sphere_stack

from msfnet.common.errors import InputError
from msfnet.common.vocabulary import speaking_as
from msfnet.runtime.api import Model
from msfnet.runtime.evaluate.detail_ratio import highpass_energy, masked_smooth
from msfnet.runtime.infer.fine_detail import enlarge, fuse, shrink
from msfnet.runtime.infer.tiling import (
    BASE_MEMORY_MB,
    HALO,
    activation_bytes,
    bytes_per_pixel,
)


def test_enlarge_keeps_dtype_lights_and_the_outline() -> None:
    stack = sphere_stack(n=5, h=20, w=24, seed=1)
    big = enlarge(stack, 2)
    assert big.images.shape == (5, 40, 48, 3) and big.images.dtype == stack.images.dtype
    np.testing.assert_array_equal(big.lights, stack.lights)
    np.testing.assert_array_equal(big.mask[::2, ::2], stack.mask)
    # the stack and its 4x enlargement (5x its memory) beside the runtime's base: at the
    # boundary it fits, a hair under it is refused
    need = BASE_MEMORY_MB + 5 * stack.images.nbytes / 2**20
    enlarge(stack, 2, max_memory_mb=need)
    with (
        speaking_as("msf-run"),
        pytest.raises(
            InputError,
            match=r": --fine-detail holds the stack and its 2x .* above --max-memory [\d.]+ MB",
        ),
    ):
        enlarge(stack, 2, max_memory_mb=need - 0.01)
    with pytest.raises(
        InputError, match=r"above max_memory_mb=.* \(use roi, downscale, max_lights"
    ):
        enlarge(stack, 2, max_memory_mb=need - 0.01)  # from Python: the keywords
    with pytest.raises(InputError, match=r"runtime's 300 MB"):  # the stack's 5x alone fits
        enlarge(stack, 2, max_memory_mb=5.1 * stack.images.nbytes / 2**20)


def test_the_enlarged_pass_counts_the_base_as_its_tiles_do(
    random_onnx, monkeypatch: pytest.MonkeyPatch
) -> None:
    """One rule for the base: what the enlargement check lets through is what the enlarged
    pass's tiles then get, less the same BASE_MEMORY_MB; both refuse before any inference."""
    from msfnet.runtime.infer import estimators

    stack = sphere_stack(n=6, h=24, w=28, seed=2)
    need = BASE_MEMORY_MB + 5 * stack.images.nbytes / 2**20

    def model(budget: float) -> Model:
        return Model(
            random_onnx,
            engine="onnxruntime",
            threads=1,
            maps=None,
            fine_detail=True,
            detail_fusion=False,
            max_memory_mb=budget,
        )

    engine = model(4096).estimator.network.engine  # type: ignore[attr-defined]
    staged = engine.chunk is not None
    per_pixel = bytes_per_pixel(
        6, engine.chunk, activation_bytes(engine.name, engine.precision, staged)
    )
    smallest = (2 * HALO + 4) ** 2 * per_pixel / 2**20  # the smallest tile's working set
    ran: list[int] = []
    real = estimators.infer_normals
    monkeypatch.setattr(estimators, "infer_normals", lambda *a, **k: ran.append(1) or real(*a, **k))
    for budget, refused in ((need - 0.01, "2x enlargement"), (need + 0.5 * smallest, "lights")):
        with pytest.raises(InputError, match=refused):
            model(budget)(stack)
    assert not ran  # refused before any inference
    # room for the base, the stack, its enlargement and a tile (twice the smallest's edge, so
    # the enlarged pass needs few of them): both passes run
    model(need + 4 * smallest)(stack)
    assert len(ran) == 2


def test_shrink_averages_back_to_unit_normals() -> None:
    n = np.zeros((8, 10, 3), np.float32)
    n[..., 2] = 1.0
    n[::2, ::2] = [0.6, 0.0, 0.8]  # one of each 2x2 block tilted
    small = shrink(n, (4, 5))
    assert small.shape == (4, 5, 3)
    np.testing.assert_allclose(np.linalg.norm(small, axis=2), 1.0, atol=1e-6)
    want = np.array([0.15, 0.0, 0.95]) / np.linalg.norm([0.15, 0.0, 0.95])
    np.testing.assert_allclose(small[1, 1], want, atol=1e-6)


def test_fuse_takes_the_shape_of_one_and_the_detail_of_the_other() -> None:
    h = w = 64
    mask = np.zeros((h, w), bool)
    mask[4:60, 4:60] = True
    tilt = np.array([0.3, 0.0, 0.954], np.float32)
    coarse = np.broadcast_to(tilt / np.linalg.norm(tilt), (h, w, 3)).copy()
    ripple = np.zeros((h, w, 3), np.float32)
    ripple[..., 1] = 0.05 * np.where((np.arange(w) // 2) % 2 == 0, 1.0, -1.0)[None, :]
    fine = np.broadcast_to(np.array([0, 0, 1], np.float32), (h, w, 3)) + ripple
    fine /= np.linalg.norm(fine, axis=2, keepdims=True)
    fused = fuse(coarse * mask[..., None], fine * mask[..., None], mask)
    inner = np.zeros_like(mask)
    inner[12:52, 12:52] = True
    # the low frequencies are the coarse map's tilt ...
    mean = masked_smooth(fused, mask, 6.0)[inner].mean(axis=0)
    np.testing.assert_allclose(mean / np.linalg.norm(mean), coarse[0, 0], atol=0.01)
    # ... the 2 px ripple is the fine map's
    assert highpass_energy(fused, mask) == pytest.approx(highpass_energy(fine, mask), rel=0.1)
    assert highpass_energy(coarse, mask) < 1e-10
    # the same map on both sides comes back unchanged
    np.testing.assert_allclose(
        fuse(fine * mask[..., None], fine * mask[..., None], mask)[inner], fine[inner], atol=1e-5
    )


# the first object by default, the second (the same check) with -m slow
@pytest.mark.parametrize(
    ("seed", "plain", "detailed"),
    [(0, 4.26, 3.67), pytest.param(1, 3.73, 2.64, marks=pytest.mark.slow)],
)
def test_the_bundled_model_keeps_more_true_relief_with_fine_detail(
    seed: int, plain: float, detailed: float
) -> None:
    """Synthetic objects with 1-3 px relief (the hard preset's fine relief, 12 lights on a
    ring): measured MAE plain -> fine detail (deg) in the parameters, bundled model of
    2026-11-23, OpenVINO bf16; the high-pass energy kept rose from 0.36 / 0.15 to 0.68 / 0.56
    of the ground truth's."""
    from msfnet.synth.render import RenderOptions, render_stack

    options = RenderOptions.hard(
        size=96, lights=12, fine_relief=1.0, interreflection=0.0, ring_rigs=1.0, bit_depths=(8,)
    )
    stack = render_stack(np.random.default_rng([91, seed]), options)
    a = Model(threads=2, maps=None, detail_fusion=False)(stack)
    b = Model(threads=2, maps=None, fine_detail=True, detail_fusion=False)(stack)
    assert a.metrics is not None and b.metrics is not None
    assert a.metrics.mae_deg == pytest.approx(plain, abs=0.3)
    assert b.metrics.mae_deg == pytest.approx(detailed, abs=0.3)
    truth = highpass_energy(stack.normals_gt, stack.mask)
    gained = highpass_energy(b.normals, stack.mask) - highpass_energy(a.normals, stack.mask)
    assert gained / truth > 0.25
    assert b.method.fine_detail == "x2, high-pass sigma 2 px"


def test_least_squares_has_no_fine_detail_mode() -> None:
    with pytest.raises(InputError, match=r"fine detail \(fine_detail=True\) runs the network a"):
        Model(method="l2", fine_detail=True)


def test_msf_run_fine_detail_is_recorded_and_refused_with_least_squares(
    random_onnx, tmp_path, capfd
) -> None:
    import json

    from msfnet.runtime.cli.run import main
    from msfnet.runtime.stack import save_stack

    src = save_stack(sphere_stack(n=6, h=24, w=28, seed=2), tmp_path / "s")
    assert (
        main(
            [
                str(src),
                "--onnx",
                str(random_onnx),
                "--fine-detail",
                "--no-maps",
                "-q",
                "-o",
                str(tmp_path / "out"),
            ]
        )
        == 0
    )
    profile = json.loads((tmp_path / "out" / "profile.json").read_text())
    assert profile["fine_detail"] == "x2, high-pass sigma 2 px"
    capfd.readouterr()
    assert main([str(src), "--method", "l2", "--fine-detail", "-o", str(tmp_path / "l2")]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--fine-detail" in err[0] and not (tmp_path / "l2").exists()


def test_msf_eval_records_fine_detail(random_onnx, tmp_path) -> None:
    import json

    from msfnet.runtime.cli.eval import main
    from msfnet.runtime.stack import save_stack

    save_stack(sphere_stack(n=6, h=24, w=28, seed=2), tmp_path / "bench" / "s")
    for flag, out in (([], "plain"), (["--fine-detail"], "fine")):
        assert (
            main(
                [
                    str(tmp_path / "bench"),
                    "--onnx",
                    str(random_onnx),
                    "--no-l2",
                    "-q",
                    "-o",
                    str(tmp_path / out),
                    *flag,
                ]
            )
            == 0
        )
    assert json.loads((tmp_path / "plain" / "results.json").read_text())["fine_detail"] is False
    assert json.loads((tmp_path / "fine" / "results.json").read_text())["fine_detail"] is True
    assert "--fine-detail" in (tmp_path / "fine" / "results.md").read_text()
