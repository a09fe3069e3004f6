"""msf-capture as a user meets it: the no-hardware rehearsal through the CLIs, re-runs, checks
before capturing, the live loop, linearisation records, CLI conventions."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from msfnet.calib.capture_cli import main as capture_main
from msfnet.calib.cli import main as calib_main
from msfnet.common.imageio import read_image
from msfnet.runtime.cli.run import main as run_main
from msfnet.runtime.evaluate.metrics import angular_error_deg
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


def test_no_hardware_rehearsal_through_the_clis(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
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
    print(
        f"least squares on the rehearsal stack: MAE {metrics['mae_deg']:.3f} deg, median "
        f"{metrics['median_deg']:.3f} deg"
    )
    # (the mean includes the rim, where attached shadows bend least squares by design)
    assert metrics["median_deg"] < 1.0 and metrics["mae_deg"] < 5.0
    assert metrics["pixels"] == int(stack.mask.sum())


@pytest.mark.slow
def test_no_hardware_rehearsal_with_the_bundled_network(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _rehearse(tmp_path, monkeypatch)
    assert run_main(["obj/", "-q"]) == 0  # exactly the README's last step
    metrics = json.loads((tmp_path / "msf-out" / "obj" / "metrics.json").read_text())
    print(f"bundled network on the rehearsal stack: {metrics['mae_deg']:.2f} deg")
    assert metrics["mae_deg"] < 10.0 and metrics["invalid"] == 0


def test_rerun_on_a_finished_folder_keeps_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
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


def test_inputs_are_checked_before_the_first_frame(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad_count = tmp_path / "five.txt"
    bad_count.write_text("0 0 1\n" * 5)
    flat = tmp_path / "flat.txt"  # 12 lights in one plane: normals cannot be recovered
    flat.write_text("".join(f"{np.cos(a):.4f} {np.sin(a):.4f} 0\n" for a in np.linspace(0, 6, 12)))
    small_mask = tmp_path / "mask.png"
    import cv2

    cv2.imwrite(str(small_mask), np.full((10, 10), 255, np.uint8))
    cases = [
        (["--light-directions", str(bad_count)], "5 light directions for 12 lights"),
        (["--light-directions", str(flat)], "do not span 3-D"),
        (["--mask", str(small_mask)], "mask is 10x10 but the camera delivers 160x128"),
        (["--mask", str(tmp_path / "none.png")], "not found"),
    ]
    for i, (extra, message) in enumerate(cases):
        out = tmp_path / f"o{i}"
        assert capture_main([str(out), "--camera", "sim", *extra]) == 2, extra
        assert message in capsys.readouterr().err
        assert not (out / "raw").exists()  # nothing was captured


def test_a_folder_of_someone_elses_images_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import cv2

    theirs = tmp_path / "photos"
    theirs.mkdir()
    cv2.imwrite(str(theirs / "IMG_0001.png"), np.zeros((4, 4), np.uint8))
    assert capture_main([str(theirs), "--camera", "sim", "--count", "4"]) == 2
    assert "images msf-capture did not take (e.g. IMG_0001.png" in capsys.readouterr().err
    assert sorted(p.name for p in theirs.iterdir()) == ["IMG_0001.png"]
    assert capture_main([str(theirs), "--camera", "sim", "--count", "4", "--overwrite", "-q"]) == 0
    assert (theirs / "IMG_0001.png").is_file() and (theirs / "004.png").is_file()


def test_loop_captures_and_runs_numbered_takes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = tmp_path / "takes"
    assert (
        capture_main(
            [str(root), "--camera", "sim", "--count", "6", "--loop", "2", "--run", "--method", "l2"]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "take 001" in printed and "take 002" in printed and "MAE" in printed
    for take in ("001", "002"):
        assert load_stack(root / take).num_lights == 6
        assert (root / f"{take}-normals" / "normals.npy").is_file()
    # an interrupted take is resumed by the next loop, not skipped
    (root / "003" / "raw").mkdir(parents=True)
    (root / "003" / "session.json").write_text(json.dumps({"count": 6, "frames": {}}))
    assert capture_main([str(root), "--camera", "sim", "--count", "6", "--loop", "1", "-q"]) == 0
    assert load_stack(root / "003").num_lights == 6 and not (root / "004").exists()


def test_capture_loop_api(tmp_path: Path) -> None:
    from msfnet.calib.cameras import SimulatedCamera
    from msfnet.calib.capture import capture_loop
    from msfnet.calib.lights import SimulatedLights, SimulatedRig
    from msfnet.runtime.api import Model
    from msfnet.synth.spheres import mirror_scene

    rig = SimulatedRig(mirror_scene(48, 40, 16, kind="matte"), ring_lights(5))
    steps = capture_loop(
        SimulatedCamera(rig),
        SimulatedLights(rig),
        tmp_path / "live",
        iterations=2,
        model=Model.least_squares(),
        light_directions=rig.lights,
        progress=False,
        log=lambda m: None,
    )
    got = list(steps)
    assert [s.stack.name for s in got] == ["001", "002"]
    assert all(s.result is not None and s.output is not None and s.output.is_dir() for s in got)


def test_linearisation_is_applied_and_recorded(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
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
    assert capture_main(["-o", str(tmp_path / "a"), "--camera", "sim", "--count", "4", "-q"]) == 0
    assert (tmp_path / "a" / "004.png").is_file()
    assert capture_main([str(tmp_path / "b"), "-o", str(tmp_path / "c"), "--camera", "sim"]) == 2
    assert "once" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        capture_main(["--version"])
    assert exc.value.code == 0 and "msf-capture" in capsys.readouterr().out


def _interrupt_after(monkeypatch: pytest.MonkeyPatch, frames: int) -> None:
    """The simulated camera's cable is pulled after ``frames`` frames (Ctrl-C, kill)."""
    from msfnet.calib.cameras import SimulatedCamera

    real = SimulatedCamera.capture
    taken = [0]

    def capture(self: SimulatedCamera) -> np.ndarray:
        if taken[0] >= frames:
            raise KeyboardInterrupt
        taken[0] += 1
        return real(self)

    monkeypatch.setattr(SimulatedCamera, "capture", capture)


