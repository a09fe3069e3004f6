"""msfnet's version: declared once, in pyproject.toml; an install records it in the package
metadata, which is where every command (and the ``msfnet.__version__`` facade) reads it."""

from __future__ import annotations

from functools import cache


@cache
def installed_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("msfnet")
    except PackageNotFoundError:  # a source tree on sys.path without an install
        return "0+unknown"


__all__ = ["installed_version"]
