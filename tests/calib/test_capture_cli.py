"""msf-capture as a user meets it: the no-hardware rehearsal through the CLIs, re-runs, checks
before capturing, the live loop, linearisation records, CLI conventions."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from msfnet.calib.capture_cli import main as capture_main
from msfnet.calib.cli import main as calib_main
from msfnet.runtime.imageio import read_image
from msfnet.runtime.metrics import angular_error_deg
from msfnet.runtime.run_cli import main as run_main
from msfnet.runtime.stack import load_stack, read_vectors
from msfnet.runtime.stack.transforms import srgb_to_linear
from msfnet.synth.spheres import ring_lights

SIM = ["--camera", "sim", "-q"]


def _rehearse(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The README's no-hardware rehearsal, up to the msf-run call."""
    monkeypatch.chdir(tmp_path)
    assert capture_main(["calib/", *SIM, "--sim-scene", "chrome"]) == 0
    assert (tmp_path / "calib" / "mask.png").is_file()  # the simulated camera's own mask
    assert calib_main(["directions", "calib/", "-o", "lights.txt"]) == 0
    assert capture_main(["obj/", *SIM, "--light-directions", "lights.txt"]) == 0


def test_no_hardware_rehearsal_through_the_clis(tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    _rehearse(tmp_path, monkeypatch)
    calibrated = read_vectors(tmp_path / "lights.txt", "light directions")
    err = angular_error_deg(calibrated, ring_lights(12))
    print(f"calibrated lights vs the rig's: mean {err.mean():.3f}, max {err.max():.3f} deg")
    assert err.max() < 1.0
    stack = load_stack(tmp_path / "obj")
    np.testing.assert_allclose(stack.lights, calibrated, atol=1e-6)  # not the rig's truth
    assert stack.normals_gt is not None and 0.2 < stack.mask.mean() < 0.6
    assert run_main(["obj/", "--method", "l2", "-q"]) == 0
    metrics = json.loads((tmp_path / "msf-out" / "obj" / "metrics.json").read_text())
    print(f"least squares on the rehearsal stack: MAE {metrics['mae_deg']:.3f} deg, median "
          f"{metrics['median_deg']:.3f} deg")
    # (the mean includes the rim, where attached shadows bend least squares by design)
    assert metrics["median_deg"] < 1.0 and metrics["mae_deg"] < 5.0
    assert metrics["pixels"] == int(stack.mask.sum())


@pytest.mark.slow
def test_no_hardware_rehearsal_with_the_bundled_network(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _rehearse(tmp_path, monkeypatch)
    assert run_main(["obj/", "-q"]) == 0  # exactly the README's last step
    metrics = json.loads((tmp_path / "msf-out" / "obj" / "metrics.json").read_text())
    print(f"bundled network on the rehearsal stack: {metrics['mae_deg']:.2f} deg")
    assert metrics["mae_deg"] < 10.0 and metrics["invalid"] == 0


def test_rerun_on_a_finished_folder_keeps_it(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "obj"
    assert capture_main([str(out), "--camera", "sim", "--count", "6"]) == 0
    stamps = {p.name: p.stat().st_mtime_ns for p in out.rglob("*.png")}
    capsys.readouterr()
    assert capture_main([str(out), "--camera", "sim", "--count", "6"]) == 0
    printed = capsys.readouterr()
    assert "stack complete: all 6 frames" in printed.out
    assert "0frame" not in printed.out + printed.err
    assert {p.name: p.stat().st_mtime_ns for p in out.rglob("*.png")} == stamps
    # a different rig size is refused, not mixed in
    assert capture_main([str(out), "--camera", "sim", "--count", "8"]) == 2
    assert "has 6 lights, this one 8" in capsys.readouterr().err


def test_inputs_are_checked_before_the_first_frame(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    bad_count = tmp_path / "five.txt"
    bad_count.write_text("0 0 1\n" * 5)
    flat = tmp_path / "flat.txt"  # 12 lights in one plane: normals cannot be recovered
    flat.write_text("".join(f"{np.cos(a):.4f} {np.sin(a):.4f} 0\n"
                            for a in np.linspace(0, 6, 12)))
    small_mask = tmp_path / "mask.png"
    import cv2

    cv2.imwrite(str(small_mask), np.full((10, 10), 255, np.uint8))
    cases = [(["--light-directions", str(bad_count)], "5 light directions for 12 lights"),
             (["--light-directions", str(flat)], "do not span 3-D"),
             (["--mask", str(small_mask)], "mask is 10x10 but the camera delivers 160x128"),
             (["--mask", str(tmp_path / "none.png")], "not found")]
    for i, (extra, message) in enumerate(cases):
        out = tmp_path / f"o{i}"
        assert capture_main([str(out), "--camera", "sim", *extra]) == 2, extra
        assert message in capsys.readouterr().err
        assert not (out / "raw").exists()  # nothing was captured


def test_a_folder_of_someone_elses_images_is_refused(tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]
                                                     ) -> None:
    import cv2

    theirs = tmp_path / "photos"
    theirs.mkdir()
    cv2.imwrite(str(theirs / "IMG_0001.png"), np.zeros((4, 4), np.uint8))
    assert capture_main([str(theirs), "--camera", "sim", "--count", "4"]) == 2
    assert "images msf-capture did not take (e.g. IMG_0001.png" in capsys.readouterr().err
    assert sorted(p.name for p in theirs.iterdir()) == ["IMG_0001.png"]
    assert capture_main([str(theirs), "--camera", "sim", "--count", "4", "--overwrite",
                         "-q"]) == 0
    assert (theirs / "IMG_0001.png").is_file() and (theirs / "004.png").is_file()


def test_loop_captures_and_runs_numbered_takes(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    root = tmp_path / "takes"
    assert capture_main([str(root), "--camera", "sim", "--count", "6", "--loop", "2",
                         "--run", "--method", "l2"]) == 0
    printed = capsys.readouterr().out
    assert "take 001" in printed and "take 002" in printed and "MAE" in printed
    for take in ("001", "002"):
        assert load_stack(root / take).num_lights == 6
        assert (root / f"{take}-normals" / "normals.npy").is_file()
    # an interrupted take is resumed by the next loop, not skipped
    (root / "003" / "raw").mkdir(parents=True)
    (root / "003" / "session.json").write_text(json.dumps({"count": 6, "frames": {}}))
    assert capture_main([str(root), "--camera", "sim", "--count", "6", "--loop", "1",
                         "-q"]) == 0
    assert load_stack(root / "003").num_lights == 6 and not (root / "004").exists()


def test_capture_loop_api(tmp_path: Path) -> None:
    from msfnet.calib.cameras import SimulatedCamera
    from msfnet.calib.capture import capture_loop
    from msfnet.calib.lights import SimulatedLights, SimulatedRig
    from msfnet.runtime.pipeline import Model
    from msfnet.synth.spheres import mirror_scene

    rig = SimulatedRig(mirror_scene(48, 40, 16, kind="matte"), ring_lights(5))
    steps = capture_loop(SimulatedCamera(rig), SimulatedLights(rig), tmp_path / "live",
                         iterations=2, model=Model.least_squares(),
                         light_directions=rig.lights, progress=False, log=lambda m: None)
    got = list(steps)
    assert [s.stack.name for s in got] == ["001", "002"]
    assert all(s.result is not None and s.output is not None and s.output.is_dir()
               for s in got)


def test_linearisation_is_applied_and_recorded(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "cam"
    assert capture_main([str(out), "--camera", "sim", "--count", "4", "--srgb", "-q"]) == 0
    session = json.loads((out / "session.json").read_text())
    assert session["linearisation"] == {"kind": "srgb"} and session["stack_white_level"] == 65535
    raw = read_image(out / "raw" / "002.png") / 65535.0
    amb = read_image(out / "raw" / "ambient.png") / 65535.0
    want = (srgb_to_linear(raw) - srgb_to_linear(amb)).clip(0) * 65535.0
    np.testing.assert_allclose(read_image(out / "002.png"), want, atol=0.51)
    # asking for another encoding rebuilds the stack from raw/ (the frames stay as taken)
    assert capture_main([str(out), "--camera", "sim", "--count", "4", "--gamma", "2.2"]) == 0
    assert "rebuilding the stack images" in capsys.readouterr().out
    session = json.loads((out / "session.json").read_text())
    assert session["linearisation"] == {"kind": "gamma", "gamma": 2.2}
    plain = tmp_path / "plain"
    assert capture_main([str(plain), "--camera", "sim", "--count", "4", "-q"]) == 0
    assert json.loads((plain / "session.json").read_text())["linearisation"] is None


def test_cli_conventions(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert capture_main(["-o", str(tmp_path / "a"), "--camera", "sim", "--count", "4",
                         "-q"]) == 0
    assert (tmp_path / "a" / "004.png").is_file()
    assert capture_main([str(tmp_path / "b"), "-o", str(tmp_path / "c"), "--camera", "sim"]) == 2
    assert "once" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        capture_main(["--version"])
    assert exc.value.code == 0 and "msf-capture" in capsys.readouterr().out
