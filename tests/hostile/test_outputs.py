"""Hostile cases, part A: where outputs go, light files, camera options, captures, full disks,
misleading messages.

Each case is the command line a user types (run through the installed command's ``main`` in
this process, in a scratch folder), the one line it must answer, its exit code, and the folder
exactly as it was before: nothing written, nothing replaced, no staging left.
"""

from __future__ import annotations

import errno
import io
import json
import os
import shlex
import shutil
import stat
import subprocess
import sys
from collections.abc import Callable, Iterator
from importlib.metadata import entry_points
from pathlib import Path

import numpy as np
import pytest
from _runtime_helpers import BUNDLED_CHECKPOINT, sphere_stack

from msfnet.common.files import STAGING_TAG
from msfnet.common.imageio import write_png
from msfnet.runtime.stack import save_stack
from msfnet.synth import spheres as S

CHECKPOINT = BUNDLED_CHECKPOINT


def _main(command: str) -> Callable[[list[str]], int]:
    found = [e for e in entry_points(group="console_scripts") if e.name == command]
    if not found:
        pytest.skip(f"{command} is not installed (pip install -e .)")
    return found[0].load()


def run(cmdline: str, capfd: pytest.CaptureFixture[str]) -> tuple[int, list[str]]:
    """Run ``cmdline`` as typed (in the current folder); its exit code and stderr lines."""
    argv = shlex.split(cmdline)
    capfd.readouterr()
    code = _main(argv[0])(argv[1:])
    return code, capfd.readouterr().err.strip().splitlines()


def tree(root: Path) -> dict[str, tuple[int, bytes]]:
    """Every entry under ``root``: its kind and, for a regular file, its bytes."""
    out = {}
    for p in sorted(root.rglob("*")):
        mode = os.lstat(p).st_mode
        data = p.read_bytes() if stat.S_ISREG(mode) else b""
        out[str(p.relative_to(root))] = (stat.S_IFMT(mode), data)
    return out


def refused(
    cmdline: str, words: list[str], capfd: pytest.CaptureFixture[str], root: Path, code: int = 2
) -> str:
    """The case's contract: exit ``code``, one line naming ``words``, ``root`` untouched."""
    before = tree(root)
    got, err = run(cmdline, capfd)
    assert got == code, (cmdline, err)
    assert len(err) == 1, (cmdline, err)
    assert err[0].startswith(f"{cmdline.split()[0]}: error: "), err[0]
    for word in words:
        assert word in err[0], (word, err[0])
    assert tree(root) == before, cmdline
    assert not [p for p in root.rglob("*") if STAGING_TAG in p.name]
    return err[0]


# ---------------------------------------------------------------------------- the scene


def _chrome(folder: Path, fill: dict[int, int] | None = None) -> Path:
    """A 6-light mirror-sphere capture with its mask; ``fill``: image index -> constant."""
    lights = S.ring_lights(6, (15, 55), seed=3)
    scene = S.mirror_scene(96, 80, 30)
    scene.ss = 1
    folder.mkdir(parents=True)
    for i, light in enumerate(lights):
        img = S.expose(S.render(scene, light), 1.0, 8, 1.0, np.random.default_rng(i))
        if fill and i in fill:
            img = np.full_like(img, fill[i])
        write_png(folder / f"{i + 1:02d}.png", img)
    write_png(folder / "mask.png", S.sphere_masks(scene)[0].astype(np.uint8) * 255)
    return folder


