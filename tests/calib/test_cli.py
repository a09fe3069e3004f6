"""msf-calib on careless and hostile input: all outputs or none, never over existing files or
inputs without --overwrite, one-line errors, no hang.

A small synthetic mirror-sphere capture (6 lights, 96 x 80 px) stands in for a real one.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from msfnet.calib import cli
from msfnet.common.files import STAGING_TAG
from msfnet.common.imageio import write_png
from msfnet.runtime.stack import read_vectors
from msfnet.synth import spheres as S


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    lights = S.ring_lights(6, (15, 55), seed=3)
    scene = S.mirror_scene(96, 80, 30)
    scene.ss = 1
    folder = tmp_path_factory.mktemp("capture") / "chrome"
    folder.mkdir()
    for i, light in enumerate(lights):
        write_png(
            folder / f"{i + 1:02d}.png",
            S.expose(S.render(scene, light), 1.0, 8, 1.0, np.random.default_rng(i)),
        )
    write_png(folder / "mask.png", S.sphere_masks(scene)[0].astype(np.uint8) * 255)
    return folder


@pytest.fixture
def chrome(capture: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(capture, tmp_path / "chrome"))


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}


def _one_line(capfd, words: list[str]) -> str:
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("msf-calib") and "error:" in err[0], err
    for word in words:
        assert word in err[0], (word, err[0])
    return err[0]


def test_directions_writes_all_three_outputs(chrome: Path, tmp_path: Path, capfd) -> None:
    out = tmp_path / "res" / "l.txt"
    assert cli.main(["directions", str(chrome), "-o", str(out), "-q"]) == 0
    assert capfd.readouterr().out == ""  # -q
    assert read_vectors(out, "l").shape == (6, 3)
    assert len((tmp_path / "res" / "l_confidence.txt").read_text().splitlines()) == 6
    assert (tmp_path / "res" / "l_diagnostic.png").stat().st_size > 0
    for p in (tmp_path / "res").iterdir():  # umask permissions, not mkstemp's 0600
        assert p.stat().st_mode & 0o077 != 0, p


# name: (prepare(tmp, chrome) -> extra argv, words) -- every case: exit 2, one line,
# nothing created and nothing changed
REFUSED: dict[str, tuple[Callable[[Path, Path], list[str]], list[str]]] = {
    "confidence file exists": (
        lambda t, c: _existing(t / "l_confidence.txt"),
        ["l_confidence.txt", "--overwrite"],
    ),
    "diagnostic exists": (
        lambda t, c: _existing(t / "l_diagnostic.png"),
        ["l_diagnostic.png", "--overwrite"],
    ),
    "--diagnostic target exists": (
        lambda t, c: ["--diagnostic", _make(t / "mine.png")[0]],
        ["mine.png", "--overwrite"],
    ),
    "lights file exists": (lambda t, c: _existing(t / "l.txt"), ["l.txt", "--overwrite"]),
    "--diagnostic is an input image": (
        lambda t, c: ["--diagnostic", str(c / "01.png"), "--overwrite"],
        ["input"],
    ),
    "--diagnostic is the mask": (
        lambda t, c: ["--diagnostic", str(c / "mask.png"), "--overwrite"],
        ["input"],
    ),
    "--diagnostic is the lights file": (
        lambda t, c: ["-o", str(t / "d.png"), "--diagnostic", str(t / "d.png")],
        ["same file"],
    ),
    "--diagnostic not an image name": (lambda t, c: ["--diagnostic", str(t / "d.txt")], [".png"]),
    # ".png" alone is a name without an ending: said so, with an example
    "--diagnostic only an ending": (
        lambda t, c: ["--diagnostic", str(t / ".png")],
        ["needs a file name ending in", "e.g."],
    ),
    "--diagnostic under a file": (
        lambda t, c: ["--diagnostic", str(Path(_make(t / "f")[0]) / "d.png")],
        ["is a file, not a folder"],
    ),
    "--intrinsics 0 0 0 0": (lambda t, c: ["--intrinsics", "0", "0", "0", "0"], ["positive"]),
    "--focal with --intrinsics": (
        lambda t, c: ["--focal", "100", "--intrinsics", "100", "100", "40", "40"],
        ["contradict"],
    ),
    "8-bit and 16-bit frames": (lambda t, c: _sixteen_bit(c / "03.png"), ["03.png", "uint16"]),
    "ambient of another size": (lambda t, c: _ambient(c, (10, 10)), ["ambient"]),
    "no sphere in the mask": (lambda t, c: _empty_mask(c), ["no sphere"]),
}


def _make(path: Path) -> list[str]:
    path.write_text("the user's file")
    return [str(path)]


def _existing(path: Path) -> list[str]:
    """A file of the user's where msf-calib would write one of its outputs (no extra args)."""
    _make(path)
    return []


