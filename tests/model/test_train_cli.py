"""msf-train on careless input: --out never an input nor holding one, --overwrite deletes only
msf-train's own files, a damaged config.json is one line; all before any training."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import pytest
from _runtime_helpers import QUICK_VALIDATION

pytest.importorskip("torch")

from msfnet.model.train_cli import main as train_main


def _foreign(t: Path) -> Path:
    (t / "notes.txt").write_text("mine")
    return t


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}


def _ckpt(t: Path) -> Path:
    path = t / "weights.pth"
    path.write_bytes(b"pretend checkpoint")
    return path


def _data(t: Path) -> Path:
    folder = t / "blobby"
    folder.mkdir()
    (folder / "list.txt").write_text("x\n")
    return folder


CONFIG = json.dumps(
    {"epochs": 2, "steps_per_epoch": 3, "batch": 2, "curriculum": "0:4-4:16", "lr": 1e-3, "seed": 0}
)


def _old_run(t: Path, *extra: str) -> Path:
    out = t / "run"
    out.mkdir()
    for name in ("config.json", "last.pth", "log.jsonl", *extra):
        (out / name).write_text(CONFIG if name == "config.json" else "x")
    return out


def _with_folder(out: Path, name: str) -> Path:
    (out / name).mkdir()
    (out / name / "notes.txt").write_text("mine")
    return out


# name: (build(tmp) -> argv, words in the error)
REFUSED: dict[str, tuple[Callable[[Path], list[str]], list[str]]] = {
    "--out is the --init checkpoint": (
        lambda t: ["--out", str(_ckpt(t)), "--init", str(t / "weights.pth"), "--overwrite"],
        ["replace an input"],
    ),
    "--out holds the --init checkpoint": (
        lambda t: ["--out", str(t), "--init", str(_ckpt(t)), "--overwrite"],
        ["contains the input"],
    ),
    "--out holds the --data folder": (
        lambda t: ["--out", str(t), "--data", str(_data(t)), "--overwrite"],
        ["contains the input"],
    ),
    "--out inside the --data folder": (
        lambda t: ["--out", str(_data(t) / "run"), "--data", str(t / "blobby")],
        ["inside the input"],
    ),
    "--out is a file": (lambda t: ["--out", str(_ckpt(t))], ["not a folder"]),
    "--overwrite over a foreign file": (
        lambda t: ["--out", str(_old_run(t, "thesis.tex")), "--overwrite"],
        ["thesis.tex", "did not"],
    ),
    "non-empty without --overwrite": (lambda t: ["--out", str(_old_run(t))], ["--resume"]),
    "--resume and --overwrite": (
        lambda t: ["--out", str(_old_run(t)), "--resume", "--overwrite"],
        ["contradict"],
    ),
    "--resume in a folder of other files": (
        lambda t: ["--out", str(_foreign(t)), "--resume"],
        ["no msf-train run", "notes.txt"],
    ),
    "--resume with binary config.json": (
        lambda t: ["--out", str(_damaged(t, b"\xff\xfe\x00")), "--resume"],
        ["damaged"],
    ),
    "--resume with a list as config": (
        lambda t: ["--out", str(_damaged(t, b"[1, 2]")), "--resume"],
        ["not an msf-train"],
    ),
    "--resume with unknown keys": (
        lambda t: ["--out", str(_damaged(t, b'{"epochz": 3}')), "--resume"],
        ["epochz"],
    ),
    "--overwrite over a folder named like a snapshot": (
        lambda t: ["--out", str(_with_folder(_old_run(t), "snap_0000001.pth")), "--overwrite"],
        ["snap_0000001.pth", "did not"],
    ),
    "--overwrite where config.json is not msf-train's": (
        lambda t: ["--out", str(_damaged(t, b'{"my": "settings"}')), "--overwrite"],
        ["not an msf-train"],
    ),
    "--resume with weights but no optimiser state": (
        lambda t: ["--out", str(_old_run(t, "best.pth")), "--resume"],
        ["best.pth, last.pth", "--init"],
    ),
    "--resume changing the network": (
        lambda t: ["--out", str(_old_run(t, "last_state.pth")), "--resume", "--no-mfe"],
        ["--no-mfe changes the network"],
    ),
    "--overwrite with an option refused later": (
        lambda t: ["--out", str(_old_run(t, "best.pth")), "--overwrite", "--render-lights", "8"],
        ["--render-lights"],
    ),
    "--overwrite with a missing --init": (
        lambda t: [
            "--out",
            str(_old_run(t, "best.pth")),
            "--overwrite",
            "--init",
            str(t / "nowhere.pth"),
        ],
        ["not found"],
    ),
    "--resume where --out does not exist": (
        lambda t: ["--out", str(t / "runs" / "mnie"), "--resume"],
        ["--resume: nothing to resume", "does not exist", "leave out --resume"],
    ),
    "--resume on an empty folder": (
        lambda t: ["--out", str(_empty(t)), "--resume"],
        ["--resume: nothing to resume", "is empty"],
    ),
    "a curriculum beyond --render-lights": (
        lambda t: ["--out", str(t / "r"), "--lights", "32", "--render-lights", "8"],
        ["32 lights", "--render-lights"],
    ),
    "--data neither synth nor a folder": (
        lambda t: ["--out", str(t / "r"), "--data", str(t / "nowhere")],
        ["--data"],
    ),
}


def _empty(t: Path) -> Path:
    (t / "run").mkdir()
    return t / "run"


def _damaged(t: Path, content: bytes) -> Path:
    out = t / "run"
    out.mkdir()
    (out / "config.json").write_bytes(content)
    return out


@pytest.mark.parametrize("case", sorted(REFUSED))
def test_train_refuses_before_training(case: str, tmp_path: Path, capfd) -> None:
    build, words = REFUSED[case]
    argv = build(tmp_path)
    before = _files(tmp_path)
    assert train_main([*argv, "--no-progress"]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("msf-train: error: "), err
    for word in words:
        assert word in err[0], (word, err[0])
    assert _files(tmp_path) == before


def test_overwrite_deletes_only_msf_train_files(tmp_path: Path, monkeypatch) -> None:
    """--overwrite over an earlier run clears its files (and nothing else) before training,
    and only once the set-up has passed: a --device cuda without a GPU (or a bad --data)
    deleted the earlier run's weights, then failed."""
    from types import SimpleNamespace

    from msfnet.common.errors import InputError
    from msfnet.common.files.locks import LOCK_NAME
    from msfnet.model import train, train_cli

    out = _old_run(tmp_path, "best.pth", "curve.png", ".last.pth.msf-partial-1-x.pth")
    before = sorted(p.name for p in out.iterdir())
    argv = ["--out", str(out), "--overwrite", "-q"]
    args = train_cli.build_parser().parse_args(argv)

    def failing_setup(cfg, resume, started=None):  # e.g. resolve_device: no CUDA GPU
        raise InputError("--device cuda: torch sees no CUDA GPU")

    monkeypatch.setattr(train, "Trainer", failing_setup)  # train_cli imports it when it starts
    with pytest.raises(InputError):
        train_cli._run(args, argv)
    assert sorted(p.name for p in out.iterdir()) == before

    started = []

    class Stop(Exception):
        pass

    def stop(**_):  # where training would start (OUT held by msf-train's lock)
        started.append(sorted(p.name for p in out.iterdir() if p.name != LOCK_NAME))
        raise Stop

    ready = SimpleNamespace(
        run=stop,
        device=SimpleNamespace(type="cpu"),
        bf16=False,
        workers=0,
        step=0,
        val_set=[],
        val_ls=0.0,
    )
    monkeypatch.setattr(train, "Trainer", lambda cfg, resume, started=None: ready)
    with pytest.raises(Stop):
        train_cli._run(args, argv)
    assert started == [[]]


