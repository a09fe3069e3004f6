"""msf-eval over a small benchmark root: model and l2 side by side, JSON + Markdown + error maps."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from _runtime_helpers import sphere_stack

from msfnet.runtime.api import Model
from msfnet.runtime.cli.eval import main
from msfnet.runtime.evaluate.datasets import find_objects
from msfnet.runtime.stack import load_stack, save_stack


@pytest.fixture
def bench_root(tmp_path: Path) -> Path:
    root = tmp_path / "bench"
    save_stack(sphere_stack(n=6, seed=1, name="a"), root / "objA")
    save_stack(sphere_stack(n=9, seed=2, name="b"), root / "objB")
    (root / "objects.txt").write_text("# name [select]\nobjB 4-9\nobjA\n")
    return root


def test_find_objects(bench_root: Path, tmp_path: Path) -> None:
    found = [(o.folder.name, o.select) for o in find_objects(bench_root)]
    assert found == [("objB", "4-9"), ("objA", None)]
    (bench_root / "objects.txt").unlink()
    assert [o.folder.name for o in find_objects(bench_root)] == ["objA", "objB"]
    assert [o.folder.name for o in find_objects(bench_root / "objA")] == ["objA"]


def test_msf_eval_table(random_onnx: Path, bench_root: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "eval"
    assert (
        main(
            [
                str(bench_root),
                "--onnx",
                str(random_onnx),
                "-o",
                str(out),
                "--tile",
                "0",
                "--threads",
                "2",
            ]
        )
        == 0
    )
    res = json.loads((out / "results.json").read_text())
    assert res["methods"] == ["msf", "l2"]
    rows = {r["object"]: r for r in res["results"]}
    assert rows["objB"]["lights"] == 6 and rows["objA"]["lights"] == 6
    # numbers equal a direct run of each method on the same stack
    stack_b = load_stack(bench_root / "objB", select="4-9")
    direct = Model.least_squares()(stack_b).metrics
    assert direct is not None
    assert rows["objB"]["results"]["l2"]["mae_deg"] == pytest.approx(direct.mae_deg)
    assert rows["objB"]["results"]["l2"]["err15"] > 0.9  # Lambertian sphere
    for obj in ("objA", "objB"):
        for m in ("msf", "l2"):
            assert (out / obj / f"{m}_error.png").is_file()
            assert (out / obj / f"{m}_normals.png").is_file()
    assert rows["objB"]["results"]["msf"]["mae_deg"] > rows["objB"]["results"]["l2"]["mae_deg"]
    # where the numbers came from: results.md's head and results.json (issue #28)
    md = (out / "results.md").read_text()
    head, table = md.split("\n\n", 1)
    sha = hashlib.sha256(random_onnx.read_bytes()).hexdigest()[:12]
    assert f"- model: `{random_onnx.name} (sha256 {sha})`" in head
    prov = res["provenance"]
    assert f"- engine: `{prov['engine']} {prov['precision']}`" in head
    assert f"- command: `msf-eval {bench_root} --onnx {random_onnx} -o {out}" in head
    assert prov["model_sha256"] == sha and prov["input"].endswith("objA")
    assert table.startswith("| object | lights | MAE msf | MAE l2 |")
    seen = capsys.readouterr()
    assert "**mean**" in table and table == seen.out.split("wrote")[0].rstrip() + "\n"
    # a line per object as it is done, in a pipe too (pytest's stderr is no terminal)
    done = [ln for ln in seen.err.splitlines() if ln.startswith("msf-eval: [")]
    assert [ln.split(":")[1] for ln in done] == [" [1/2] objB", " [2/2] objA"], seen.err
    assert all(" lights, msf " in ln and ", l2 " in ln for ln in done), done
    # refuses to overwrite without --overwrite
    assert main([str(bench_root), "--l2-only", "-o", str(out)]) == 2
    assert main([str(bench_root), "--l2-only", "-o", str(out), "--overwrite"]) == 0
    assert json.loads((out / "results.json").read_text())["methods"] == ["l2"]


def test_objects_without_ground_truth_get_the_detail_ratio(
    bench_root: Path, tmp_path: Path
) -> None:
    """No ground truth: the model's high-pass energy over least squares' (random weights
    smooth everything away, so the ratio is far below 1)."""
    import numpy as np

    (bench_root / "objA" / "Normal_gt.mat").unlink()
    out = tmp_path / "eval"
    model = Model.least_squares()
    from msfnet.runtime.cli.eval import evaluate

    summary = evaluate(find_objects(bench_root / "objA"), out, model=model)
    row = summary.results[0]
    assert not row.has_ground_truth and row.scores["msf"].metrics is None
    assert row.detail_ratio == pytest.approx(1.0)  # least squares against itself
    assert "detail msf / l2" in (out / "results.md").read_text()
    written = json.loads((out / "results.json").read_text())["results"][0]
    assert written["note"] == "no ground truth" and np.isfinite(written["detail_ratio"])


def test_diligent_protocol_selects_bear_21_96(tmp_path: Path) -> None:
    root = tmp_path / "DiLiGenT"
    save_stack(sphere_stack(n=24, name="bear"), root / "bearPNG")
    save_stack(sphere_stack(n=5, name="ball"), root / "ballPNG")
    objs = {o.folder.name: o.select for o in find_objects(root)}
    assert objs == {"ballPNG": None, "bearPNG": "21-96"}


def test_closing_line_lists_only_what_was_written(bench_root: Path, tmp_path: Path, capsys) -> None:
    """Objects without ground truth get normal maps only; the line said "error maps"."""
    assert main([str(bench_root), "--l2-only", "-o", str(tmp_path / "gt")]) == 0
    assert "normal maps and error maps per object" in capsys.readouterr().out
    for obj in ("objA", "objB"):
        (bench_root / obj / "Normal_gt.mat").unlink()
    assert main([str(bench_root), "--l2-only", "-o", str(tmp_path / "nogt")]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert "normal maps per object" in last and "error" not in last
    assert not list((tmp_path / "nogt").rglob("*_error.png"))


def test_a_light_file_that_fits_no_later_object_is_refused_before_the_first_runs(
    bench_root: Path, tmp_path: Path, capfd, monkeypatch: pytest.MonkeyPatch
) -> None:
    """msf-eval scored the first objects for minutes, then met the mismatch and kept nothing."""
    lights = tmp_path / "six.txt"
    lights.write_text((bench_root / "objA" / "light_directions.txt").read_text())  # 6 lights
    ran = []
    real = Model.__call__
    monkeypatch.setattr(
        Model, "__call__", lambda self, *a, **k: ran.append(1) or real(self, *a, **k)
    )
    out = tmp_path / "out"
    argv = [str(bench_root / "objA"), str(bench_root / "objB"), "--lights", str(lights)]
    assert main([*argv, "--l2-only", "-o", str(out)]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "6 light directions for 9 images" in err[0], err
    assert ran == [] and not out.exists()


def test_the_protocol_line_and_the_published_least_squares_are_shown(
    tmp_path: Path, capsys
) -> None:
    """--help promised a line for a benchmark's own selection (DiLiGenT bear 21-96) that
    msf-eval never printed; L2 (paper) was left out beside our l2."""
    root = tmp_path / "bench"
    save_stack(sphere_stack(n=9, seed=2, name="ball"), root / "ballPNG")
    (root / "objects.txt").write_text("ballPNG 2-9\n")
    out = tmp_path / "out"
    assert main([str(root), "--l2-only", "-o", str(out)]) == 0
    assert "ballPNG: using images 2-9" in capsys.readouterr().err
    table = (out / "results.md").read_text()
    assert "MAE l2 | L2 (paper) |" in table and "| 4.10 |" in table
    assert "rows at fewer lights do not compare one to one" in table


def test_a_stack_file_is_not_a_benchmark(tmp_path: Path, capfd) -> None:
    """msf-eval x.npz said "benchmark root or object folder not found" for a file there."""
    npz = tmp_path / "good.npz"
    np.savez(npz, images=np.ones((3, 4, 4, 3)), lights=np.eye(3))
    assert main([str(npz), "--l2-only", "-q", "-o", str(tmp_path / "o")]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "good.npz: a file, not a benchmark" in err[0], err
    assert "msf-run takes .npz" in err[0] and "not found" not in err[0]


def _shared_lights_root(root: Path) -> Path:
    """psmImages' layout: stacks in sub-folders, one lights.txt at the top (the same lights)."""
    for i, name in enumerate(("cat", "owl")):
        folder = save_stack(sphere_stack(n=6, h=24, w=28 + 4 * i, seed=3), root / name)
        lights = folder / "light_directions.txt"
        if i == 0:
            lights.rename(root / "lights.txt")
        else:
            lights.unlink()
    return root


