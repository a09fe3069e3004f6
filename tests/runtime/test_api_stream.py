"""The Python API for a station and a lab: model.stream over folders, lists and capture loops,
typed LoadOptions with str paths, errors in the API's words, results a person can read."""

from __future__ import annotations

import json
import shutil
import sys
import threading
import time
import typing
import warnings
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from _runtime_helpers import sphere_stack

import msfnet
from msfnet import LoadOptions, MapOptions, Model, Result, load_stack
from msfnet.common.errors import InputError, MsfError
from msfnet.runtime.cli.run import main as msf_run
from msfnet.runtime.stack import Stack, save_stack


def _folder_of_stacks(root: Path, count: int = 3) -> list[Path]:
    return [
        save_stack(sphere_stack(n=5 + i, h=24 + 4 * i, w=28, seed=i), root / f"s{i}")
        for i in range(count)
    ]


@pytest.fixture(scope="module")
def l2() -> Model:
    return Model.least_squares(maps=None)


def test_stream_over_a_folder_equals_one_call_per_stack(l2: Model, tmp_path: Path) -> None:
    paths = _folder_of_stacks(tmp_path / "stacks")
    streamed = l2.stream(tmp_path / "stacks")
    assert isinstance(streamed, Iterator)  # a generator: nothing runs before it is asked
    results = list(streamed)
    assert [r.name for r in results] == ["s0", "s1", "s2"]
    for r, p in zip(results, paths, strict=True):
        np.testing.assert_array_equal(r.normals, l2(p).normals)
        assert r.batch is not None and r.timings.runs[-1]["load"] == r.batch.decode_s
    assert [r.batch.prefetched for r in results if r.batch] == [False, True, True]
    assert list(tmp_path.glob("**/normals.npy")) == []  # a stream writes nothing


def test_stream_takes_a_list_of_paths_and_stacks_with_str_paths(l2: Model, tmp_path: Path) -> None:
    a, b = _folder_of_stacks(tmp_path, 2)
    c = sphere_stack(n=6, h=20, w=20, seed=9, name="in-memory")
    got = list(l2.stream([str(a), c, b], prefetch=False))
    assert [r.name for r in got] == ["s0", "in-memory", "s1"]
    np.testing.assert_array_equal(got[1].normals, l2(c).normals)


def test_stream_pulls_a_capture_loop_one_stack_ahead_at_most(l2: Model) -> None:
    pulled: list[int] = []
    threads: set[str] = set()

    def camera() -> Iterator[Stack]:
        for i in range(4):
            pulled.append(i)
            threads.add(threading.current_thread().name)
            yield sphere_stack(n=5, h=20, w=22, seed=i, name=f"part{i}")

    names = []
    for r in l2.stream(camera()):
        # the current stack, and at most the next one being decoded beside it
        assert len(pulled) <= len(names) + 2
        names.append(r.name)
    assert names == ["part0", "part1", "part2", "part3"]
    assert len(threads) == 1  # advanced by one thread only, never concurrently


def test_stopping_a_stream_early_stops_its_reader(l2: Model) -> None:
    pulled: list[int] = []

    def endless() -> Iterator[Stack]:
        i = 0
        while True:
            pulled.append(i)
            yield sphere_stack(n=5, h=20, w=22, seed=i % 3, name=f"p{i}")
            i += 1

    stream = l2.stream(endless())
    first = next(stream)
    stream.close()  # what a `break` out of a for loop does
    assert first.name == "p0" and len(pulled) <= 2
    _reader_ends()
    # the one taken ahead is handed back, not dropped
    assert [s.name for s in stream.unprocessed] == ["p1"]


