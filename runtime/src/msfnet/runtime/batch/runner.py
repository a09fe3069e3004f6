"""Batches: many stacks through one loaded model, the next stack decoded while one runs.

A single stack cannot overlap its own decoding with inference (the normalisation needs every
image of a pixel first), but in a batch the next stack's images can be decoded in a background
thread while the current stack is inferred. The summary measures how much that hid:
``decode - wait`` seconds of decoding ran under inference, and the wall time is compared with
the sum of the stages run one after the other.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

from msfnet.common.errors import InputError
from msfnet.common.files import MANIFEST, STAGING_TAG, json_text, write_text
from msfnet.common.imageio import list_images
from msfnet.runtime.evaluate.datasets import PROTOCOL_SELECT, find_objects, protocol_note
from msfnet.runtime.evaluate.metrics import NormalMetrics
from msfnet.runtime.results.profile import BatchStats
from msfnet.runtime.stack import LIGHTS_NAMES, LoadOptions, Stack, load_stack, selection
from msfnet.runtime.stack.load import count_images

if TYPE_CHECKING:
    from msfnet.runtime.api import Model, Result

SUMMARY_FILES = ("summary.json", "summary.md")


@dataclass(frozen=True)
class BatchItem:
    """One stack of a batch: its path and its own image selection, from an objects.txt or
    from a benchmark's protocol (DiLiGenT bear: 21-96), which --select overrides (as in
    msf-eval)."""

    path: Path
    select: str | None = None
    origin: str = "objects.txt"  # where ``select`` comes from: "objects.txt" or "protocol"

    @property
    def name(self) -> str:
        return self.path.stem if self.path.suffix.lower() == ".npz" else self.path.name

    def options(self, load: LoadOptions) -> LoadOptions:
        if self.select is None or load.select is not None:
            return load
        return replace(load, select=self.select)

    def note(self, load: LoadOptions) -> str | None:
        """The line to print when the benchmark's selection applies (it changes the result,
        so it is never silent)."""
        if self.origin != "protocol" or self.select is None or load.select is not None:
            return None
        return protocol_note(self.name, self.select)

    def describe_input(self, load: LoadOptions) -> dict[str, object]:
        """profile.json's "input": the options in effect and where the selection came from."""
        info = self.options(load).describe()
        if load.select is not None:
            info["select_from"] = "--select"
        elif self.select is not None:
            info["select_from"] = (
                "benchmark protocol" if self.origin == "protocol" else "objects.txt"
            )
        return info


def _is_stack_folder(folder: Path) -> bool:
    return (
        (folder / "filenames.txt").is_file()
        or any((folder / n).is_file() for n in LIGHTS_NAMES)
        or bool(list_images(folder))
    )


def _protocol_item(folder: Path) -> BatchItem:
    """A stack folder, with its benchmark's selection when its name is a known object's (as
    msf-eval does, however the folder is named on the command line) and the selection fits
    its images: a folder of ours that happens to be called bearPNG but holds 24 images is not
    DiLiGenT's bear, and runs whole."""
    select = PROTOCOL_SELECT.get(folder.name)
    if select is not None:
        try:
            selection(count_images(folder), select, None)
        except InputError:
            select = None
    return BatchItem(folder, select, "protocol")


