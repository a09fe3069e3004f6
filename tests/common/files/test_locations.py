"""Where an output may go (common/files/locations.py): never over, into or around an input,
never over anything but a regular file or msfnet's own folder, checked before any work.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from _runtime_helpers import msfnet_folder as _msfnet_folder
from _runtime_helpers import staging_leftovers as _leftovers

from msfnet.common.errors import InputError
from msfnet.common.files import (
    check_output,
    staged_files,
    staged_folder,
    write_atomic,
)

# ---------------------------------------------------------------------------- check_output


def _tree(tmp: Path) -> dict[str, Path]:
    stack = tmp / "data" / "stack"
    stack.mkdir(parents=True)
    (stack / "001.png").write_bytes(b"x")
    lights = tmp / "data" / "lights.txt"
    lights.write_text("0 0 1\n")
    (tmp / "a_file").write_text("not a folder")
    (tmp / "a_dir").mkdir()
    (tmp / "link_to_stack").symlink_to(stack)
    (tmp / "link_to_lights").symlink_to(lights)
    os.link(lights, tmp / "hard_link_to_lights")
    return {"stack": stack, "lights": lights}


# name: (target relative to tmp, folder output?, --overwrite?, words of the refusal)
REFUSED: dict[str, tuple[str, bool, bool, str]] = {
    "output is the input file": ("data/lights.txt", False, True, "replace an input"),
    "output is the input folder": ("data/stack", True, True, "replace an input"),
    "output folder contains the input (parent)": ("data", True, True, "contains the input"),
    "output inside the input folder": ("data/stack/res", True, False, "inside the input"),
    "file output inside the input folder": ("data/stack/l.txt", False, False, "inside the input"),
    "symlink to the input file": ("link_to_lights", False, True, "replace an input"),
    "hard link to the input file": ("hard_link_to_lights", False, True, "replace an input"),
    "inside the input through a symlink": ("link_to_stack/res", True, False, "inside the input"),
    "parent path is a file": ("a_file/out", True, False, "is a file, not a folder"),
    "deeper under a file": ("a_file/x/y/out.txt", False, False, "is a file, not a folder"),
    "file output exists": ("a_file", False, False, "overwrite=True"),
    "folder output is an existing file": ("a_file", True, True, "not a folder"),
    "file output is an existing folder": ("a_dir", False, True, "is a folder"),
}


@pytest.mark.parametrize("case", sorted(REFUSED))
def test_check_output_refuses(case: str, tmp_path: Path) -> None:
    inputs = _tree(tmp_path)
    target, folder, overwrite, words = REFUSED[case]
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    with pytest.raises(InputError, match=words):
        check_output(tmp_path / target, inputs.values(), overwrite=overwrite, folder=folder)
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before


def test_missing_input_under_the_output_is_not_found(tmp_path: Path) -> None:
    """An input that does not exist, named inside (or as) the output, is reported missing:
    "the output contains the input" sent users to fix the wrong thing."""
    for target, missing in (("ej", "ej/l.txt"), ("x.txt", "x.txt")):
        with pytest.raises(InputError, match="not found") as err:
            check_output(tmp_path / target, [tmp_path / missing], folder=target == "ej")
        assert err.value.path == tmp_path / missing
    assert not any(tmp_path.iterdir())


def test_check_output_folder_rules(tmp_path: Path) -> None:
    out = tmp_path / "out"
    check_output(out, folder=True)  # new
    out.mkdir()
    check_output(out, folder=True)  # empty: fine without --overwrite
    (out / "mine.txt").write_text("the user's")
    with pytest.raises(InputError, match="overwrite=True"):
        check_output(out, folder=True)
    with pytest.raises(InputError, match=r"did not write.*mine\.txt"):
        check_output(out, folder=True, overwrite=True)
    (out / "mine.txt").unlink()
    _msfnet_folder(out)
    check_output(out, folder=True, overwrite=True)  # msfnet's own: may be replaced
    (out / "added.txt").write_text("by hand")  # ... until someone adds a file to it
    with pytest.raises(InputError, match=r"added\.txt"):
        check_output(out, folder=True, overwrite=True)


def test_check_output_unwritable_parent_before_any_work(tmp_path: Path, monkeypatch) -> None:
    """A read-only destination is reported by the check, not after the computation (root can
    write anywhere, so the permission answer is simulated)."""
    real_access = os.access
    monkeypatch.setattr(
        os, "access", lambda p, mode: False if Path(p) == tmp_path else real_access(p, mode)
    )
    with pytest.raises(InputError, match="not writable"):
        check_output(tmp_path / "out", folder=True)


# ---------------------------------------------------------------------------- special files


def _special(kind: str, path: Path) -> None:
    """Put a non-regular entry of ``kind`` at ``path`` (skip where the system refuses)."""
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "char device":
        import stat

        try:  # the node of /dev/null (1, 3): only root may make one
            os.mknod(path, 0o666 | stat.S_IFCHR, os.makedev(1, 3))
        except PermissionError:
            pytest.skip("making a device node needs root")
    elif kind == "socket":
        import socket

        sock = socket.socket(socket.AF_UNIX)
        try:
            sock.bind(str(path))
        except OSError as exc:  # a path too long for AF_UNIX
            pytest.skip(f"cannot bind a socket here: {exc}")
        finally:
            sock.close()
    elif kind == "link to stdout":
        path.symlink_to("/proc/self/fd/1")
    elif kind == "link to a file":
        (path.parent / "real.txt").write_text("the user's")
        path.symlink_to(path.parent / "real.txt")
    elif kind == "dangling link":
        path.symlink_to(path.parent / "nowhere")
    else:
        raise AssertionError(kind)


SPECIAL = ["fifo", "char device", "socket", "link to stdout", "link to a file", "dangling link"]


def _entries(folder: Path) -> dict[str, int]:
    return {p.name: os.lstat(p).st_mode for p in folder.iterdir()}


@pytest.mark.parametrize("folder", [False, True], ids=["file output", "folder output"])
@pytest.mark.parametrize("kind", SPECIAL)
def test_check_output_never_replaces_a_special_file(
    kind: str, folder: bool, tmp_path: Path
) -> None:
    """--overwrite replaced /dev/null, a FIFO or a link to /proc/self/fd/1 with a regular file
    (issue #27): only a regular file (or msfnet's own folder) is ever replaced, and the refusal
    does not advise --overwrite."""
    target = tmp_path / "out.x"
    _special(kind, target)
    before = _entries(tmp_path)
    for overwrite in (False, True):
        with pytest.raises(InputError) as exc:
            check_output(target, overwrite=overwrite, folder=folder)
        message = str(exc.value)
        assert ("symbolic link" if "link" in kind else "not a regular file") in message
        assert "pass --overwrite" not in message
    assert _entries(tmp_path) == before


@pytest.mark.parametrize("kind", SPECIAL)
@pytest.mark.parametrize("writer", ["write_atomic", "staged_files", "staged_folder"])
def test_a_special_file_that_appears_meanwhile_is_not_replaced(
    writer: str, kind: str, tmp_path: Path
) -> None:
    """The commit checks again, under the folder's lock, whatever ``overwrite`` says: every
    writer goes through the one check (a cache or checkpoint writer never runs check_output)."""
    target = tmp_path / "out.x"

    def meanwhile(tmp: Path) -> None:
        (tmp / "f.txt").write_text("new") if tmp.is_dir() else tmp.write_text("new")
        _special(kind, target)

    with pytest.raises(InputError, match="symbolic link" if "link" in kind else "regular file"):
        if writer == "write_atomic":
            write_atomic(target, meanwhile, overwrite=True)
        elif writer == "staged_files":
            with staged_files([target], overwrite=True) as (tmp,):
                meanwhile(tmp)
        else:
            with staged_folder(target, overwrite=True) as tmp:
                meanwhile(tmp)
    assert not stat_is_regular(target)
    assert not _leftovers(tmp_path)


def stat_is_regular(path: Path) -> bool:
    import stat

    return stat.S_ISREG(os.lstat(path).st_mode)


def test_regular_files_and_own_folders_are_still_replaced(tmp_path: Path) -> None:
    target = tmp_path / "out.txt"
    target.write_text("old")
    check_output(target, overwrite=True)
    write_atomic(target, lambda t: t.write_text("new"))
    assert target.read_text() == "new"
    out = _msfnet_folder(tmp_path / "out")
    check_output(out, overwrite=True, folder=True)
    _msfnet_folder(out, ("b.txt",))
    assert (out / "b.txt").is_file()


def test_a_hard_link_of_an_input_in_the_output_is_refused(tmp_path: Path) -> None:
    out = _msfnet_folder(tmp_path / "out", ("normals.png",))
    stack = tmp_path / "stk"
    stack.mkdir()
    os.link(out / "normals.png", stack / "003.png")
    with pytest.raises(InputError, match=r"hard link\) of the input .*003\.png"):
        check_output(out, [stack / "003.png"], overwrite=True, folder=True)
    check_output(tmp_path / "new", [stack / "003.png"], folder=True)


def test_an_output_under_a_link_loop_says_so(tmp_path: Path) -> None:
    """It said "loopA: File exists"."""
    (tmp_path / "loopA").symlink_to("loopB")
    (tmp_path / "loopB").symlink_to("loopA")
    with pytest.raises(InputError, match="loopA is a link that leads nowhere"):
        check_output(tmp_path / "loopA" / "sub", folder=True)


def test_an_output_is_walked_for_linked_inputs_only_once_it_would_be_replaced(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """review-links23.md 5: `-o ~` with a stack of links walked 278k files (2.9-6.7 s) before
    saying the folder was not empty."""
    import msfnet.common.files.locations as loc

    walked: list[Path] = []
    real_walk = loc._file_ids
    monkeypatch.setattr(loc, "_file_ids", lambda folder: walked.append(folder) or real_walk(folder))
    home = tmp_path / "home"
    home.mkdir()
    (home / "notes.txt").write_text("x")
    store = tmp_path / "store.png"
    store.write_bytes(b"x")
    link = tmp_path / "001.png"
    link.symlink_to(store)
    with pytest.raises(InputError, match="not empty"):
        check_output(home, [], folder=True, reads=[link])
    assert walked == []
    out = _msfnet_folder(tmp_path / "out")
    check_output(out, [], overwrite=True, folder=True, reads=[link])
    assert walked == [out.resolve()]
