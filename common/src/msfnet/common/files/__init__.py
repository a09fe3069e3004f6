"""The one way msfnet writes files: atomically, never over an input, all-or-nothing.

Rules every command follows, by module:
- ``locations``: an output never is, contains or lies inside an input (symlinks resolved,
  checked both ways); only a regular file or a folder is ever replaced, never a symbolic
  link, device node, FIFO or socket (:func:`check_replaceable`, also at every commit); output
  locations are checked before any long computation (:func:`check_output`);
- ``manifest``: an existing output is replaced only with ``overwrite``, and a folder only if
  msfnet wrote it (its ``.msfnet-output.json`` manifest lists every file in it): nothing else
  is ever deleted; the manifest also names the command that wrote the folder, so a command can
  refuse to replace another's (msf-synth replaces only a benchmark root it rendered);
- ``staging``: files are written to a temporary sibling and folders staged beside the target;
  on SIGINT/SIGTERM the staging is removed, and staging left by a killed process (``kill -9``)
  is removed by the next run writing to the same place; intermediate files a command needs on
  disk go to a scratch folder beside the output that is always removed (:func:`scratch_folder`);
- ``atomic``: outputs are renamed into place under a lock on the parent folder with Ctrl-C and
  SIGTERM deferred, so two commands writing to the same place never mix their files and a
  signal never lands between removing an old output and renaming the new one into place;
  several output files of one command appear together or not at all (:func:`staged_files`);
  contents are flushed to disk before the rename that publishes them; files get the user's
  normal permissions (umask), like any other tool's output;
- ``locks``: a lock a long-running writer holds on its folder (msf-capture's sessions);
- ``text``: JSON without bare NaN, rows of numbers.
"""

from __future__ import annotations

from msfnet.common.files.atomic import (
    forget_written,
    staged_files,
    staged_folder,
    write_atomic,
    write_json,
    write_text,
    write_vectors,
    written_outputs,
)
from msfnet.common.files.locations import (
    check_not_holding,
    check_not_input,
    check_output,
    check_replaceable,
    numbered_folder,
    same_file,
)
from msfnet.common.files.locks import FolderBusy, folder_lock
from msfnet.common.files.manifest import (
    API_WRITER,
    MANIFEST,
    current_writer,
    foreign_files,
    refuse_foreign,
    writing_as,
)
from msfnet.common.files.staging import (
    STAGING_TAG,
    remove_stale_staging,
    remove_stale_staging_in,
    scratch_folder,
)
from msfnet.common.files.text import json_text, to_jsonable, vectors_text

__all__ = [
    "API_WRITER",
    "MANIFEST",
    "STAGING_TAG",
    "FolderBusy",
    "check_not_holding",
    "check_not_input",
    "check_output",
    "check_replaceable",
    "current_writer",
    "folder_lock",
    "foreign_files",
    "forget_written",
    "json_text",
    "numbered_folder",
    "refuse_foreign",
    "remove_stale_staging",
    "remove_stale_staging_in",
    "same_file",
    "scratch_folder",
    "staged_files",
    "staged_folder",
    "to_jsonable",
    "vectors_text",
    "write_atomic",
    "write_json",
    "write_text",
    "write_vectors",
    "writing_as",
    "written_outputs",
]