def _sixteen_bit(path: Path) -> list[str]:
    from msfnet.common.imageio import read_image

    write_png(path, read_image(path).astype(np.uint16) * 257)
    return []


def _ambient(folder: Path, shape: tuple[int, int]) -> list[str]:
    write_png(folder / "ambient.png", np.zeros((*shape, 3), np.uint8))
    return []


def _empty_mask(folder: Path) -> list[str]:
    write_png(folder / "mask.png", np.zeros((80, 96), np.uint8))
    return []


@pytest.mark.parametrize("case", sorted(REFUSED))
def test_directions_refused(case: str, chrome: Path, tmp_path: Path, capfd) -> None:
    prepare, words = REFUSED[case]
    extra = prepare(tmp_path, chrome)
    before = _files(tmp_path)
    out = [] if "-o" in extra else ["-o", str(tmp_path / "l.txt")]
    assert cli.main(["directions", str(chrome), *out, *extra]) == 2
    _one_line(capfd, words)
    assert _files(tmp_path) == before
    assert not [p for p in tmp_path.rglob("*") if STAGING_TAG in p.name]


@pytest.mark.parametrize("target", ["01.png", "sub/l.txt"])
def test_output_never_replaces_or_lands_in_an_input(target: str, chrome: Path, capfd) -> None:
    before = _files(chrome.parent)
    assert cli.main(["directions", str(chrome), "-o", str(chrome / target), "--overwrite"]) == 2
    _one_line(capfd, ["input"])
    assert _files(chrome.parent) == before


def test_unwritable_diagnostic_leaves_no_lights_file(
    chrome: Path, tmp_path: Path, monkeypatch, capfd
) -> None:
    """The diagnostic image fails to encode after the lights were computed: no output at all
    (the lights file used to be written first and left behind)."""
    monkeypatch.setattr("msfnet.common.imageio.cv2.imencode", lambda *a, **k: (False, None))
    out = tmp_path / "res" / "l.txt"
    assert cli.main(["directions", str(chrome), "-o", str(out), "-q"]) == 2
    _one_line(capfd, ["diagnostic"])
    assert not (tmp_path / "res").exists()


def test_the_diagnostic_goes_through_the_shared_encoder(
    chrome: Path, tmp_path: Path, monkeypatch
) -> None:
    from msfnet.common.imageio import encode_png

    calls: list[tuple[Path, Path | None]] = []

    def spy(path: Path, img: np.ndarray, name: Path | None = None) -> None:
        calls.append((path, name))
        encode_png(path, img, name=name)

    monkeypatch.setattr(cli, "encode_png", spy)
    diag = tmp_path / "diag.png"
    assert (
        cli.main(
            [
                "directions",
                str(chrome),
                "-o",
                str(tmp_path / "l.txt"),
                "--diagnostic",
                str(diag),
                "-q",
            ]
        )
        == 0
    )
    # written into staging (the name ends in .png: OpenCV picks the encoder from it), errors
    # name the diagnostic file
    assert len(calls) == 1 and calls[0][1] == diag and calls[0][0].suffix == ".png"
    assert diag.is_file()


def test_overwrite_replaces_every_output_together(chrome: Path, tmp_path: Path) -> None:
    out = tmp_path / "l.txt"
    for name in ("l.txt", "l_confidence.txt", "l_diagnostic.png"):
        (tmp_path / name).write_text("old")
    assert cli.main(["directions", str(chrome), "-o", str(out), "--overwrite", "-q"]) == 0
    assert all(
        (tmp_path / n).read_bytes() != b"old"
        for n in ("l.txt", "l_confidence.txt", "l_diagnostic.png")
    )
    assert read_vectors(out, "l").shape == (6, 3)


