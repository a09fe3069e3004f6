"""Batches: many stacks through one loaded model, the next stack decoded while one runs.

A single stack cannot overlap its own decoding with inference (the normalisation needs every
image of a pixel first), but in a batch the next stack's images can be decoded in a background
thread while the current stack is inferred. The summary measures how much that hid:
``decode - wait`` seconds of decoding ran under inference, and the wall time is compared with
the sum of the stages run one after the other.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from msfnet.common.errors import InputError
from msfnet.common.files import MANIFEST, STAGING_TAG, json_text, write_text
from msfnet.common.vocabulary import opt
from msfnet.runtime.engines.method import RunMethod
from msfnet.runtime.evaluate.metrics import NormalMetrics
from msfnet.runtime.results.result import SaveOptions
from msfnet.runtime.sources import BatchItem, StackSource, decode_ahead, expand_stacks
from msfnet.runtime.stack import LoadOptions

if TYPE_CHECKING:
    from msfnet.runtime.api import Model, Result

SUMMARY_FILES = ("summary.json", "summary.md")


@dataclass
class StackRow:
    """One stack's line in the summary (seconds are wall time of that stage)."""

    name: str
    source: str
    output: str | None = None
    lights: int = 0
    width: int = 0
    height: int = 0
    mask_px: int = 0
    decode_s: float = 0.0  # decoding + real-camera transforms (background thread / worker)
    wait_s: float = 0.0  # what the runner waited for the decoded stack (decode not hidden)
    compute_s: float = 0.0  # normalise + infer + metrics
    save_s: float = 0.0  # writing the output folder
    metrics: NormalMetrics | None = None  # with ground truth
    worker: str | None = None
    error: str | None = None


