"""Conventions every command keeps (README, "The data flow"): --help shows examples, every
option says what it does, and the common flags (-q, --debug) are accepted everywhere,
before or after a sub-command's name."""

from __future__ import annotations

import argparse
import importlib
from importlib.metadata import entry_points

import pytest

# the installed commands (pyproject.toml's [project.scripts])
SCRIPTS = {
    e.name: e.value for e in entry_points(group="console_scripts") if e.value.startswith("msfnet.")
}


def _parser(command: str) -> argparse.ArgumentParser:
    module = SCRIPTS[command].split(":")[0]
    try:
        return importlib.import_module(module).build_parser()
    except ModuleNotFoundError as exc:  # an extra's package (torch for msf-train, ...)
        pytest.skip(f"{command}: {exc.name} not installed")


def _parsers(p: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    """The parser and those of its sub-commands."""
    subs = [
        sp
        for a in p._actions
        if isinstance(a, argparse._SubParsersAction)
        for sp in a.choices.values()
    ]
    return [p, *subs]


@pytest.mark.parametrize("command", sorted(SCRIPTS))
def test_every_option_has_help_text(command: str) -> None:
    missing = [
        f"{sp.prog}: {'/'.join(a.option_strings) or a.dest}"
        for sp in _parsers(_parser(command))
        for a in sp._actions
        if not isinstance(a, argparse._SubParsersAction)
        and a.help != argparse.SUPPRESS
        and not (a.help or "").strip()
    ]
    assert missing == [], missing


@pytest.mark.parametrize("command", sorted(SCRIPTS))
def test_help_ends_with_examples_of_the_command(command: str) -> None:
    text = _parser(command).format_help()
    assert "examples:" in text, command
    examples = text.split("examples:", 1)[1].splitlines()
    assert any(line.strip().startswith(command + " ") for line in examples), examples


@pytest.mark.parametrize("command", sorted(SCRIPTS))
def test_common_flags_everywhere(command: str) -> None:
    p = _parser(command)
    for sp in _parsers(p):
        flags = {s for a in sp._actions for s in a.option_strings}
        assert {"-q", "--debug"} <= flags, sp.prog
    assert "--version" in {s for a in p._actions for s in a.option_strings}


def test_common_flags_before_or_after_the_sub_command() -> None:
    p = _parser("msf-calib")
    tail = ["chrome/", "-o", "l.txt"]
    for argv in (
        ["-q", "directions", *tail],
        ["directions", "-q", *tail],
        ["--debug", "-q", "intensities", "w/", "--lights", "l.txt", "-o", "i.txt"],
    ):
        args = p.parse_args(argv)
        assert args.quiet is True, argv
    args = p.parse_args(["--debug", "directions", *tail])
    assert args.debug is True and args.quiet is False
    plain = p.parse_args(["directions", *tail])
    assert plain.quiet is False and plain.debug is False


@pytest.mark.parametrize(
    ("command", "module", "extra"),
    [
        ("msfnet.bench.cli", "onnx", "bench"),  # was [export]: msf-bench also needs matplotlib
        ("msfnet.bench.cli", "torch", "bench"),
        ("msfnet.bench.cli", "matplotlib", "bench"),
        ("msfnet.export.cli", "onnx", "export"),
        ("msfnet.model.train_cli", "torch", "train"),
        ("msfnet.runtime.cli.run", "ray", "ray"),
        ("msfnet.synth.cli", "torch", "export,train"),  # no extra of its own: the torch side's
    ],
)
def test_install_hint_names_the_commands_own_extra(command: str, module: str, extra: str) -> None:
    import importlib

    from msfnet.common.cli import Command, install_hint

    own = getattr(importlib.import_module(command), "COMMAND", Command("msf-x"))
    hint = install_hint(module, own.extra)
    assert f"pip install 'msfnet[{extra}]'" in hint and f"-e '.[{extra}]'" in hint, hint
