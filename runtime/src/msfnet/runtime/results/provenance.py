"""Where a result came from: the input, the model file and its checksum, the engine and
precision, the date, the msfnet version and the command line. Every report carries it
(profile.json and report.html for msf-run, results.json and results.md for msf-eval), so a
picture or a table found later can be traced to the run that made it."""

from __future__ import annotations

import hashlib
import shlex
import sys
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from functools import lru_cache
from pathlib import Path

from msfnet.runtime.engines.method import RunMethod

SHA_DIGITS = 12  # enough to tell two model files apart, short enough to read


@lru_cache(maxsize=16)
def _sha256(path: str, size: int, mtime_ns: int) -> str:
    """The file's SHA-256 (hex); size and mtime key the cache, so a batch hashes its model
    once and a file replaced in between is hashed again."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def file_sha256(path: str | Path) -> str | None:
    """SHA-256 of a file (hex), or None when it cannot be read."""
    try:
        st = Path(path).stat()
        return _sha256(str(Path(path).resolve()), st.st_size, st.st_mtime_ns)
    except OSError:
        return None


def command_line(argv: Sequence[str] | None = None) -> str:
    """The command as typed (program name without its folder), quoted for a shell: ``argv``,
    else the msfnet command running (:func:`msfnet.common.cli.current_command`), else
    sys.argv."""
    from msfnet.common.cli import current_command

    args = list(argv if argv is not None else current_command() or sys.argv)
    if not args:
        return "-"
    return shlex.join([Path(args[0]).name, *args[1:]])


@dataclass(frozen=True)
class Provenance:
    """What made a result. ``model`` is None for least squares."""

    input: str
    model: str | None
    model_sha256: str | None  # the first SHA_DIGITS hex digits
    engine: str
    precision: str
    date: str  # ISO 8601, UTC, seconds
    version: str
    command: str

    @classmethod
    def of(
        cls,
        input: str | Path | Sequence[str | Path],
        method: RunMethod | None,
        *,
        argv: Sequence[str] | None = None,
        now: datetime | None = None,
    ) -> Provenance:
        """From the input(s) and what ran (``Model.describe()``: model, engine, precision;
        None: not known)."""
        from msfnet.common.version import installed_version

        inputs = [input] if isinstance(input, (str, Path)) else list(input)
        m = method or RunMethod()
        sha = file_sha256(m.model) if m.model else None
        when = (now or datetime.now(timezone.utc)).astimezone(timezone.utc)
        return cls(
            input=", ".join(str(i) for i in inputs) or "-",
            model=m.model or None,
            model_sha256=sha[:SHA_DIGITS] if sha else None,
            engine=m.engine or "-",
            precision=m.precision or "-",
            date=when.strftime("%Y-%m-%dT%H:%M:%SZ"),
            version=installed_version(),
            command=command_line(argv),
        )

    @classmethod
    def from_dict(cls, data: Mapping[str, object]) -> Provenance:
        """Back from :meth:`as_dict` (profile.json); missing entries read as "-"."""

        def given(key: str) -> str | None:
            value = data.get(key)
            return None if value in (None, "") else str(value)

        def text(key: str) -> str:
            return given(key) or "-"

        return cls(
            input=text("input"),
            model=given("model"),
            model_sha256=given("model_sha256"),
            engine=text("engine"),
            precision=text("precision"),
            date=text("date"),
            version=text("version"),
            command=text("command"),
        )

    def as_dict(self) -> dict[str, str | None]:
        return asdict(self)

    def model_text(self) -> str:
        if self.model is None:
            return "none (least squares)"
        sha = f" (sha256 {self.model_sha256})" if self.model_sha256 else ""
        return f"{Path(self.model).name}{sha}"

    def facts(self) -> dict[str, str]:
        """Label -> text, in reading order, for a report's header."""
        return {
            "input": self.input,
            "model": self.model_text(),
            "engine": f"{self.engine} {self.precision}",
            "date": self.date,
            "msfnet": self.version,
            "command": self.command,
        }

    def markdown(self) -> str:
        """A bullet list for a Markdown report (results.md)."""
        return "\n".join(f"- {k}: `{v}`" for k, v in self.facts().items())


__all__ = ["SHA_DIGITS", "Provenance", "command_line", "file_sha256"]
