"""common.vocabulary: a setting is written as its reader sets it, flag or keyword."""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import pytest

from msfnet.common.cli import add_flags, flag_names, options_from_args
from msfnet.common.vocabulary import declare, flag, opt, options_type, speaking_as, verbatim


@options_type
@dataclass(frozen=True)
class _Knobs:
    budget_mb: float | None = flag(
        None, "memory budget", name="--budget", type=float, category="limits"
    )
    halo: bool = flag(True, "no halo", name="--no-halo", action="store_false")
    turbo: bool = flag(False, "go fast", action="store_true", category="limits")
    pattern: str | None = flag(None, "which images")
    untold: int = 3  # no flag: the API only


def test_a_setting_reads_as_a_flag_under_a_command_and_a_keyword_from_python() -> None:
    cases = [  # (the message's reference, under a command, from Python)
        (lambda: opt("budget_mb"), "--budget", "budget_mb"),
        (lambda: opt("budget_mb", 512.0), "--budget 512", "budget_mb=512"),
        (lambda: opt("budget_mb", verbatim("0.25")), "--budget 0.25", "budget_mb=0.25"),
        (lambda: opt("halo"), "--no-halo", "halo=False"),
        (lambda: opt("turbo"), "--turbo", "turbo=True"),
        (lambda: opt("pattern", "1-x"), "--pattern 1-x", "pattern='1-x'"),
        (lambda: opt("pattern", "1-x", quote=True), "--pattern '1-x'", "pattern='1-x'"),
        (lambda: opt("pattern", Path("a b")), "--pattern a b", "pattern='a b'"),
        (lambda: opt("overwrite"), "--overwrite", "overwrite=True"),
    ]
    for said, flag_text, keyword_text in cases:
        assert said() == keyword_text
        with speaking_as("msf-test"):
            assert said() == flag_text
        assert said() == keyword_text  # the block ended: Python's words again


def test_a_keyword_has_one_spelling() -> None:
    declare("budget_mb", "--budget")  # the same again: fine
    with pytest.raises(TypeError, match="spelled --budget and --memory"):
        declare("budget_mb", "--memory")


def test_a_command_builds_its_groups_by_category_and_reads_the_options_back() -> None:
    assert flag_names(_Knobs, "limits") == ("budget_mb", "turbo")
    p = argparse.ArgumentParser()
    add_flags(p, _Knobs, only=flag_names(_Knobs, "limits"))
    args = p.parse_args(["--budget", "64", "--turbo"])
    assert options_from_args(_Knobs, args) == _Knobs(budget_mb=64.0, turbo=True)
    with pytest.raises(TypeError, match="declares no flag for \\['untold'\\]"):
        add_flags(p, _Knobs, only=("untold",))