@pytest.fixture
def world(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A user's folder: a chrome capture, a stack, lights files, two checkpoints."""
    _chrome(tmp_path / "chrome")
    save_stack(sphere_stack(n=6), tmp_path / "stack")
    (tmp_path / "L.txt").write_text("".join(f"{0.1 * i} 0.2 0.9\n" for i in range(6)))
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _special(kind: str, path: Path) -> None:
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "link to stdout":
        path.symlink_to("/proc/self/fd/1")
    elif kind == "device node":
        try:
            os.mknod(path, 0o666 | stat.S_IFCHR, os.makedev(1, 3))  # what /dev/null is
        except PermissionError:
            pytest.skip("making a device node needs root")
    else:
        raise AssertionError(kind)


SPECIAL_WORDS = {
    "fifo": "named pipe",
    "link to stdout": "symbolic link",
    "device node": "character device",
}


# ---------------------------------------------------------------------------- 1. special files


@pytest.mark.parametrize("kind", sorted(SPECIAL_WORDS))
def test_calib_never_replaces_a_special_file(kind: str, world: Path, capfd) -> None:
    _special(kind, world / "out.txt")
    line = refused(
        "msf-calib directions chrome -o out.txt --overwrite", [SPECIAL_WORDS[kind]], capfd, world
    )
    assert "pass --overwrite" not in line


@pytest.mark.parametrize("kind", sorted(SPECIAL_WORDS))
def test_average_never_replaces_a_special_file(kind: str, world: Path, capfd) -> None:
    pytest.importorskip("torch")
    shutil.copy(CHECKPOINT, world / "a.pth")
    shutil.copy(CHECKPOINT, world / "b.pth")
    _special(kind, world / "avg.pth")
    refused("msf-average a.pth b.pth -o avg.pth --overwrite", [SPECIAL_WORDS[kind]], capfd, world)


@pytest.mark.parametrize("kind", sorted(SPECIAL_WORDS))
def test_export_never_replaces_a_special_file(kind: str, world: Path, capfd) -> None:
    pytest.importorskip("torch")
    pytest.importorskip("onnx")
    shutil.copy(CHECKPOINT, world / "model.pth")
    _special(kind, world / "model.onnx")
    refused("msf-export model.pth -o model.onnx --overwrite", [SPECIAL_WORDS[kind]], capfd, world)


# ---------------------------------------------------------------------------- 2, 12. captures


def test_capture_overwrite_keeps_the_users_own_stack(world: Path, capfd) -> None:
    mine = world / "mine"
    mine.mkdir()
    write_png(mine / "001.png", np.full((8, 8), 9, np.uint8))
    (mine / "light_directions.txt").write_text("0 0 1\n")
    (mine / "notes.jpg").write_bytes(b"a photo")
    refused(
        "msf-capture mine --camera sim --count 4 --overwrite",
        ["not msf-capture's", "would be replaced"],
        capfd,
        world,
    )


def test_a_second_capture_into_the_same_folder_is_refused(world: Path, capfd) -> None:
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys\n"
            "from msfnet.common.files import folder_lock\n"
            "with folder_lock('busy', 'msf-capture'):\n"
            "    print('held', flush=True)\n"
            "    sys.stdin.readline()\n",
        ],
        cwd=world,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        refused(
            "msf-capture busy --camera sim --count 4",
            ["another msf-capture is working in this folder"],
            capfd,
            world,
        )
    finally:
        assert holder.stdin is not None
        holder.stdin.close()
        holder.wait(timeout=30)


# ---------------------------------------------------------------------------- 4. camera options


@pytest.mark.parametrize(
    ("options", "words"),
    [
        ("--intrinsics 500 500 1e308 0", ["--intrinsics", "principal point"]),
        ("--focal 1e-300", ["--focal", "outside"]),
        ("--focal 1e300", ["--focal", "outside"]),
        ("--intrinsics 1e-300 1e-300 48 40", ["--intrinsics", "outside"]),
    ],
)
def test_absurd_camera_options_write_no_nan(options: str, words: list[str], world, capfd) -> None:
    refused(f"msf-calib directions chrome -o l.txt {options}", words, capfd, world)
    refused(f"msf-calib intensities chrome --lights L.txt -o i.txt {options}", words, capfd, world)


# ---------------------------------------------------------------------------- 5. light files


