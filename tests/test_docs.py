"""The maintainer docs match the tree: docs/design.md names every module of every part, the
README's layout table every part, and every relative link in the docs points at a file."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PARTS = ("common", "runtime", "calib", "synth", "model", "export", "bench")
LINK = re.compile(r"\]\(([^)\s]+)\)")


def _section(text: str, part: str) -> str:
    """The '### <part> (...)' section of design.md's module list, up to the next heading."""
    start = text.index(f"### {part} (")
    end = text.find("\n#", start + 1)
    return text[start : end if end >= 0 else len(text)]


def _names_in(package: Path) -> set[str]:
    """`module` for each module and `sub/` for each subpackage, recursively, as design.md
    writes them."""
    names = set()
    for path in package.rglob("*.py"):
        if path.name != "__init__.py":
            names.add(f"`{path.stem}`")
    for init in package.rglob("__init__.py"):
        if init.parent != package:
            names.add(f"`{init.parent.name}/`")
    return names


@pytest.mark.parametrize("part", PARTS)
def test_design_doc_names_every_module(part: str) -> None:
    section = _section((REPO / "docs" / "design.md").read_text(encoding="utf-8"), part)
    missing = sorted(
        n for n in _names_in(REPO / part / "src" / "msfnet" / part) if n not in section
    )
    assert not missing, f"docs/design.md, section {part}: add a line for {', '.join(missing)}"


def test_readme_layout_lists_every_part() -> None:
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    layout = readme[readme.index("## Layout") :]
    assert [p for p in PARTS if f"| `{p}/` |" not in layout] == []


def test_relative_links_resolve() -> None:
    broken = []
    for doc in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
        for target in LINK.findall(doc.read_text(encoding="utf-8")):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue  # a web address or an anchor on the same page
            if not (doc.parent / target.split("#")[0]).exists():
                broken.append(f"{doc.relative_to(REPO)}: {target}")
    assert broken == []


def test_design_doc_names_every_command() -> None:
    tomllib = pytest.importorskip("tomllib", reason="Python >= 3.11 reads pyproject.toml")
    with open(REPO / "pyproject.toml", "rb") as f:
        commands = tomllib.load(f)["project"]["scripts"]
    design = (REPO / "docs" / "design.md").read_text(encoding="utf-8")
    assert [c for c in commands if c not in design] == []
