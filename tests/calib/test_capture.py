"""Simulated capture: chrome calibration, interrupted + resumed object capture, load_stack, LS."""

from __future__ import annotations

import json

import numpy as np
import pytest

from msfnet.calib import capture_cli, cli
from msfnet.calib.cameras import SimulatedCamera
from msfnet.calib.capture import capture_stack, exposure_check
from msfnet.calib.lights import ManualLights, SerialLights, SimulatedLights, SimulatedRig
from msfnet.common.errors import InputError
from msfnet.common.imageio import read_image
from msfnet.runtime.evaluate.metrics import angular_error_deg
from msfnet.runtime.infer.least_squares import least_squares_normals
from msfnet.runtime.stack import load_stack, save_stack
from msfnet.synth import spheres as S


class Interrupting(SimulatedCamera):
    """A camera whose cable is pulled after ``limit`` frames."""

    def __init__(self, rig, limit):
        super().__init__(rig)
        self.limit, self.count = limit, 0

    def capture(self):
        if self.count >= self.limit:
            raise KeyboardInterrupt
        self.count += 1
        return super().capture()


def test_capture_calibrate_resume_load(tmp_path, rng):
    lights = S.ring_lights(10, (15, 55), seed=11)
    intens = rng.uniform(0.7, 1.3, (10, 3))
    # 1. Calibration capture of a chrome sphere, then msf-calib directions on it.
    chrome = SimulatedRig(S.mirror_scene(160, 128, 56), lights, intens, gain=0.02, bit_depth=8)
    cal = capture_stack(
        SimulatedCamera(chrome),
        SimulatedLights(chrome),
        tmp_path / "cal",
        mask=S.sphere_masks(chrome.scene)[0],
        progress=False,
        log=lambda m: None,
    )
    write = tmp_path / "light_directions.txt"
    # raw/ holds ambient.png (subtracted automatically); the sphere mask comes from the rig.
    assert (
        cli.main(
            ["directions", str(cal / "raw"), "--mask", str(cal / "mask.png"), "-o", str(write)]
        )
        == 0
    )
    # 2. Object capture (matte sphere), interrupted after 6 of 11 frames (ambient + 10).
    rig = SimulatedRig(S.mirror_scene(160, 128, 56, kind="matte"), lights, intens, noise=20.0)
    out = tmp_path / "obj"
    with pytest.raises(KeyboardInterrupt):
        capture_stack(
            Interrupting(rig, 6), SimulatedLights(rig), out, progress=False, log=lambda m: None
        )
    assert len(list((out / "raw").glob("*.png"))) == 6
    assert not (out / "filenames.txt").exists()
    assert not list((out / "raw").glob(".*"))  # no half-written temporaries
    cam = Interrupting(rig, 100)
    logs = []
    mask = S.sphere_masks(rig.scene)[0]
    capture_stack(
        cam,
        SimulatedLights(rig),
        out,
        light_directions=write,
        light_intensities=intens,
        mask=mask,
        progress=False,
        log=logs.append,
    )
    assert cam.count == 5 and any("resuming: 6 of 11" in m for m in logs)
    session = json.loads((out / "session.json").read_text())
    assert len(session["frames"]) == 10 and session["count"] == 10
    # 3. The runtime reads the stack; plain least squares gives the sphere's normals.
    stack = load_stack(out)
    assert stack.num_lights == 10 and stack.mask.sum() == mask.sum()
    assert angular_error_deg(stack.lights, lights).max() < 0.5
    gt = S.sphere_normals(rig.scene)
    lit = (np.einsum("hwc,nc->nhw", gt, lights) > 0.05).all(0) & stack.mask
    err = angular_error_deg(least_squares_normals(stack)[lit], gt[lit])
    print(f"LS normals from the captured stack: mean {err.mean():.2f} deg over {lit.sum()} px")
    assert lit.sum() > 2000 and err.mean() < 1.5
    # Resuming a finished session captures nothing and rebuilds the same stack.
    cam2 = Interrupting(rig, 0)
    capture_stack(
        cam2, SimulatedLights(rig), out, light_directions=write, progress=False, log=lambda m: None
    )
    assert cam2.count == 0