def test_overwrite_rebuilds_the_stack_from_the_new_frames(tmp_path: Path) -> None:
    """--overwrite used to re-capture raw/ but keep the old stack images and filenames.txt
    (the 'already built' test passed on the fresh session): a silently stale stack."""
    out = tmp_path / "o"
    assert capture_main([str(out), *SIM, "--count", "6"]) == 0
    assert (
        capture_main([str(out), *SIM, "--count", "4", "--sim-scene", "chrome", "--overwrite"]) == 0
    )
    amb = read_image(out / "raw" / "ambient.png").astype(np.int64)
    for i in range(1, 5):  # each stack image is the new raw frame less the new ambient
        raw = read_image(out / "raw" / f"{i:03d}.png").astype(np.int64)
        np.testing.assert_array_equal(read_image(out / f"{i:03d}.png"), (raw - amb).clip(0))
    assert (out / "filenames.txt").read_text().split() == [f"{i:03d}.png" for i in range(1, 5)]
    assert not (out / "005.png").exists() and not (out / "raw" / "005.png").exists()
    session = json.loads((out / "session.json").read_text())
    assert session["count"] == 4 and session["camera"]["scene"] == "chrome"
    assert session["linearisation"] is None and session["ambient_subtracted"] is True
    assert load_stack(out).num_lights == 4


def test_overwrite_deletes_only_the_frames_msf_capture_writes(tmp_path: Path) -> None:
    """--overwrite used to delete every PNG in raw/, the user's own pictures too."""
    out = tmp_path / "o"
    assert capture_main([str(out), *SIM, "--count", "6"]) == 0
    holiday = out / "raw" / "holiday.png"
    import cv2

    cv2.imwrite(str(holiday), np.full((4, 4), 7, np.uint8))
    kept = holiday.read_bytes()
    assert capture_main([str(out), *SIM, "--count", "4", "--overwrite"]) == 0
    assert holiday.read_bytes() == kept
    assert sorted(p.name for p in (out / "raw").iterdir()) == [
        "001.png",
        "002.png",
        "003.png",
        "004.png",
        "ambient.png",
        "holiday.png",
    ]


