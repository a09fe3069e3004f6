"""Provenance: what a report says about the run that made it."""

from __future__ import annotations

import hashlib
from datetime import datetime, timezone
from pathlib import Path

from msfnet.common.cli import command_main, make_parser
from msfnet.runtime.engines.method import RunMethod
from msfnet.runtime.results.provenance import Provenance, command_line


def test_a_network_run_names_its_model_by_file_and_checksum(tmp_path: Path) -> None:
    model = tmp_path / "mine.onnx"
    model.write_bytes(b"not really a model")
    when = datetime(2026, 12, 1, 21, 0, 5, tzinfo=timezone.utc)
    p = Provenance.of(
        [tmp_path / "a", tmp_path / "b"],
        RunMethod(model=str(model), engine="openvino", precision="bf16"),
        argv=["/usr/bin/msf-run", "a b", "-o", "out"],
        now=when,
    )
    sha = hashlib.sha256(model.read_bytes()).hexdigest()[:12]
    assert p.model_sha256 == sha and p.date == "2026-12-01T21:00:05Z"
    assert p.input == f"{tmp_path / 'a'}, {tmp_path / 'b'}"
    assert p.command == "msf-run 'a b' -o out"  # as a shell would take it back
    facts = p.facts()
    assert facts["model"] == f"mine.onnx (sha256 {sha})" and facts["engine"] == "openvino bf16"
    assert Provenance.from_dict(p.as_dict()) == p  # profile.json round trip
    assert "- model: `mine.onnx (sha256" in p.markdown()


def test_least_squares_has_no_model() -> None:
    p = Provenance.of("obj/", RunMethod(method="l2", engine="numpy", precision="fp64"), argv=["x"])
    assert p.model is None and p.model_sha256 is None
    assert p.facts()["model"] == "none (least squares)"
    assert Provenance.from_dict({}).engine == "-"  # an old profile.json: blanks, no crash


def test_the_command_line_is_the_commands_own_argv_in_process() -> None:
    seen: list[str] = []
    parser = make_parser("msf-x", "a test command")
    parser.add_argument("thing")

    def body(args: object) -> int:
        seen.append(command_line())
        return 0

    assert command_main("msf-x", parser, body, ["it", "-q"]) == 0
    assert seen == ["msf-x it -q"]  # not pytest's sys.argv