@pytest.mark.parametrize(
    ("name", "content", "words"),
    [
        ("l.json", json.dumps({"positions_mm": [[10, 20, 300]] * 6}), ["'positions_mm'"]),
        (
            "l.json",
            json.dumps({"positions_mm": [[10, 20, 300]] * 6, "lights": [[0, 0, 1]] * 6}),
            ["unknown key 'positions_mm'"],
        ),
        ("l.txt", "0 0 1\n0_5 0 1\n" + "0 0.1 1\n" * 4, ["'0_5' is not a number"]),
        ("l.txt", "0 0 1\n" * 10_001, ["10,001 rows"]),
    ],
    ids=["positions_mm", "unknown key beside lights", "0_5", "10,001 rows"],
)
def test_light_files_are_read_by_name_and_bounded(
    name: str, content: str, words: list[str], world: Path, capfd
) -> None:
    (world / name).write_text(content)
    refused(f"msf-run stack --lights {name} --method l2 -o res -q", words, capfd, world)


def test_a_57_mb_light_file_is_refused_by_its_size(world: Path, capfd) -> None:
    with open(world / "huge.txt", "wb") as f:
        f.truncate(57 * 2**20)  # sparse: the size alone must refuse it
    refused("msf-run stack --lights huge.txt --method l2 -o res -q", ["57.0 MB"], capfd, world)


# ---------------------------------------------------------------------------- 9. a full disk


@pytest.fixture(params=["tmpfs", "simulated"])
def full(request: pytest.FixtureRequest, world: Path, monkeypatch) -> Iterator[Path]:
    """A folder on a full disk: a real 64 KiB tmpfs filled up where this user may mount one
    (root), else writes into staging files fail with ENOSPC as a full disk's do."""
    folder = world / "full"
    folder.mkdir()
    if request.param == "tmpfs":
        if os.geteuid() != 0 or shutil.which("mount") is None:
            pytest.skip("mounting a tmpfs needs root")
        done = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(folder)], capture_output=True
        )
        if done.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()!r}")
        try:
            with open(folder / "filler", "wb") as f:
                f.write(b"\0" * (64 * 1024 - 4096))  # a page left: text fits, nothing bigger
        except OSError:
            pass
        try:
            yield folder
        finally:
            subprocess.run(["umount", str(folder)], capture_output=True)
        return
    real_open = io.open

    class _Full(io.RawIOBase):
        def __init__(self, raw: io.IOBase) -> None:
            self._raw = raw

        def writable(self) -> bool:
            return True

        def write(self, data: object) -> int:  # what a full disk answers, without a file name
            raise OSError(errno.ENOSPC, "No space left on device")

        def close(self) -> None:
            self._raw.close()
            super().close()

    def open_(file: object, mode: str = "r", *args: object, **kwargs: object) -> object:
        handle = real_open(file, mode, *args, **kwargs)  # type: ignore[call-overload]
        if any(c in mode for c in "wax") and str(folder) in str(file):
            return _Full(handle)
        return handle

    monkeypatch.setattr("builtins.open", open_)
    monkeypatch.setattr(io, "open", open_)
    yield folder


@pytest.mark.slow
def test_average_on_a_full_disk_is_one_line(full: Path, world: Path, capfd) -> None:
    """An "internal error" (torch's RuntimeError "unexpected pos") before."""
    pytest.importorskip("torch")
    shutil.copy(CHECKPOINT, world / "a.pth")
    shutil.copy(CHECKPOINT, world / "b.pth")
    refused(
        "msf-average a.pth b.pth -o full/avg.pth",
        ["full/avg.pth", "No space left on device"],
        capfd,
        world,
    )


def test_calib_on_a_full_disk_is_one_line(full: Path, world: Path, capfd) -> None:
    refused(
        "msf-calib directions chrome -o full/l.txt",
        ["full/l", "No space left on device"],
        capfd,
        world,
    )


# ---------------------------------------------------------------------------- 15. messages


def test_a_saturated_chrome_image_is_not_called_under_exposed(world: Path, capfd) -> None:
    _chrome(world / "sat", fill={2: 255})
    line = refused("msf-calib directions sat -o l.txt", ["03.png", "saturated"], capfd, world)
    assert "too low" not in line


