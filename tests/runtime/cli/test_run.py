"""msf-run end to end on real data: l2 accuracy on ball, tiled ONNX runs, outputs and profile."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from _runtime_helpers import MAP_FILES, sphere_stack

from msfnet.runtime.api import Model
from msfnet.runtime.cli.run import main


def _check_outputs(out: Path, shape: tuple[int, int], with_gt: bool) -> dict:
    normals = np.load(out / "normals.npy")
    assert normals.shape == (*shape, 3) and normals.dtype == np.float32
    inside = np.any(normals != 0, axis=2)
    np.testing.assert_allclose(np.linalg.norm(normals[inside], axis=1), 1.0, atol=1e-4)
    if (out / "normals.png").is_file():  # --normals-png: the same normals, 16-bit
        png = cv2.imread(str(out / "normals.png"), cv2.IMREAD_UNCHANGED)[:, :, ::-1]
        assert png.dtype == np.uint16 and png.shape == (*shape, 3)
        np.testing.assert_allclose(png[inside] / 65535.0 * 2 - 1, normals[inside], atol=2e-5)
        assert np.all(png[~inside] == 0)
    profile = json.loads((out / "profile.json").read_text())
    for stage in ("load", "preprocess", "inference", "postprocess", "total"):
        assert profile["stages"][stage]["p90_s"] >= profile["stages"][stage]["median_s"] >= 0
    assert profile["peak_rss_mb"] > 50
    assert (out / "metrics.json").is_file() == with_gt == (out / "error.png").is_file()
    return profile


@pytest.mark.slow
def test_l2_on_ball_matches_published(ball_dir: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "ball_l2"
    args = ["--method", "l2", str(ball_dir), "-o", str(out), "--repeat", "2", "--normals-png"]
    assert main(args) == 0
    assert (out / "normals.png").is_file()
    metrics = json.loads((out / "metrics.json").read_text())
    assert abs(metrics["mae_deg"] - 4.1) < 0.3, metrics  # DiLiGenT's L2 baseline: 4.10 deg
    assert metrics["pixels"] == 15791
    profile = _check_outputs(out, (512, 612), with_gt=True)
    assert profile["repeat"] == 2 and len(profile["runs"]) == 2
    printed = capsys.readouterr().out
    assert "MAE 4.2" in printed and "p90 s" in printed and "peak RSS" in printed
    normals = np.load(out / "normals.npy")
    mask = cv2.imread(str(ball_dir / "mask.png"), cv2.IMREAD_GRAYSCALE) > 127
    assert np.all(normals[~mask] == 0) and np.all(np.any(normals[mask] != 0, axis=1))


def test_onnx_on_ball_tiled(random_onnx: Path, ball_dir: Path, tmp_path: Path, capsys) -> None:
    """Default-suite version: 8 of the 96 lights, small tiles (the full run is marked slow)."""
    out = tmp_path / "ball_msf"
    assert (
        main(
            [
                "--onnx",
                str(random_onnx),
                str(ball_dir),
                "-o",
                str(out),
                "--max-lights",
                "8",
                "--tile",
                "96",
                "--threads",
                "2",
            ]
        )
        == 0
    )
    profile = _check_outputs(out, (512, 612), with_gt=True)
    assert profile["lights"] == 8
    assert profile["tiles"]["run"] >= 4 and profile["tiles"]["tile_px"] == 96
    assert profile["inference_gflops_per_s"] > 0
    assert "tiles:" in capsys.readouterr().out


@pytest.mark.slow
def test_onnx_on_full_ball_all_lights(random_onnx: Path, ball_dir: Path, tmp_path: Path) -> None:
    """All 96 lights, default 4096 MB budget; a fresh process so peak RSS is the run's own."""
    out = tmp_path / "full"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "msfnet.runtime.cli.run",
            "--onnx",
            str(random_onnx),
            str(ball_dir),
            "-o",
            str(out),
            "--threads",
            "2",
        ],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stderr
    profile = _check_outputs(out, (512, 612), with_gt=True)
    assert profile["lights"] == 96
    assert profile["tiles"]["run"] >= 2  # the budget forces tiling
    assert profile["peak_rss_mb"] < 4096  # --max-memory default