def _small_capture(out, normals=None, log=lambda m: None):
    rig = SimulatedRig(
        S.mirror_scene(48, 40, 16, kind="matte"),
        S.ring_lights(6),
        np.linspace(0.8, 1.2, 18).reshape(6, 3),
    )
    gt = S.sphere_normals(rig.scene) if normals is None else normals
    return capture_stack(
        SimulatedCamera(rig),
        SimulatedLights(rig),
        out,
        light_directions=rig.lights,
        light_intensities=rig.intensities,
        mask=S.sphere_masks(rig.scene)[0],
        normals_gt=gt,
        progress=False,
        log=log,
    )


def test_capture_writes_the_files_save_stack_writes(tmp_path):
    """One stack writer: a captured stack, loaded and saved again, gives the same files."""
    out = _small_capture(tmp_path / "cap")
    stack = load_stack(out)
    again = save_stack(stack, tmp_path / "saved")
    for name in (
        "filenames.txt",
        "light_directions.txt",
        "light_intensities.txt",
        "mask.png",
        *stack.filenames,
    ):
        assert (out / name).read_bytes() == (again / name).read_bytes(), name
    assert (out / "Normal_gt.mat").is_file() and not (out / "Normal_gt.npy").exists()
    np.testing.assert_array_equal(load_stack(again).normals_gt, stack.normals_gt)


def test_resume_keeps_an_older_captures_npy_ground_truth(tmp_path):
    out = _small_capture(tmp_path / "cap")
    before = load_stack(out)
    # the layout earlier msf-capture versions wrote: Normal_gt.npy (float32)
    (out / "Normal_gt.mat").unlink()
    np.save(out / "Normal_gt.npy", before.normals_gt)
    stamps = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    logs = []
    _small_capture(out, log=logs.append)  # finished: nothing captured, nothing rewritten
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == stamps
    assert not any(m.startswith("updated") for m in logs)
    np.testing.assert_array_equal(load_stack(out).normals_gt, before.normals_gt)
    # new ground truth goes through the stack writer; the old file does not linger
    flat = np.where(before.mask[..., None], np.float32([0, 0, 1]), 0).astype(np.float32)
    _small_capture(out, normals=flat)
    assert (out / "Normal_gt.mat").is_file() and not (out / "Normal_gt.npy").exists()
    np.testing.assert_array_equal(load_stack(out).normals_gt, flat)


def test_exposure_checks():
    dark = np.full((10, 10, 3), 3, np.uint8)
    assert exposure_check(dark, 255).too_dark
    bright = np.full((10, 10, 3), 255, np.uint8)
    assert exposure_check(bright, 255).too_bright
    assert exposure_check(bright, 255).problems() == ["100.0% saturated"]
    ok = np.tile(np.linspace(0, 200, 10, dtype=np.uint8), (10, 1))
    chk = exposure_check(ok, 255)
    assert not chk.too_dark and not chk.too_bright and chk.problems() == []


class FakePort:
    """The controller side of the serial line protocol."""

    def __init__(self, count=4, broken=False):
        self.count, self.broken, self.sent, self.replies = count, broken, [], []

    def write(self, data: bytes):
        line = data.decode().strip()
        self.sent.append(line)
        if self.broken:
            self.replies.append(b"")
        elif line == "PING":
            self.replies.append(f"OK MSF-LED {self.count}\n".encode())
        elif line == "OFF" or (line.startswith("ON ") and 1 <= int(line[3:]) <= self.count):
            self.replies.append(b"OK\n")
        else:
            self.replies.append(b"ERR bad index\n")

    def readline(self):
        return self.replies.pop(0)


def test_serial_protocol_and_manual_prompt():
    port = FakePort(4)
    lights = SerialLights(port, settle=0)
    assert lights.count == 4
    lights.on(0)
    lights.on(3)
    lights.off()
    assert port.sent == ["PING", "ON 1", "ON 4", "OFF"]
    with pytest.raises(InputError, match="refused 'ON 5'"):
        lights.on(4)
    with pytest.raises(InputError, match="reports 4 lights but 5"):
        SerialLights(FakePort(4), count=5, settle=0)
    with pytest.raises(InputError, match="did not answer"):
        SerialLights(FakePort(broken=True), settle=0)
    prompts = []
    m = ManualLights(3, ask=prompts.append)
    m.on(1)
    m.off()
    assert "light 2 of 3" in prompts[0] and "off" in prompts[1].lower()