def test_several_captures_name_their_diagnostics(chrome: Path, tmp_path: Path) -> None:
    second = Path(shutil.copytree(chrome, tmp_path / "chrome2"))
    diag = tmp_path / "d" / "diag.png"
    assert (
        cli.main(
            [
                "directions",
                str(chrome),
                str(second),
                "-o",
                str(tmp_path / "l.txt"),
                "--diagnostic",
                str(diag),
                "-q",
            ]
        )
        == 0
    )
    assert sorted(p.name for p in diag.parent.iterdir()) == ["diag_1.png", "diag_2.png"]


def test_ctrl_c_writes_nothing(chrome: Path, tmp_path: Path, monkeypatch, capfd) -> None:
    def interrupted(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "estimate_directions", interrupted)
    assert cli.main(["directions", str(chrome), "-o", str(tmp_path / "l.txt")]) == 130
    err = capfd.readouterr().err.strip().splitlines()
    assert err == ["msf-calib: interrupted; nothing was written"], err
    assert not (tmp_path / "l.txt").exists()


def test_intrinsics_zero_does_not_hang(chrome: Path, tmp_path: Path) -> None:
    """Issue 13: a subprocess with a timeout, so the old hang fails instead of blocking."""
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "msfnet.calib.cli",
            "directions",
            str(chrome),
            "-o",
            str(tmp_path / "l.txt"),
            "--intrinsics",
            "0",
            "0",
            "0",
            "0",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert not (tmp_path / "l.txt").exists()


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_library_rejects_broken_intrinsics_and_nan_fits() -> None:
    from msfnet.calib.directions import Intrinsics, sphere_geometry
    from msfnet.calib.sphere import Circle, fit_circle
    from msfnet.common.errors import InputError

    with pytest.raises(InputError, match="positive focal"):
        Intrinsics(0.0, 0.0, 0.0, 0.0)
    with pytest.raises(InputError, match="non-finite"):
        fit_circle(np.array([0.0, 1.0, np.nan, 2.0]), np.array([0.0, 1.0, 2.0, 0.0]))
    with pytest.raises(InputError, match="non-finite"):
        sphere_geometry(
            Circle(40.0, 40.0, np.inf),
            np.array([40.0]),
            np.array([40.0]),
            Intrinsics(100.0, 100.0, 40.0, 40.0),
        )


# ---------------------------------------------------------------------------- intensities


def _intensity_args(chrome: Path, tmp_path: Path, *extra: str) -> list[str]:
    lights = tmp_path / "dirs.txt"
    if not lights.exists():
        lights.write_text(
            "".join(f"{a} {b} {c}\n" for a, b, c in S.ring_lights(6, (15, 55), seed=3))
        )
    return ["intensities", str(chrome), "--lights", str(lights), *extra]


INTENSITY_REFUSED: dict[str, tuple[list[str], list[str]]] = {
    "plane normal zero": (["--target", "plane", "--normal", "0", "0", "0"], ["--normal"]),
    "plane facing away": (["--target", "plane", "--normal", "0", "0", "-1"], ["face the camera"]),
    # was ignored without a word (the sphere was fitted, or not found)
    "normal for a sphere": (["--normal", "0", "0.2", "1"], ["--normal", "--target plane"]),
    "output is the lights file": (["-o", "{lights}", "--overwrite"], ["input"]),
    "output exists": (["-o", "{existing}"], ["--overwrite"]),
}


@pytest.mark.parametrize("case", sorted(INTENSITY_REFUSED))
def test_intensities_refused(case: str, chrome: Path, tmp_path: Path, capfd) -> None:
    extra, words = INTENSITY_REFUSED[case]
    argv = _intensity_args(chrome, tmp_path)
    (tmp_path / "existing.txt").write_text("keep")
    subst = {"{lights}": str(tmp_path / "dirs.txt"), "{existing}": str(tmp_path / "existing.txt")}
    extra = [subst.get(a, a) for a in extra]
    if "-o" not in extra:
        extra += ["-o", str(tmp_path / "ints.txt")]
    before = _files(tmp_path)
    assert cli.main([*argv, *extra]) == 2
    _one_line(capfd, words)
    assert _files(tmp_path) == before


