"""The defect step (inspection.defects and msf-inspect): every relief defect of a rendered plate
found, no printed mark reported, a golden reference aligned, bad input refused with exit 2."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from msfnet.common.errors import InputError
from msfnet.runtime.api import Model
from msfnet.runtime.cli.inspect import main as inspect_main
from msfnet.runtime.inspection.defects import (
    DefectOptions,
    InspectionInput,
    _align,
    find_defects,
    from_maps,
    read_run,
    shift_map,
)
from msfnet.runtime.results.maps import MapOptions
from msfnet.runtime.results.maps.registered import Frame
from msfnet.synth.plates import PlateOptions, render_plate

DEPTH_PX = 0.06  # below the plate's shallowest measured scratch (0.11 px), 15x the noise s.d.
MAPS = MapOptions(maps=("albedo", "height", "curvature"))


@pytest.fixture(scope="module")
def plate():
    return render_plate(PlateOptions(seed=0))


@pytest.fixture(scope="module")
def plate_run(plate, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The plate through least squares (what the default path gives on a matte part, where
    the Lambertian fit holds everywhere), written as msf-run writes it."""
    out = tmp_path_factory.mktemp("inspect") / "run"
    Model.least_squares(maps=MAPS)(plate.stack).save(out)
    return out


def _hits(plate, labels: np.ndarray) -> tuple[set[int], list[int]]:
    found = {
        k for k in range(1, len(plate.defect_list) + 1) if (labels[plate.defects == k] > 0).any()
    }
    false = [
        k for k in range(1, int(labels.max()) + 1) if not (plate.defects[labels == k] > 0).any()
    ]
    return found, false


def test_every_relief_defect_and_no_printed_mark(plate) -> None:
    result = Model.least_squares(maps=MAPS)(plate.stack)
    assert result.maps is not None
    part = from_maps(result.maps, "plate")
    verdict, labels = find_defects(part, DefectOptions(depth=DEPTH_PX))
    inside = {
        d.label for d in plate.defect_list if (plate.stack.mask & (plate.defects == d.label)).any()
    }
    found, false = _hits(plate, labels)
    assert found == inside and len(inside) == 5
    assert false == []  # nothing else, printed marks included
    assert not (labels[plate.marks] > 0).any()
    assert not verdict.passed and verdict.exit_code == 1
    for r in verdict.regions:
        # each region's depth is the defect's, as measured in the local shape (px)
        truth = plate.defect_list[int(np.bincount(plate.defects[labels == r.label]).argmax()) - 1]
        assert 0.4 * truth.depth <= r.depth <= 1.2 * truth.depth
        assert r.signed_depth < 0  # scratches and dents go down


def test_a_clean_part_passes_and_a_golden_reference_keeps_only_the_defects(plate) -> None:
    golden = render_plate(PlateOptions(seed=0, relief=False))  # same plate, marks, no defects
    ls = Model.least_squares(maps=MAPS)
    clean = from_maps(ls(golden.stack).maps, "golden")  # type: ignore[arg-type]
    verdict, _ = find_defects(clean, DefectOptions(depth=DEPTH_PX))
    assert verdict.passed and verdict.exit_code == 0  # marks and all
    part = from_maps(ls(plate.stack).maps, "part")  # type: ignore[arg-type]
    verdict, labels = find_defects(part, DefectOptions(depth=DEPTH_PX), reference=clean)
    found, false = _hits(plate, labels)
    assert len(found) == 5 and false == []
    assert verdict.shift is not None and max(map(abs, verdict.shift)) < 0.2


def test_reference_alignment_recovers_a_shift() -> None:
    rng = np.random.default_rng(0)
    base = cv2_smooth(rng.normal(size=(96, 120)).astype(np.float32))
    moved = shift_map(base, 3.0, -2.0)
    dx, dy, _ = _align(base, moved)
    assert dx == pytest.approx(3.0, abs=0.2) and dy == pytest.approx(-2.0, abs=0.2)