def test_model_api_on_stack_object(random_onnx: Path, tmp_path: Path) -> None:
    stack = sphere_stack(n=6)
    untiled = Model(random_onnx, tile=0, threads=2)(stack)
    assert untiled.metrics is not None and untiled.plan is not None
    assert len(untiled.plan.tiles) == 1 and untiled.profile()["tiles"]["tile_px"] is None
    l2 = Model.least_squares()(stack)
    assert l2.metrics is not None and l2.metrics.median_deg < 0.01
    assert not any(tmp_path.iterdir())  # nothing written until save()
    files = l2.save(tmp_path / "l2")
    assert {f.name for f in files} == {
        "normals.npy",
        "normals_view.png",
        "profile.json",
        "metrics.json",
        "error.png",
    } | MAP_FILES
    assert l2.maps is not None and l2.maps.height is not None
    from msfnet.runtime.results.maps.registered import read_tiff

    height = read_tiff(tmp_path / "l2" / "height.tif")
    assert np.isnan(height[~stack.mask]).all() and np.isfinite(height[stack.mask]).all()
    # a sphere bulges towards the camera: the centre is higher than the rim
    h, w = stack.shape
    rim = height[stack.mask].min()
    assert height[h // 2, w // 2] - rim > 0.3 * 0.45 * min(h, w)
    assert "data:image/png;base64," in (tmp_path / "l2" / "report.html").read_text()


@pytest.mark.parametrize(
    ("preset", "written", "left_out"),
    [
        ("inspect", {"local_shape.tif", "curvature.tif", "albedo.tif"}, {"mesh.ply"}),
        ("none", {"normals.npy"}, {"height.tif", "maps.json", "report.html"}),
    ],
)
def test_maps_presets_choose_what_is_written(
    tmp_path: Path, preset: str, written: set[str], left_out: set[str]
) -> None:
    stack = _npz(sphere_stack(n=6), tmp_path)
    out = tmp_path / preset
    assert main(["--method", "l2", str(stack), "-o", str(out), "--maps", preset, "-q"]) == 0
    names = {p.name for p in out.iterdir()}
    assert written <= names and not (left_out & names), sorted(names)


def test_an_unknown_maps_word_names_the_presets(tmp_path: Path, capsys) -> None:
    stack = _npz(sphere_stack(n=6), tmp_path)
    with pytest.raises(SystemExit) as ended:
        main(["--method", "l2", str(stack), "-o", str(tmp_path / "o"), "--maps", "inspekt"])
    assert ended.value.code == 2
    assert "or one of all, inspect, none, got 'inspekt'" in capsys.readouterr().err


def test_normals_only_without_maps(tmp_path: Path) -> None:
    stack = sphere_stack(n=6)
    res = Model.least_squares(maps=None)(stack)
    assert res.maps is None
    names = {f.name for f in res.save(tmp_path / "o")}
    assert "height.tif" not in names and "normals.npy" in names
    assert (
        main(
            [
                "--method",
                "l2",
                str(_npz(stack, tmp_path)),
                "-o",
                str(tmp_path / "cli"),
                "--maps",
                "height",
                "--integration",
                "fc",
                "--no-report",
            ]
        )
        == 0
    )
    written = {p.name for p in (tmp_path / "cli").iterdir()}
    assert {"height.tif", "height.png"} <= written
    assert not {"albedo.png", "curvature.tif", "height.npy", "mesh.ply", "report.html"} & written


def _npz(stack, tmp_path: Path) -> Path:
    path = tmp_path / "sphere.npz"
    np.savez(
        path,
        images=stack.images,
        lights=stack.lights,
        intensities=stack.intensities,
        mask=stack.mask,
        normals=stack.normals_gt,
    )
    return path


def test_a_bad_model_is_reported_before_a_bad_stack(tmp_path: Path, capsys) -> None:
    """Both inputs bad: the model's error, as when the stack was read after it, and nothing
    written; a good model and a bad stack: the stack's error, nothing written."""
    bad_model = tmp_path / "model.onnx"
    bad_model.write_text("not an onnx file")
    bad_stack = tmp_path / "stack.npz"
    bad_stack.write_bytes(b"PK\x03\x04 damaged")
    out = tmp_path / "o"
    assert main([str(bad_stack), "--onnx", str(bad_model), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"msf-run: error: {bad_model}:")
    assert main([str(bad_stack), "--method", "l2", "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"msf-run: error: {bad_stack}:")
    assert not out.exists()


def test_a_batchs_results_never_go_inside_the_batch_folder(tmp_path: Path, capsys) -> None:
    """Each stack's folder was an input, the batch folder named on the command line was not:
    -o inside it (or a default ./msf-out there) wrote the results into the dataset."""
    import os

    batch = tmp_path / "batch"
    for i in range(2):
        stack = sphere_stack(n=6, h=20, w=24, seed=i, name=f"s{i}")
        from msfnet.runtime.stack import save_stack

        save_stack(stack, batch / f"s{i}")
    code = main([str(batch), "--method", "l2", "--no-maps", "-q", "-o", str(batch / "results")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "inside the input folder" in err[0], err
    here = os.getcwd()
    try:
        os.chdir(batch)
        assert main([".", "--method", "l2", "--no-maps", "-q"]) == 2
    finally:
        os.chdir(here)
    assert sorted(p.name for p in batch.iterdir()) == ["s0", "s1"]


def test_the_normals_are_written_once_unless_asked_and_a_batch_keeps_the_writer_flags(
    tmp_path: Path,
) -> None:
    """By default the normals' data is normals.npy, once (no normals.tif), and their picture
    normals_view.png; --normals-png adds the 16-bit PNG. A batch honours the
    writer flags as one stack does (--no-report was dropped for each stack of a batch)."""
    from msfnet.runtime.stack import save_stack

    batch = tmp_path / "batch"
    for i in range(2):
        save_stack(sphere_stack(n=6, h=20, w=24, seed=i, name=f"s{i}"), batch / f"s{i}")
    one = tmp_path / "one"
    assert main([str(batch / "s0"), "--method", "l2", "--no-maps", "-q", "-o", str(one)]) == 0
    assert {"normals.npy", "normals_view.png"} <= {p.name for p in one.iterdir()}
    assert not (one / "normals.png").exists() and not (one / "normals.tif").exists()
    out = tmp_path / "out"
    flags = ["--method", "l2", "--maps", "height", "--no-report", "--normals-png", "-q"]
    assert main([str(batch), *flags, "-o", str(out)]) == 0
    for name in ("s0", "s1"):
        written = {p.name for p in (out / name).iterdir()}
        assert "normals.png" in written and "report.html" not in written, written
        assert "height.tif" in written and not {"height.npy", "normals.tif"} & written


def test_a_stack_named_like_the_batch_summary_is_refused_before_any_work(
    tmp_path: Path, capsys
) -> None:
    from msfnet.runtime.stack import save_stack

    batch = tmp_path / "weird"
    save_stack(sphere_stack(n=6, h=20, w=24, seed=0, name="a"), batch / "summary.json")
    save_stack(sphere_stack(n=6, h=20, w=24, seed=1, name="b"), batch / "b")
    out = tmp_path / "out"
    code = main([str(batch), "--method", "l2", "--no-maps", "-q", "-o", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "summary file" in err[0], err
    assert not out.exists()


def _run_maps(tmp_path: Path, name: str, *flags: str, stack=None) -> Path:
    stack = stack if stack is not None else sphere_stack(n=8, h=72, w=88)
    src = tmp_path / "in"
    src.mkdir(exist_ok=True)
    out = tmp_path / name
    code = main(["--method", "l2", str(_npz(stack, src)), "-o", str(out), "-q", *flags])
    assert code == 0
    return out


def test_pixel_size_is_the_stored_images_under_downscale(tmp_path: Path) -> None:
    """--pixel-size is a stored-image pixel (as --roi): with --downscale 2 the heights in mm
    are those of the full-size run (were half), and maps.json records both sizes."""
    full = _run_maps(tmp_path, "k1", "--pixel-size", "0.05")
    half = _run_maps(tmp_path, "k2", "--pixel-size", "0.05", "--downscale", "2")
    ranges = []
    for out in (full, half):
        h = cv2.imread(str(out / "height.tif"), cv2.IMREAD_UNCHANGED)
        ranges.append(float(np.nanmax(h) - np.nanmin(h)))
    assert ranges[1] == pytest.approx(ranges[0], rel=0.03), ranges
    reg = json.loads((half / "maps.json").read_text())["registered"]
    assert reg["image_pixel_size_mm"] == 0.05 and reg["pixel_size_mm"] == pytest.approx(0.1)
    assert reg["height"] == "mm"


def test_maps_json_frame_places_the_maps_in_the_stored_image(tmp_path: Path) -> None:
    """--roi and --downscale: maps.json's "frame" maps a map pixel (col, row) to image
    (x0 + K col + (K - 1) / 2, y0 + K row + (K - 1) / 2): the sphere's mask centre lands on
    the rendered centre (21.5, 17.5), within a quarter pixel."""
    stack = sphere_stack(n=8, h=36, w=44)
    out = _run_maps(tmp_path, "roi", "--roi", "4,1,40,34", "--downscale", "2", stack=stack)
    frame = json.loads((out / "maps.json").read_text())["frame"]
    assert frame == {"origin_xy": [4, 1], "downscale": 2}
    normals = np.load(out / "normals.npy")
    assert normals.shape[:2] == (17, 20)
    rows, cols = np.nonzero(np.any(normals != 0, axis=2))
    (x0, y0), k = frame["origin_xy"], frame["downscale"]
    x = x0 + k * cols.mean() + (k - 1) / 2
    y = y0 + k * rows.mean() + (k - 1) / 2
    assert abs(x - 21.5) < 0.25 and abs(y - 17.5) < 0.25, (x, y)
    assert cv2.imread(str(out / "height.tif"), cv2.IMREAD_UNCHANGED).shape == (17, 20)


@pytest.mark.parametrize("roi", [None, "0,0,40,30"])
def test_a_local_size_above_the_image_is_refused_quickly(
    tmp_path: Path, capsys, roi: str | None
) -> None:
    """--local-size 1e9 was minutes of Gaussian sums, then bad_alloc or the OOM killer: now one
    line, exit 2, nothing written (with --roi before the stack is even read)."""
    stack = sphere_stack(n=8, h=36, w=44)
    out = tmp_path / "o"
    flags = ["--roi", roi] if roi else []
    # with --roi the maps' size is known from the flags: refused before the input is read
    path = tmp_path / "not-read.npz" if roi else _npz(stack, tmp_path)
    code = main(["--method", "l2", str(path), "-o", str(out), "--local-size", "1e9", *flags])
    assert code == 2 and not out.exists()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("msf-run: error: ")
    longer = 40 if roi else 44
    assert f"longer side ({longer} px" in err[0] and "--local-size" in err[0]
    assert not out.exists()