def test_negative_grad_loss_is_an_option_error(tmp_path: Path, capfd) -> None:
    with pytest.raises(SystemExit) as exc:
        train_main(["--out", str(tmp_path / "r"), "--grad-loss", "-1", "--no-progress"])
    assert exc.value.code == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert err[-1] == "msf-train: error: --grad-loss: must be 0 or more, got '-1'"
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("mode", ["--overwrite", "--resume"])
def test_without_torch_an_earlier_run_is_left_alone(tmp_path: Path, mode: str) -> None:
    """On an install without torch msf-train says so in one line before it clears OUT."""
    from _runtime_helpers import run_without_torch

    out = _old_run(tmp_path, "best.pth", "snap_0000100.pth")
    before = _files(out)
    done = run_without_torch("msfnet.model.train_cli", ["--out", str(out), mode])
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "needs the Python package 'torch'" in lines[0], lines
    assert done.stdout == ""
    assert _files(out) == before


def test_the_run_says_how_long_it_will_take(monkeypatch, capsys) -> None:
    """The defaults are hours on a small CPU: after the first steps msf-train says how many
    (from the steps it timed, the first left out), before the user has to find out."""
    from types import SimpleNamespace

    from msfnet.model import train_cli
    from msfnet.model.train_config import TrainConfig

    clock = iter([100.0, 130.0, 140.0, 150.0, 160.0, 170.0, 180.0])  # 30 s set-up, then 10 s
    monkeypatch.setattr(train_cli.time, "perf_counter", lambda: next(clock))
    trainer = SimpleNamespace(step=0, device=SimpleNamespace(type="cpu"))
    trainer.train_step = lambda batch: setattr(trainer, "step", trainer.step + 1)
    cfg = TrainConfig(out="x", epochs=20, steps_per_epoch=300, batch=8)
    train_cli._announce_duration(trainer, cfg)
    first = capsys.readouterr().out
    assert "6,000 steps to go (20 epochs x 300 steps of batch 8)" in first
    for _ in range(6):
        trainer.train_step(None)
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1, lines  # said once
    # 10 s a step for the 5,995 steps left when it spoke (the 30 s set-up step left out)
    assert "10 s a step on this cpu: about 16.7 h for the remaining 5,995 steps" in lines[0]


