"""What every msfnet command shares: common flags, validated option types, one-line errors.

:func:`run_command` is the only place where exceptions become exit codes: InputError and
every other failure the user can act on (output, disk, memory, the engine on their model) ->
one line, exit 2; Ctrl-C -> one line, exit 130; SIGTERM -> exit 143; anything unexpected -> one
line and exit 1 (msf-inspect: 3). Tracebacks reach the user only with ``--debug``; so do
library warnings (numpy's RuntimeWarnings and the like are noise on a user's terminal and would
break the one-line rule).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import importlib.util
import math
import os
import re
import sys
import traceback
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextvars import ContextVar
from pathlib import Path
from typing import Any, NoReturn, TypeVar

from msfnet.common.errors import InputError, MsfError, first_line, one_line
from msfnet.common.files import forget_written, writing_as, written_outputs
from msfnet.common.signals import (
    Terminated,
    install_signal_handlers,
    interrupt_once,
    restore_signal_handlers,
)
from msfnet.common.vocabulary import Flag, speaking_as


def _number(text: str, kind: type) -> float:
    try:
        value = kind(text)
    except (ValueError, OverflowError) as exc:
        what = "an integer" if kind is int else "a number"
        raise argparse.ArgumentTypeError(f"{text!r} is not {what}") from exc
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


def path_arg(text: str) -> Path:
    """A path argument; "" is refused (``Path("")`` is the current folder, which nobody
    means by an empty argument, e.g. an unset shell variable)."""
    if not text:
        raise argparse.ArgumentTypeError("an empty path")
    return Path(text)


def path_text(text: str) -> str:
    """:func:`path_arg` for options kept as text (a config's fields): "" refused."""
    path_arg(text)
    return text


N = TypeVar("N", int, float)


def _bounded(kind: type[N], ok: Callable[[N], bool], must: str, name: str) -> Callable[[str], N]:
    """A parser of finite ``kind`` values for which ``ok`` holds ("must <must>, got ...")."""

    def parse(text: str) -> N:
        value = kind(_number(text, kind))
        if not ok(value):
            raise argparse.ArgumentTypeError(f"must {must}, got {text!r}")
        return value

    parse.__name__ = name
    return parse


positive_int = _bounded(int, lambda v: v >= 1, "be a positive integer", "positive_int")
nonnegative_int = _bounded(int, lambda v: v >= 0, "be 0 or more", "nonnegative_int")
positive_float = _bounded(float, lambda v: v > 0, "be a positive number", "positive_float")
nonnegative_float = _bounded(float, lambda v: v >= 0, "be 0 or more", "nonnegative_float")
finite_float = _bounded(float, lambda v: True, "be finite", "finite_float")


def float_range(lo: float, hi: float) -> Callable[[str], float]:
    return _bounded(
        float, lambda v: lo <= v <= hi, f"lie in {lo:g}..{hi:g}", f"number {lo:g}..{hi:g}"
    )


def int_range(lo: int, hi: int) -> Callable[[str], int]:
    return _bounded(int, lambda v: lo <= v <= hi, f"lie in {lo}..{hi}", f"integer {lo}..{hi}")


def thread_count(text: str) -> int:
    """A --threads value: an integer in 1..MAX_THREADS (common.cpu), the same in every
    command."""
    from msfnet.common.cpu import MAX_THREADS

    return int_range(1, MAX_THREADS)(text)


class Parser(argparse.ArgumentParser):
    """argparse with one-line errors in the ``<prog>: error: <problem>`` form and exit code 2
    (argparse's own usage dump is noise when one option is wrong). The option leads the
    problem as a file does: ``msf-x: error: --tile: must be a positive integer, got '0'``
    (argparse's ``argument `` prefix dropped)."""

    def error(self, message: str) -> NoReturn:
        message = re.sub(r"^argument ([^:]+): ", r"\1: ", message)
        self.exit(2, f"{self.prog}: error: {message}\n")


def make_parser(
    prog: str,
    description: str,
    examples: Sequence[str] = (),
    *,
    common: bool = True,
    verbose: bool = False,
) -> Parser:
    """A parser with the flags every command has: --version, -q, --debug (and -v where the
    command has more to say: ``verbose=True``).

    ``common=False``: only --version here. A command with sub-commands keeps ``common=True``
    and gives each sub-command the flags again with ``add_common_flags(sp, sub_command=True)``,
    so they may come before or after the sub-command's name.
    """
    from msfnet.common.version import installed_version

    epilog = None
    if examples:
        epilog = "examples:\n" + "\n".join(f"  {e}" for e in examples)
    p = Parser(
        prog=prog,
        description=description,
        epilog=epilog,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--version", action="version", version=f"%(prog)s {installed_version()}")
    if common:
        add_common_flags(p, verbose=verbose)
    return p


# ---------------------------------------------------------------- flags from option dataclasses

T = TypeVar("T")


def _flags_of(cls: type) -> dict[str, Flag]:
    return {f.name: f.metadata["flag"] for f in dataclasses.fields(cls) if "flag" in f.metadata}


def flag_names(cls: type, category: str) -> tuple[str, ...]:
    """The fields of ``cls`` whose flag is in ``category``, in declaration order."""
    return tuple(n for n, spec in _flags_of(cls).items() if spec.category == category)


def add_flags(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup,
    cls: type,
    *,
    only: Sequence[str] | None = None,
    skip: Sequence[str] = (),
    help_override: Mapping[str, str] | None = None,
) -> None:
    """Add one flag per field of the dataclass ``cls`` that declares one (:func:`flag`), all
    of them or ``only`` those, except ``skip``. Defaults come from the dataclass, so a command
    and the Python API cannot drift apart."""
    defaults = {f.name: f.default for f in dataclasses.fields(cls)}
    flags = _flags_of(cls)
    unknown = [n for n in (only or ()) if n not in flags]
    if unknown:  # a list that drifted from its dataclass: a bug, said at once
        raise TypeError(f"{cls.__name__} declares no flag for {unknown}")
    for name, spec in flags.items():
        if name in skip or (only is not None and name not in only):
            continue
        kwargs: dict[str, Any] = {"dest": name, "help": (help_override or {}).get(name, spec.help)}
        if spec.action:
            kwargs["action"] = spec.action
        else:
            default = defaults[name]
            kwargs["default"] = None if default is dataclasses.MISSING else default
            for key in ("type", "choices", "metavar", "nargs", "const"):
                if getattr(spec, key) is not None:
                    kwargs[key] = getattr(spec, key)
            if spec.required:
                kwargs["required"] = True
        parser.add_argument(spec.flag_name(name), *spec.aliases, **kwargs)


def options_from_args(
    cls: type[T], args: argparse.Namespace, *, overrides: Mapping[str, Any] | None = None
) -> T:
    """The ``cls`` instance the parsed flags describe (fields without a flag keep their
    defaults; ``overrides`` win). Flags a command did not add keep the defaults too."""
    values = {n: getattr(args, n) for n in _flags_of(cls) if hasattr(args, n)}
    values = {n: tuple(v) if isinstance(v, list) else v for n, v in values.items()}
    return cls(**{**values, **(overrides or {})})


def add_common_flags(
    p: argparse.ArgumentParser, *, verbose: bool = False, sub_command: bool = False
) -> None:
    """-q, --debug (and -v). ``sub_command=True`` for a sub-command's parser when the main
    parser has them too: there they set nothing unless given, because argparse copies a
    sub-command's defaults over what the main parser read (``msf-calib -q directions`` would
    otherwise lose its -q)."""
    unset: dict[str, Any] = {"default": argparse.SUPPRESS} if sub_command else {}
    p.add_argument("-q", "--quiet", action="store_true", help="print errors only", **unset)
    if verbose:  # only where it changes something: a flag that does nothing would mislead
        p.add_argument("-v", "--verbose", action="store_true", help="print more detail", **unset)
    p.add_argument(
        "--debug",
        action="store_true",
        help="show Python tracebacks instead of one-line errors",
        **unset,
    )


# Optional packages (pyproject.toml's extras) by import name -> the extras that bring them,
# the one to name when the command has no extra of its own first.
_EXTRAS = {
    "torch": ("export,train", "export", "train", "bench"),
    "onnx": ("export", "bench"),
    "onnxslim": ("export",),
    "matplotlib": ("pictures", "train", "bench"),
    "openvino": ("openvino",),
    "depthai": ("camera",),
    "serial": ("camera",),
    "ray": ("ray",),
}


@dataclasses.dataclass(frozen=True)
class Command:
    """What :func:`run_command` knows of a command beyond its name: each command's main
    passes its own (nothing here lists commands)."""

    prog: str  # "msf-run"
    extra: str | None = None  # the pip extra it is installed with, named by its install hints
    failure_exit: int = 1  # a failure of the tool itself (msf-inspect: 3, its 1 is a verdict)
    memory_advice: str = "close other programs or give smaller inputs"  # its own options only


def _as_command(command: str | Command) -> Command:
    return command if isinstance(command, Command) else Command(command)


def install_hint(module: str, own: str | None = None) -> str:
    """How to install the optional package imported as ``module`` (a top-level name): the
    extra ``own`` (the command's) where that extra brings the package."""
    extras = _EXTRAS.get(module)
    if extras is None:
        return f"pip install {module}"
    extra = own if own in extras else extras[0]
    how = f"pip install 'msfnet[{extra}]' (in a checkout: pip install -e '.[{extra}]')"
    if module == "torch":  # PyPI's default torch for Linux is the multi-GB CUDA build
        how = (
            "pip install torch --index-url https://download.pytorch.org/whl/cpu (the CPU "
            "build), then " + how
        )
    return how


def _missing_optional(exc: BaseException) -> str | None:
    """The optional package whose absence raised ``exc``, or None: a module missing inside an
    installed package (a broken install) or any other missing module stays an internal error."""
    if not isinstance(exc, ModuleNotFoundError) or not exc.name:
        return None
    top = exc.name.partition(".")[0]
    if top not in _EXTRAS:
        return None
    try:
        present = importlib.util.find_spec(top) is not None
    except (ImportError, ValueError):
        present = False
    return None if present else top


def _left_behind() -> str:
    done = written_outputs()
    if not done:
        return "nothing was written"
    return (
        f"{len(done)} output(s) were complete and are kept (last: {done[-1]}); nothing "
        "else was written"
    )


def command_main(
    command: str | Command,
    parser: argparse.ArgumentParser,
    body: Callable[[argparse.Namespace], int],
    argv: Sequence[str] | None = None,
    *,
    check: Callable[[argparse.ArgumentParser, argparse.Namespace], None] | None = None,
) -> int:
    """A command's whole ``main``: parse ``argv``, then run ``body(args)`` through
    :func:`run_command` (one-line errors and exit codes), with every output manifest naming
    the command as its writer.

    ``check(parser, args)``: rules between flags that argparse cannot state (msf-export's
    checkpoint is required unless --list-variants), run right after parsing; it reports with
    ``parser.error``, so a broken rule reads and exits as any other usage error, before any
    body code runs."""
    cmd = _as_command(command)
    prog = cmd.prog
    with speaking_as(prog):  # also the options' own checks, made while parsing
        args = parser.parse_args(argv)
        if check is not None:
            check(parser, args)
    typed = (prog, *(sys.argv[1:] if argv is None else argv))

    def run() -> int:
        with writing_as(prog), speaking_as(prog):
            return body(args)

    token = _command.set(typed)
    debug = bool(getattr(args, "debug", False))
    try:
        return run_command(cmd, run, debug=debug)
    except Exception as exc:
        if cmd.failure_exit == 1:
            raise  # --debug: Python prints the traceback and exits 1
        traceback.print_exc()  # the traceback --debug asks for, but never exit 1 (a verdict)
        return 2 if isinstance(exc, _ACTIONABLE) else cmd.failure_exit
    finally:
        _command.reset(token)


# the running command's line, for reports that say how they were made (also when main(argv)
# is called in-process, where sys.argv is the host's)
_command: ContextVar[tuple[str, ...] | None] = ContextVar("msfnet_command", default=None)


def current_command() -> tuple[str, ...] | None:
    """(prog, *argv) of the command running in this context, or None outside one."""
    return _command.get()


def run_command(command: str | Command, body: Callable[[], int], debug: bool = False) -> int:
    """Run a command's body and turn every failure into one line and an exit code."""
    previous = install_signal_handlers()
    forget_written()
    try:
        with interrupt_once(), _printable_streams():
            # (a second Ctrl-C never interrupts the cleanup or the line)
            return _run_body(_as_command(command), body, debug)
    finally:
        # in-process callers (tests, the Python API) get their own handlers back
        restore_signal_handlers(previous)


@contextlib.contextmanager
def _printable_streams() -> Iterator[None]:
    """Any name prints, whatever the terminal's encoding: under LANG=C or
    PYTHONIOENCODING=ascii a path with a non-ASCII (or undecodable) byte ended in a
    UnicodeEncodeError, once after the output was written. Such characters print escaped."""
    changed = []
    for stream in (sys.stdout, sys.stderr):
        reconfigure = getattr(stream, "reconfigure", None)
        errors = getattr(stream, "errors", None)
        # strict only: a surrogateescape stream (LANG=C) prints an undecodable name back as
        # its own bytes, which a script reading the output path needs
        if reconfigure is not None and errors == "strict":
            with contextlib.suppress(ValueError, OSError, TypeError):
                reconfigure(errors="backslashreplace")
                changed.append((reconfigure, errors))
    try:
        yield
    finally:
        for reconfigure, errors in changed:
            with contextlib.suppress(ValueError, OSError, TypeError):
                reconfigure(errors=errors)


# The one exit-code rule: 0 done (msf-inspect: pass), 2 anything the user can change (bad
# input, an unwritable output, a full disk, out of memory, an engine that fails on the model
# or tile given), and the command's failure code only for a failure of the tool itself (an
# internal error). That code is 1, except where 1 is a verdict (msf-inspect: defects found,
# Command.failure_exit), so a PLC never reads a crash as a verdict, nor a full disk as a crash.
# what --debug re-raises that still exits 2 by that rule (a broken pipe is no failure)
_ACTIONABLE = (InputError, MsfError, OSError, MemoryError, RecursionError)


def _run_body(command: Command, body: Callable[[], int], debug: bool) -> int:
    def fail(message: str, code: int) -> int:
        print(f"{command.prog}: {one_line(message)}", file=sys.stderr)
        return code

    try:
        with warnings.catch_warnings():
            if not debug:
                warnings.simplefilter("ignore")
            return body()
    except KeyboardInterrupt:
        return fail(f"interrupted; {_left_behind()}", 130)
    except Terminated as exc:
        return fail(f"terminated (signal {exc.signum}); {_left_behind()}", 128 + exc.signum)
    except BrokenPipeError as exc:
        if exc.filename is not None:  # a broken pipe as an output file: an ordinary error
            return fail(f"error: {exc.filename}: {exc.strerror}", 2)
        # stdout's reader went away (msf-run --json | head): exit quietly like other tools,
        # and keep Python from complaining again when it flushes stdout at exit
        with contextlib.suppress(OSError):
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        return 141  # 128 + SIGPIPE
    except Exception as exc:
        if debug:
            raise
        return fail(*_failure(exc, command))


def _failure(exc: Exception, command: Command) -> tuple[str, int]:
    """The one line and the exit code of a failure :func:`run_command` caught."""
    if isinstance(exc, InputError):
        return f"error: {exc}", 2
    if isinstance(exc, MemoryError):
        return f"error: out of memory; {command.memory_advice}", 2
    if isinstance(exc, OSError):  # disk full, permission denied, ... on an output
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        if exc.strerror:
            return f"error: {where}{exc.strerror}", 2
        # no errno: e.g. numpy's short write "4752 requested and 1968 written"
        return f"error: {where}input/output failed ({first_line(exc)}; disk full?)", 2
    if isinstance(exc, MsfError):
        return f"error: {first_line(exc, 500)}", 2
    if isinstance(exc, RecursionError):  # e.g. absurdly nested JSON given as input
        return f"error: input too deeply nested ({first_line(exc)})", 2
    missing = _missing_optional(exc)
    if missing:  # an optional part not installed, not a bug of ours
        hint = install_hint(missing, command.extra)
        return f"error: needs the Python package {missing!r}, which is not installed: {hint}", 2
    return (
        f"internal error: {type(exc).__name__}: {first_line(exc)} (run with --debug for the "
        "traceback; please report it)",
        command.failure_exit,
    )


__all__ = [
    "Command",
    "Flag",
    "Parser",
    "add_common_flags",
    "add_flags",
    "command_main",
    "current_command",
    "finite_float",
    "flag_names",
    "float_range",
    "install_hint",
    "int_range",
    "make_parser",
    "nonnegative_float",
    "nonnegative_int",
    "options_from_args",
    "positive_float",
    "positive_int",
    "run_command",
    "thread_count",
]