def test_a_black_image_is_not_blamed_on_an_ambient_frame(world: Path, capfd) -> None:
    _chrome(world / "dark", fill={2: 0})
    line = refused("msf-calib directions dark -o l.txt", ["03.png", "black"], capfd, world)
    assert "ambient" not in line
    line = refused("msf-calib intensities dark --lights L.txt -o i.txt", ["black"], capfd, world)
    assert "ambient" not in line


def test_a_loop_never_advises_the_overwrite_it_refuses(world: Path, capfd) -> None:
    (world / "takes" / "001").mkdir(parents=True)
    (world / "takes" / "001" / "session.json").write_text(json.dumps({"count": 6, "frames": {}}))
    line = refused("msf-capture takes --camera sim --count 4 --loop 1", ["6 lights"], capfd, world)
    assert "--overwrite" not in line


def test_a_session_without_a_count_is_not_none_lights(world: Path, capfd) -> None:
    (world / "sess").mkdir()
    (world / "sess" / "session.json").write_text('{"frames": {}}')
    line = refused("msf-capture sess --camera sim --count 4", ["no light count"], capfd, world)
    assert "None" not in line


@pytest.mark.slow
def test_train_on_a_full_disk_is_one_line(full: Path, world: Path, capfd) -> None:
    """msf-train's checkpoint save was an "internal error" on a full disk."""
    pytest.importorskip("torch")
    refused(
        "msf-train --out full/run --epochs 1 --steps-per-epoch 1 --batch 2 --lights 4 "
        "--crop 16 --pool 3 --render-size 32 --val-objects 1 --no-progress --precision fp32 -q",
        ["full/run", "No space left on device"],
        capfd,
        world,
    )


def test_a_stack_path_ending_in_dotdot_names_its_default_output(world: Path, capfd) -> None:
    """``msf-run proj/stack/..`` named its default output "msf-out/..": the current folder."""
    (world / "proj").mkdir()
    shutil.copytree(world / "stack", world / "proj" / "stack")
    before = tree(world)
    code, err = run("msf-run proj/stack/.. --method l2 -q", capfd)
    assert code == 0, err
    assert (world / "msf-out" / "proj" / "stack" / "normals.npy").is_file()
    after = {k: v for k, v in tree(world).items() if not k.startswith("msf-out")}
    assert after == before


def test_synth_on_a_full_disk_is_one_line(full: Path, world: Path, capfd) -> None:
    """msf-synth added a libpng line to its own on a full disk."""
    refused(
        "msf-synth full/bench --objects 1 --lights 4 --size 32",
        ["full/bench", "No space left on device"],
        capfd,
        world,
    )


def test_a_capture_after_a_killed_one_leaves_no_staging(tmp_path: Path) -> None:
    """Issue #48: SIGKILL during msf-capture left its session's staging file, and a resumed
    capture that did not write session.json again left it for good. A dead writer's staging
    of any file is swept when the next capture takes the folder (kill -9 cannot be caught)."""
    from msfnet.calib.capture_cli import main as capture_main
    from msfnet.common.files.staging import new_staging

    out = tmp_path / "cap"
    argv = [str(out), "--camera", "sim", "--light-rig", "sim", "--count", "4", "-q"]
    assert capture_main(argv) == 0
    dead = subprocess.run(  # the staging a killed writer leaves: its pid is gone
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True
    ).stdout.strip()
    left = [
        new_staging(out / "session.json", folder=False),
        new_staging(out / "raw" / "x.png", folder=False),
    ]
    for path in left:
        mine = path.name.split(".msf-partial-")[1].split("@")[0]
        path.rename(path.with_name(path.name.replace(f"-{mine}@", f"-{dead}@")))
    assert capture_main(argv) == 0  # resumes: every frame is there, session.json unchanged
    assert not [p for p in out.rglob("*") if ".msf-partial-" in p.name]
