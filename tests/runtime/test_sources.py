"""Stack sources: a folder of stacks that share one light file at the top (psmImages' layout)
is a batch, each stack read with that file, exactly as a single run given it with --lights."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from _runtime_helpers import sphere_stack

from msfnet.runtime.cli.run import main
from msfnet.runtime.sources import BatchItem, decode_ahead, expand_stacks
from msfnet.runtime.stack import LoadOptions, save_stack


def _shared_lights_root(root: Path, count: int = 3) -> Path:
    """Stacks in sub-folders with the same lights, the light file moved to the top."""
    for i in range(count):
        folder = save_stack(sphere_stack(n=6, h=24, w=28 + 4 * i, seed=0), root / f"obj{i}")
        moved = folder / "light_directions.txt"
        if i == 0:
            shutil.move(moved, root / "lights.txt")
        else:
            moved.unlink()
    return root


def test_a_root_with_one_light_file_expands_to_its_stacks(tmp_path: Path) -> None:
    root = _shared_lights_root(tmp_path / "psm")
    items = expand_stacks([root])
    assert [i.name for i in items] == ["obj0", "obj1", "obj2"]
    assert {i.lights for i in items} == {(root / "lights.txt").resolve()}
    # --lights still overrides the shared file; a stack's own selection is kept
    other = tmp_path / "other.txt"
    assert items[0].options(LoadOptions(lights=other)).lights == other
    assert items[0].options(LoadOptions()).lights == (root / "lights.txt").resolve()


def test_a_sub_folder_with_its_own_light_file_keeps_it(tmp_path: Path) -> None:
    root = _shared_lights_root(tmp_path / "psm", 2)
    own = save_stack(sphere_stack(n=6, h=24, w=28, seed=5), root / "own")
    items = {i.name: i for i in expand_stacks([root])}
    assert items["own"].lights is None and items["obj1"].lights is not None
    assert items["own"].path == own


def test_a_stack_folder_is_still_one_stack(tmp_path: Path) -> None:
    stack = save_stack(sphere_stack(n=6, h=24, w=28), tmp_path / "s")
    assert expand_stacks([stack]) == [BatchItem(stack, None, "protocol")]


def test_msf_run_on_a_shared_light_root_equals_single_runs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = _shared_lights_root(tmp_path / "psm")
    assert main([str(root), "--method", "l2", "--no-maps", "-o", str(tmp_path / "batch")]) == 0
    for name in ("obj0", "obj1", "obj2"):
        single = tmp_path / "single" / name
        args = [str(root / name), "--lights", str(root / "lights.txt"), "-o", str(single)]
        assert main([*args, "--method", "l2", "--no-maps"]) == 0
        np.testing.assert_array_equal(
            np.load(tmp_path / "batch" / name / "normals.npy"), np.load(single / "normals.npy")
        )
        profile = json.loads((tmp_path / "batch" / name / "profile.json").read_text())
        assert profile["input"]["lights"] == str((root / "lights.txt").resolve())
    summary = json.loads((tmp_path / "batch" / "summary.json").read_text())
    assert summary["totals"]["stacks"] == 3 and summary["totals"]["failed"] == 0
    capsys.readouterr()


def test_decode_ahead_without_prefetch_reads_in_the_callers_turn(tmp_path: Path) -> None:
    root = _shared_lights_root(tmp_path / "psm", 2)
    items = expand_stacks([root])
    got = list(decode_ahead(items, LoadOptions(), prefetch=False, total=len(items)))
    assert [d.item.name for d in got] == ["obj0", "obj1"]
    assert all(d.stack is not None and not d.prefetched and not d.beside for d in got)
    ahead = list(decode_ahead(items, LoadOptions(), prefetch=True, total=len(items)))
    assert [(d.prefetched, d.beside) for d in ahead] == [(False, True), (True, False)]


def test_psmimages_root_is_a_batch_of_its_objects(psm_dir: Path) -> None:
    items = expand_stacks([psm_dir])
    names = [i.name for i in items]
    assert {"cat", "owl", "horse"} <= set(names) and len(names) >= 7
    assert all(i.lights == (psm_dir / "lights.txt").resolve() for i in items)


def test_a_stack_given_as_dot_or_through_a_link_keeps_its_name_and_protocol(
    tmp_path: Path, monkeypatch
) -> None:
    """review-stack23.md 4 and 9: "." had an empty name (its batch outputs went into the
    batch's root, msf-eval failed), and bear given as "." or through a link ran on all 96
    images, the 20 corrupted ones too."""
    from msfnet.runtime.sources import path_item

    bear = tmp_path / "bearPNG"
    save_stack(sphere_stack(n=96, h=12, w=12), bear)
    link = tmp_path / "bear"
    link.symlink_to(bear)
    for given in (bear, link, Path(".")):
        monkeypatch.chdir(bear if given == Path(".") else tmp_path)
        item = path_item(given)
        assert item.select == "21-96", given
        assert item.name == ("bear" if given == link else "bearPNG")
        assert "DiLiGenT" in (item.note(LoadOptions()) or "")


def test_a_batch_with_a_stack_given_as_dot_writes_it_into_its_own_folder(
    tmp_path: Path, monkeypatch
) -> None:
    for name in ("a", "b"):
        save_stack(sphere_stack(seed=len(name)), tmp_path / name)
    monkeypatch.chdir(tmp_path / "a")
    out = tmp_path / "out"
    assert (
        main([".", str(tmp_path / "b"), "--method", "l2", "--no-maps", "-q", "-o", str(out)]) == 0
    )
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == [
        "a",
        "b",
        "summary.json",
        "summary.md",
    ]


def test_a_stray_broken_link_beside_the_stacks_does_not_stop_a_batch(tmp_path: Path) -> None:
    """review-today23.md 2: a dangling preview.png at a batch's root, or in a sub-folder that is
    no stack, ended the whole batch before any stack ran."""
    for name in ("a", "b"):
        save_stack(sphere_stack(seed=len(name)), tmp_path / "root" / name)
    (tmp_path / "root" / "preview.png").symlink_to("gone.png")
    (tmp_path / "root" / "misc").mkdir()
    (tmp_path / "root" / "misc" / "old.png").symlink_to("../gone.png")
    items = expand_stacks([tmp_path / "root"])
    assert sorted(i.name for i in items) == ["a", "b"]