@pytest.mark.parametrize(
    ("option", "bound"),
    [(["--threads", "100000"], "1..1024"), (["--lights", "2"], "3..")],
    ids=["threads", "lights"],
)
def test_threads_and_lights_are_bounded_at_parse_time(
    option: list[str], bound: str, tmp_path: Path, capfd
) -> None:
    """--threads shares every command's bound (common.cpu.MAX_THREADS); --lights starts at
    MIN_LIGHTS, as the curriculum does."""
    from msfnet.common.cpu import MAX_THREADS
    from msfnet.runtime.stack import MIN_LIGHTS

    assert (MAX_THREADS, MIN_LIGHTS) == (1024, 3)  # the bounds the messages name
    with pytest.raises(SystemExit) as exc:
        train_main(["--out", str(tmp_path / "r"), *option, "--no-progress"])
    assert exc.value.code == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"msf-train: error: {option[0]}: "), err
    assert bound in err[0] and not (tmp_path / "r").exists()


def test_a_run_stopped_before_its_first_validation_says_so(
    tmp_path: Path, monkeypatch, capsys
) -> None:
    """A --time-budget shorter than an epoch printed "best held-out MAE inf deg"."""
    from types import SimpleNamespace

    from msfnet.model import train, train_cli

    def trainer(cfg, resume, started=None):  # a run that stops before any validation
        return SimpleNamespace(
            device=SimpleNamespace(type="cpu"),
            bf16=False,
            workers=0,
            step=3,
            val_set=[0, 1],
            val_ls=7.2,
            run=lambda **_: SimpleNamespace(
                stopped=None, step=3, best_val_mae=float("inf"), val_ls_mae=7.2, budget_spent=True
            ),
        )

    monkeypatch.setattr(train, "Trainer", trainer)
    argv = ["--out", str(tmp_path / "r"), "--no-progress"]
    args = train_cli.build_parser().parse_args(argv)
    monkeypatch.setattr(train_cli, "_announce_duration", lambda *a: None)
    assert train_cli._run(args, argv) == 0
    out = capsys.readouterr()
    text = out.out + out.err
    assert "before the first validation" in text and "inf" not in text


