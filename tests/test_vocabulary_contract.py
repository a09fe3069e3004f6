"""The vocabulary as a contract: the library never spells a command-line flag itself.

A message below the commands names a setting through ``msfnet.common.vocabulary.opt``, which
writes ``--max-memory`` under a command and ``max_memory_mb`` from Python; only the modules
that build a command's parser, help texts and docstrings spell flags. Advice to run another
command (``msf-export --int8``) or tool (``ray start --head``) is a command line on both
front ends and stays as written.
"""

from __future__ import annotations

import ast
import importlib
import re
from pathlib import Path

import pytest
from _layout import REPO, source_files

FLAG = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*")
OTHER_COMMAND = re.compile(r"(msf-[a-z]+|ray start|pip install)\b[^'\"]*$")
# calls whose text arguments are help or declarations, not messages
DECLARING = {"flag", "Flag", "add_argument", "add_argument_group", "declare", "make_parser"}
# parts whose messages have not moved to the vocabulary yet
NOT_YET: tuple[str, ...] = ()


def _is_command(source: str) -> bool:
    """A module that builds a command's parser, or one of its option groups."""
    return any(s in source for s in ("make_parser(", "ArgumentParser(", "add_argument("))


def _docstrings(tree: ast.AST) -> set[int]:
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                out.add(id(body[0].value))
    return out


def _declaring(tree: ast.AST) -> set[int]:
    """Every node inside a declaring call or a ``help=`` argument."""
    out: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")
            held = (
                [node] if name in DECLARING else [k.value for k in node.keywords if k.arg == "help"]
            )
            for h in held:
                out.update(id(n) for n in ast.walk(h))
    return out


def spelled_flags(path: Path) -> list[str]:
    """``line: text`` for each message literal of a library module that spells a flag."""
    source = path.read_text()
    if _is_command(source):
        return []
    tree = ast.parse(source)
    skip = _docstrings(tree) | _declaring(tree)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in skip:
            if FLAG.fullmatch(node.value.strip()):  # one argv token of a command line built
                continue
            for m in FLAG.finditer(node.value):
                if not OTHER_COMMAND.search(node.value[: m.start()]):
                    found.append(f"{node.lineno}: {node.value.strip()[:90]}")
                    break
    return found


def test_the_library_names_settings_through_the_vocabulary() -> None:
    bad = {
        module: lines
        for module, path in source_files().items()
        if not module.startswith(NOT_YET) and (lines := spelled_flags(path))
    }
    assert not bad, "spell these through msfnet.common.vocabulary.opt:\n" + "\n".join(
        f"{m}:{line}" for m, lines in bad.items() for line in lines
    )


def _opt_keywords(path: Path) -> list[str]:
    """The keywords a module's messages name with opt("keyword", ...)."""
    return [
        node.args[0].value
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, ast.Call)
        and getattr(node.func, "id", "") == "opt"
        and node.args
        and isinstance(node.args[0], ast.Constant)
    ]


def _named_settings() -> dict[str, str]:
    """keyword -> a module whose messages name it."""
    out: dict[str, str] = {}
    for module, path in source_files().items():
        for keyword in _opt_keywords(path):
            out.setdefault(keyword, module)
    return out


def test_every_setting_a_message_names_is_declared_and_a_command_has_its_flag() -> None:
    """A keyword no options type declares would be spelled by rule, maybe as no command
    spells it; and each declared flag is one some command takes (tests/api_surface.txt)."""
    pytest.importorskip("torch", reason="the train command's options import torch")
    from msfnet.common import vocabulary

    for module in source_files():
        if not module.startswith(NOT_YET):
            importlib.import_module(module)
    named = _named_settings()
    undeclared = sorted(f"{k} ({m})" for k, m in named.items() if k not in vocabulary._WORDS)
    assert not undeclared, f"declare these settings: {undeclared}"
    surface = (REPO / "tests" / "api_surface.txt").read_text().split()
    unknown = sorted(
        w.flag for k, w in vocabulary._WORDS.items() if k in named and w.flag not in surface
    )
    assert not unknown, f"no command takes {unknown}"


def _declared_in() -> dict[str, set[str]]:
    """keyword -> the modules whose import declares its spelling (a flag() field of an
    @options_type class, or declare())."""
    out: dict[str, set[str]] = {}
    for module, path in source_files().items():
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            called = isinstance(node, ast.Call) and getattr(node.func, "id", "") == "declare"
            if called and node.args and isinstance(node.args[0], ast.Constant):  # type: ignore[attr-defined]
                out.setdefault(node.args[0].value, set()).add(module)  # type: ignore[attr-defined]
            if isinstance(node, ast.ClassDef) and any(
                getattr(d, "id", "") == "options_type" for d in node.decorator_list
            ):
                for stmt in node.body:
                    value = getattr(stmt, "value", None)
                    if (
                        isinstance(stmt, ast.AnnAssign)
                        and isinstance(value, ast.Call)
                        and getattr(value.func, "id", "") == "flag"
                        and isinstance(stmt.target, ast.Name)
                    ):
                        out.setdefault(stmt.target.id, set()).add(module)
    return out


def test_a_message_sees_the_declaration_of_every_setting_it_names() -> None:
    """Without it a message would be spelled by the rule (``--max-memory-mb``) whenever the
    declaring module happens not to be imported yet (a worker process, a library call). Only
    settings the rule would get wrong count: another spelling, or a switch (``=True``)."""
    pytest.importorskip("torch", reason="the train command's options import torch")
    from _layout import import_graph

    from msfnet.common import vocabulary

    for module in source_files():
        importlib.import_module(module)
    special = {
        k
        for k, w in vocabulary._WORDS.items()
        if w.action is not None or w.flag != "--" + k.replace("_", "-")
    }

    graph = {m: {e.target for e in edges} for m, edges in import_graph().items()}

    def reach(module: str) -> set[str]:
        seen, todo = {module}, [module]
        while todo:
            for t in graph.get(todo.pop(), ()):
                if t not in seen:
                    seen.add(t)
                    todo.append(t)
        return seen

    declared = _declared_in()
    blind = []
    for module, path in source_files().items():
        named = {k for k in _opt_keywords(path) if k in special and k != "overwrite"}
        if named:  # overwrite: declared in the vocabulary itself
            seen = reach(module)
            blind += [f"{module}: {k}" for k in named if not declared.get(k, set()) & seen]
    assert not blind, "\n".join(sorted(set(blind)))
