"""The import graph of msfnet's source, read with ast (nothing imported): modules, parts and
the edges between them, for the layout contract tests and the code map."""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PARTS = ("common", "runtime", "calib", "synth", "model", "export", "bench")


def source_files() -> dict[str, Path]:
    """Dotted module name -> file, for every module of every part (the facade once)."""
    out: dict[str, Path] = {"msfnet": REPO / "runtime" / "src" / "msfnet" / "__init__.py"}
    for part in PARTS:
        root = REPO / part / "src"
        for path in sorted((root / "msfnet" / part).rglob("*.py")):
            rel = path.relative_to(root).with_suffix("")
            parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
            out[".".join(parts)] = path
    return out


@dataclass(frozen=True)
class Edge:
    source: str
    target: str
    line: int


def imports_of(module: str, path: Path, known: set[str]) -> list[Edge]:
    """Every msfnet module ``module`` imports, at any depth of its code (lazy and
    TYPE_CHECKING imports included: a cycle through them is still a cycle to a reader)."""
    edges = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for a in node.names:
                sub = f"{node.module}.{a.name}"
                targets.append(sub if sub in known else node.module)
        for t in targets:
            if t == "msfnet" or t.startswith("msfnet."):
                while t not in known and "." in t:
                    t = t.rsplit(".", 1)[0]
                if t in known and t != module:
                    edges.append(Edge(module, t, node.lineno))
    return edges


def import_graph() -> dict[str, list[Edge]]:
    files = source_files()
    known = set(files)
    return {m: imports_of(m, p, known) for m, p in files.items()}


def part_of(module: str) -> str | None:
    bits = module.split(".")
    return bits[1] if len(bits) > 1 and bits[1] in PARTS else None


def find_cycle(graph: dict[str, list[Edge]]) -> list[str] | None:
    """One cycle of the module graph, or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        stack.append(m)
        for e in graph.get(m, []):
            if state.get(e.target) == 1:
                return [*stack[stack.index(e.target) :], e.target]
            if e.target not in state:
                found = visit(e.target)
                if found:
                    return found
        stack.pop()
        state[m] = 2
        return None

    for m in graph:
        if m not in state:
            found = visit(m)
            if found:
                return found
    return None