# ---------------------------------------------------------------- errors name their file


def test_no_sphere_in_the_images_names_the_folder(tmp_path: Path, capfd) -> None:
    """Noise, no mask: the message used to name no file."""
    noise = tmp_path / "noise"
    noise.mkdir()
    rng = np.random.default_rng(0)
    for i in range(4):
        write_png(noise / f"{i + 1:02d}.png", rng.integers(0, 256, (80, 96, 3), np.uint8))
    out = tmp_path / "l.txt"
    assert cli.main(["directions", str(noise), "-o", str(out)]) == 2
    line = _one_line(capfd, ["could not find the sphere", "--mask"])
    assert line.startswith(f"msf-calib: error: {noise}: "), line
    assert (
        cli.main(
            ["intensities", str(noise), "--lights", str(_lights_file(tmp_path, 4)), "-o", str(out)]
        )
        == 2
    )
    assert _one_line(capfd, ["could not find the sphere"]).startswith(
        f"msf-calib: error: {noise}: "
    )
    assert not out.exists()


@pytest.mark.parametrize("command", ["directions", "intensities"])
def test_an_empty_mask_is_named(command: str, chrome: Path, tmp_path: Path, capfd) -> None:
    mask = tmp_path / "empty.png"
    write_png(mask, np.zeros((80, 96), np.uint8))
    extra = ["--lights", str(_lights_file(tmp_path, 6))] if command == "intensities" else []
    assert (
        cli.main([command, str(chrome), *extra, "--mask", str(mask), "-o", str(tmp_path / "l.txt")])
        == 2
    )
    line = _one_line(capfd, ["no sphere found in the mask"])
    assert line.startswith(f"msf-calib: error: {mask}: "), line


def _lights_file(folder: Path, count: int) -> Path:
    path = folder / "dirs.txt"
    path.write_text("".join(f"{a} {b} {c}\n" for a, b, c in S.ring_lights(count, (15, 55))))
    return path


@pytest.mark.parametrize(
    ("options", "words"),
    [
        (["--intrinsics", "500", "500", "1e308", "0"], ["--intrinsics", "principal point"]),
        (["--focal", "1e-300"], ["--focal", "outside"]),
        (["--focal", "1e300"], ["--focal", "outside"]),
        (["--intrinsics", "1e-300", "1e-300", "48", "40"], ["--intrinsics", "outside"]),
        (["--intrinsics", "500", "1e300", "48", "40"], ["--intrinsics", "FY"]),
    ],
)
@pytest.mark.parametrize("command", ["directions", "intensities"])
def test_finite_but_absurd_camera_options_write_nothing(
    command: str, options: list[str], words: list[str], chrome: Path, tmp_path: Path, capfd
) -> None:
    """``--intrinsics 500 500 1e308 0`` and ``--focal 1e-300`` wrote NaN light directions with
    exit 0 (issue #27); ``--focal 1e300`` wrote the same direction for every light. The camera
    is now checked against the images it is used on, and the result before it is written."""
    lights = tmp_path / "lights.txt"
    lights.write_text("".join(f"{0.1 * i} 0.2 0.9\n" for i in range(6)))
    before = _files(tmp_path)
    extra = ["--lights", str(lights)] if command == "intensities" else []
    out = tmp_path / "l.txt"
    assert cli.main([command, str(chrome), "-o", str(out), *extra, *options]) == 2
    _one_line(capfd, words)
    assert _files(tmp_path) == before


def test_a_result_that_is_not_unit_length_is_never_written(
    chrome: Path, tmp_path: Path, monkeypatch, capfd
) -> None:
    """The last guard: whatever the options checks miss, NaN directions are refused."""
    from msfnet.calib import directions

    real = directions.estimate_directions

    def nan_light(*args: object, **kwargs: object) -> directions.DirectionResult:
        res = real(*args, **kwargs)  # type: ignore[arg-type]
        res.directions[2] = np.nan
        return res

    monkeypatch.setattr(cli, "estimate_directions", nan_light)
    before = _files(tmp_path)
    assert cli.main(["directions", str(chrome), "-o", str(tmp_path / "l.txt")]) == 2
    _one_line(capfd, ["light directions", "[3]"])
    assert _files(tmp_path) == before


