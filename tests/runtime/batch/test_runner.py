"""msf-run on several stacks: one model load, background decoding, summary; the same on Ray."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from _runtime_helpers import sphere_stack

from msfnet.common.errors import InputError
from msfnet.runtime.api import Model
from msfnet.runtime.batch.runner import BatchItem, expand_stacks, run_batch
from msfnet.runtime.cli.run import main
from msfnet.runtime.engines.method import RunMethod
from msfnet.runtime.stack import LoadOptions, save_stack


def _stacks(root: Path, count: int = 3) -> list[Path]:
    """Small spheres of different sizes and light counts (a batch is rarely uniform)."""
    return [
        save_stack(sphere_stack(n=5 + i, h=28 + 4 * i, w=32, seed=i), root / f"s{i}")
        for i in range(count)
    ]


@pytest.mark.slow
def test_batch_equals_single_runs_and_writes_a_summary(
    random_onnx: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    stacks = _stacks(tmp_path / "in")
    common = ["--onnx", str(random_onnx), "--threads", "1"]
    for s in stacks:
        assert main([*common, str(s), "-o", str(tmp_path / "single" / s.name)]) == 0
    capsys.readouterr()
    assert main([*common, *map(str, stacks), "-o", str(tmp_path / "batch")]) == 0
    printed = capsys.readouterr().out
    for s in stacks:
        np.testing.assert_array_equal(
            np.load(tmp_path / "batch" / s.name / "normals.npy"),
            np.load(tmp_path / "single" / s.name / "normals.npy"),
        )
    summary = json.loads((tmp_path / "batch" / "summary.json").read_text())
    assert [r["name"] for r in summary["stacks"]] == ["s0", "s1", "s2"]
    totals = summary["totals"]
    assert totals["failed"] == 0 and totals["wall_s"] > 0
    assert totals["serial_s"] == pytest.approx(
        totals["decode_s"] + totals["compute_s"] + totals["save_s"]
    )
    assert "| s1 | 6 | 32x32 |" in (tmp_path / "batch" / "summary.md").read_text()
    assert "stages run one after another" in printed and "decoding hidden" in printed
    profile = json.loads((tmp_path / "batch" / "s2" / "profile.json").read_text())
    assert profile["batch"]["prefetched"] is True and profile["stages"]["load"]["median_s"] > 0


@pytest.mark.slow
def test_folder_of_stacks_and_objects_txt(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    stacks = _stacks(tmp_path / "set")
    (tmp_path / "set" / "notes").mkdir()  # not a stack: ignored
    assert [i.name for i in expand_stacks([tmp_path / "set"])] == ["s0", "s1", "s2"]
    (tmp_path / "set" / "objects.txt").write_text("s2 1-4\n# comment\ns0\n")
    items = expand_stacks([tmp_path / "set"])
    assert items == [BatchItem(stacks[2], "1-4"), BatchItem(stacks[0], None)]
    assert (
        main(["--method", "l2", str(tmp_path / "set"), "-o", str(tmp_path / "out"), "--json"]) == 0
    )
    lines = capsys.readouterr().out
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert [(r["name"], r["lights"]) for r in summary["stacks"]] == [("s2", 4), ("s0", 5)]
    assert '"summary"' in lines
    # --select overrides objects.txt, as in msf-eval
    assert items[0].options(LoadOptions(select="1-3")).select == "1-3"
    assert items[0].options(LoadOptions()).select == "1-4"
    with pytest.raises(InputError, match="named 's0'"):
        expand_stacks([stacks[0], stacks[0]])


def test_a_bad_stack_is_reported_and_the_batch_goes_on(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    good = _stacks(tmp_path / "in", 2)
    bad = tmp_path / "in" / "broken"
    save_stack(sphere_stack(n=4, seed=9), bad)
    (bad / "002.png").write_bytes(b"not a png")
    assert (
        main(["--method", "l2", str(good[0]), str(bad), str(good[1]), "-o", str(tmp_path / "out")])
        == 2
    )
    err = capsys.readouterr().err
    assert "002.png" in err and "1 of 3 stack(s) failed" in err
    assert (tmp_path / "out" / "s1" / "normals.npy").is_file()
    assert not (tmp_path / "out" / "broken").exists()
    rows = json.loads((tmp_path / "out" / "summary.json").read_text())["stacks"]
    assert [r["error"] is None for r in rows] == [True, False, True]


def test_prefetch_decodes_the_next_stack_during_inference(monkeypatch: pytest.MonkeyPatch) -> None:
    """A slow estimator and a slow decoder: with prefetch, decoding hides under inference."""
    import time

    import msfnet.runtime.stack as stack_module

    stacks = [sphere_stack(n=4, seed=i, name=f"m{i}") for i in range(3)]
    model = Model.least_squares()
    estimate, prepare = model.estimator.estimate, stack_module.prepare_stack

    def slow_estimate(*a: object, **k: object) -> object:
        time.sleep(0.6)
        return estimate(*a, **k)  # type: ignore[arg-type]

    def slow_prepare(*a: object, **k: object) -> object:
        time.sleep(0.4)
        return prepare(*a, **k)  # type: ignore[arg-type]

    monkeypatch.setattr(model.estimator, "estimate", slow_estimate)
    monkeypatch.setattr(stack_module, "prepare_stack", slow_prepare)
    on = run_batch(model, stacks, LoadOptions(), lambda n: None, progress=False)
    off = run_batch(model, stacks, LoadOptions(), lambda n: None, prefetch=False, progress=False)
    print(on.totals_line())
    print(off.totals_line())
    # stacks 2 and 3 were decoded while 1 and 2 ran: ~0.8 s hidden, none without prefetch
    # (sleeps long against the real work, so a busy machine keeps the margins)
    assert on.hidden_s > 0.5 and off.hidden_s < 0.1
    assert on.wall_s < off.wall_s - 0.4


@pytest.mark.slow
def test_ray_batch_equals_single_runs(random_onnx: Path, tmp_path: Path) -> None:
    ray = pytest.importorskip("ray")
    stacks = _stacks(tmp_path / "in")
    common = ["--onnx", str(random_onnx), "--threads", "1"]
    for s in stacks:
        assert main([*common, str(s), "-o", str(tmp_path / "single" / s.name)]) == 0
    ray.init(num_cpus=2, include_dashboard=False)
    try:
        assert main([*common, *map(str, stacks), "--ray", "-o", str(tmp_path / "ray")]) == 0
        assert ray.is_initialized()  # the caller's session is left running
    finally:
        ray.shutdown()
    for s in stacks:
        got = np.load(tmp_path / "ray" / s.name / "normals.npy")
        want = np.load(tmp_path / "single" / s.name / "normals.npy")
        np.testing.assert_allclose(got, want, atol=1e-6, rtol=0)
    summary = json.loads((tmp_path / "ray" / "summary.json").read_text())
    assert summary["mode"] == "ray" and summary["workers"] == 2
    assert [r["name"] for r in summary["stacks"]] == ["s0", "s1", "s2"]
    assert all(r["worker"] for r in summary["stacks"])
    assert summary["model"]["model"] == str(random_onnx)


def test_ray_missing_gives_a_clear_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import builtins

    real_import = builtins.__import__

    def no_ray(name: str, *args: object, **kwargs: object) -> object:
        if name == "ray" or name.startswith("ray."):
            raise ImportError("No module named 'ray'")
        return real_import(name, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(builtins, "__import__", no_ray)
    stacks = _stacks(tmp_path / "in", 2)
    assert main(["--method", "l2", *map(str, stacks), "--ray", "-o", str(tmp_path / "o")]) == 2
    assert "pip install 'msfnet[ray]'" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()  # it was left behind, empty
    # "--ray A B" would make A the cluster address: caught before anything runs
    assert main(["--method", "l2", "--ray", *map(str, stacks)]) == 2
    assert "put --ray after the stacks" in capsys.readouterr().err


# name: (extra argv, how the model file is spoiled)
FAILS_AFTER_CHECKS: dict[str, list[str]] = {
    "bad --onnx": ["--onnx", "{junk}"],
    "--workers without --ray": ["--method", "l2", "--workers", "2"],
    # (--precision int8 alone now opens the bundled model's int8 twin)
    "--precision the engine lacks": ["--engine", "onnxruntime", "--precision", "bf16"],
    "--intrinsics with a zero focal length": ["--method", "l2", "--intrinsics", "0", "1", "2", "3"],
}


@pytest.mark.parametrize("case", sorted(FAILS_AFTER_CHECKS))
def test_a_refused_batch_leaves_no_folder(
    case: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The batch made its output folder (and the parents) before opening the model: every
    refused try left an empty folder, and used up a numbered name (batch, batch-2, ...)."""
    stacks = _stacks(tmp_path / "in", 2)
    (tmp_path / "junk.onnx").write_text("junk")
    argv = [a.format(junk=tmp_path / "junk.onnx") for a in FAILS_AFTER_CHECKS[case]]
    monkeypatch.chdir(tmp_path)
    assert main([*argv, *map(str, stacks), "-o", "p1/p2/p3"]) == 2
    assert main([*argv, *map(str, stacks)]) == 2  # the default ./msf-out/batch
    assert capsys.readouterr().err.count("error") == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in", "junk.onnx"]