def _reader_ends(timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while [t for t in threading.enumerate() if t.name.startswith("msf-decode")]:
        assert time.monotonic() < deadline, "the reader thread did not end"
        time.sleep(0.01)


def test_a_bad_stack_in_a_stream_raises_at_its_turn(l2: Model, tmp_path: Path) -> None:
    (good,) = _folder_of_stacks(tmp_path, 1)
    stream = l2.stream([good, tmp_path / "missing"])
    assert next(stream).name == "s0"  # the results before it stay valid
    with pytest.raises(InputError, match="missing"):
        next(stream)


def test_stream_refuses_what_is_no_stack_source(l2: Model) -> None:
    with pytest.raises(InputError, match="got int"):
        list(l2.stream(3))  # type: ignore[arg-type]
    with pytest.raises(InputError, match="an element of type int"):
        list(l2.stream([3]))  # type: ignore[list-item]


def test_calling_a_model_on_a_list_points_to_stream(l2: Model, tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"model\.stream"):
        l2([tmp_path, tmp_path])  # type: ignore[arg-type]


def test_load_options_take_str_paths(l2: Model, tmp_path: Path) -> None:
    path = save_stack(sphere_stack(n=6, h=20, w=24, seed=4), tmp_path / "s")
    lights = path / "light_directions.txt"
    opts = LoadOptions(lights=str(lights), mask=str(path / "mask.png"))  # type: ignore[arg-type]
    assert opts.lights == lights and isinstance(opts.mask, Path)
    assert opts.inputs() == [lights, path / "mask.png"]
    np.testing.assert_array_equal(l2(path, opts).normals, l2(path).normals)


def test_errors_speak_keywords_in_python_and_flags_in_msf_run(
    l2: Model, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = save_stack(sphere_stack(n=6, h=20, w=24, seed=4), tmp_path / "s")
    (path / "light_directions.txt").unlink()
    with pytest.raises(InputError) as caught:
        load_stack(path)
    assert "(or pass lights)" in str(caught.value) and "--lights" not in str(caught.value)
    assert msf_run([str(path), "--method", "l2", "-o", str(tmp_path / "cli")]) == 2
    assert "--lights" in capsys.readouterr().err  # the command keeps its flags

    result = l2(save_stack(sphere_stack(n=6, h=20, w=24), tmp_path / "t"))
    result.save(tmp_path / "out")
    with pytest.raises(InputError) as caught:
        result.save(tmp_path / "out")
    assert "overwrite=True" in str(caught.value) and "--overwrite" not in str(caught.value)
    result.save(tmp_path / "out", overwrite=True)
    with pytest.raises(InputError, match=r"select='1-99'"):
        l2(path, LoadOptions(lights=tmp_path / "t" / "light_directions.txt", select="1-99"))


def test_result_reads_as_a_line_json_and_a_picture(random_onnx: Path) -> None:
    model = Model(random_onnx, engine="onnxruntime", threads=1)
    stack = sphere_stack(n=6, h=28, w=32, name="ball")
    result = model(stack)
    line = result.summary()
    assert "\n" not in line and line.startswith("ball: 6 lights, 32x28")
    assert "onnxruntime fp32" in line and "MAE" in line
    text = repr(result)
    assert len(text) < 300 and text.startswith("Result('ball', 32x28")
    data = json.loads(result.to_json())
    assert data["name"] == "ball" and data["lights"] == 6
    assert data["metrics"]["mae_deg"] == pytest.approx(result.metrics.mae_deg, abs=1e-9)  # type: ignore[union-attr]
    assert "\n" not in result.to_json(indent=None)  # one line, for a log
    for what in ("normals", "error", "height"):
        picture = result.plot(what)
        assert picture.dtype == np.uint8 and picture.ndim == 3 and picture.shape[2] == 3
        assert picture.std() > 0  # not a blank image
    no_gt = Model.least_squares(maps=None)(replace(stack, normals_gt=None))
    with pytest.raises(InputError, match="no ground truth"):
        no_gt.plot("error")
    with pytest.raises(InputError, match="no height map"):
        no_gt.plot("height")
    pytest.importorskip("matplotlib", reason="figures need matplotlib")
    fig = result.plot(figure=True)
    assert fig.axes and fig.axes[0].images  # one axes showing the picture


def test_a_figure_without_matplotlib_says_what_to_install(monkeypatch) -> None:
    """matplotlib is an optional extra: plot(figure=True) without it is one InputError naming
    the extra to install, not a bare ModuleNotFoundError; the picture itself needs no
    matplotlib; a user's mistake is still said first."""
    result = Model.least_squares(maps=None)(sphere_stack(n=6, h=16, w=16, name="ball"))
    mpl = [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")]
    for name in {"matplotlib", *mpl}:
        monkeypatch.setitem(sys.modules, name, None)  # importing it raises ModuleNotFoundError
    rgb = result.plot()  # drawn with numpy, OpenCV and Pillow
    assert rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3
    with pytest.raises(InputError, match=r"matplotlib, which is not installed") as exc:
        result.plot(figure=True)
    assert "\n" not in str(exc.value) and "msfnet[pictures]" in str(exc.value)
    with pytest.raises(InputError, match="expected one of normals"):
        result.plot("nothing")


def test_leaving_a_capture_loop_hands_back_the_part_taken_ahead(l2: Model) -> None:
    """The prefetching thread takes the next part while the current one runs: a `break`
    must not drop a photographed part unseen (stop() returns it; a stream dropped unclosed
    warns)."""

    def camera() -> Iterator[Stack]:
        for i in range(3):
            yield sphere_stack(n=5, h=20, w=22, seed=i, name=f"part{i}")

    stream = l2.stream(camera())
    for r in stream:
        assert r.name == "part0"
        break
    left = stream.stop()
    assert [s.name for s in left] == ["part1"] and isinstance(left[0], Stack)
    with pytest.warns(RuntimeWarning, match=r"1 stack\(s\) taken from the source.*part1"):
        for _r in l2.stream(camera()):
            break
        _reader_ends()  # the part may land after the loop: it warns then


def test_leaving_a_stream_does_not_wait_for_a_camera_that_has_not_fired(l2: Model) -> None:
    """break while the capture loop waits for its trigger: back at once, not at the next
    part; a part that arrives later is kept in unprocessed, not decoded and dropped."""
    import queue

    triggers: queue.Queue[Stack] = queue.Queue()
    triggers.put(sphere_stack(n=5, h=20, w=22, seed=0, name="first"))

    def camera() -> Iterator[Stack]:
        while True:
            yield triggers.get()

    stream = l2.stream(camera())
    assert next(stream).name == "first"
    start = time.monotonic()
    assert stream.stop(timeout=0.1) == []  # the pull is still waiting on the camera
    assert stream.pending
    assert time.monotonic() - start < 2.0
    triggers.put(sphere_stack(n=5, h=20, w=22, seed=1, name="late"))
    _reader_ends()
    assert [s.name for s in stream.unprocessed] == ["late"] and not stream.pending


def test_a_stack_whose_run_fails_is_handed_back(l2: Model, monkeypatch: pytest.MonkeyPatch) -> None:
    calls = {"n": 0}
    real = l2._run_decoded

    def flaky(decoded, load):  # type: ignore[no-untyped-def]
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt  # Ctrl-C during the second part's inference
        return real(decoded, load)

    monkeypatch.setattr(l2, "_run_decoded", flaky)
    parts = [sphere_stack(n=5, h=20, w=22, seed=i, name=f"p{i}") for i in range(4)]
    stream = l2.stream(iter(parts))
    assert next(stream).name == "p0"
    with pytest.raises(KeyboardInterrupt):
        next(stream)
    # the interrupted one first, then the one decoded ahead of it
    assert [s.name for s in stream.stop()] == ["p1", "p2"]


def test_skipping_bad_stacks_goes_on_and_says_which(l2: Model, tmp_path: Path) -> None:
    good = _folder_of_stacks(tmp_path, 2)
    stream = l2.stream([good[0], tmp_path / "missing", good[1]], on_error="skip")
    with pytest.warns(RuntimeWarning, match="missing.*skipped"):
        names = [r.name for r in stream]
    assert names == ["s0", "s1"]
    assert [s.source.name for s in stream.skipped] == ["missing"]
    assert "not found" in str(stream.skipped[0].error)
    with pytest.raises(InputError, match="on_error"):
        l2.stream(good, on_error="ignore")


def test_a_stack_refused_while_running_is_skipped_or_raised(
    l2: Model, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    paths = _folder_of_stacks(tmp_path, 3)
    real = l2._run_decoded

    def refuse_s1(decoded, load):  # type: ignore[no-untyped-def]
        if decoded.item.name == "s1":  # what a map its normals cannot make raises
            raise InputError("perspective depth: past float32's range")
        return real(decoded, load)

    monkeypatch.setattr(l2, "_run_decoded", refuse_s1)
    stream = l2.stream(paths, on_error="skip")
    with pytest.warns(RuntimeWarning, match="s1: perspective depth.*skipped"):
        assert [r.name for r in stream] == ["s0", "s2"]
    assert [s.source.name for s in stream.skipped] == ["s1"]
    stream = l2.stream(paths, prefetch=False)
    assert next(stream).name == "s0"
    with pytest.raises(InputError, match="float32"):
        next(stream)
    assert [p.name for p in stream.stop()] == ["s1"]  # taken, not run: given back


# ---------------------------------------------------------------- one path, three entry points


def _bear(root: Path, n: int = 96) -> Path:
    """A folder named like DiLiGenT's bear with as many images (small, generated)."""
    return save_stack(sphere_stack(n=n, h=12, w=12, name="bear"), root / "bearPNG")


def test_a_path_is_read_with_its_benchmark_selection_by_every_entry_point(
    l2: Model, tmp_path: Path
) -> None:
    """``model(bearPNG)`` and ``load_stack(bearPNG)`` used all 96 images where
    ``model.stream(bearPNG)`` and msf-run use DiLiGenT's 21-96: the same path gave two inputs,
    and nothing said so on the ``model(path)`` side."""
    bear = _bear(tmp_path)
    said = r"bearPNG: using images 21-96 \(DiLiGenT's protocol: .*\); select overrides"
    with pytest.warns(UserWarning, match=said):
        called = l2(bear)
    with pytest.warns(UserWarning, match=said):
        (streamed,) = list(l2.stream(bear))
    with pytest.warns(UserWarning, match=said):
        loaded = load_stack(str(bear))
    assert called.stack.num_lights == streamed.stack.num_lights == loaded.num_lights == 76
    assert loaded.filenames[0] == "021.png" and called.stack.filenames == loaded.filenames
    np.testing.assert_array_equal(called.normals, streamed.normals)
    assert called.input == streamed.input
    assert called.input is not None and called.input["select"] == "21-96"
    assert called.input["select_from"] == "benchmark protocol"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a selection of one's own overrides it, silently
        own = l2(bear, LoadOptions(select="1-96"))
        assert load_stack(bear, select="1-10").num_lights == 10
        ours = l2(_bear(tmp_path / "ours", 24))  # 24 images: not DiLiGenT's bear, run whole
    assert own.stack.num_lights == 96 and own.input is not None and own.input["select"] == "1-96"
    assert ours.stack.num_lights == 24 and ours.input is None


def test_diligent_bear_is_read_from_image_21_by_model_and_load_stack(
    l2: Model, ball_dir: Path
) -> None:
    bear = ball_dir.parent / "bearPNG"
    if not bear.is_dir():
        pytest.skip(f"DiLiGenT's bear not found at {bear}")
    with pytest.warns(UserWarning, match="bearPNG: using images 21-96"):
        stack = load_stack(bear, max_lights=4)
    with pytest.warns(UserWarning, match="bearPNG: using images 21-96"):
        result = l2(bear, LoadOptions(max_lights=4, downscale=4))
    assert stack.filenames == result.stack.filenames == ["021.png", "046.png", "071.png", "096.png"]
    assert result.input is not None and result.input["select"] == "21-96"


def test_a_result_names_the_files_given_in_place_of_the_stacks_own(
    l2: Model, tmp_path: Path
) -> None:
    """A light file given as LoadOptions(lights=...) was recorded nowhere in the saved result:
    a mirrored light file gave normals 53 deg off, and nothing in the folder said why."""
    path = save_stack(sphere_stack(n=6, h=20, w=24, seed=4), tmp_path / "s")
    rig = tmp_path / "rig"
    rig.mkdir()
    for name in ("light_directions.txt", "light_intensities.txt", "mask.png"):
        shutil.copy(path / name, rig / name)
    load = LoadOptions(
        lights=str(rig / "light_directions.txt"),
        intensities=rig / "light_intensities.txt",
        mask=rig / "mask.png",
    )
    given = {
        "lights": str(rig / "light_directions.txt"),
        "intensities": str(rig / "light_intensities.txt"),
        "mask": str(rig / "mask.png"),
    }
    result = l2(path, load)
    result.save(tmp_path / "out")
    profile = json.loads((tmp_path / "out" / "profile.json").read_text())
    assert given.items() <= profile["input"].items()
    (streamed,) = list(l2.stream([path], load))
    assert streamed.input is not None and given.items() <= streamed.input.items()
    assert not {"lights", "intensities", "mask"} & set(l2(path, LoadOptions()).input or {})


# ---------------------------------------------------------------- messages in the API's words


def test_a_ragged_list_is_refused_in_one_line(l2: Model) -> None:
    """numpy's "inhomogeneous shape" ValueError came out of predict raw."""
    stack = sphere_stack(n=6, h=20, w=24)
    images = list(stack.images)
    images[1] = images[1][:10]
    with pytest.raises(InputError, match="images are ragged"):
        l2.predict(images, stack.lights)
    rows = stack.lights.tolist()
    rows[2] = rows[2][:2]
    with pytest.raises(InputError, match="light directions are ragged"):
        l2.predict(stack.images, rows)
    lists = l2.predict(
        stack.images.tolist(), stack.lights.tolist(), intensities=stack.intensities.tolist()
    )
    np.testing.assert_array_equal(lists.normals, l2(stack).normals)


def test_messages_name_keywords_that_work(
    random_onnx: Path, l2: Model, monkeypatch: pytest.MonkeyPatch
) -> None:
    """API messages read "detail_fusion=... runs without it" (the keyword to pass is
    detail_fusion=False), "threads=... must be", an engine failure's "try a smaller --tile or
    --max-memory", and a map hint named MapOptions, which msfnet did not export."""
    with pytest.raises(InputError) as caught:
        Model(random_onnx, threads=0)
    assert str(caught.value).startswith("threads must be an integer in 1..")
    stack = sphere_stack(n=6, h=28, w=32)
    small = Model(random_onnx, engine="onnxruntime", threads=1, max_memory_mb=10, maps=None)
    with pytest.raises(InputError, match=r"\(detail_fusion=False runs without it\)"):
        small(stack)
    model = Model(random_onnx, engine="onnxruntime", threads=1, detail_fusion=False, maps=None)

    def fails(images: np.ndarray, lights: np.ndarray) -> np.ndarray:
        raise RuntimeError("out of device memory")

    monkeypatch.setattr(model.estimator.engine, "run", fails)  # type: ignore[attr-defined]
    with pytest.raises(MsfError) as failed:
        model(stack)
    assert "try a smaller tile or max_memory_mb" in str(failed.value)
    assert "--" not in str(failed.value) and isinstance(failed.value.__cause__, RuntimeError)
    plain = l2(stack)  # maps=None
    with pytest.raises(InputError, match=r"Model\(maps='height'\) or .*msfnet\.MapOptions"):
        plain.plot("height")
    assert msfnet.MapOptions is MapOptions
    assert Model.least_squares(maps=msfnet.MapOptions(maps=("height",)))(stack).maps is not None


def test_public_hints_take_what_the_runtime_takes() -> None:
    """``predict`` takes lists (a type error for a checker while the hints said ndarray), and
    ``plot`` says what it returns (Any before: ``r.plot().shape`` went unchecked)."""
    hints = typing.get_type_hints(Model.predict)
    assert hints["images"] == hints["lights"] == npt.ArrayLike
    assert hints["mask"] == npt.ArrayLike | None
    returns = [o.__annotations__["return"] for o in typing.get_overloads(Result.plot)]
    assert returns == ["np.ndarray", "Figure", "np.ndarray | Figure"]


@pytest.mark.parametrize("prefetch", [True, False])
@pytest.mark.parametrize("failure", [MemoryError, KeyboardInterrupt])
def test_a_part_whose_decoding_fails_is_handed_back(
    l2: Model, monkeypatch: pytest.MonkeyPatch, prefetch: bool, failure: type
) -> None:
    """Only an InputError kept its item: a MemoryError while preparing a large stack, or
    Ctrl-C while one decodes in the calling thread, dropped a part taken from the camera."""
    from msfnet.runtime import sources

    real = sources._decode

    def decode(item, load):  # type: ignore[no-untyped-def]
        if getattr(item, "name", "") == "p1":
            raise failure
        return real(item, load)

    monkeypatch.setattr(sources, "_decode", decode)
    parts = [sphere_stack(n=5, h=20, w=22, seed=i, name=f"p{i}") for i in range(3)]
    stream = l2.stream(iter(parts), prefetch=prefetch)
    assert next(stream).name == "p0"
    with pytest.raises(failure):
        next(stream)
    assert [s.name for s in stream.stop()] == ["p1"]
    assert not stream.pending