def cv2_smooth(a: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.GaussianBlur(a, (0, 0), 2.0)


def test_cli_verdict_overlay_and_exit_codes(plate, plate_run: Path, tmp_path: Path) -> None:
    out = tmp_path / "v"
    assert inspect_main([str(plate_run), "--depth", str(DEPTH_PX), "-o", str(out), "-q"]) == 1
    verdict = json.loads((out / "verdict.json").read_text())
    assert verdict["verdict"] == "fail" and verdict["defects"] == 5
    assert verdict["units"]["depth"] == "px"
    import cv2

    overlay = cv2.imread(str(out / "overlay.png"), cv2.IMREAD_UNCHANGED)
    assert overlay.shape == (*plate.stack.shape, 3)
    # a threshold above every defect: pass, exit 0
    out2 = tmp_path / "v2"
    assert inspect_main([str(plate_run), "--depth", "5", "-o", str(out2), "-q"]) == 0
    assert json.loads((out2 / "verdict.json").read_text())["verdict"] == "pass"
    # against itself as the golden part: nothing differs
    out3 = tmp_path / "v3"
    code = inspect_main(
        [str(plate_run), "--reference", str(plate_run), "--depth", str(DEPTH_PX), "-o", str(out3)]
    )
    assert code == 0


def _code(argv: list[str]) -> int:
    """msf-inspect's exit code, also when argparse refuses a flag (it exits itself)."""
    try:
        return inspect_main(argv)
    except SystemExit as exc:
        return int(exc.code or 0)


@pytest.mark.parametrize(
    "extra, problem",
    [
        (["--depth", "nan"], "--depth"),
        (["--depth", "inf"], "--depth"),
        ([], "give a depth threshold"),
    ],
)
def test_cli_bad_thresholds(plate_run: Path, tmp_path: Path, capsys, extra, problem) -> None:
    out = tmp_path / "bad"
    assert _code([str(plate_run), "-o", str(out), *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("msf-inspect: error:") and problem in err[0]
    assert not out.exists()


def test_cli_reference_of_another_size_and_empty_mask(
    plate_run: Path, tmp_path: Path, capsys
) -> None:
    small = render_plate(PlateOptions(height=96, width=128, mask_edge=100))
    ref = tmp_path / "small"
    Model.least_squares(maps=MAPS)(small.stack).save(ref)
    out = tmp_path / "v"
    code = inspect_main([str(plate_run), "--reference", str(ref), "--depth", "0.1", "-o", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "128x96 but the part is 192x128" in err[0]
    assert not out.exists()
    # a run whose mask is empty: the local shape is NaN everywhere
    from msfnet.runtime.results.maps.registered import read_tiff, write_tiff

    empty = tmp_path / "empty"
    empty.mkdir()
    for name in ("maps.json", "curvature.tif", "albedo.tif"):
        (empty / name).write_bytes((plate_run / name).read_bytes())
    write_tiff(empty / "local_shape.tif", read_tiff(plate_run / "local_shape.tif") * np.nan)
    code = inspect_main([str(empty), "--depth", "0.1", "-o", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "mask is empty" in err[0]
    assert not out.exists()


def test_options_refuse_bad_values() -> None:
    with pytest.raises(InputError, match="positive, finite"):
        DefectOptions(depth=float("nan"))
    with pytest.raises(InputError, match="polarity"):
        DefectOptions(depth=0.1, polarity="sideways")


@pytest.mark.slow
def test_default_path_on_a_stack_finds_every_defect(plate, tmp_path: Path) -> None:
    """msf-inspect on the stack itself (msf-run's default path: network + detail fusion)."""
    stack = plate.stack
    src = tmp_path / "plate.npz"
    np.savez(src, images=stack.images, lights=stack.lights, mask=stack.mask)
    out = tmp_path / "v"
    code = inspect_main([str(src), "--depth", str(DEPTH_PX), "--threads", "2", "-o", str(out)])
    assert code == 1
    verdict = json.loads((out / "verdict.json").read_text())
    assert verdict["defects"] == 5
    centres = [tuple(r["centroid"]) for r in verdict["regions"]]
    for x, y in centres:  # each region sits on a defect, none on a printed mark
        assert plate.defects[round(y), round(x)] > 0 or any(
            plate.defects[max(0, int(y) - 3) : int(y) + 4, max(0, int(x) - 3) : int(x) + 4].ravel()
        )


def _edited_run(plate_run: Path, folder: Path) -> Path:
    import shutil

    shutil.copytree(plate_run, folder)
    (folder / ".msfnet-output.json").unlink()
    return folder


@pytest.mark.parametrize(
    "tiff, data, problem",
    [
        ("curvature.tif", np.zeros((10, 10), np.float32), "but local_shape.tif is"),
        ("albedo.tif", np.zeros((5, 5, 3), np.float32), "but local_shape.tif is"),
        ("albedo.tif", np.zeros((128, 192), np.float32), "H x W x 3"),
        ("local_shape.tif", np.zeros((128, 192, 3), np.float32), "H x W map"),
        ("local_shape.tif", np.zeros((128, 192), np.complex64), "real numbers"),
    ],
)
def test_a_run_folder_with_maps_that_do_not_fit_is_bad_input(
    plate_run: Path, tmp_path: Path, capsys, tiff: str, data: np.ndarray, problem: str
) -> None:
    """They crashed (exit 1: "defects found" to a PLC) or, complex, passed."""
    import tifffile

    run = _edited_run(plate_run, tmp_path / "run")
    tifffile.imwrite(run / tiff, data, photometric="minisblack")
    out = tmp_path / "v"
    assert _code([str(run), "--depth", "0.1", "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and tiff in err[0] and problem in err[0], err
    assert not out.exists()


@pytest.mark.parametrize("size", ["true", "1e400", "-5", '"0.1"'])
def test_a_pixel_size_that_is_no_length_is_bad_input(
    plate_run: Path, tmp_path: Path, capsys, size: str
) -> None:
    """1e400 reached verdict.json as Infinity (not JSON); true read as 1 mm."""
    import json

    run = _edited_run(plate_run, tmp_path / "run")
    info = json.loads((run / "maps.json").read_text())
    info["registered"]["pixel_size_mm"] = "SIZE"
    text = json.dumps(info).replace('"SIZE"', size)
    (run / "maps.json").write_text(text)
    assert _code([str(run), "--depth", "0.1", "-o", str(tmp_path / "v")]) == 2
    assert "pixel_size_mm" in capsys.readouterr().err


@pytest.mark.parametrize("debug", [False, True])
def test_a_failure_of_the_tool_never_reads_as_defects_found(
    plate_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys, debug: bool
) -> None:
    """A crash exited 1, "defects found" to a PLC; so did one under --debug, which the crash
    message tells the user to rerun with."""
    from msfnet.runtime.cli import inspect as cli

    def broken(*args, **kwargs):  # type: ignore[no-untyped-def]
        raise RuntimeError("a bug")

    monkeypatch.setattr(cli, "find_defects", broken)
    extra = ["--debug"] if debug else []
    assert _code([str(plate_run), "--depth", "0.1", "-o", str(tmp_path / "v"), *extra]) == 3
    assert ("Traceback" if debug else "internal error") in capsys.readouterr().err
    assert _code([str(plate_run), "-o", str(tmp_path / "w"), *extra]) == 2  # bad input


# ------------------------------------------------- a second review: references, frames, peaks


def _bumpy(shift: float = 0.0, seed: int = 1) -> np.ndarray:
    """A smooth random relief (a ring of bumps' stand-in), moved ``shift`` px along x."""
    rng = np.random.default_rng(seed)
    base = cv2_smooth(rng.normal(size=(96, 128)).astype(np.float32)) * 0.05
    return shift_map(base, shift, 0.0) if shift else base


def _part(local: np.ndarray, **kw: object) -> InspectionInput:
    args: dict[str, object] = {
        "local_shape": local,
        "curvature": None,
        "albedo": None,
        "units": {"depth": "px", "curvature": "1/px"},
        "pixel_size_mm": None,
        "source": "part",
        "local_size_px": 12.0,
    }
    args.update(kw)
    return InspectionInput(**args)  # type: ignore[arg-type]


def test_a_uniform_albedo_does_not_decide_the_alignment() -> None:
    """A machined part's albedo is one value plus noise: aligned on it, a golden part moved
    2 px read as 0 px, and the good part failed."""
    rng = np.random.default_rng(3)

    def flat_albedo() -> np.ndarray:
        return (0.7 + 0.0005 * rng.normal(size=(96, 128, 3))).astype(np.float32)

    part = _part(_bumpy(), albedo=flat_albedo())
    golden = _part(_bumpy(shift=2.0), albedo=flat_albedo(), source="golden")
    verdict, labels = find_defects(part, DefectOptions(depth=0.01), golden)
    assert verdict.aligned_on == "local shape"
    assert verdict.shift == pytest.approx((-2.0, 0.0), abs=0.1)
    assert verdict.passed and labels.max() == 0
    # a printed part: the albedo's features align it (and the local shape could too)
    printed = flat_albedo()
    printed[30:50, 40:60] = 0.2
    part = _part(_bumpy(), albedo=printed)
    golden = _part(_bumpy(2.0), albedo=shift_map_rgb(printed, 2.0), source="golden")
    verdict, _ = find_defects(part, DefectOptions(depth=0.01), golden)
    assert verdict.shift == pytest.approx((-2.0, 0.0), abs=0.1) and verdict.passed


def shift_map_rgb(rgb: np.ndarray, dx: float) -> np.ndarray:
    return np.stack([shift_map(rgb[..., c], dx, 0.0) for c in range(3)], axis=2)


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (
            {"units": {"depth": "mm", "curvature": "1/mm"}, "pixel_size_mm": 0.05},
            "units: reference px, part mm; pixel size: reference None mm, part 0.05 mm",
        ),
        ({"local_size_px": 30.0}, "local size: reference 12 px, part 30 px"),
        ({"frame": Frame((10, 0), 1)}, "ROI corner / downscale"),
    ],
)
def test_a_reference_mapped_differently_is_refused(change: dict, words: str) -> None:
    """A part in mm minus itself in px failed (exit 1, "0.32 mm"); so did another local size."""
    part = _part(_bumpy(), **change)
    golden = _part(_bumpy(), source="golden")
    with pytest.raises(InputError) as err:
        find_defects(part, DefectOptions(depth=0.01), golden)
    assert words in err.value.message and err.value.path == Path("golden")


def test_curvature_keeps_the_polarity_and_the_reference() -> None:
    """--curvature ignored both: --polarity up reported dents, a part against itself failed."""
    yy, xx = np.mgrid[:64, :64].astype(np.float32)
    dent = -0.2 * np.exp(-((xx - 20) ** 2 + (yy - 30) ** 2) / 8.0)  # concave: negative
    bump = 0.2 * np.exp(-((xx - 45) ** 2 + (yy - 30) ** 2) / 8.0)
    curv = (dent + bump).astype(np.float32)
    part = InspectionInput(
        local_shape=None,
        curvature=curv,
        albedo=None,
        units={"depth": "px", "curvature": "1/px"},
        pixel_size_mm=None,
        source="part",
    )
    for polarity, x in (("up", 45), ("down", 20)):
        verdict, _ = find_defects(part, DefectOptions(curvature=0.1, polarity=polarity))
        assert len(verdict.regions) == 1 and verdict.regions[0].peak == (x, 30), polarity
    both, _ = find_defects(part, DefectOptions(curvature=0.1))
    assert len(both.regions) == 2
    against_itself, _ = find_defects(part, DefectOptions(curvature=0.1), part)
    assert against_itself.passed
    with pytest.raises(InputError, match=r"^part: depth needs local_shape\.tif"):
        find_defects(part, DefectOptions(depth=0.1))


def test_the_peak_is_the_deepest_point_and_is_placed_in_the_camera_image() -> None:
    """The message named the region's centroid (a ring's is its empty centre), and with --roi
    every coordinate was the ROI's, with nothing to say so."""
    yy, xx = np.mgrid[:64, :80].astype(np.float32)
    r = np.hypot(xx - 40, yy - 32)
    ring = -0.3 * np.exp(-((r - 15) ** 2) / 4.0)
    ring[32, 55] = -0.6  # the deepest point, on the ring's right
    frame = Frame((100, 50), 2)
    verdict, _ = find_defects(_part(ring.astype(np.float32), frame=frame), DefectOptions(0.1))
    (region,) = verdict.regions
    assert region.peak == (55, 32) and region.depth == pytest.approx(0.6)
    assert region.centroid == pytest.approx((40, 32), abs=0.5)  # the empty centre
    # map pixel (55, 32) covers image pixels 210-211 x 114-115: its centre is 210.5, 114.5
    assert region.image_peak == (210.5, 114.5)
    x, y, w, h = region.bbox
    assert region.image_bbox == (100 + 2 * x, 50 + 2 * y, 2 * w, 2 * h)
    assert verdict.as_dict()["frame"] == {"origin_xy": [100, 50], "downscale": 2}


def test_a_plain_part_is_compared_in_place_not_at_a_peak_of_noise() -> None:
    """Without features (uniform albedo, no relief) the best correlation was noise: a golden
    taken 13 px off hid a 0.34 px dent outside the compared area, and others were refused as
    "more than 32 px off"."""

    def plain(seed: int) -> InspectionInput:
        r = np.random.default_rng(seed)
        return _part(
            (0.002 * r.normal(size=(96, 128))).astype(np.float32),
            albedo=(0.7 + 0.002 * r.normal(size=(96, 128, 3))).astype(np.float32),
        )

    part = plain(1)
    yy, xx = np.mgrid[:96, :128]
    part.local_shape = part.local_shape - 0.4 * np.exp(-((xx - 64) ** 2 + (yy - 88) ** 2) / 8.0)
    for seed in range(2, 8):
        verdict, _ = find_defects(part, DefectOptions(depth=0.1), plain(seed))
        assert verdict.shift == (0.0, 0.0) and verdict.aligned_on.startswith("none")
        assert len(verdict.regions) == 1 and verdict.regions[0].peak == (64, 88)


def test_a_reference_too_far_off_is_a_mismatch_verdict() -> None:
    """A part 40 px from where the reference lies is not judged against it: a verdict of its
    own (exit 4) a station logs and goes on from, not an input error."""
    part = _part(_bumpy())
    golden = _part(_bumpy(shift=40.0), source="golden")
    verdict, labels = find_defects(part, DefectOptions(depth=0.01), golden)
    assert verdict.word == "mismatch" and verdict.exit_code == 4 and not labels.any()
    assert verdict.mismatch is not None and "px off the reference (over 32)" in verdict.mismatch


def test_older_run_folders_and_curvature_only_runs_keep_their_frame_and_units(
    plate, tmp_path: Path
) -> None:
    """A run from before maps.json had "frame" read as the whole image (its --roi is in
    profile.json); a curvature-only run in mm read as px (no local_shape unit written)."""
    from msfnet.runtime.inspection.defects import read_run

    run = tmp_path / "run"
    maps = MapOptions(maps=("albedo", "height", "curvature"))
    Model.least_squares(maps=maps)(plate.stack).save(run)
    info = json.loads((run / "maps.json").read_text())
    del info["frame"]
    (run / "maps.json").write_text(json.dumps(info))
    profile = json.loads((run / "profile.json").read_text())
    profile["input"] = {"roi": [64, 10, 64, 60], "downscale": 2}
    (run / "profile.json").write_text(json.dumps(profile))
    assert read_run(run).frame == Frame((64, 10), 2)
    (run / "profile.json").unlink()
    assert read_run(run).frame == Frame()  # nothing recorded: the whole image, as then
    curv = tmp_path / "curv"
    mm = MapOptions(maps=("curvature",), pixel_size_mm=0.05)
    Model.least_squares(maps=mm)(plate.stack).save(curv)
    assert read_run(curv).units == {"depth": "mm", "curvature": "1/mm"}


def test_the_judged_map_statistics_are_printed_and_kept(plate_run: Path, tmp_path: Path, capsys):
    """msf-inspect printed no statistics of the map it judges, so a user could not choose a
    threshold (issue #49): p50 / p99 / max of |local shape| in its units, beside the threshold."""
    out = tmp_path / "v"
    inspect_main([str(plate_run), "--depth", "0.1", "-o", str(out)])
    printed = capsys.readouterr().out.splitlines()
    stats = json.loads((out / "verdict.json").read_text())["statistics"]
    assert [s["map"] for s in stats] == ["local shape"] and stats[0]["units"] == "px"
    part = read_run(plate_run)
    assert part.local_shape is not None
    values = np.abs(part.local_shape[part.mask])
    assert stats[0]["p99"] == pytest.approx(float(np.percentile(values, 99)), rel=1e-5)
    assert stats[0]["max"] == pytest.approx(float(values.max()), rel=1e-6)
    assert printed[-1].startswith("local shape: p50 ") and "(threshold 0.1 px)" in printed[-1]


def test_region_shapes_tell_a_scratch_from_a_dent_a_pit_and_a_bump() -> None:
    from msfnet.runtime.inspection.defects import region_shape

    rows, cols = np.mgrid[0:40, 0:40]
    line = (np.abs(rows - cols) <= 1) & (rows > 5) & (rows < 35)  # a 45 deg scratch
    disk = (rows - 20) ** 2 + (cols - 20) ** 2 <= 16
    dot = (rows - 20) ** 2 + (cols - 20) ** 2 <= 1
    scratch = region_shape(*np.nonzero(line), sunk=True)
    assert scratch.kind == "scratch" and scratch.orientation_deg == pytest.approx(45, abs=1)
    assert scratch.length_px == pytest.approx(29 * 2**0.5, rel=0.1) and scratch.width_px < 4
    assert region_shape(*np.nonzero(disk), sunk=True).kind == "dent"
    assert region_shape(*np.nonzero(dot), sunk=True).kind == "pit"
    assert region_shape(*np.nonzero(line), sunk=False).kind == "bump"
    across = region_shape(*np.nonzero((rows == 20) & (cols > 3)), sunk=True)
    assert across.orientation_deg == pytest.approx(0, abs=0.5) and across.width_px == 1


def test_the_plate_defects_come_out_by_kind_in_the_verdict_and_its_table(plate) -> None:
    result = Model.least_squares(maps=MAPS)(plate.stack)
    verdict, _ = find_defects(from_maps(result.maps, "plate"), DefectOptions(depth=DEPTH_PX))  # type: ignore[arg-type]
    truth = sorted(d.kind for d in plate.defect_list)
    assert sorted(r.kind for r in verdict.regions) == truth
    rows = verdict.csv_text().splitlines()
    assert len(rows) == 1 + len(verdict.regions)
    header = rows[0].split(",")
    assert {"kind", "length_px", "width_px", "centroid_x", "bbox_h"} <= set(header)
    assert all(len(r.split(",")) == len(header) for r in rows[1:])


def test_a_keep_out_leaves_the_rim_where_the_mask_ends_on_the_part() -> None:
    """A rim 2 px inside the mask's edge (what a mask on a part's own edge draws) is a defect
    without a keep-out and none with --keep-out 4; the image's border is not an edge."""
    h, w = 60, 80
    local = np.zeros((h, w), np.float32)
    local[:, 60:62] = -0.3  # a rim 2-3 px inside the mask's edge (column 63 is its last)
    local[20:24, 2:6] = -0.3  # a dent 2 px from the image's left border: still judged
    local[:, 64:] = np.nan
    part = InspectionInput(local, None, None, {"depth": "px", "curvature": "1/px"}, None, "p")
    plain, _ = find_defects(part, DefectOptions(depth=0.1))
    kept, labels = find_defects(part, DefectOptions(depth=0.1, keep_out_px=4))
    assert len(plain.regions) == 2 and len(kept.regions) == 1
    assert labels[20:24, 2:6].all() and not labels[:, 58:].any()
    with pytest.raises(InputError, match="leaves nothing"):
        find_defects(part, DefectOptions(depth=0.1, keep_out_px=100))


def test_the_deviation_picture_has_one_scale_the_threshold_sets() -> None:
    """deviation.png: grey where the part is as it should be, full red at a sunk pixel at the
    threshold, blue raised, dark outside, whatever the map's own range; a bar below."""
    from msfnet.runtime.inspection.defects import BAR_PX, deviation_picture

    local = np.zeros((40, 50), np.float32)
    local[10, 10], local[20, 20] = -0.1, 0.1  # at the threshold, sunk and raised
    local[:, 45:] = np.nan
    part = InspectionInput(local, None, None, {"depth": "px", "curvature": "1/px"}, None, "p")
    verdict, _ = find_defects(part, DefectOptions(depth=0.1, min_area_px=1))
    rgb = deviation_picture(verdict)
    assert rgb.shape == (40 + BAR_PX, 50, 3)
    assert tuple(rgb[30, 30]) == (150, 150, 150)  # calm
    assert tuple(rgb[10, 10]) == (230, 40, 40) and tuple(rgb[20, 20]) == (40, 90, 235)
    assert rgb[5, 47].max() < 40  # not inspected