def _bench_root(root: Path) -> Path:
    """A DiLiGenT-like root: a small bear with 96 images (the protocol keeps 21-96), a ball."""
    save_stack(sphere_stack(n=96, h=12, w=12, name="bear"), root / "bearPNG")
    save_stack(sphere_stack(n=5, name="ball"), root / "ballPNG")
    return root


@pytest.mark.slow
def test_benchmark_selection_is_printed_recorded_and_overridable(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """msf-run DiLiGenT/ used bear's 21-96 silently, and --select was refused with an error
    about an objects.txt that did not exist. Now it is said, kept in profile.json, and
    --select overrides it, as in msf-eval; naming the folder directly does the same."""
    root = _bench_root(tmp_path / "DiLiGenT")
    assert main(["--method", "l2", "--no-maps", str(root), "-o", str(tmp_path / "a")]) == 0
    out = capsys.readouterr().out
    assert "bearPNG: using images 21-96" in out and "--select overrides" in out
    assert "ballPNG: using" not in out
    profile = json.loads((tmp_path / "a" / "bearPNG" / "profile.json").read_text())
    assert profile["lights"] == 76
    assert profile["input"]["select"] == "21-96"
    assert profile["input"]["select_from"] == "benchmark protocol"
    assert (
        "select"
        not in json.loads((tmp_path / "a" / "ballPNG" / "profile.json").read_text())["input"]
    )
    assert (
        main(
            ["--method", "l2", "--no-maps", str(root), "--select", "1-3", "-o", str(tmp_path / "b")]
        )
        == 0
    )
    assert "using images" not in capsys.readouterr().out
    rows = json.loads((tmp_path / "b" / "summary.json").read_text())["stacks"]
    assert [(r["name"], r["lights"]) for r in rows] == [("ballPNG", 3), ("bearPNG", 3)]
    profile = json.loads((tmp_path / "b" / "bearPNG" / "profile.json").read_text())
    assert profile["input"]["select_from"] == "--select"
    # the same object named directly gets the same images
    assert (
        main(["--method", "l2", "--no-maps", str(root / "bearPNG"), "-o", str(tmp_path / "c")]) == 0
    )
    assert "bearPNG: using images 21-96" in capsys.readouterr().out
    assert json.loads((tmp_path / "c" / "profile.json").read_text())["lights"] == 76
    # a folder of the user's that is merely called bearPNG (not 96 images) runs whole
    save_stack(sphere_stack(n=6, name="bear"), tmp_path / "mine" / "bearPNG")
    assert (
        main(["--method", "l2", "--no-maps", str(tmp_path / "mine"), "-o", str(tmp_path / "d")])
        == 0
    )
    assert "using images" not in capsys.readouterr().out
    assert json.loads((tmp_path / "d" / "bearPNG" / "profile.json").read_text())["lights"] == 6


def test_batch_output_folder_rules(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """-o's help: "an existing non-empty folder is refused unless --overwrite". A batch wrote
    into any folder, beside the user's files or into a single stack's output."""
    stacks = _stacks(tmp_path / "in", 2)
    run = ["--method", "l2", "--no-maps", "-q", *map(str, stacks), "-o"]
    mine = tmp_path / "myphotos"
    mine.mkdir()
    (mine / "notes.txt").write_text("precious")
    assert main([*run, str(mine)]) == 2
    assert "not empty; pass --overwrite" in capsys.readouterr().err
    assert main([*run, str(mine), "--overwrite"]) == 2
    assert "notes.txt" in capsys.readouterr().err
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"]
    single = tmp_path / "single"
    assert main(["--method", "l2", "--no-maps", "-q", str(stacks[0]), "-o", str(single)]) == 0
    assert main([*run, str(single), "--overwrite"]) == 2
    assert "one stack's output" in capsys.readouterr().err
    # a batch's own folder is replaced with --overwrite, also when it had other stacks
    batch = tmp_path / "batch"
    assert main([*run, str(batch)]) == 0
    (batch / "s1").rename(batch / "old")
    assert main([*run, str(batch)]) == 2
    assert main([*run, str(batch), "--overwrite"]) == 0
    assert sorted(p.name for p in batch.iterdir()) == [
        "old",
        "s0",
        "s1",
        "summary.json",
        "summary.md",
    ]


def test_a_summary_names_every_engine_choice_its_workers_made() -> None:
    """Ray workers on a mixed cluster choose per CPU (bf16 on one, the int8 twin on another):
    the summary keeps the first as ``model`` and lists each other choice once."""
    from msfnet.runtime.batch.runner import BatchSummary, StackRow

    amx = RunMethod(method="msf", model="msfnet_default.onnx", engine="openvino", precision="bf16")
    avx2 = RunMethod(
        method="msf", model="msfnet_default_int8.onnx", engine="openvino", precision="int8"
    )
    one = BatchSummary("ray", None)
    for method in (amx, amx):
        one.note_model(method)
    assert one.model == amx and "other_models" not in one.as_dict()
    assert "did not all run the same" not in one.totals_line()
    # another install path and OpenVINO build, the same choice: nothing to report
    elsewhere = replace(amx, model="/opt/site/msfnet_default.onnx", openvino="2026.5")
    one.note_model(elsewhere)
    assert "other_models" not in one.as_dict()
    mixed = BatchSummary("ray", None, rows=[StackRow("a", "a"), StackRow("b", "b")])
    for method in (amx, avx2, amx, elsewhere, avx2):
        mixed.note_model(method)
    assert mixed.model == amx and mixed.as_dict()["other_models"] == [avx2.as_json()]
    assert "2 engine/model choices" in mixed.totals_line()


def test_a_stack_refused_while_running_is_reported_and_the_batch_goes_on(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    good = _stacks(tmp_path / "in", 3)
    real = Model._run_decoded

    def refuse_s1(self, decoded, load):  # type: ignore[no-untyped-def]
        if decoded.item.name == "s1":  # what a map its normals cannot make raises
            raise InputError("perspective depth: past float32's range")
        return real(self, decoded, load)

    monkeypatch.setattr(Model, "_run_decoded", refuse_s1)
    out = tmp_path / "out"
    assert main(["--method", "l2", *map(str, good), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "float32's range" in err and "1 of 3 stack(s) failed" in err, err
    assert (out / "s0" / "normals.npy").is_file() and (out / "s2" / "normals.npy").is_file()
    assert not (out / "s1").exists()
    rows = json.loads((out / "summary.json").read_text())["stacks"]
    assert [r["error"] is None for r in rows] == [True, False, True]


def test_one_stack_refused_while_running_names_the_stack(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (stack,) = _stacks(tmp_path / "in", 1)
    out = tmp_path / "out"
    # a ~175-degree camera for a 28 x 32 image (within what the intrinsics check takes before
    # the run): no float32 depth holds what the normals say
    argv = ["--method", "l2", str(stack), "-o", str(out), "--intrinsics", ".4", ".4", "16", "14"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"msf-run: error: {stack}: perspective depth"), err
    assert not out.exists()
