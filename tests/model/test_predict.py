"""python -m msfnet.model.predict, the checkpoint check of docs/training.md: bad options are
one line and exit code 2, as in the msf-* commands (they were tracebacks)."""

from __future__ import annotations

from pathlib import Path

import pytest
from _runtime_helpers import sphere_stack

pytest.importorskip("torch", reason="needs torch: the [train] extra")

from msfnet.model.checkpoint import default_checkpoint_path
from msfnet.model.predict import main
from msfnet.runtime.stack import save_stack


@pytest.mark.parametrize(
    ("extra", "words"),
    [(["--threads", "0"], "--threads"), (["--tile", "7"], "--tile 7: must be a multiple of 4")],
)
def test_bad_options_are_one_line(extra: list[str], words: str, tmp_path: Path, capfd) -> None:
    stack = save_stack(sphere_stack(n=4, h=24, w=24), tmp_path / "s")
    try:
        code = main([str(default_checkpoint_path()), str(stack), *extra])
    except SystemExit as exc:  # argparse's own refusals exit from parse_args
        code = exc.code  # type: ignore[assignment]
    assert code == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("python -m msfnet.model.predict: error: "), err
    assert words in err[0], err