def test_sane_perspective_options_still_work(chrome: Path, tmp_path: Path) -> None:
    for options in (["--focal", "300"], ["--intrinsics", "300", "280", "50", "38"]):
        out = tmp_path / "l.txt"
        assert (
            cli.main(["directions", str(chrome), "-o", str(out), "-q", "--overwrite", *options])
            == 0
        )
        rows = read_vectors(out, "light directions")
        np.testing.assert_allclose(np.linalg.norm(rows, axis=1), 1.0, atol=1e-5)


# ---------------------------------------------------------------- warnings


def _matte(folder: Path, gain: float) -> Path:
    """A matte sphere under the chrome fixture's six lights (no mirror highlight at all)."""
    folder.mkdir()
    scene = S.mirror_scene(96, 80, 30, kind="matte")
    scene.ss = 1
    for i, light in enumerate(S.ring_lights(6, (15, 55), seed=3)):
        write_png(folder / f"{i + 1:02d}.png", S.expose(S.render(scene, light), gain, 8, 0.0))
    write_png(folder / "mask.png", S.sphere_masks(scene)[0].astype(np.uint8) * 255)
    return folder


def _matte_lights(path: Path, flip: tuple[int, int, int] = (1, 1, 1)) -> Path:
    """The lights _matte's images were rendered under (times ``flip``)."""
    rows = S.ring_lights(6, (15, 55), seed=3) * np.asarray(flip)
    path.write_text("".join(f"{a} {b} {c}\n" for a, b, c in rows))
    return path


def _stray_light(chrome: Path) -> None:
    """A white spot on the sphere of 02.png, away from its highlight: a second highlight."""
    from msfnet.common.imageio import read_image, read_mask

    mask = read_mask(chrome / "mask.png")
    img = read_image(chrome / "02.png")
    ys, xs = np.nonzero(mask)
    cy, cx = int(ys.mean()), int(xs.mean())
    peak = np.unravel_index(np.argmax(img.max(-1) * mask), mask.shape)
    dy, dx = (-1 if peak[0] > cy else 1), (-1 if peak[1] > cx else 1)
    y, x = cy + dy * 12, cx + dx * 12  # the opposite quarter of the sphere
    img[y - 3 : y + 3, x - 3 : x + 3] = 255
    img[peak[0] - 1 : peak[0] + 2, peak[1] - 1 : peak[1] + 2] = 255  # (a 1-pixel highlight)
    write_png(chrome / "02.png", img)


def test_warnings_carry_the_command_and_are_silent_with_q(
    chrome: Path, tmp_path: Path, capfd
) -> None:
    """msf-calib printed "warning: ..." without its name, and also with -q (errors only)."""
    _stray_light(chrome)
    assert cli.main(["directions", str(chrome), "-o", str(tmp_path / "a.txt")]) == 0
    err = capfd.readouterr().err.strip().splitlines()
    assert err and all(line.startswith("msf-calib: warning: ") for line in err), err
    assert any("02.png: a second highlight" in line for line in err), err
    assert cli.main(["directions", str(chrome), "-o", str(tmp_path / "b.txt"), "-q"]) == 0
    assert capfd.readouterr().err == ""
    # intensities: a matte target partly saturated (under its own lights: other lights are
    # refused by the fit check)
    bright = _matte(tmp_path / "bright", gain=1.3)
    argv = ["intensities", str(bright), "--lights", str(_matte_lights(tmp_path / "m.txt"))]
    assert cli.main([*argv, "-o", str(tmp_path / "i.txt")]) == 0
    err = capfd.readouterr().err.strip().splitlines()
    assert err and all(line.startswith("msf-calib: warning: ") for line in err), err
    assert any("of the lit target is saturated" in line for line in err), err
    assert cli.main([*argv, "-o", str(tmp_path / "j.txt"), "-q"]) == 0
    assert capfd.readouterr().err == ""


