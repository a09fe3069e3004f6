"""What every msfnet command shares: common flags, validated option types, one-line errors.

:func:`run_command` is the only place where exceptions become exit codes: InputError -> one
line, exit 2; Ctrl-C -> one line, exit 130; SIGTERM -> exit 143; anything unexpected -> one line
and exit 1. Tracebacks reach the user only with ``--debug``.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable, Sequence

from .errors import InputError, MsfError, first_line
from .files import Terminated, install_signal_handlers


def _number(text: str, kind: type) -> float:
    try:
        value = kind(text)
    except ValueError as exc:
        what = "an integer" if kind is int else "a number"
        raise argparse.ArgumentTypeError(f"{text!r} is not {what}") from exc
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


def positive_int(text: str) -> int:
    value = int(_number(text, int))
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text!r}")
    return value


def nonnegative_int(text: str) -> int:
    value = int(_number(text, int))
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, got {text!r}")
    return value


def positive_float(text: str) -> float:
    value = _number(text, float)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text!r}")
    return value


def finite_float(text: str) -> float:
    return _number(text, float)


def int_range(lo: int, hi: int) -> Callable[[str], int]:
    def parse(text: str) -> int:
        value = int(_number(text, int))
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"must lie in {lo}..{hi}, got {text!r}")
        return value

    parse.__name__ = f"integer {lo}..{hi}"
    return parse


class Parser(argparse.ArgumentParser):
    """argparse with one-line errors in the ``<prog>: error: <problem>`` form and exit code 2
    (argparse's own usage dump is noise when one option is wrong)."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message}\n")


def make_parser(prog: str, description: str, examples: Sequence[str] = ()) -> Parser:
    """A parser with the flags every command has: --version, -q/-v, --debug."""
    from msfnet import __version__

    epilog = None
    if examples:
        epilog = "examples:\n" + "\n".join(f"  {e}" for e in examples)
    p = Parser(prog=prog, description=description, epilog=epilog,
               formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    p.add_argument("-q", "--quiet", action="store_true", help="print errors only")
    p.add_argument("-v", "--verbose", action="store_true", help="print more detail")
    p.add_argument("--debug", action="store_true",
                   help="show Python tracebacks instead of one-line errors")
    return p


def run_command(prog: str, body: Callable[[], int], debug: bool = False) -> int:
    """Run a command's body and turn every failure into one line and an exit code."""
    install_signal_handlers()
    try:
        return body()
    except InputError as exc:
        if debug:
            raise
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: interrupted; nothing was written", file=sys.stderr)
        return 130
    except Terminated as exc:
        print(f"{prog}: terminated (signal {exc.signum}); nothing was written", file=sys.stderr)
        return 128 + exc.signum
    except MemoryError:
        if debug:
            raise
        print(f"{prog}: error: out of memory; lower --max-memory (or --tile)", file=sys.stderr)
        return 2
    except OSError as exc:  # disk full, permission denied, ... on an output
        if debug:
            raise
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        print(f"{prog}: error: {where}{exc.strerror or first_line(exc)}", file=sys.stderr)
        return 2
    except MsfError as exc:
        if debug:
            raise
        print(f"{prog}: error: {first_line(exc, 500)}", file=sys.stderr)
        return 1
    except Exception as exc:
        if debug:
            raise
        print(f"{prog}: internal error: {type(exc).__name__}: {first_line(exc)} (run with "
              "--debug for the traceback; please report it)", file=sys.stderr)
        return 1


__all__ = ["Parser", "finite_float", "int_range", "make_parser", "nonnegative_int",
           "positive_float", "positive_int", "run_command"]