# Options that change no refusal below but keep a regression (a refusal that no longer
# happens) from starting hours of training at the defaults.
GUARD = [
    "--epochs",
    "1",
    "--steps-per-epoch",
    "1",
    *QUICK_VALIDATION,
    "--time-budget",
    "20",
    "--no-progress",
]

# review-train-synth.md 12: config.json's values pass the options' own checks
EDITED_CONFIG = {
    "batch 1.5": ({"batch": 1.5}, '"batch": must be an integer, got 1.5'),
    "noise null": ({"noise": None}, '"noise": must be a number, got null'),
    "pool 0": ({"pool": 0}, '"pool": must be a positive integer, got 0'),
    "lr as text": ({"lr": "1e-3"}, '"lr": must be a number, got "1e-3"'),
    "threads 0": ({"threads": 0}, '"threads": must lie in 1..1024, got 0'),
    "mfe 1": ({"mfe": 1}, '"mfe": must be true or false, got 1'),
    "device gpu": ({"device": "gpu"}, '"device": must be one of auto, cpu, cuda, got "gpu"'),
    "workers -1": ({"workers": -1}, '"workers": must be 0 or more, got -1'),
    "val_lights 2": ({"val_lights": 2}, '"val_lights": must lie in 3..1024, got 2'),
    "curriculum twice from 0": (
        {"curriculum": "0:4-8:16,0:8-8:32"},
        "\"curriculum\": '0:4-8:16,0:8-8:32': two phases start at epoch 0; give each its own",
    ),
}