def test_capture_cli_sim(tmp_path, capsys):
    out = tmp_path / "s"
    args = [str(out), "--camera", "sim", "--light-rig", "sim", "--count", "4"]
    assert capture_cli.main(args) == 0
    assert (out / "004.png").is_file() and (out / "raw" / "ambient.png").is_file()
    assert capture_cli.main([str(out), "--camera", "opencv", "--light-rig", "sim"]) == 2
    assert "go together" in capsys.readouterr().err


class Configured(SimulatedCamera):
    """A simulated camera reporting driver settings, as the OpenCV and OAK back-ends do."""

    def __init__(self, rig, **settings):
        super().__init__(rig)
        self.settings = settings

    def info(self):
        return {"backend": "opencv", "device": "0", **self.settings}


def test_resume_with_another_exposure_is_refused(tmp_path):
    rig = SimulatedRig(S.mirror_scene(48, 40, 16, kind="matte"), S.ring_lights(6))
    out = tmp_path / "cap"
    with pytest.raises(KeyboardInterrupt):
        capture_stack(
            Interrupting(rig, 3), SimulatedLights(rig), out, progress=False, log=lambda m: None
        )
    # Interrupting reports the simulated camera's info: give the session an exposure
    session = json.loads((out / "session.json").read_text())
    session["camera"] = {"backend": "opencv", "device": "0", "exposure": -6.0, "gain": 0.0}
    (out / "session.json").write_text(json.dumps(session))
    cam = Configured(rig, exposure=-5.0, gain=0.0)
    with pytest.raises(InputError, match=r"exposure=-6\.0.*exposure=-5\.0.*overwrite=True") as exc:
        capture_stack(cam, SimulatedLights(rig), out, progress=False, log=lambda m: None)
    assert exc.value.path == out / "session.json" and "gain" not in str(exc.value)
    assert rig.frames == 3 and len(list((out / "raw").iterdir())) == 3
    # the recorded settings resume (a key the session lacks, from an older version, is no
    # difference)
    cam = Configured(rig, exposure=-6.0, gain=0.0, focus=1.0)
    capture_stack(cam, SimulatedLights(rig), out, progress=False, log=lambda m: None)
    assert rig.frames == 7


def test_overwrite_replaces_every_file_of_the_previous_stack(tmp_path):
    out = _small_capture(tmp_path / "cap")
    (out / "Normal_gt.npy").write_bytes(b"an older capture's ground truth")
    rig = SimulatedRig(S.mirror_scene(48, 40, 16, kind="matte"), S.ring_lights(4))
    capture_stack(
        SimulatedCamera(rig),
        SimulatedLights(rig),
        out,
        overwrite=True,
        progress=False,
        log=lambda m: None,
    )
    # nothing of the 6-light session is left to be read with the new frames
    assert sorted(p.name for p in out.iterdir()) == [
        "001.png",
        "002.png",
        "003.png",
        "004.png",
        "filenames.txt",
        "raw",
        "session.json",
    ]


def test_frames_captured_into_a_built_session_rebuild_its_stack(tmp_path):
    """A frame re-taken (deleted from raw/, object lit anew) must reach the stack images: the
    session's record of how they were built is dropped when new frames arrive."""
    out = _small_capture(tmp_path / "cap")
    (out / "raw" / "002.png").unlink()
    brighter = SimulatedRig(
        S.mirror_scene(48, 40, 16, kind="matte"), S.ring_lights(6), gain=0.4
    )  # same camera info, another picture
    capture_stack(
        SimulatedCamera(brighter),
        SimulatedLights(brighter),
        out,
        progress=False,
        log=lambda m: None,
    )
    raw = read_image(out / "raw" / "002.png").astype(np.int64)
    amb = read_image(out / "raw" / "ambient.png").astype(np.int64)
    np.testing.assert_array_equal(read_image(out / "002.png"), (raw - amb).clip(0))
    assert json.loads((out / "session.json").read_text())["ambient_subtracted"] is True


def test_a_chrome_frame_with_a_clipped_highlight_is_not_under_exposed() -> None:
    """A dark chrome sphere with a saturated highlight was reported "under-exposed" (its
    99.5th percentile is low): more exposure would only clip more."""
    frame = np.zeros((100, 100, 3), np.uint16)
    frame[10:14, 10:14] = 65535  # 0.16 % of the frame at the white level
    chk = exposure_check(frame, 65535.0)
    assert not chk.too_dark and not any("under" in p for p in chk.problems())
    assert exposure_check(np.full((100, 100, 3), 100, np.uint16), 65535.0).too_dark  # still seen


