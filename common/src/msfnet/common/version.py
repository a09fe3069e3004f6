"""msfnet's version, declared once, here: pyproject.toml reads it (hatch's version source), an
install records it in the package metadata, and every command, the provenance of every output
and the ``msfnet.__version__`` facade read it from this constant. A constant, not the
metadata: importlib.metadata costs ~55 ms of every fresh process (its email parser), which an
inspection station that runs a part a process pays on each part."""

from __future__ import annotations

__version__ = "0.2.0"


def installed_version() -> str:
    return __version__


__all__ = ["__version__", "installed_version"]
