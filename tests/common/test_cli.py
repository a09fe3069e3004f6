"""Shared CLI behaviour (common/cli.py): option types, one-line errors, exit codes.

The per-command tables at the end run every command's parser on the numeric option values a
careless or hostile user types (nan, inf, 0, negatives, words): each must be refused by argparse
in one line with exit 2, before any work.
"""

from __future__ import annotations

import argparse
import errno
import warnings
from collections.abc import Callable
from pathlib import Path

import pytest

from msfnet.common import cli as cliutil
from msfnet.common.cli import (
    finite_float,
    float_range,
    int_range,
    make_parser,
    nonnegative_float,
    nonnegative_int,
    positive_float,
    positive_int,
    run_command,
)
from msfnet.common.errors import InputError, MsfError
from msfnet.common.files import write_text
from msfnet.common.signals import Terminated

# type: (accepted text -> value, refused texts)
TYPES: dict[str, tuple[Callable[[str], object], dict[str, object], list[str]]] = {
    "positive_int": (positive_int, {"1": 1, "12": 12}, ["0", "-3", "nan", "inf", "1.5", "x", ""]),
    "nonnegative_int": (nonnegative_int, {"0": 0, "7": 7}, ["-1", "nan", "2.0", "1e3", "seven"]),
    "positive_float": (
        positive_float,
        {"0.5": 0.5, "1e3": 1000.0},
        ["0", "-1", "nan", "NaN", "inf", "-inf", "1e999", "x"],
    ),
    "nonnegative_float": (nonnegative_float, {"0": 0.0, "2.5": 2.5}, ["-1e-9", "nan", "inf"]),
    "finite_float": (finite_float, {"-2": -2.0, "0": 0.0}, ["nan", "inf", "-inf", "1e400", "?"]),
    "int_range(3, 9)": (int_range(3, 9), {"3": 3, "9": 9}, ["2", "10", "nan", "4.5"]),
    "float_range(0, 1)": (float_range(0, 1), {"0": 0.0, "1": 1.0}, ["-0.1", "1.01", "nan"]),
}


@pytest.mark.parametrize("name", sorted(TYPES))
def test_option_types(name: str) -> None:
    parse, good, bad = TYPES[name]
    for text, value in good.items():
        assert parse(text) == value
    for text in bad:
        with pytest.raises(argparse.ArgumentTypeError):
            parse(text)