def test_an_interrupted_overwrite_never_resumes_into_old_frames(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Killed right after --overwrite discarded the old session: the next plain run captures
    every frame anew (none of the old ones counts) and builds the stack from them."""
    out = tmp_path / "o"
    assert capture_main([str(out), *SIM, "--count", "4"]) == 0
    with monkeypatch.context() as m:
        _interrupt_after(m, 0)
        assert (
            capture_main([str(out), *SIM, "--count", "4", "--sim-scene", "chrome", "--overwrite"])
            == 130
        )
    assert sorted(p.name for p in out.iterdir()) == ["raw", "session.json"]
    assert not list((out / "raw").iterdir())
    assert capture_main([str(out), *SIM, "--count", "4", "--sim-scene", "chrome"]) == 0
    assert json.loads((out / "session.json").read_text())["camera"]["scene"] == "chrome"


def test_resume_with_other_camera_settings_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Resuming with another scene used to mix frames of both setups into one stack."""
    out = tmp_path / "b"
    with monkeypatch.context() as m:
        _interrupt_after(m, 3)
        assert capture_main([str(out), *SIM, "--count", "6"]) == 130
    capsys.readouterr()
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert capture_main([str(out), *SIM, "--count", "6", "--sim-scene", "chrome"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("msf-capture: error: "), err
    assert (
        "session.json" in err[0]
        and "scene" in err[0]
        and "matte" in err[0]
        and "chrome" in err[0]
        and "--overwrite" in err[0]
    ), err
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    # the same settings resume; a finished stack is refused another scene as well
    assert capture_main([str(out), *SIM, "--count", "6"]) == 0
    assert capture_main([str(out), *SIM, "--count", "6", "--sim-scene", "chrome"]) == 2
    assert "scene" in capsys.readouterr().err


def test_a_kill_while_overwrite_discards_leaves_no_resumable_mix(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Killed while the old frames go: a plain re-run refuses the folder (no old frame is
    resumed into a new session); --overwrite, still seeing msf-capture's session (marked as
    being discarded, removed last), starts over."""
    out = tmp_path / "o"
    assert capture_main([str(out), *SIM, "--count", "4"]) == 0
    real = Path.unlink

    def unlink(self: Path, missing_ok: bool = False) -> None:
        if self.parent.name == "raw":
            raise KeyboardInterrupt
        real(self, missing_ok)

    with monkeypatch.context() as m:
        m.setattr(Path, "unlink", unlink)
        assert capture_main([str(out), *SIM, "--count", "4", "--overwrite"]) == 130
    assert json.loads((out / "session.json").read_text())["discarding"] is True
    assert not (out / "filenames.txt").exists()
    capsys.readouterr()
    assert capture_main([str(out), *SIM, "--count", "4"]) == 2
    assert "interrupted" in capsys.readouterr().err
    assert capture_main([str(out), *SIM, "--count", "4", "--overwrite"]) == 0
    assert load_stack(out).num_lights == 4


def _tree_bytes(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}


@pytest.mark.parametrize(
    "theirs", ["001.png", "light_directions.txt", "filenames.txt", "raw/002.png", "mask.png"]
)
def test_overwrite_never_replaces_a_stack_it_did_not_capture(
    theirs: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--overwrite in a folder holding the user's own stack (no session.json) replaced their
    images and light file, though the help says other images stay: now refused, naming the
    file, and nothing in the folder changes."""
    _refused_over_users_file(tmp_path, theirs, capsys, "--overwrite")


def _refused_over_users_file(
    tmp_path: Path, theirs: str, capsys: pytest.CaptureFixture[str], *flags: str
) -> str:
    """msf-capture into a folder holding the user's ``theirs``: refused in one line naming
    it, nothing in the folder changed; returns the line."""
    import cv2

    folder = tmp_path / "mine"
    (folder / "raw").mkdir(parents=True)
    path = folder / theirs
    if path.suffix == ".png":
        cv2.imwrite(str(path), np.full((8, 8), 9, np.uint8))
    else:
        path.write_text("the user's own\n")
    before = _tree_bytes(folder)
    assert capture_main([str(folder), *SIM, "--count", "4", *flags]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and theirs in err[0] and "not msf-capture's" in err[0], err
    assert _tree_bytes(folder) == before
    return err[0]


@pytest.mark.parametrize(
    "theirs",
    [
        "001.png",
        "light_directions.txt",
        "light_intensities.txt",
        "filenames.txt",
        "Normal_gt.mat",
        "mask.png",
        "raw/002.png",
    ],
)
def test_a_file_under_a_name_msf_capture_writes_is_refused_without_overwrite(
    theirs: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """In a folder without session.json a plain capture replaced the user's light files,
    mask and ground truth (only images were looked for): every name msf-capture writes is
    refused, as with --overwrite, and nothing in the folder changes."""
    line = _refused_over_users_file(tmp_path, theirs, capsys)
    assert "--overwrite" not in line  # it would be refused with --overwrite too


@pytest.mark.parametrize(
    ("option", "name"),
    [
        ("--light-directions", "light_directions.txt"),
        ("--light-intensities", "light_intensities.txt"),
        ("--mask", "mask.png"),
    ],
)
@pytest.mark.parametrize("session", [False, True])
def test_an_input_inside_the_folder_under_an_output_name_is_refused(
    option: str, name: str, session: bool, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--light-directions obj/light_directions.txt`` was replaced by the run's own output
    (reformatted): an input the capture would write over is refused, in a new folder and in
    a session of msf-capture's alike."""
    import cv2

    folder = tmp_path / "obj"
    if session:
        assert capture_main([str(folder), *SIM, "--count", "12"]) == 0
    folder.mkdir(exist_ok=True)
    path = folder / name
    if option == "--mask":
        cv2.imwrite(str(path), np.full((128, 160), 255, np.uint8))
    elif option == "--light-directions":
        path.write_text("".join(f"{x:.3f} {y:.3f} {z:.3f}\n" for x, y, z in ring_lights(12)))
    else:
        path.write_text("1 1 1\n" * 12)
    before = _tree_bytes(folder)
    assert capture_main([str(folder), *SIM, "--count", "12", option, str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and name in err[0] and "would replace it" in err[0], err
    assert _tree_bytes(folder) == before


def test_overwrite_of_its_own_session_keeps_frames_beyond_its_count(tmp_path: Path) -> None:
    """Only the session's own frame names go: a 013.png the user put beside a 4-light
    session's frames is not msf-capture's to delete."""
    import cv2

    out = tmp_path / "o"
    assert capture_main([str(out), *SIM, "--count", "4"]) == 0
    extra = out / "raw" / "013.png"
    cv2.imwrite(str(extra), np.full((4, 4), 5, np.uint8))
    assert capture_main([str(out), *SIM, "--count", "4", "--overwrite"]) == 0
    assert extra.is_file()


def test_a_second_capture_into_a_busy_folder_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Two simultaneous captures into one folder both reported success, one's frames gone.
    The second, started while the first holds the folder, is refused at once; the first
    finishes untouched, and the folder is free again afterwards."""
    from _runtime_helpers import folder_held

    out = tmp_path / "o"
    with folder_held(out, "msf-capture") as holder:
        assert capture_main([str(out), *SIM, "--count", "4"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "another msf-capture is working in this folder" in err[0], err
        assert f"pid {holder.pid}" in err[0]
        assert not (out / "raw").exists() and not (out / "session.json").exists()
    assert capture_main([str(out), *SIM, "--count", "4"]) == 0
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == []  # no lock left


def test_a_session_without_a_light_count_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """It said "existing session has None lights"."""
    out = tmp_path / "o"
    out.mkdir()
    (out / "session.json").write_text('{"frames": {}}')
    assert capture_main([str(out), *SIM, "--count", "4"]) == 2
    err = capsys.readouterr().err
    assert "None" not in err and "no light count" in err


def test_loop_messages_never_advise_overwrite(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--loop refuses --overwrite, so its refusals must not suggest it."""
    root = tmp_path / "takes"
    (root / "001").mkdir(parents=True)
    (root / "001" / "session.json").write_text(json.dumps({"count": 6, "frames": {}}))
    assert capture_main([str(root), *SIM, "--count", "4", "--loop", "1"]) == 2
    err = capsys.readouterr().err
    assert "6 lights, this one 4" in err and "--overwrite" not in err, err


def test_with_run_json_stdout_holds_the_json_alone(tmp_path: Path, capsys) -> None:
    """'frames -> obj (stack)' went to stdout before msf-run's JSON: unparseable."""
    out = tmp_path / "obj"
    argv = [str(out), "--camera", "sim", "--light-rig", "sim", "--count", "8", "--run"]
    run_args = ["--method", "l2", "--no-maps", "--json", "-o", str(tmp_path / "res")]
    assert capture_main([*argv, *run_args]) == 0
    captured = capsys.readouterr()
    json.loads(captured.out)  # nothing else on stdout
    assert "frames ->" in captured.err


def test_exposure_takes_a_drivers_negative_units_but_not_for_an_oak(tmp_path: Path, capsys) -> None:
    """docs/calibration.md's `--exposure -6` (V4L2 / DirectShow log2 seconds) was refused."""
    from msfnet.calib.capture_cli import build_parser

    assert build_parser().parse_args([str(tmp_path / "o"), "--exposure", "-6"]).exposure == -6
    code = capture_main(
        [str(tmp_path / "o"), "--camera", "oak", "--exposure", "-6", "--count", "8"]
    )
    assert code == 2 and "microseconds" in capsys.readouterr().err


# ------------------------------------------------- review of light calibration and capture


@pytest.mark.parametrize("theirs", ["013.png", "raw/013.png"])
def test_overwrite_refuses_a_file_only_the_longer_new_session_would_write(
    theirs: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--overwrite of a 12-light session with 20 lights wrote its 013.png over the user's
    013.png beside the session (the old session never wrote that name): now refused before
    anything is discarded or captured."""
    import cv2

    out = tmp_path / "o"
    assert capture_main([str(out), *SIM]) == 0
    cv2.imwrite(str(out / theirs), np.full((4, 4), 7, np.uint8))
    before = _tree_bytes(out)
    capsys.readouterr()
    assert capture_main([str(out), *SIM, "--overwrite", "--count", "20"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"msf-capture: error: {out}: --overwrite"), err
    assert theirs in err[0] and "12 lights" in err[0], err
    assert _tree_bytes(out) == before
    # the session's own names are still replaced: the same count goes through
    assert capture_main([str(out), *SIM, "--overwrite"]) == 0


def test_a_finished_take_without_its_result_is_run_by_the_next_loop(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A take captured whole but whose run was stopped was skipped for good (the next loop
    took 002); now the next loop runs it. A take captured without --run is owed no result:
    the next --run loop captures a new one."""
    from msfnet.runtime.api import Model

    root = tmp_path / "takes"
    loop = [str(root), "--camera", "sim", "--count", "6", "--loop", "1", "-q"]
    run = [*loop, "--run", "--method", "l2"]

    def stopped(*_a: object, **_k: object) -> None:
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(Model, "__call__", stopped)  # Ctrl-C during the take's run
        assert capture_main(run) == 130
    assert (root / "001").is_dir() and not (root / "001-normals").exists()
    assert capture_main(run) == 0
    assert (root / "001-normals" / "normals.npy").is_file()
    assert not (root / "002").exists()
    # with its result the take is done: the next loop takes 002
    assert capture_main(run) == 0
    assert (root / "002-normals" / "normals.npy").is_file()
    # a take without --run, then a --run loop: a new take, 003 is not re-run
    assert capture_main(loop) == 0
    assert capture_main(run) == 0
    assert (root / "004-normals").is_dir() and not (root / "003-normals").exists()
    assert not list(root.glob(".*run-pending"))


@pytest.mark.parametrize("frame", ["003.png", "ambient.png"])
def test_a_raw_frame_of_another_size_is_one_line_and_builds_nothing(
    frame: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    """A damaged or replaced frame in raw/ crashed the resumed session with a broadcast error
    (exit 1) after writing some stack images; now refused before capturing, naming it."""
    import cv2

    out = tmp_path / "o"
    _interrupt_after(monkeypatch, 6)
    assert capture_main([str(out), *SIM, "--count", "8"]) == 130
    monkeypatch.undo()
    cv2.imwrite(str(out / "raw" / frame), np.zeros((50, 50, 3), np.uint16))
    capsys.readouterr()
    assert capture_main([str(out), *SIM, "--count", "8"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"msf-capture: error: {out / 'raw' / frame}: "), err
    assert "50x50" in err[0], err
    assert not list(out.glob("*.png"))  # no stack image


def test_a_frame_of_another_size_is_refused_before_any_stack_image(tmp_path: Path) -> None:
    """finish_stack checks every frame before writing the first stack image."""
    import cv2

    from msfnet.calib.capture import finish_stack
    from msfnet.common.errors import InputError

    out = tmp_path / "o"
    assert capture_main([str(out), *SIM, "--count", "6"]) == 0
    for p in out.glob("*.png"):
        p.unlink()
    cv2.imwrite(str(out / "raw" / "005.png"), np.zeros((50, 50, 3), np.uint8))
    with pytest.raises(InputError, match=r"005\.png: frame is 50x50, 8-bit but"):
        finish_stack(out, log=lambda m: None)
    assert not list(out.glob("*.png"))


def test_run_options_are_checked_before_capturing(tmp_path: Path, capfd) -> None:
    """--run --method bogus captured every frame, then failed in msf-run."""
    out = tmp_path / "o"
    try:
        code = capture_main([str(out), *SIM, "--run", "--method", "bogus"])
    except SystemExit as exc:
        code = int(exc.code or 0)
    assert code == 2
    assert "--method" in capfd.readouterr().err
    assert not out.exists()


def test_new_light_directions_drop_the_intensities_of_the_old_ones(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The simulated rig's light_intensities.txt stayed beside new --light-directions, though
    it belongs to the rig's true directions only."""
    out = tmp_path / "st"
    assert capture_main([str(out), *SIM]) == 0
    assert (out / "light_intensities.txt").is_file()
    lights = tmp_path / "lights.txt"
    rows = read_vectors(out / "light_directions.txt", "l") * np.array([1.0, 1.0, 1.02])
    lights.write_text("".join(f"{x} {y} {z}\n" for x, y, z in rows))
    assert capture_main([str(out), "--camera", "sim", "--light-directions", str(lights)]) == 0
    said = capsys.readouterr().out
    assert "removed light_intensities.txt" in said, said
    assert not (out / "light_intensities.txt").exists()
    assert load_stack(out).num_lights == 12
    # given with them, intensities are written
    ints = tmp_path / "ints.txt"
    ints.write_text("1 1 1\n" * 12)
    lights.write_text("".join(f"{x} {y} {z}\n" for x, y, z in rows * np.array([1, 1, 1.01])))
    argv = ["--light-directions", str(lights), "--light-intensities", str(ints)]
    assert capture_main([str(out), *SIM, *argv]) == 0
    assert (out / "light_intensities.txt").is_file()


def test_a_circle_fitted_to_the_highlights_suggests_a_mask(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Without a mask, the circle fitted to a chrome capture's ring of highlights missed the
    sphere, and the error blamed the exposure."""
    calib = tmp_path / "calib"
    assert capture_main([str(calib), *SIM, "--sim-scene", "chrome"]) == 0
    capsys.readouterr()
    assert calib_main(["directions", str(calib / "raw"), "-o", str(tmp_path / "l.txt")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no highlight found" in err[0] and "--mask" in err[0], err
    assert err[0].index("--mask") < err[0].index("exposure"), err  # the likelier cause first