@dataclass
class BatchSummary:
    mode: str  # "local" or "ray"
    model: RunMethod | None  # None: no stack has run yet
    rows: list[StackRow] = field(default_factory=list)
    wall_s: float = 0.0
    workers: int = 1
    prefetch: bool = True
    worker_memory_mb: float | None = None  # ray: each worker's share of --max-memory
    # ray: what workers ran other than ``model`` (a worker on another CPU class may pick
    # another engine, precision or the bundled model's int8 twin), each listed once
    other_models: list[RunMethod] = field(default_factory=list)

    def note_model(self, method: RunMethod) -> None:
        """What ran one stack: the first becomes ``model``, another choice is listed too. A
        choice is the engine, precision, device, graph and the model's file name: workers
        installed under other paths, or with another OpenVINO build, chose the same."""
        if self.model is None:
            self.model = method
            return
        seen = [_choice(m) for m in (self.model, *self.other_models)]
        if _choice(method) not in seen:
            self.other_models.append(method)

    @property
    def decode_s(self) -> float:
        return sum(r.decode_s for r in self.rows)

    @property
    def compute_s(self) -> float:
        return sum(r.compute_s for r in self.rows)

    @property
    def save_s(self) -> float:
        return sum(r.save_s for r in self.rows)

    @property
    def serial_s(self) -> float:
        """The stages' sum: the wall time of running them one after another."""
        return self.decode_s + self.compute_s + self.save_s

    @property
    def hidden_s(self) -> float:
        """Decoding that ran while something else did (local: under inference)."""
        return (
            max(0.0, self.decode_s - sum(r.wait_s for r in self.rows))
            if self.mode == "local"
            else max(0.0, self.serial_s - self.wall_s)
        )

    @property
    def failed(self) -> list[StackRow]:
        return [r for r in self.rows if r.error is not None]

    def as_dict(self) -> dict[str, object]:
        others = [m.as_json() for m in self.other_models]
        return {
            "mode": self.mode,
            "workers": self.workers,
            "prefetch": self.prefetch,
            "worker_memory_mb": self.worker_memory_mb,
            "model": self.model.as_json() if self.model else {},
            **({"other_models": others} if others else {}),
            "stacks": [asdict(r) for r in self.rows],
            "totals": {
                "stacks": len(self.rows),
                "failed": len(self.failed),
                "wall_s": self.wall_s,
                "decode_s": self.decode_s,
                "compute_s": self.compute_s,
                "save_s": self.save_s,
                "serial_s": self.serial_s,
                "saved_s": self.serial_s - self.wall_s,
                "decode_hidden_s": self.hidden_s,
            },
        }

    def _table(self, md: bool) -> list[str]:
        head = (
            "stack",
            "lights",
            "size",
            "decode s",
            "wait s",
            "infer s",
            "save s",
            "MAE deg",
            "output",
        )
        rows = []
        for r in self.rows:
            mae = r.metrics.mae_deg if r.metrics else None
            rows.append(
                (
                    r.name,
                    str(r.lights),
                    f"{r.width}x{r.height}",
                    f"{r.decode_s:.2f}",
                    f"{r.wait_s:.2f}",
                    f"{r.compute_s:.2f}",
                    f"{r.save_s:.2f}",
                    "-" if mae is None else f"{mae:.2f}",
                    f"error: {r.error}" if r.error else (r.output or "-"),
                )
            )
        if md:
            return [
                "| " + " | ".join(head) + " |",
                "|" + "---|" * len(head),
                *("| " + " | ".join(r) + " |" for r in rows),
            ]
        widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(head[:-1])]
        fmt = "  ".join(f"{{:{'<' if i == 0 else '>'}{w}}}" for i, w in enumerate(widths))
        return [
            fmt.format(*head[:-1]) + "  " + head[-1],
            *(fmt.format(*r[:-1]) + "  " + r[-1] for r in rows),
        ]

    def totals_line(self) -> str:
        share = "" if self.worker_memory_mb is None else f", {self.worker_memory_mb:.0f} MB each"
        where = (
            f"{self.workers} Ray worker(s){share}"
            if self.mode == "ray"
            else "next stack decoded in the background"
            if self.prefetch
            else "no prefetch"
        )
        hidden = (
            f"decoding hidden under inference {self.hidden_s:.2f} of {self.decode_s:.2f} s"
            if self.mode == "local"
            else f"parallel speed-up {self.serial_s / max(self.wall_s, 1e-9):.2f}x (the wall "
            "time includes starting the workers and loading the model in each)"
        )
        if self.other_models:
            where += (
                f" (the workers did not all run the same: {1 + len(self.other_models)} "
                "engine/model choices, summary.json: model, other_models)"
            )
        return (
            f"{len(self.rows)} stack(s), {len(self.failed)} failed, {where}: wall "
            f"{self.wall_s:.2f} s vs {self.serial_s:.2f} s of stages run one after another "
            f"(decode {self.decode_s:.2f} + infer {self.compute_s:.2f} + save "
            f"{self.save_s:.2f}); saved {self.serial_s - self.wall_s:.2f} s, {hidden}"
        )

    def text(self) -> str:
        return "\n".join([*self._table(md=False), self.totals_line()])

    def markdown(self) -> str:
        return "\n".join([*self._table(md=True), "", self.totals_line()]) + "\n"

    def write(self, folder: Path) -> None:
        """summary.json and summary.md, each replaced atomically (after every stack, so an
        interrupted batch still says what it finished)."""
        write_text(folder / "summary.json", json_text(self.as_dict()))
        write_text(folder / "summary.md", self.markdown())


def _choice(m: RunMethod) -> tuple[str | None, ...]:
    """What a worker chose to run (Model.describe), without where it is installed."""
    name = Path(m.model).name if m.model is not None else ""
    return (m.method, m.engine, m.precision, m.device, m.graph, name)