@pytest.mark.parametrize("saved", [True, False], ids=["resume", "before-first-save"])
@pytest.mark.parametrize("case", sorted(EDITED_CONFIG))
def test_a_hand_edited_config_is_checked_like_the_options(
    case: str, saved: bool, tmp_path: Path, capfd
) -> None:
    """A wrong type or range in config.json was "internal error ... please report it" (or an
    error blaming "config.json or last_state.pth" with a Python exception's text)."""
    edit, problem = EDITED_CONFIG[case]
    out = _old_run(tmp_path, "last_state.pth") if saved else _damaged(tmp_path, b"{}")
    if not saved:
        (out / "last.pth").unlink(missing_ok=True)
    (out / "config.json").write_text(json.dumps({**json.loads(CONFIG), **edit}))
    before = _files(tmp_path)
    assert train_main(["--out", str(out), "--resume", *GUARD]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert err == [f"msf-train: error: {out / 'config.json'}: {problem}"]
    assert _files(tmp_path) == before


def test_every_stored_default_passes_the_config_check() -> None:
    from msfnet.model.train_config import TrainConfig, stored_value_problem

    stored = json.loads(json.dumps(TrainConfig(out="run", workers=2, lr=1).stored()))
    assert {k: stored_value_problem(k, v) for k, v in stored.items()} == dict.fromkeys(stored)


# review-train-synth.md 13: what --render-on device does not use is refused, not stored
@pytest.mark.parametrize(
    "given",
    [
        ["--noise", "0"],
        ["--render-size", "8", "--render-lights", "3"],
        ["--pool", "2", "--refresh", "1", "--workers", "2"],
        ["--render-size-max", "128", "--render-max-depth", "2"],
    ],
    ids=["noise", "size-lights", "pool-refresh-workers", "depth-size-max"],
)
def test_render_on_device_refuses_the_options_it_ignores(
    given: list[str], tmp_path: Path, capfd
) -> None:
    out = tmp_path / "r"
    argv = ["--out", str(out), "--render-on", "device", *given, *GUARD]
    assert train_main(argv) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("msf-train: error: "), err
    flags = [word for word in given if word.startswith("--")]
    assert err[0].startswith(
        f"msf-train: error: {', '.join(flags)}: not used by --render-on device"
    )
    assert not out.exists()


def test_render_on_device_help_and_defaults(monkeypatch) -> None:
    from msfnet.model import train_cli

    monkeypatch.setenv("COLUMNS", "1000")  # no option names wrapped at their hyphens
    # the defaults of those options are stored, but only what was typed is refused
    cfg = train_cli.config_from(
        vars(train_cli.build_parser().parse_args(["--out", "r", "--render-on", "device"])),
        {},
        {"out", "render_on"},
    )
    assert cfg.render_on == "device"
    text = " ".join(train_cli.build_parser().format_help().split())
    for flag in train_cli.CPU_RENDER_ONLY:
        assert "--" + flag.replace("_", "-") in text.split("where synthetic batches are")[1]
    assert text.count("--render-on cpu only") == len(train_cli.CPU_RENDER_ONLY)


# review-train-synth.md 8: --lights / --crop replace only their part of the curriculum
@pytest.mark.parametrize(
    ("argv", "curriculum"),
    [
        (["--crop", "16"], "0:16-32:16"),  # was 0:32-32:16: the light range dropped
        (["--lights", "8"], "0:8-8:32"),
        (["--lights", "8", "--crop", "16"], "0:8-8:16"),
        (["--curriculum", "0:4-8:16,2:8-16:32", "--crop", "8"], "0:4-8:8,2:8-16:8"),
        (["--curriculum", "0:4-8:16,2:8-16:32", "--lights", "8"], "0:8-8:16,2:8-8:32"),
        (["--curriculum", "0:4-8:16,2:4-8:32", "--crop", "8"], "0:4-8:8"),
    ],
)
def test_crop_and_lights_keep_the_rest_of_the_curriculum(argv: list[str], curriculum: str) -> None:
    from msfnet.model import train_cli

    args = train_cli.build_parser().parse_args(["--out", "r", *argv])
    typed = set(train_cli._explicit(["--out", "r", *argv]))
    assert train_cli.config_from(vars(args), {}, typed).curriculum == curriculum


def test_crop_on_resume_keeps_the_stored_phases() -> None:
    from dataclasses import asdict

    from msfnet.model import train_cli
    from msfnet.model.train_config import TrainConfig

    stored = asdict(TrainConfig(out="r", curriculum="0:8-16:32,2:16-32:32"))
    explicit = train_cli._explicit(["--out", "r", "--crop", "16"])
    cfg = train_cli.config_from(explicit, stored, set(explicit))
    assert cfg.curriculum == "0:8-16:16,2:16-32:16"


@pytest.mark.parametrize(
    ("argv", "line"),
    [
        (["--crop", "30"], "--crop: must be a multiple of 4, got '30'"),
        (
            ["--curriculum", "0:4-8:16,0:8-8:32"],
            "--curriculum '0:4-8:16,0:8-8:32': two phases start at epoch 0; give each its own",
        ),
        (["--crop", "128"], "--crop 128 asks for 128 px crops but --render-size is 64"),
        (
            ["--lights", "48"],
            "--lights 48 asks for up to 48 lights but --render-lights renders 40",
        ),
        (
            ["--render-lights", "24"],
            "the default --curriculum '0:16-32:32' asks for up to 32 lights but "
            "--render-lights renders 24",
        ),
    ],
    ids=["crop-30", "duplicate-epochs", "crop-beyond-render", "lights-beyond-render", "default"],
)
def test_curriculum_errors_name_what_was_typed(
    argv: list[str], line: str, tmp_path: Path, capfd
) -> None:
    """--crop 30 blamed a --curriculum '0:32-32:30' the user never gave; two phases from epoch
    0 were accepted, the first never applying."""
    out = tmp_path / "r"
    try:
        rc = train_main(["--out", str(out), *argv, *GUARD])
    except SystemExit as exc:  # argparse's refusals
        rc = int(exc.code or 0)
    assert rc == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert err == [f"msf-train: error: {line}"]
    assert not out.exists()