def test_parser_errors_are_one_line_exit_2(capsys) -> None:
    p = make_parser("msf-x", "test")
    p.add_argument("--n", type=positive_int)
    with pytest.raises(SystemExit) as exc:
        p.parse_args(["--n", "nan"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["msf-x: error: --n: 'nan' is not an integer"]  # no "argument " prefix
    with pytest.raises(SystemExit):
        p.parse_args(["--m"])
    assert capsys.readouterr().err == "msf-x: error: unrecognized arguments: --m\n"


def _raise(exc: BaseException) -> Callable[[], int]:
    def body() -> int:
        raise exc

    return body


# failure -> (exit code, start of the one stderr line, words in it)
FAILURES: dict[str, tuple[BaseException, int, str, str]] = {
    "input error": (
        InputError("bad lights", Path("l.txt")),
        2,
        "msf-x: error: l.txt: bad",
        "bad lights",
    ),
    "multi-line input error": (
        InputError("line one\nline two"),
        2,
        "msf-x: error:",
        "line one line two",
    ),
    "file name with a newline": (
        InputError("not found", Path("a\nb.png")),
        2,
        "msf-x: error:",
        "a b.png",
    ),
    "ctrl-c": (KeyboardInterrupt(), 130, "msf-x: interrupted", "nothing was written"),
    "sigterm": (Terminated(15), 143, "msf-x: terminated", "nothing was written"),
    "sighup": (Terminated(1), 129, "msf-x: terminated", "signal 1"),
    "disk full": (
        OSError(errno.ENOSPC, "No space left on device", "out/normals.npy"),
        2,
        "msf-x: error: out/normals.npy",
        "No space left",
    ),
    "read-only disk": (
        OSError(errno.EROFS, "Read-only file system", "out"),
        2,
        "msf-x: error:",
        "Read-only",
    ),
    # msf-x has no --max-memory: the advice must not name one (test below for msf-run's)
    "out of memory": (MemoryError(), 2, "msf-x: error: out of memory", "smaller inputs"),
    "engine failure": (MsfError("engine failed\ndetails"), 2, "msf-x: error:", "engine failed"),
    "nested json": (
        RecursionError("maximum recursion depth exceeded"),
        2,
        "msf-x: error:",
        "nested",
    ),
    "unexpected": (
        ZeroDivisionError("division by zero"),
        1,
        "msf-x: internal error:",
        "ZeroDivisionError",
    ),
    "own module missing (a bug)": (
        ModuleNotFoundError("x", name="msfnet.gone"),
        1,
        "msf-x: internal error:",
        "ModuleNotFoundError",
    ),
    "a typo in an import (a bug)": (
        ModuleNotFoundError("x", name="nmupy"),
        1,
        "msf-x: internal error:",
        "ModuleNotFoundError",
    ),
}


@pytest.mark.parametrize("case", sorted(FAILURES))
def test_run_command_turns_failures_into_one_line(case: str, capfd) -> None:
    exc, code, start, words = FAILURES[case]
    assert run_command("msf-x", _raise(exc)) == code
    captured = capfd.readouterr()
    lines = captured.err.splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith(start) and words in lines[0], lines[0]
    assert "Traceback" not in captured.err and captured.out == ""


@pytest.mark.parametrize(
    "exc", [MemoryError(), OSError(errno.ENOSPC, "No space left on device", "v/verdict.json")]
)
def test_a_full_disk_or_memory_is_exit_2_in_every_command(exc, capfd) -> None:
    """One rule (issue #48): 2 is bad input or output, which a full disk or memory is; 3 (a
    crash to a PLC reading msf-inspect) only for a failure of the tool itself."""
    from msfnet.runtime.cli import inspect, run

    assert run_command(inspect.COMMAND, _raise(exc)) == 2
    assert run_command(run.COMMAND, _raise(exc)) == 2
    assert capfd.readouterr().err.count("\n") == 2


@pytest.mark.parametrize(
    ("module", "words"),
    [
        ("torch", "pip install torch --index-url https://download.pytorch.org/whl/cpu"),
        ("depthai", "pip install 'msfnet[camera]'"),
        ("ray", "pip install -e '.[ray]'"),
    ],
)
def test_a_missing_optional_package_is_one_line_with_the_install_command(
    module: str, words: str, monkeypatch, capfd
) -> None:
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == module else real(name, *a)
    )
    exc = ModuleNotFoundError(f"No module named '{module}.sub'", name=f"{module}.sub")
    assert run_command("msf-x", _raise(exc)) == 2
    lines = capfd.readouterr().err.splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"msf-x: error: needs the Python package '{module}'"), lines
    assert words in lines[0], lines
    with pytest.raises(ModuleNotFoundError):  # --debug: the traceback
        run_command("msf-x", _raise(exc), debug=True)


def test_a_module_missing_inside_an_installed_optional_package_is_no_install_hint(
    monkeypatch, capfd
) -> None:
    """torch present but torch._C missing (a broken install): "pip install torch" would answer
    "already satisfied"; it stays an internal error naming the module."""
    import importlib.machinery
    import importlib.util

    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: importlib.machinery.ModuleSpec(name, None)
    )
    exc = ModuleNotFoundError("No module named 'torch._C'", name="torch._C")
    assert run_command("msf-x", _raise(exc)) == 1
    err = capfd.readouterr().err
    assert err.startswith("msf-x: internal error: ModuleNotFoundError") and "torch._C" in err


@pytest.mark.parametrize("case", ["input error", "disk full", "unexpected", "engine failure"])
def test_debug_shows_the_traceback(case: str) -> None:
    exc = FAILURES[case][0]
    with pytest.raises(type(exc)):
        run_command("msf-x", _raise(exc), debug=True)


