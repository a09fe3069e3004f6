"""Reliability round three (issue #48): the exit-code table a line controller reads, applied by
one rule: 0 pass, 1 defects, 2 bad input or output (also a full disk, memory, an engine that
fails on the model given), 3 the tool failed. msf-inspect exited 3 for an unwritable output, a
full disk and a model that failed at inference: a PLC wrapper read each as a crash."""

from __future__ import annotations

import errno
from pathlib import Path

import numpy as np
import pytest

from msfnet import Model
from msfnet.common.errors import MsfError
from msfnet.runtime.cli.inspect import main as inspect_main
from msfnet.runtime.results.maps import MapOptions
from msfnet.synth.plates import PlateOptions, render_plate


@pytest.fixture(scope="module")
def plate_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    plate = render_plate(PlateOptions(seed=0))
    out = tmp_path_factory.mktemp("exit") / "run"
    Model.least_squares(maps=MapOptions(maps=("albedo", "height", "curvature")))(plate.stack).save(
        out
    )
    return out


def _failing(exc: BaseException):  # type: ignore[no-untyped-def]
    def fail(*args, **kwargs):  # type: ignore[no-untyped-def]
        raise exc

    return fail


@pytest.mark.parametrize("debug", [False, True])
@pytest.mark.parametrize(
    ("failure", "code"),
    [
        (OSError(errno.ENOSPC, "No space left on device", "verdict.json"), 2),
        (OSError(errno.EACCES, "Permission denied", "out"), 2),
        (MemoryError(), 2),
        (MsfError("model.onnx: onnxruntime failed on a 64x64 tile with 12 lights"), 2),
        (RuntimeError("a bug"), 3),
    ],
    ids=["full disk", "unwritable", "memory", "engine", "bug"],
)
def test_msf_inspect_codes_by_one_rule(
    plate_run: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    failure: BaseException,
    code: int,
    debug: bool,
) -> None:
    from msfnet.runtime.cli import inspect as cli

    monkeypatch.setattr(cli, "find_defects", _failing(failure))
    out = tmp_path / "v"
    argv = [str(plate_run), "--depth", "0.1", "-o", str(out), *(["--debug"] if debug else [])]
    assert inspect_main(argv) == code
    err = capsys.readouterr().err
    if not debug:
        assert len(err.strip().splitlines()) == 1 and err.startswith("msf-inspect: ")
    assert not out.exists()


def test_an_unwritable_output_folder_is_exit_2(plate_run: Path, tmp_path: Path, capsys) -> None:
    """For real, not monkeypatched: the output's parent is a file."""
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert inspect_main([str(plate_run), "--depth", "0.1", "-o", str(blocker / "v")]) == 2
    assert capsys.readouterr().err.startswith("msf-inspect: error:")
    assert np.array_equal(np.frombuffer(blocker.read_bytes(), np.uint8), [ord("x")])


def test_result_to_json_is_strict_json_with_non_finite_values() -> None:
    """A flat stack's result wrote NaN / Infinity into Result.to_json(), which no strict JSON
    reader takes; the one JSON writer turns them into null."""
    import json
    from dataclasses import replace

    from _runtime_helpers import sphere_stack

    result = Model.least_squares()(sphere_stack(n=6, h=16, w=16))
    result = replace(result, input={"odd": float("nan"), "big": float("inf"), "set": {2, 1}})

    def refuse(name: str) -> object:
        raise ValueError(f"bare {name} in the JSON")

    parsed = json.loads(result.to_json(indent=None), parse_constant=refuse)
    assert parsed["input"] == {"odd": None, "big": None, "set": [1, 2]}
    assert "\n" not in result.to_json(indent=None)
