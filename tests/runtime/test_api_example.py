"""The Python API as the README shows it: the README's snippet, run verbatim."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from _runtime_helpers import sphere_stack

from msfnet import Model
from msfnet.runtime.stack import Stack, save_stack

REPO = Path(__file__).resolve().parents[2]


def readme_example(block: int = 0) -> str:
    """The code block after the ``<!-- api-example -->`` marker in README.md (``block``: the
    first, or one of those after it)."""
    text = (REPO / "README.md").read_text()
    after = text.split("<!-- api-example -->", 1)[1]
    return after.split("```python")[1 + block].split("```", 1)[0]


README_EXAMPLE = readme_example()


def _mae_deg(normals: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    cos = np.clip((normals[mask] * truth[mask]).sum(axis=-1), -1.0, 1.0)
    return float(np.degrees(np.arccos(cos)).mean())


def _files(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


def test_readme_example_runs_verbatim(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import msfnet.runtime.api as pipeline

    assert README_EXAMPLE.strip() in (pipeline.__doc__ or "").replace("\n    ", "\n"), (
        "the pipeline docstring shows another example"
    )
    save_stack(sphere_stack(n=10, h=36, w=44), tmp_path / "obj")
    for i in range(2):  # the folder of stacks the example streams over
        save_stack(sphere_stack(n=6, h=24, w=28, seed=i), tmp_path / "stacks" / f"part{i}")
    monkeypatch.chdir(tmp_path)
    before = _files(tmp_path)
    scope: dict[str, object] = {}
    exec(compile(README_EXAMPLE, "README example", "exec"), scope)
    printed = capsys.readouterr().out
    assert "(36, 44, 3)" in printed and "mae_deg=" in printed
    streamed = [ln for ln in printed.splitlines() if ln.startswith("part")]
    assert [ln.split(":")[0] for ln in streamed] == ["part0", "part1"]  # one line per stack
    view = scope["view"]
    assert view.dtype == np.uint8 and view.shape[2] == 3  # type: ignore[attr-defined]
    written = _files(tmp_path) - before
    assert {"out", "out/obj", "out/obj/normals.npy", "out/obj/metrics.json"} <= written
    assert all(w.startswith("out") for w in written)  # nothing else, nothing in obj/
    result, l2 = scope["result"], scope["l2"]
    normals = np.load(tmp_path / "out/obj/normals.npy")
    np.testing.assert_array_equal(normals, result.normals)  # type: ignore[attr-defined]
    assert l2.normals.shape == (36, 44, 3)  # type: ignore[attr-defined]
    # least squares on the whole stack, intensities included: the line passed the images
    # without them (images as stored are not divided by them: 15.6 deg instead of 4.1 on
    # DiLiGenT's ball); these lights' intensities span 0.5-1.5
    loaded: Stack = scope["stack"]  # type: ignore[assignment]
    images, lights, mask = loaded.images, loaded.lights, loaded.mask
    baseline = Model.least_squares(maps=None)
    right = baseline.predict(images, lights, mask=mask, intensities=loaded.intensities)
    dropped = baseline.predict(images, lights, mask=mask)  # what the old line computed
    assert _mae_deg(l2.normals, right.normals, mask) < 0.01  # type: ignore[attr-defined]
    assert _mae_deg(dropped.normals, right.normals, mask) > 3.0


def test_readme_station_block_imports_what_it_uses(tmp_path: Path) -> None:
    """The README's second block used LoadOptions without importing it: pasted after the
    first block, a NameError. Run with a camera loop of two parts (``model`` from the first
    block; ``capture_next_part`` and ``reject`` are the reader's)."""
    parts = [save_stack(sphere_stack(n=6, h=20, w=24, seed=i), tmp_path / f"p{i}") for i in (0, 1)]
    (tmp_path / "rig").mkdir()
    shutil.copy(parts[0] / "light_directions.txt", tmp_path / "rig" / "lights.txt")
    taken: list[Path] = []

    class StationStopped(Exception):
        pass

    def capture_next_part() -> Path:
        if len(taken) == len(parts):
            raise StationStopped
        taken.append(parts[len(taken)])
        return taken[-1]

    kept: list[object] = []
    scope: dict[str, object] = {
        "model": Model.least_squares(maps=None),  # the first block's
        "capture_next_part": capture_next_part,
        "reject": lambda normals: True,
        "stop_pressed": lambda: True,  # the operator stops after the first part
        "keep_for_later": kept.append,
    }
    code = compile(readme_example(1), "README station example", "exec")
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        exec(code, scope)
    finally:
        os.chdir(cwd)
    assert taken == parts  # the second was taken while the first ran...
    assert kept == [parts[1]]  # ...and handed back, not dropped


def test_two_calls_in_a_row_agree_and_write_nothing(
    random_onnx: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    stack = sphere_stack(n=6, h=28, w=32)
    model = Model(random_onnx, threads=1)
    first, second = model(stack), model(stack)
    np.testing.assert_array_equal(first.normals, second.normals)
    assert first.metrics == second.metrics and first is not second
    again = model.predict(
        stack.images, stack.lights, mask=stack.mask, intensities=stack.intensities
    )
    np.testing.assert_array_equal(again.normals, first.normals)
    assert os.listdir(tmp_path) == []  # no output folder, no cache, nothing
    assert "threads=1" in repr(model)