def test_closed_stdout_pipe_exits_quietly() -> None:
    """`msf-run --json | head -c 10`: the reader goes away; no traceback, no error line."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "from msfnet.common.cli import run_command\n"
        "def body():\n"
        "    for _ in range(100000):\n"
        "        print('x' * 100)\n"
        "    return 0\n"
        "sys.exit(run_command('msf-x', body))\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.read(10)
    proc.stdout.close()  # like `head` exiting
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == 141 and err == "", err


def test_library_warnings_only_with_debug(capfd) -> None:
    def noisy() -> int:
        warnings.warn("numpy says: invalid value encountered", RuntimeWarning, stacklevel=1)
        return 0

    assert run_command("msf-x", noisy) == 0
    assert capfd.readouterr().err == ""
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        assert run_command("msf-x", noisy, debug=True) == 0
    assert len(seen) == 1


def test_interrupt_after_a_complete_output_says_what_is_kept(tmp_path: Path, capfd) -> None:
    """msf-run on two stacks, Ctrl-C during the second: the first stack's folder is complete
    and kept, so 'nothing was written' would be false."""

    def body() -> int:
        write_text(tmp_path / "first.txt", "done")
        raise KeyboardInterrupt

    assert run_command("msf-x", body) == 130
    line = capfd.readouterr().err.strip()
    assert "kept" in line and "first.txt" in line and "\n" not in line
    assert run_command("msf-x", _raise(KeyboardInterrupt())) == 130  # a fresh command
    assert "nothing was written" in capfd.readouterr().err


# ---------------------------------------------------------------------------- every command


def _run_main(argv: list[str]) -> int:
    from msfnet.runtime.cli.run import main

    return main(argv)


def _eval_main(argv: list[str]) -> int:
    from msfnet.runtime.cli.eval import main

    return main(argv)


def _calib_main(argv: list[str]) -> int:
    from msfnet.calib.cli import main

    return main(argv)


def _synth_main(argv: list[str]) -> int:
    from msfnet.synth.cli import main

    return main(argv)


def _export_main(argv: list[str]) -> int:
    from msfnet.export.cli import main

    return main(argv)


def _train_main(argv: list[str]) -> int:
    pytest.importorskip("torch")
    from msfnet.model.train_cli import main

    return main(argv)


MAINS = {
    "msf-run": _run_main,
    "msf-eval": _eval_main,
    "msf-calib": _calib_main,
    "msf-synth": _synth_main,
    "msf-train": _train_main,
    "msf-export": _export_main,
}

# command: (argv before the option, [(option, bad values)])
NUMERIC: dict[str, tuple[list[str], list[tuple[str, list[str]]]]] = {
    "msf-run": (
        ["stack", "--method", "l2"],
        [
            ("--max-memory", ["nan", "inf", "-inf", "0", "-5", "1e999", "lots"]),
            ("--max-lights", ["0", "-1", "nan", "2.5"]),
            ("--threads", ["0", "-2", "nan"]),
            ("--repeat", ["0", "-1", "inf"]),
        ],
    ),
    "msf-eval": (
        ["root", "--l2-only"],
        [
            ("--max-memory", ["nan", "inf", "0"]),
            ("--max-lights", ["0", "nan"]),
            ("--threads", ["0"]),
        ],
    ),
    "msf-calib": (
        ["directions", "chrome", "-o", "l.txt"],
        [
            ("--focal", ["0", "-100", "nan", "inf"]),
            ("--spheres", ["0", "-1", "100000", "nan"]),
        ],
    ),
    "msf-synth": (
        ["root"],
        [
            ("--objects", ["0", "-1", "nan"]),
            ("--lights", ["2", "0", "100000", "nan"]),
            ("--size", ["0", "7", "1000000", "nan"]),
            ("--seed", ["-1", "nan"]),
        ],
    ),
    "msf-train": (
        ["--out", "run"],
        [
            ("--epochs", ["0", "-1", "nan"]),
            ("--batch", ["0"]),
            ("--lr", ["0", "-1e-3", "nan", "inf"]),
            ("--noise", ["-0.1", "nan"]),
            ("--threads", ["0", "100000"]),
            ("--ckpt-minutes", ["0", "nan"]),
            ("--val-objects", ["0"]),
            ("--render-size", ["0", "nan", "1000000"]),
            ("--seed", ["-1"]),
        ],
    ),
    "msf-export": (
        ["model.pth"],
        [
            ("--opset", ["8", "21", "nan", "17.0"]),
            ("--train-lights", ["0", "-1", "nan", "2.5"]),
            ("--tolerance", ["0", "-0.1", "nan", "inf", "deg"]),
        ],
    ),
}


def _numeric_cases() -> list[tuple[str, str, str]]:
    return [
        (cmd, opt, value)
        for cmd, (_, opts) in NUMERIC.items()
        for opt, values in opts
        for value in values
    ]


@pytest.mark.parametrize(("cmd", "option", "value"), _numeric_cases())
def test_every_numeric_option_is_validated_by_argparse(
    cmd: str, option: str, value: str, tmp_path: Path, monkeypatch, capfd
) -> None:
    monkeypatch.chdir(tmp_path)
    before, _ = NUMERIC[cmd]
    with pytest.raises(SystemExit) as exc:
        MAINS[cmd]([*before, f"{option}={value}"])
    assert exc.value.code == 2
    lines = capfd.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{cmd}") and "error:" in lines[0], lines
    assert option in lines[0]
    assert list(tmp_path.iterdir()) == []


EMPTY_PATHS = {
    "msf-run": [[""], ["stack", "-o", ""], ["stack", "--lights", ""]],
    "msf-eval": [[""], ["root", "-o", ""]],
    "msf-synth": [[""]],
    "msf-calib": [["directions", "", "-o", "l.txt"]],
    "msf-export": [[""], ["model.pth", "-o", ""]],
    "msf-train": [["--init", "", "-o", "run"], ["--data", "", "-o", "run"]],
}


@pytest.mark.parametrize(
    ("cmd", "argv"), [(cmd, argv) for cmd, cases in EMPTY_PATHS.items() for argv in cases]
)
def test_an_empty_path_is_refused_not_read_as_here(
    cmd: str, argv: list[str], tmp_path: Path, monkeypatch, capfd
) -> None:
    """Path("") is ".": msf-synth "" offered to replace the current folder."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exc:
        MAINS[cmd](argv)
    assert exc.value.code == 2
    lines = capfd.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(cmd) and "an empty path" in lines[0], lines
    assert list(tmp_path.iterdir()) == []