def expand_stacks(paths: Sequence[Path]) -> list[BatchItem]:
    """The stacks named on the command line: a stack folder or .npz stands for itself; a folder
    with an objects.txt (msf-eval's format, e.g. ``bearPNG 21-96``) or whose sub-folders are
    stacks stands for those. Names must be unique (they name the output folders)."""

    items: list[BatchItem] = []
    for path in paths:
        if path.is_dir() and (path / "objects.txt").is_file():
            items += [BatchItem(o.folder, o.select) for o in find_objects(path)]
        elif path.is_dir() and not _is_stack_folder(path):
            subs = [d for d in sorted(path.iterdir()) if d.is_dir() and _is_stack_folder(d)]
            if not subs:
                raise InputError(
                    "neither a stack (images + light_directions.txt) nor a folder "
                    "of stacks (sub-folders holding them, or an objects.txt)",
                    path,
                )
            items += [_protocol_item(d) for d in subs]
        elif path.is_dir():
            items.append(_protocol_item(path))
        else:
            items.append(BatchItem(path))  # an .npz, or a path the loader reports
    names = [i.name for i in items]
    dup = next((n for n in names if names.count(n) > 1), None)
    if dup is not None:
        raise InputError(f"two stacks are named {dup!r}; their output folders would clash")
    return items


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
    model: dict[str, object]
    rows: list[StackRow] = field(default_factory=list)
    wall_s: float = 0.0
    workers: int = 1
    prefetch: bool = True

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
        return {
            "mode": self.mode,
            "workers": self.workers,
            "prefetch": self.prefetch,
            "model": self.model,
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
        where = (
            f"{self.workers} Ray worker(s)"
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


def check_batch_root(root: Path, names: Sequence[str], overwrite: bool) -> None:
    """The parent of a batch's output folders: a new or empty folder, or with ``overwrite``
    one holding only what a batch writes (msfnet output folders and the summary), so results
    never mix with other files and no single output's manifest is broken by new entries."""
    if not root.is_dir() or not any(root.iterdir()):
        return  # absent (or a file: check_output names that problem for each stack)
    if not overwrite:
        raise InputError(
            "output folder exists and is not empty; pass --overwrite to write "
            "the batch into it (replacing its earlier results)",
            root,
        )
    if (root / MANIFEST).exists():
        raise InputError(
            "--overwrite: the folder is one stack's output, not a batch's; "
            "choose another folder for the batch",
            root,
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
            f"--overwrite: the folder holds files msfnet did not write (e.g. "
            f"{foreign[0]}); refusing to write the batch among them",
            root,
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


def _decode(item: BatchItem | Stack, load: LoadOptions) -> tuple[Stack, float]:
    start = time.perf_counter()
    if isinstance(item, Stack):
        from msfnet.runtime.stack import prepare_stack

        stack = prepare_stack(item, load)
    else:
        stack = load_stack(item.path, item.options(load))
    return stack, time.perf_counter() - start


def _prefetched(
    items: Sequence[BatchItem | Stack], load: LoadOptions, prefetch: bool
) -> Iterator[tuple[int, Future[tuple[Stack, float]]]]:
    """Futures of the decoded stacks, in order. With ``prefetch`` the next stack is submitted
    when the current one is handed out, so it decodes while the current one runs; without,
    only after the caller is done with it. One decoding thread: at most two stacks in memory.
    """
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="msf-decode")
    try:
        upcoming = pool.submit(_decode, items[0], load) if items else None
        for i in range(len(items)):
            current, upcoming = upcoming, None
            more = i + 1 < len(items)
            if prefetch and more:
                upcoming = pool.submit(_decode, items[i + 1], load)
            assert current is not None
            yield i, current
            if not prefetch and more:
                upcoming = pool.submit(_decode, items[i + 1], load)
    finally:
        # Ctrl-C or an error: do not wait for a stack nobody will use
        pool.shutdown(wait=True, cancel_futures=True)


def run_batch(
    model: Model,
    items: Sequence[BatchItem | Stack],
    load: LoadOptions,
    out_for: Callable[[str], Path | None],
    *,
    overwrite: bool = False,
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
    budget = model.tiling
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
        for i, future in _prefetched(items, load, prefetch):
            item = items[i]
            name = item.name
            waited = time.perf_counter()
            try:
                stack, decode_s = future.result()
            except InputError as exc:
                row = StackRow(
                    name,
                    str(getattr(item, "path", name)),
                    error=str(exc),
                    wait_s=time.perf_counter() - waited,
                )
                summary.rows.append(row)
                if on_result:
                    on_result(row, None)
                bar.update(1)
                continue
            wait_s = time.perf_counter() - waited
            if prefetch and i + 1 < len(items):
                # the next stack is being decoded beside this one: leave its memory out of the
                # tile budget (estimated by this stack's size; batches are rarely mixed)
                model.tiling = replace(
                    budget,
                    max_memory_mb=max(budget.max_memory_mb - stack.images.nbytes / 2**20, 256.0),
                )
            try:
                t0 = time.perf_counter()
                result = model(stack)
                compute_s = time.perf_counter() - t0
            finally:
                model.tiling = budget
            runs = result.timings.runs
            if runs:  # the profile shows what the stack cost, decoding included
                runs[-1]["load"] = decode_s
                runs[-1]["total"] = runs[-1].get("total", 0.0) + decode_s
            # what model(path, load) records itself (auto-mask -> mask.png on save)
            result.input = (
                item.describe_input(load) if isinstance(item, BatchItem) else load.describe()
            )
            result.batch = BatchStats(decode_s, wait_s=wait_s, prefetched=prefetch and i > 0)
            out = out_for(name)
            t0 = time.perf_counter()
            if out is not None:
                result.save(out, overwrite=overwrite, inputs=inputs)
            row = row_for(result, out)
            row.decode_s, row.wait_s, row.compute_s = decode_s, wait_s, compute_s
            row.save_s = time.perf_counter() - t0
            summary.rows.append(row)
            summary.wall_s = time.perf_counter() - start
            if summary_dir is not None:
                summary.write(summary_dir)
            if on_result:
                on_result(row, result)
            del stack, result  # keep at most the next stack in memory
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
