"""msf-eval over a small benchmark root: model and l2 side by side, JSON + Markdown + error maps."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from _runtime_helpers import sphere_stack

from msfnet.runtime.eval_cli import find_objects, main
from msfnet.runtime.pipeline import Model
from msfnet.runtime.stack import load_stack, save_stack


@pytest.fixture
def bench_root(tmp_path: Path) -> Path:
    root = tmp_path / "bench"
    save_stack(sphere_stack(n=6, seed=1, name="a"), root / "objA")
    save_stack(sphere_stack(n=9, seed=2, name="b"), root / "objB")
    (root / "objects.txt").write_text("# name [select]\nobjB 4-9\nobjA\n")
    return root


def test_find_objects(bench_root: Path, tmp_path: Path) -> None:
    assert [(f.name, s) for f, s in find_objects(bench_root)] == [("objB", "4-9"),
                                                                   ("objA", None)]
    (bench_root / "objects.txt").unlink()
    assert [f.name for f, _ in find_objects(bench_root)] == ["objA", "objB"]
    assert [f.name for f, _ in find_objects(bench_root / "objA")] == ["objA"]


def test_msf_eval_table(random_onnx: Path, bench_root: Path, tmp_path: Path,
                        capsys) -> None:
    out = tmp_path / "eval"
    assert main([str(bench_root), "--onnx", str(random_onnx), "-o", str(out), "--tile", "0",
                 "--threads", "2"]) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["methods"] == ["msf", "l2"]
    rows = {r["object"]: r for r in res["objects"]}
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
            assert 0 <= rows[obj]["results"][m]["err30"] <= 1
    md = (out / "results.md").read_text()
    assert md.startswith("| object | lights | MAE deg msf | MAE deg l2 |")
    assert "**mean**" in md and md == capsys.readouterr().out.split("wrote")[0].rstrip() + "\n"
    # refuses to overwrite without --overwrite
    assert main([str(bench_root), "--l2-only", "-o", str(out)]) == 2
    assert main([str(bench_root), "--l2-only", "-o", str(out), "--overwrite"]) == 0
    assert json.loads((out / "results.json").read_text())["methods"] == ["l2"]
