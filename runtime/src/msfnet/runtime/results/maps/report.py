"""One self-contained report.html per run: every picture embedded as a base64 PNG, no external
files, scripts or fonts, so the page can be mailed or archived on its own."""

from __future__ import annotations

import base64
import html
from collections.abc import Mapping, Sequence
from pathlib import Path

from msfnet.common.files import write_atomic

STYLE = """
body { font-family: system-ui, sans-serif; margin: 1.5em; color: #222; }
h1 { font-size: 1.4em; margin-bottom: 0.2em; }
.meta { color: #555; margin-bottom: 1em; }
.grid { display: flex; flex-wrap: wrap; gap: 1em; align-items: flex-start; }
figure { margin: 0; border: 1px solid #ddd; padding: 0.5em; background: #fff; }
figure.wide { flex-basis: 100%; }
figcaption { font-size: 0.9em; color: #444; margin-top: 0.3em; }
figure img { max-width: 100%; height: auto; display: block; }
table { border-collapse: collapse; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; }
th:first-child, td:first-child { text-align: left; }
"""


def img_tag(png: bytes, alt: str) -> str:
    data = base64.b64encode(png).decode("ascii")
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


def latency_rows(
    profile: Mapping[str, object] | None, map_seconds: Mapping[str, float] | None
) -> list[tuple[str, str, str]]:
    """(stage, median, p90) rows: the run's stages (profile.json's ``stages``: name ->
    {median_s, p90_s}) followed by the inspection maps' own timings (single runs)."""
    rows: list[tuple[str, str, str]] = []
    stages = profile.get("stages") if profile else None
    if isinstance(stages, Mapping):
        for name, vals in stages.items():
            if isinstance(vals, Mapping):
                median, p90 = (float(vals.get(k, float("nan"))) for k in ("median_s", "p90_s"))
                rows.append((str(name), f"{median:.3f}", f"{p90:.3f}"))
    for name, sec in (map_seconds or {}).items():
        rows.append((f"maps: {name}", f"{sec:.3f}", "-"))
    return rows


def build_report(
    title: str,
    figures: Sequence[tuple[str, bytes]],
    *,
    meta: Mapping[str, object] | None = None,
    profile: Mapping[str, object] | None = None,
    map_seconds: Mapping[str, float] | None = None,
) -> str:
    """HTML text: a title, a line of facts (``meta``), the pictures side by side (``figures``:
    caption and PNG bytes; a caption starting with "wide:" spans the full width) and a latency
    table (run stages from ``profile``, then ``map_seconds``)."""
    parts = [
        f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>{html.escape(title)}</title><style>{STYLE}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
    ]
    if meta:
        facts = " · ".join(f"{html.escape(str(k))}: {html.escape(str(v))}" for k, v in meta.items())
        parts.append(f'<div class="meta">{facts}</div>')
    parts.append('<div class="grid">')
    for caption, png in figures:
        wide = caption.startswith("wide:")
        text = caption.removeprefix("wide:").strip()
        cls = ' class="wide"' if wide else ""
        parts.append(
            f"<figure{cls}>{img_tag(png, text)}<figcaption>{html.escape(text)}"
            "</figcaption></figure>"
        )
    rows = latency_rows(profile, map_seconds)
    if rows:
        body = "".join(
            f"<tr><td>{html.escape(a)}</td><td>{b}</td><td>{c}</td></tr>" for a, b, c in rows
        )
        parts.append(
            "<figure><table><tr><th>stage</th><th>median s</th><th>p90 s</th></tr>"
            f"{body}</table><figcaption>latency profile</figcaption></figure>"
        )
    parts.append("</div></body></html>\n")
    return "\n".join(parts)


def write_report(path: str | Path, text: str) -> Path:
    """Write the report atomically (a temporary sibling, then a rename)."""
    path = Path(path)
    write_atomic(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))
    return path


__all__ = ["build_report", "img_tag", "latency_rows", "write_report"]