def test_calib_intrinsics_refused_before_any_work(tmp_path: Path, capfd) -> None:
    """--intrinsics 0 0 0 0 used to hang in LAPACK at 100 % CPU, ignoring Ctrl-C."""
    for values, words in (
        (["nan", "1", "2", "3"], "finite"),
        (["1", "1", "inf", "0"], "finite"),
        (["0", "0", "0", "0"], "positive"),
        (["-5", "5", "1", "1"], "positive"),
    ):
        argv = [
            "directions",
            str(tmp_path / "missing"),
            "-o",
            str(tmp_path / "l.txt"),
            "--intrinsics",
            *values,
        ]
        try:
            code = _calib_main(argv)
        except SystemExit as exc:
            code = exc.code
        assert code == 2
        lines = capfd.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and words in lines[0] and "--intrinsics" in lines[0], lines
    assert list(tmp_path.iterdir()) == []


def test_cliutil_exports() -> None:
    assert set(cliutil.__all__) >= {
        "run_command",
        "make_parser",
        "positive_float",
        "finite_float",
        "int_range",
        "add_common_flags",
    }


@pytest.mark.parametrize(
    "module",
    ["msfnet.model.train_cli", "msfnet.model.average", "msfnet.export.cli", "msfnet.bench.cli"],
)
def test_commands_needing_torch_parse_their_options_without_it(module: str) -> None:
    """On the edge install (no torch) --help works (the work itself ends in one line, exit 2:
    tests/model/test_train_cli.py, tests/bench/test_reliability_bench.py)."""
    from _runtime_helpers import run_without_torch

    done = run_without_torch(module, ["--help"])
    assert done.returncode == 0 and "usage:" in done.stdout, done.stderr


@pytest.mark.parametrize(
    ("module", "prog", "advice"),
    [
        ("msfnet.runtime.cli.run", "msf-run", "lower --max-memory (or --tile)"),
        ("msfnet.calib.cli", "msf-calib", "close other programs or give smaller inputs"),
    ],
)
def test_out_of_memory_advice_names_only_options_the_command_has(
    module: str, prog: str, advice: str, capfd
) -> None:
    """Every command advised "lower --max-memory (or --tile)", options msf-calib, msf-average
    or msf-synth do not have: each command passes its own advice (or none) to command_main."""
    import importlib

    own = importlib.import_module(module)
    assert run_command(getattr(own, "COMMAND", prog), _raise(MemoryError())) == 2
    line = capfd.readouterr().err.strip()
    assert line == f"{prog}: error: out of memory; {advice}"


def test_command_main_check_runs_after_parsing_and_before_the_body(capsys) -> None:
    """The ``check`` hook: a rule argparse cannot state fails as a usage error (one line, exit
    2, also with --debug) and the body never runs; a kept rule lets the body run as usual."""
    calls: list[str] = []

    def parser() -> argparse.ArgumentParser:
        p = make_parser("msf-x", "test")
        p.add_argument("name", nargs="?")
        p.add_argument("--list", action="store_true")
        return p

    def check(p: argparse.ArgumentParser, args: argparse.Namespace) -> None:
        calls.append("check")
        if args.name is None and not args.list:
            p.error("the following arguments are required: name")

    def body(args: argparse.Namespace) -> int:
        calls.append("body")
        return 7

    for argv in ([], ["--debug"]):
        with pytest.raises(SystemExit) as exc:
            cliutil.command_main("msf-x", parser(), body, argv, check=check)
        assert exc.value.code == 2
        assert capsys.readouterr().err == (
            "msf-x: error: the following arguments are required: name\n"
        )
    assert calls == ["check", "check"]
    assert cliutil.command_main("msf-x", parser(), body, ["--list"], check=check) == 7
    assert calls == ["check", "check", "check", "body"]


def test_a_huge_message_is_cut_to_a_readable_line() -> None:
    """A lights file holding one 3 MB token printed a 3 MB error line."""
    from msfnet.common.errors import MAX_LINE, one_line

    line = one_line("x: " + "A" * 3_000_000 + " is not a number")
    assert len(line) < MAX_LINE + 60 and line.endswith("is not a number")
    assert "characters ..." in line
    assert one_line("short\nline") == "short line"