def test_no_highlight_names_the_capture_folder(tmp_path: Path, capfd) -> None:
    """A matte sphere given as a chrome one: the error named no file."""
    folder = _matte(tmp_path / "matte", gain=0.8)
    assert cli.main(["directions", str(folder), "-o", str(tmp_path / "l.txt")]) == 2
    line = _one_line(capfd, ["no highlight found for", "01.png"])
    assert line.startswith(f"msf-calib: error: {folder}: "), line
    assert not (tmp_path / "l.txt").exists()


# ------------------------------------------------- review of light calibration and capture


@pytest.mark.parametrize("command", ["directions", "intensities"])
@pytest.mark.parametrize("output", [".", "/"])
def test_an_output_that_is_a_folder_is_one_line(
    command: str, output: str, chrome: Path, tmp_path: Path, capfd
) -> None:
    """``-o .`` crashed directions with "ValueError: PosixPath('.') has an empty name"."""
    extra = ["--lights", str(_lights_file(tmp_path, 6))] if command == "intensities" else []
    before = _files(tmp_path)
    assert cli.main([command, str(chrome), *extra, "-o", output]) == 2
    _one_line(capfd, [f"error: {output}: ", "not a folder"])
    assert _files(tmp_path) == before


@pytest.mark.parametrize("suffix", [".jpg", ".pgm"])
def test_a_mask_and_ambient_frame_in_any_image_format_are_used(
    suffix: str, chrome: Path, tmp_path: Path, capfd
) -> None:
    """mask.jpg / mask.pgm and ambient.jpg were left out as images and then never used: the
    sphere was fitted without its mask, the ambient frame silently skipped."""
    import cv2

    mask = cv2.imread(str(chrome / "mask.png"), cv2.IMREAD_GRAYSCALE)
    (chrome / "mask.png").unlink()
    cv2.imwrite(str(chrome / f"mask{suffix}"), mask)
    assert cli.main(["directions", str(chrome), "-o", str(tmp_path / "l.txt")]) == 0
    assert f"mask mask{suffix}" in capfd.readouterr().out
    # an ambient frame of another size: refused, so it is read
    cv2.imwrite(str(chrome / f"ambient{suffix}"), np.zeros((10, 10), np.uint8))
    assert cli.main(["directions", str(chrome), "-o", str(tmp_path / "m.txt")]) == 2
    _one_line(capfd, [f"ambient{suffix}", "size differs"])


def test_captures_of_different_lengths_name_the_folder(chrome: Path, tmp_path: Path, capfd) -> None:
    """ "captures have different image counts: [6, 5]" named no folder."""
    short = Path(shutil.copytree(chrome, tmp_path / "short"))
    (short / "06.png").unlink()
    assert cli.main(["directions", str(chrome), str(short), "-o", str(tmp_path / "l.txt")]) == 2
    line = _one_line(capfd, ["5 images", f"{chrome} has 6"])
    assert line.startswith(f"msf-calib: error: {short}: "), line


def test_intensity_errors_name_the_folder_and_hint_at_z(tmp_path: Path, capfd) -> None:
    """A z-flipped lights file gave "002.png: fewer than 30 lit target pixels", naming no
    folder and not the likely cause."""
    folder = _matte(tmp_path / "matte", gain=0.8)
    lights = _matte_lights(tmp_path / "back.txt", (1, 1, -1))
    argv = ["intensities", str(folder), "--lights", str(lights), "-o", str(tmp_path / "i.txt")]
    assert cli.main(argv) == 2
    line = _one_line(capfd, ["png: fewer than 30 lit", "flip the sign of z"])
    assert line.startswith(f"msf-calib: error: {folder}: "), line


