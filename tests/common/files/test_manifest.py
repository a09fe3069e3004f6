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