class _SaturatingRig:
    """Camera and lights in one: lights 1-3 give fully saturated frames, the others a good
    exposure; ``stop_at`` (0-based light) stands for a Ctrl-C when that light is switched on."""

    white_level = 255.0
    frame_shape = (16, 16)

    def __init__(self, count=6, stop_at=None):
        self.count, self.stop_at, self.lit, self.frames = count, stop_at, None, 0

    def on(self, i):
        if i == self.stop_at:
            raise KeyboardInterrupt
        self.lit = i

    def off(self):
        self.lit = None

    def capture(self):
        self.frames += 1
        level = 5 if self.lit is None else (255 if self.lit < 3 else 120)
        return np.full((16, 16, 3), level, np.uint8)

    def info(self):
        return {"backend": "fake"}


def _capture_fake(rig, out, **kw):
    return capture_stack(rig, rig, out, progress=False, log=kw.pop("log", lambda m: None), **kw)


def test_strict_resume_judges_the_frames_taken_before_the_interruption(tmp_path):
    """--strict was bypassed by a resume: only this run's frames were judged, not the
    saturated ones session.json recorded before the Ctrl-C."""
    with pytest.raises(InputError) as whole:
        _capture_fake(_SaturatingRig(), tmp_path / "whole", strict=True)
    out = tmp_path / "resumed"
    with pytest.raises(KeyboardInterrupt):
        _capture_fake(_SaturatingRig(stop_at=4), out, strict=True)
    with pytest.raises(InputError) as resumed:
        _capture_fake(_SaturatingRig(), out, strict=True)
    assert resumed.value.message == whole.value.message
    assert "001.png: 100.0% saturated" in resumed.value.message
    assert not (out / "filenames.txt").exists()  # no stack built from the saturated frames
    # and again once every frame is on disk (nothing left to capture): still refused
    with pytest.raises(InputError, match=r"001\.png: 100\.0% saturated"):
        _capture_fake(_SaturatingRig(), out, strict=True)
    assert _capture_fake(_SaturatingRig(), out) == out  # without --strict: built


def test_a_frame_on_disk_without_its_exposure_record_is_checked_on_resume(tmp_path):
    """A frame written before its record (signal in between) was skipped by every resume,
    its exposure never checked: it is checked from raw/ and recorded."""
    out = tmp_path / "cap"
    with pytest.raises(KeyboardInterrupt):
        _capture_fake(_SaturatingRig(stop_at=4), out)
    session = json.loads((out / "session.json").read_text())
    del session["frames"]["002.png"]  # what the old write-then-record order left behind
    (out / "session.json").write_text(json.dumps(session))
    logs = []
    with pytest.raises(InputError, match=r"002\.png: 100\.0% saturated"):
        _capture_fake(_SaturatingRig(), out, strict=True, log=logs.append)
    assert any(m.startswith("warning: 002.png: 100.0% saturated") for m in logs), logs
    frames = json.loads((out / "session.json").read_text())["frames"]
    assert sorted(frames) == [f"{i:03d}.png" for i in range(1, 7)]
    assert frames["002.png"]["too_bright"] is True


@pytest.mark.parametrize("kill_at", range(1, 9))
def test_an_interruption_while_saving_never_leaves_an_unrecorded_frame(
    tmp_path, monkeypatch, kill_at
):
    """A Ctrl-C at every session.json save: after the resume every frame on disk has its
    exposure record (the record is saved before its frame is written)."""
    from msfnet.calib import capture as capture_module

    real, calls = capture_module.write_atomic, []

    def dying(path, *args, **kwargs):
        calls.append(path)
        if len(calls) == kill_at:
            raise KeyboardInterrupt
        return real(path, *args, **kwargs)

    out = tmp_path / "cap"
    monkeypatch.setattr(capture_module, "write_atomic", dying)
    with pytest.raises(KeyboardInterrupt):
        _capture_fake(_SaturatingRig(), out)
    monkeypatch.setattr(capture_module, "write_atomic", real)
    rig = _SaturatingRig()
    _capture_fake(rig, out)
    frames = json.loads((out / "session.json").read_text())["frames"]
    on_disk = sorted(p.name for p in (out / "raw").glob("[0-9]*.png"))
    assert on_disk == sorted(frames) == [f"{i:03d}.png" for i in range(1, 7)]
    assert [frames[f"{i:03d}.png"]["too_bright"] for i in range(1, 7)] == [True] * 3 + [False] * 3