def test_a_root_with_one_shared_light_file_is_a_benchmark_of_its_folders(
    tmp_path: Path, capsys
) -> None:
    """msf-eval psmImages read the root as one object; its objects share the top light file."""
    root = _shared_lights_root(tmp_path / "psm")
    objs = find_objects(root)
    assert [(o.folder.name, o.lights) for o in objs] == [
        ("cat", (root / "lights.txt").resolve()),
        ("owl", (root / "lights.txt").resolve()),
    ]
    # a sub-folder's own light file wins over the shared one
    save_stack(sphere_stack(n=6, h=24, w=28, seed=3), root / "own")
    assert {o.folder.name: o.lights for o in find_objects(root)}["own"] is None

    out = tmp_path / "eval"
    assert main([str(root), "--l2-only", "-q", "-o", str(out)]) == 0
    rows = {r["object"]: r for r in json.loads((out / "results.json").read_text())["results"]}
    assert sorted(rows) == ["cat", "owl", "own"]
    # the same numbers as one object evaluated with the light file given by hand
    single = tmp_path / "single"
    args = [str(root / "owl"), "--lights", str(root / "lights.txt"), "--l2-only", "-q"]
    assert main([*args, "-o", str(single)]) == 0
    alone = json.loads((single / "results.json").read_text())["results"][0]
    assert rows["owl"]["lights"] == alone["lights"] == 6
    mae = rows["owl"]["results"]["l2"]["mae_deg"]
    assert mae == pytest.approx(alone["results"]["l2"]["mae_deg"], abs=1e-9)
    # cat (shared file) and own (its own file) are the same stack: the same error
    cat, own = (rows[n]["results"]["l2"]["mae_deg"] for n in ("cat", "own"))
    assert cat == pytest.approx(own, abs=1e-9) and np.isfinite(cat)


def test_psmimages_root_is_a_benchmark_of_its_objects(psm_dir: Path) -> None:
    objs = find_objects(psm_dir)
    assert len(objs) > 1 and "cat" in {o.folder.name for o in objs}
    assert {o.lights for o in objs} == {(psm_dir / "lights.txt").resolve()}