@pytest.mark.parametrize("case", ["y negated", "mirror sphere"])
def test_intensities_refuse_a_target_that_does_not_fit(
    case: str, chrome: Path, tmp_path: Path, capfd
) -> None:
    """Wrong lights (y negated), a sphere fitted as a plane and a mirror sphere as the matte
    target all wrote plausible intensities with exit 0; the fit residual refuses them."""
    folder = chrome if case == "mirror sphere" else _matte(tmp_path / "matte", gain=0.8)
    flip = (1, -1, 1) if case == "y negated" else (1, 1, 1)
    lights = _matte_lights(tmp_path / "lights.txt", flip)
    out = tmp_path / "i.txt"
    extra = ["--target", "plane"] if case == "plane" else []
    before = _files(tmp_path)
    assert (
        cli.main(["intensities", str(folder), "--lights", str(lights), "-o", str(out), *extra]) == 2
    )
    line = _one_line(capfd, ["fit residual", "wrong lights file", "glossy"])
    assert line.startswith(f"msf-calib: error: {folder}: "), line
    assert _files(tmp_path) == before
    # a target known to be imperfect: written anyway on request, with the warning
    argv = ["intensities", str(folder), "--lights", str(lights), "-o", str(out), *extra]
    assert cli.main([*argv, "--accept-poor-fit"]) == 0 and out.is_file()
    assert "fits matte shading poorly" in capfd.readouterr().err


def test_a_plane_target_that_fits_poorly_warns_and_is_written(tmp_path: Path, capfd) -> None:
    """A plane's shading is one value per light, so its residual sees only what varies across
    the image under every light alike (vignetting, which cancels in the ratios): a rendered
    matte plane under cos^4 vignetting was refused. It now warns, and writes."""
    folder = _matte(tmp_path / "matte", gain=0.8)  # a sphere given as a plane: no plane at all
    lights = _matte_lights(tmp_path / "lights.txt", (1, 1, 1))
    out = tmp_path / "i.txt"
    argv = ["intensities", str(folder), "--lights", str(lights), "--target", "plane"]
    assert cli.main([*argv, "-o", str(out)]) == 0 and out.is_file()
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "check the target is a plane" in err[0], err


def test_intensities_fitting_well_pass_and_a_poor_fit_warns(
    tmp_path: Path, capfd, monkeypatch: pytest.MonkeyPatch
) -> None:
    from msfnet.calib import intensities

    folder = _matte(tmp_path / "matte", gain=0.8)
    argv = ["intensities", str(folder), "--lights", str(_matte_lights(tmp_path / "l.txt"))]
    assert cli.main([*argv, "-o", str(tmp_path / "i.txt")]) == 0
    assert capfd.readouterr().err == ""
    monkeypatch.setattr(intensities, "FIT_WARN", 0.0)  # the band between warning and refusal
    assert cli.main([*argv, "-o", str(tmp_path / "j.txt")]) == 0
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"msf-calib: warning: {folder}: "), err
    assert "fits matte shading poorly" in err[0], err


def test_a_diagnostic_left_by_an_earlier_run_is_named(chrome: Path, tmp_path: Path, capfd) -> None:
    out = tmp_path / "l.txt"
    assert cli.main(["directions", str(chrome), "-o", str(out), "-q"]) == 0
    old = tmp_path / "l_diagnostic.png"
    assert old.is_file()
    capfd.readouterr()
    args = ["directions", str(chrome), "-o", str(out), "--overwrite", "--no-diagnostic"]
    assert cli.main(args) == 0
    err = capfd.readouterr().err
    assert "warning" in err and "l_diagnostic.png: from an earlier run" in err, err
    assert old.is_file()  # named, not deleted
    # a run that rewrites it says nothing
    assert cli.main(["directions", str(chrome), "-o", str(out), "--overwrite"]) == 0
    assert "earlier run" not in capfd.readouterr().err


def test_stale_diagnostics_are_the_default_names_only_in_capture_order(tmp_path: Path) -> None:
    out = tmp_path / "l[1].txt"  # glob characters in the name are literal
    names = ["l[1]_diagnostic.png", "l[1]_diagnostic_10.png", "l[1]_diagnostic_2.png"]
    names += ["l[1]_diagnostic_0.png", "l[1]_diagnostic_x.png", "l1_diagnostic.png"]
    for name in names:
        (tmp_path / name).write_bytes(b"")
    written = [tmp_path / "l[1]_diagnostic_2.png"]
    stale = cli._stale_diagnostics(out, written)
    assert [p.name for p in stale] == ["l[1]_diagnostic.png", "l[1]_diagnostic_10.png"]
