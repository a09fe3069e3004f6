"""The floor plan as a contract: one facade, parts that depend one way, no import cycle, and a
public surface (the Python API's names and every command's flags) that changes only on purpose.

When a change of the surface is intended, regenerate the file and commit it with the change:
``MSFNET_UPDATE_SURFACE=1 python -m pytest -q tests/test_layout.py``.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import os
import shutil
import subprocess
import sys

import pytest
from _layout import PARTS, REPO, find_cycle, import_graph, part_of

SURFACE_FILE = REPO / "tests" / "api_surface.txt"

# Which parts each part may import (lower layers only): common at the bottom, bench on top.
ALLOWED = {
    "common": set(),
    "runtime": {"common"},
    "synth": {"common", "runtime"},
    "calib": {"common", "runtime", "synth"},  # synth only for the simulated rig, lazily
    "model": {"common", "runtime", "synth"},
    "export": {"common", "runtime", "synth", "model"},
    "bench": {"common", "runtime", "synth", "model", "export"},
}
# Inside runtime, each subpackage imports only those of a lower rank (the data flows upward:
# a stack is read, inferred on by engines, measured, written; the API, batches and CLIs on top).
RUNTIME_RANK = {
    "contract": 0,
    "instrument": 0,  # the stage timer and memory readings every stage measures with
    "stack": 1,
    "engines": 1,
    "evaluate": 2,
    "demo": 2,
    "infer": 3,
    "results": 4,
    "options": 5,
    "sources": 5,  # stack sources and decode-ahead, for the API's stream and the batch runner
    "stream": 5,  # what Model.stream returns: its results, and the stacks it did not run
    "api": 6,
    "inspection": 7,  # defects from maps, the station (on the API) and its watch loop
    "batch": 7,
    "cli": 8,
}


def test_the_facade_is_one_file_in_every_source_root() -> None:
    facades = {p: (REPO / p / "src" / "msfnet" / "__init__.py") for p in PARTS}
    reference = facades["runtime"].read_bytes()
    differ = [p for p, f in facades.items() if not f.is_file() or f.read_bytes() != reference]
    assert not differ, f"msfnet/__init__.py differs from runtime's in {differ}"
    typed = [p for p in PARTS if not (REPO / p / "src" / "msfnet" / "py.typed").is_file()]
    assert not typed, f"py.typed missing in {typed}"


def test_the_import_graph_has_no_cycle() -> None:
    cycle = find_cycle(import_graph())
    assert cycle is None, " -> ".join(cycle or [])


def test_parts_import_only_lower_parts() -> None:
    bad = []
    for edges in import_graph().values():
        for e in edges:
            src, dst = part_of(e.source), part_of(e.target)
            if src and dst and src != dst and dst not in ALLOWED[src]:
                bad.append(f"{e.source}:{e.line} imports {e.target}")
            if src and dst is None:  # the facade is for users, not for the parts
                bad.append(f"{e.source}:{e.line} imports the facade {e.target}")
    assert not bad, "\n".join(bad)


def test_runtime_subpackages_import_only_lower_ranks() -> None:
    def sub(module: str) -> str:
        return module.split(".")[2]

    bad = []
    for edges in import_graph().values():
        for e in edges:
            if part_of(e.source) == part_of(e.target) == "runtime" and e.source.count(".") > 1:
                if e.target.count(".") < 2:
                    continue  # msfnet.runtime itself (a docstring-only package)
                a, b = sub(e.source), sub(e.target)
                unknown = {a, b} - set(RUNTIME_RANK)
                assert not unknown, f"new runtime subpackage {unknown}: give it a rank here"
                if a != b and RUNTIME_RANK[b] > RUNTIME_RANK[a]:
                    bad.append(f"{e.source}:{e.line} ({a}) imports {e.target} ({b})")
    assert not bad, "\n".join(bad)


# ---------------------------------------------------------------- the public surface


def _commands() -> dict[str, str]:
    tomllib = pytest.importorskip("tomllib", reason="Python >= 3.11 reads pyproject.toml")
    with open(REPO / "pyproject.toml", "rb") as f:
        return dict(tomllib.load(f)["project"]["scripts"])


def _flags(parser: argparse.ArgumentParser, prefix: str) -> list[str]:
    lines = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in sorted(action.choices.items()):
                lines += _flags(sub, f"{prefix} {name}")
        elif action.option_strings:
            lines.append(f"{prefix} {' '.join(sorted(action.option_strings))}")
        else:
            lines.append(f"{prefix} <{action.dest}>")
    return lines


def _fields(cls: type) -> str:
    return ", ".join(f.name for f in dataclasses.fields(cls))


def surface() -> str:
    """The names users build on, one per line."""
    import msfnet
    from msfnet.runtime.api import Model, Result
    from msfnet.runtime.options import ModelOptions
    from msfnet.runtime.stack import LoadOptions

    lines = [f"msfnet: {', '.join(sorted(msfnet.__all__))}"]
    public = sorted(n for n in dir(Model) if not n.startswith("_"))
    lines.append(f"Model: {', '.join(public)}")
    fields = {f.name for f in dataclasses.fields(Result)}
    methods = sorted(n for n in vars(Result) if not n.startswith("_") and n not in fields)
    lines.append(f"Result: {_fields(Result)}; {', '.join(methods)}")
    lines.append(f"ModelOptions: {_fields(ModelOptions)}")
    lines.append(f"LoadOptions: {_fields(LoadOptions)}")
    for command, target in sorted(_commands().items()):
        module = importlib.import_module(target.split(":")[0])
        lines += _flags(module.build_parser(), command)
    return "\n".join(lines) + "\n"


def test_the_public_surface_changes_only_on_purpose() -> None:
    pytest.importorskip("torch", reason="the export and train commands' parsers need torch")
    now = surface()
    if os.environ.get("MSFNET_UPDATE_SURFACE"):
        SURFACE_FILE.write_text(now)
    old = SURFACE_FILE.read_text() if SURFACE_FILE.is_file() else ""
    assert now == old, (
        "the public API or a command's flags changed; if intended, regenerate "
        f"{SURFACE_FILE.name} (see this module's docstring) and commit it"
    )


@pytest.mark.slow
def test_editors_resolve_every_msfnet_import() -> None:
    """basedpyright (the engine of VS Code's analyser), run over the seven parts as an editor
    would see the editable install: no unresolved msfnet import, no missing stub, no cycle."""
    exe = shutil.which("basedpyright")
    if exe is None:
        pytest.skip("basedpyright not installed (pip install -e '.[dev]')")
    import json

    out = subprocess.run(
        [exe, *PARTS, "--outputjson"], cwd=REPO, capture_output=True, text=True, timeout=600
    )
    found = json.loads(out.stdout)["generalDiagnostics"]
    rules = {"reportMissingImports", "reportMissingTypeStubs", "reportImportCycles",
             "reportMissingModuleSource"}  # fmt: skip
    bad = [
        f"{d['file']}: {d['message'].splitlines()[0]}"
        for d in found
        if d.get("rule") in rules
        and ("msfnet" in d["message"] or d["rule"] == "reportImportCycles")
    ]
    assert not bad, "\n".join(bad[:20])


if __name__ == "__main__":
    sys.stdout.write(surface())


MAX_FUNCTION_LINES = 100


def test_no_function_is_longer_than_a_screenful_or_two() -> None:
    """A function over 100 lines does several jobs: each step gets its own name."""
    import ast

    from _layout import source_files

    long = []
    for module, path in source_files().items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                lines = (node.end_lineno or node.lineno) - node.lineno + 1
                if lines > MAX_FUNCTION_LINES:
                    long.append(f"{module}.{node.name}: {lines} lines")
    assert not long, long
