"""msf-train's options come from TrainConfig's fields (common.cli.flag metadata): the parsed
defaults are the dataclass's, every flag lands on its field, and --resume's "only what was
typed" keeps working with the --no-* switches stored under their fields. Torch-free."""

from __future__ import annotations

import dataclasses

import pytest

from msfnet.model import train_cli
from msfnet.model.train_config import TrainConfig

# fields that are no option: the run folder (-o, a required Path written by hand) and the
# validation set's fixed light count and seed (runs compare only on the same set)
NOT_FLAGS = {"out", "val_lights", "val_seed", "extra"}


def _parse(*argv: str) -> TrainConfig:
    args = train_cli.build_parser().parse_args(["--out", "run", *argv])
    return train_cli.config_from(vars(args), {})


def test_every_setting_is_a_flag_with_the_dataclass_default() -> None:
    parser = train_cli.build_parser()
    dests = {a.dest for a in parser._actions}
    fields = {f.name for f in dataclasses.fields(TrainConfig)}
    assert fields - NOT_FLAGS <= dests
    assert _parse() == TrainConfig(out="run")


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["--no-mfe", "--no-channels-last"], {"mfe": False, "channels_last": False}),
        (["--no-mff", "--no-sus"], {"mff": False, "sus": False}),
        (["--steps-per-epoch", "7", "--lr", "0.5"], {"steps_per_epoch": 7, "lr": 0.5}),
        (["--render-preset", "hard", "--time-budget", "60"], {"render_preset": "hard"}),
        (["--init", "w.pth", "--workers", "0"], {"init": "w.pth", "workers": 0}),
        (["--lights", "8", "--crop", "16"], {"curriculum": "0:8-8:16"}),
    ],
)
def test_flags_land_on_their_fields(argv: list[str], expected: dict[str, object]) -> None:
    cfg = _parse(*argv)
    for name, value in expected.items():
        assert getattr(cfg, name) == value, name
    untouched = {f.name for f in dataclasses.fields(TrainConfig)} - set(expected) - {"out"}
    changed = {n for n in untouched if getattr(cfg, n) != getattr(TrainConfig(out="run"), n)}
    assert changed <= {"time_budget", "curriculum"}  # only what the command line said


def test_resume_sees_only_what_was_typed() -> None:
    explicit = train_cli._explicit(["--out", "run", "--no-mfe", "--epochs", "3"])
    assert {k: v for k, v in explicit.items() if k != "out"} == {"mfe": False, "epochs": 3}
    stored = dataclasses.asdict(TrainConfig(out="run", batch=4))
    cfg = train_cli.config_from(explicit, stored)
    assert (cfg.mfe, cfg.epochs, cfg.batch) == (False, 3, 4)


def test_help_prints_the_defaults() -> None:
    text = " ".join(train_cli.build_parser().format_help().split())  # argparse wraps lines
    assert "(default '0:16-32:32'; one phase = fixed setting)" in text
    assert "Adam learning rate (default 0.001)" in text
    assert "synthetic domes up to this height/radius (default 1.2;" in text
