"""Output-folder manifests (common/files/manifest.py): --overwrite replaces only msfnet's own
folders, and a command naming itself only its own.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from _runtime_helpers import msfnet_folder as _msfnet_folder

from msfnet.common import files
from msfnet.common.errors import InputError
from msfnet.common.files import (
    MANIFEST,
    check_output,
    staged_folder,
)


@pytest.mark.parametrize(
    "manifest", ['{"files": 5}', '{"files": [["a"]]}', "[1, 2]", '{"files": ', "\xff"]
)
def test_a_damaged_manifest_refuses_the_folder(tmp_path: Path, manifest: str) -> None:
    """It raised TypeError ("internal error", exit 1) for {"files": 5}; now nothing in the
    folder is taken for msfnet's, and --overwrite is refused (exit 2)."""
    out = _msfnet_folder(tmp_path / "out")
    (out / MANIFEST).write_bytes(manifest.encode("latin-1"))
    with pytest.raises(InputError, match=f"{MANIFEST} is damaged"):
        check_output(out, folder=True, overwrite=True)
    assert files.foreign_files(out) == ["a.txt"]
    assert (out / "a.txt").is_file()


def test_the_manifest_names_the_writer_and_a_command_replaces_only_its_own(tmp_path: Path) -> None:
    """msf-synth --overwrite replaced any msfnet folder (an msf-run result too), though its
    help says "only one msf-synth wrote"."""
    with files.writing_as("msf-run"):
        run_out = _msfnet_folder(tmp_path / "run")
    api_out = _msfnet_folder(tmp_path / "api")
    assert json.loads((run_out / MANIFEST).read_text())["command"] == "msf-run"
    assert json.loads((api_out / MANIFEST).read_text())["command"] == files.API_WRITER
    with pytest.raises(InputError, match="msf-run's output, not msf-synth's"):
        check_output(run_out, folder=True, overwrite=True, command="msf-synth")
    check_output(run_out, folder=True, overwrite=True)  # "only one msfnet wrote": still fine
    with (
        pytest.raises(InputError, match="msf-run's output"),
        staged_folder(run_out, overwrite=True, command="msf-synth") as tmp,
    ):
        (tmp / "x.txt").write_text("x")  # ... and at the commit, should it appear meanwhile
    assert (run_out / "a.txt").is_file()
    with staged_folder(tmp_path / "syn", command="msf-synth") as tmp:
        (tmp / "x.txt").write_text("x")
    check_output(tmp_path / "syn", folder=True, overwrite=True, command="msf-synth")
    # folders from before the writer was recorded stay replaceable
    (run_out / MANIFEST).write_text(json.dumps({"files": ["a.txt"]}))
    check_output(run_out, folder=True, overwrite=True, command="msf-synth")


def _write_tree(out: Path, writer: str, overwrite: bool = False) -> None:
    with files.writing_as(writer), staged_folder(out, overwrite=overwrite) as tmp:
        (tmp / "obj").mkdir()
        (tmp / "obj" / "normals.png").write_text("x")
        (tmp / "summary.json").write_text("{}")


def test_a_users_file_inside_a_sub_folder_is_never_deleted(tmp_path: Path) -> None:
    """The manifest listed the top level only: --overwrite deleted a user's notes put in
    an msf-eval per-object folder or an msf-synth object folder."""
    out = tmp_path / "ev"
    _write_tree(out, "msf-eval")
    assert json.loads((out / MANIFEST).read_text())["files"] == [
        "obj",
        "obj/normals.png",
        "summary.json",
    ]
    _write_tree(out, "msf-eval", overwrite=True)  # its own tree: replaced
    (out / "obj" / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match=r"did not write \(e.g. obj/notes.txt\)"):
        _write_tree(out, "msf-eval", overwrite=True)
    assert (out / "obj" / "notes.txt").read_text() == "mine"


def test_a_top_level_manifest_cannot_vouch_for_sub_folders(tmp_path: Path) -> None:
    """A folder from before the tree listing: its sub-folders' contents are unknown."""
    out = tmp_path / "old"
    (out / "obj").mkdir(parents=True)
    (out / "obj" / "anything.txt").write_text("?")
    (out / "a.txt").write_text("a")
    (out / MANIFEST).write_text(json.dumps({"files": ["a.txt", "obj"], "command": "msf-eval"}))
    assert files.foreign_files(out) == ["obj/"]
    (out / "obj" / "anything.txt").unlink()
    assert files.foreign_files(out) == []  # an empty listed folder holds nothing to lose


def test_commands_replace_only_folders_of_their_own_kind(tmp_path: Path) -> None:
    """msf-run, msf-eval and msf-inspect replaced any msfnet folder: a rendered dataset, a
    whole msf-run result under a mistyped msf-inspect -o. msf-run and the Python API write
    the same per-stack result and may replace each other's."""
    data = tmp_path / "dataset"
    _write_tree(data, "msf-synth")
    for other in ("msf-run", "msf-inspect", "msf-eval", files.API_WRITER):
        with files.writing_as(other), pytest.raises(InputError, match="msf-synth's output"):
            check_output(data, folder=True, overwrite=True)
        with pytest.raises(InputError, match="msf-synth's output"):
            _write_tree(data, other, overwrite=True)
    assert (data / "obj" / "normals.png").is_file()
    run = tmp_path / "run"
    _write_tree(run, "msf-run")
    _write_tree(run, files.API_WRITER, overwrite=True)
    _write_tree(run, "msf-run", overwrite=True)


def test_an_older_folder_says_why_it_is_not_replaced(tmp_path: Path) -> None:
    out = tmp_path / "old"
    (out / "obj").mkdir(parents=True)
    (out / "obj" / "l2_normals.png").write_text("?")
    (out / MANIFEST).write_text(json.dumps({"files": ["obj"], "command": "msf-eval"}))
    with files.writing_as("msf-eval"), pytest.raises(InputError, match="an older msfnet"):
        check_output(out, folder=True, overwrite=True)