def check_batch_root(root: Path, names: Sequence[str], overwrite: bool) -> None:
    """The parent of a batch's output folders: a new or empty folder, or with ``overwrite``
    one holding only what a batch writes (msfnet output folders and the summary), so results
    never mix with other files and no single output's manifest is broken by new entries."""
    if not root.is_dir() or not any(root.iterdir()):
        return  # absent (or a file: check_output names that problem for each stack)
    if not overwrite:
        raise InputError(
            f"output folder exists and is not empty; pass {opt('overwrite')} to write "
            "the batch into it (replacing its earlier results)",
            root,
        )
    if (root / MANIFEST).exists():
        raise InputError(
            f"{opt('overwrite')}: the folder is one stack's output, not a batch's; "
            "choose another folder for the batch",
            root,
            option="overwrite",
        )
    ours = set(names) | set(SUMMARY_FILES)
    foreign = sorted(
        p.name
        for p in root.iterdir()
        if p.name not in ours
        and STAGING_TAG not in p.name
        and not (p.is_dir() and (p / MANIFEST).is_file())
    )
    if foreign:
        raise InputError(
            f"{opt('overwrite')}: the folder holds files msfnet did not write (e.g. "
            f"{foreign[0]}); refusing to write the batch among them",
            root,
            option="overwrite",
        )


def row_for(result: Result, output: Path | None) -> StackRow:
    stack = result.stack
    h, w = stack.shape
    return StackRow(
        stack.name,
        str(stack.source or stack.name),
        None if output is None else str(output),
        stack.num_lights,
        w,
        h,
        int(stack.mask.sum()),
        metrics=result.metrics,
    )


OnResult = Callable[[StackRow, "Result | None"], None]


def run_batch(
    model: Model,
    items: Sequence[StackSource],
    load: LoadOptions,
    out_for: Callable[[str], Path | None],
    *,
    overwrite: bool = False,
    save: SaveOptions | None = None,
    prefetch: bool = True,
    summary_dir: Path | None = None,
    on_result: OnResult | None = None,
    progress: bool | None = None,
    inputs: tuple[Path, ...] = (),
) -> BatchSummary:
    """Run every stack through ``model`` (loaded once); write each result to
    ``out_for(name)`` (None: keep nothing) and the summary into ``summary_dir``.

    A stack that fails (bad input) is recorded in the summary and the batch goes on.
    ``progress``: False hides the bar over the stacks; otherwise it shows on a terminal only.
    """
    from tqdm import tqdm

    summary = BatchSummary("local", model.describe(), prefetch=prefetch)
    start = time.perf_counter()
    # disable=None: a bar on a terminal, nothing in a log file
    bar = tqdm(
        total=len(items),
        unit="stack",
        desc="batch",
        leave=False,
        disable=True if progress is False else None,
    )
    try:
        load = model._loading(load)  # an ROI grown by the network's halo (Model._loading)
        for decoded in decode_ahead(items, load, prefetch=prefetch, total=len(items)):
            item = decoded.item
            error = decoded.error
            if decoded.stack is not None:
                t0 = time.perf_counter()
                out = out_for(item.name)
                try:
                    result = model._run_decoded(decoded, load)
                    compute_s = time.perf_counter() - t0
                    t0 = time.perf_counter()
                    if out is not None:  # all or nothing: a refused stack leaves no folder
                        result.save(out, overwrite=overwrite, inputs=inputs, options=save)
                except InputError as exc:  # e.g. intrinsics this stack's normals cannot use
                    error = exc
            if error is not None:
                row = StackRow(
                    item.name,
                    str(getattr(item, "path", item.name)),
                    error=str(error),
                    wait_s=decoded.wait_s,
                )
                summary.rows.append(row)
                if on_result:
                    on_result(row, None)
                bar.update(1)
                continue
            row = row_for(result, out)
            row.decode_s, row.wait_s, row.compute_s = decoded.decode_s, decoded.wait_s, compute_s
            row.save_s = time.perf_counter() - t0
            summary.rows.append(row)
            summary.wall_s = time.perf_counter() - start
            if summary_dir is not None:
                summary.write(summary_dir)
            if on_result:
                on_result(row, result)
            del decoded, result  # keep at most the next stack in memory
            bar.update(1)
    finally:
        bar.close()
    summary.wall_s = time.perf_counter() - start
    if summary_dir is not None:
        summary.write(summary_dir)
    return summary


__all__ = [
    "SUMMARY_FILES",
    "BatchItem",
    "BatchSummary",
    "StackRow",
    "check_batch_root",
    "expand_stacks",
    "row_for",
    "run_batch",
]
