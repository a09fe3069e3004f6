"""Hostile inputs, round two (issue #27, part B): odd file names, models that answer in the
wrong shape, one photo listed twice, values one command refused and another took.

Each test reproduces a case the audit found; each fails on the code before the fix (noted)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from _runtime_helpers import sphere_stack, tiny_msfnet_onnx

from msfnet.common.errors import InputError
from msfnet.common.imageio import read_image, read_mask, write_png
from msfnet.runtime.stack import MIN_LIGHTS, LoadOptions, Stack, load_stack, save_stack

LATIN1 = b"caf\xe9"  # "café" in Latin-1: not UTF-8, so Python holds it as a surrogate escape


def _latin1(parent: Path, name: bytes) -> Path:
    """``parent / name`` for a name that is not UTF-8 (the str form Python gives such names)."""
    return Path(os.fsdecode(os.fsencode(parent) + b"/" + name))


# -- 3. file names that are not UTF-8: OpenCV's imread/imwrite crashed (SIGSEGV) on them


def test_a_latin1_image_name_is_read_and_written(tmp_path: Path) -> None:
    """In a subprocess: the old code died of SIGSEGV inside cv2.imread / cv2.imwrite."""
    folder = _latin1(tmp_path, LATIN1)
    folder.mkdir()
    code = (
        "import sys, numpy as np\n"
        "from pathlib import Path\n"
        "from msfnet.common.imageio import read_image, write_png\n"
        "p = Path(sys.argv[1]) / 'img.png'\n"
        "write_png(p, np.full((5, 7, 3), 1234, np.uint16))\n"
        "img = read_image(p)\n"
        "assert img.shape == (5, 7, 3) and int(img[0, 0, 0]) == 1234\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, os.fsencode(folder)], capture_output=True, timeout=60
    )
    assert proc.returncode == 0, (proc.returncode, proc.stderr[-500:])


def test_msf_run_takes_a_stack_with_latin1_names(tmp_path: Path) -> None:
    """Folder, image and mask names with a Latin-1 byte; output into such a folder too."""
    stack = sphere_stack(n=6, h=24, w=28)
    folder = save_stack(stack, _latin1(tmp_path, LATIN1 + b"_in"))
    for i, name in enumerate(sorted(p.name for p in folder.glob("0*.png"))):
        (folder / name).rename(_latin1(folder, f"{i + 1:03d}_".encode() + LATIN1 + b".png"))
    (folder / "filenames.txt").unlink()  # names come from the folder listing
    (folder / "mask.png").rename(_latin1(folder, b"obj.mask_" + LATIN1 + b".png"))
    out = _latin1(tmp_path, LATIN1 + b"_out")
    proc = subprocess.run(
        [
            *(sys.executable, "-m", "msfnet.runtime.cli.run", "--method", "l2", "--no-maps"),
            *(os.fsencode(folder), "-o", os.fsencode(out)),
        ],
        capture_output=True,
        timeout=120,
    )
    assert proc.returncode == 0, (proc.returncode, proc.stderr[-800:])
    normals = np.load(out / "normals.npy")
    assert normals.shape == (24, 28, 3)
    assert np.abs(np.linalg.norm(normals[stack.mask], axis=1) - 1).max() < 1e-3


def test_a_latin1_mask_name_is_read(tmp_path: Path) -> None:
    path = _latin1(tmp_path, b"mask_" + LATIN1 + b".png")
    write_png(path, np.full((4, 6), 255, np.uint8))
    assert read_mask(path, (4, 6)).all()
    assert read_image(path).shape == (4, 6)


# -- 6. the model's output shape: a larger one was cropped silently, a smaller one crashed


def _model_with_output(path: Path, change: str) -> Path:
    """tiny_msfnet_onnx with its normals padded by 4 px ('larger') or cut by 4 px ('smaller')."""
    import onnx
    from onnx import helper, numpy_helper

    tiny_msfnet_onnx(path)
    model = onnx.load(str(path))
    graph = model.graph
    last = graph.node[-1]
    last.output[0] = "normals_raw"
    if change == "larger":
        pads = numpy_helper.from_array(np.array([0, 0, 0, 0, 0, 0, 4, 4], np.int64), "pads")
        graph.initializer.append(pads)
        graph.node.append(helper.make_node("Pad", ["normals_raw", "pads"], ["normals"]))
    else:
        for name, values in (("starts", [0, 0]), ("ends", [-4, -4]), ("axes", [2, 3])):
            graph.initializer.append(numpy_helper.from_array(np.array(values, np.int64), name))
        graph.node.append(
            helper.make_node("Slice", ["normals_raw", "starts", "ends", "axes"], ["normals"])
        )
    onnx.save(model, str(path))
    return path


@pytest.mark.parametrize("change", ["larger", "smaller"])
def test_a_model_answering_in_the_wrong_shape_is_one_line(tmp_path: Path, change: str) -> None:
    pytest.importorskip("onnx")
    from msfnet.runtime.engines import open_onnxruntime

    path = _model_with_output(tmp_path / f"{change}.onnx", change)
    engine = open_onnxruntime(path, threads=1)
    images = np.ones((1, 4, 3, 16, 20), np.float32)
    lights = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (1, 4, 1))
    with pytest.raises(InputError, match=r"returned normals of shape 1x3x\d+x\d+ for a 20x16") as e:
        engine.run(images, lights)
    assert e.value.path == path and "\n" not in str(e.value)


@pytest.mark.parametrize("change", ["larger", "smaller"])
def test_openvino_checks_the_output_shape_too(tmp_path: Path, change: str) -> None:
    pytest.importorskip("onnx")
    pytest.importorskip("openvino", reason="openvino not installed")
    from msfnet.runtime.engines import open_openvino

    path = _model_with_output(tmp_path / f"{change}.onnx", change)
    engine = open_openvino(path, threads=1, precision="fp32")
    images = np.ones((1, 4, 3, 16, 20), np.float32)
    lights = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (1, 4, 1))
    with pytest.raises(InputError, match="returned normals of shape"):
        engine.run(images, lights)


@pytest.mark.parametrize(
    ("normals", "words"),
    [(np.float32(1.0), r"shape \(\) \(a single number\) for"), (None, "shape no array for")],
)
def test_a_shapeless_answer_is_named(normals: object, words: str) -> None:
    from msfnet.runtime.engines.ort_session import check_normals

    images = np.ones((1, 4, 3, 16, 20), np.float32)
    with pytest.raises(InputError, match=words):
        check_normals(Path("m.onnx"), images, normals)


def test_msf_run_names_the_model_that_answers_wrongly(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip("onnx")
    from msfnet.runtime.cli.run import main

    folder = save_stack(sphere_stack(n=6, h=24, w=28), tmp_path / "s")
    model = _model_with_output(tmp_path / "larger.onnx", "larger")
    argv = [str(folder), "--onnx", str(model), "-o", str(tmp_path / "o"), "--no-maps"]
    assert main([*argv, "-q"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "returned normals of shape" in err, err
    assert f"{model}:" in err and "--tile" not in err  # no advice that would not help
    assert not (tmp_path / "o").exists()


# -- 10. the same photo listed twice in filenames.txt


@pytest.mark.parametrize("second", ["002.png", "./002.png", "sub/../002.png"])
def test_a_photo_listed_twice_is_refused(tmp_path: Path, second: str) -> None:
    folder = save_stack(sphere_stack(n=5), tmp_path / "s")
    (folder / "sub").mkdir()
    names = (folder / "filenames.txt").read_text().split()
    names[3] = second  # 004.png's line now names 002.png again
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    with pytest.raises(InputError, match=r"listed twice \(lines 2 and 4\)") as e:
        load_stack(folder)
    assert e.value.path == folder / "filenames.txt"


def test_a_link_to_a_listed_photo_is_the_same_photo(tmp_path: Path) -> None:
    folder = save_stack(sphere_stack(n=5), tmp_path / "s")
    (folder / "copy.png").symlink_to(folder / "002.png")
    names = (folder / "filenames.txt").read_text().split()
    names[3] = "copy.png"
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    with pytest.raises(InputError, match=r"002\.png and copy\.png are the same photo"):
        load_stack(folder)


# -- 14. values one entry point refused and another accepted


def test_complex_arrays_are_refused_by_the_python_api() -> None:
    ref = sphere_stack(n=6)
    images = ref.images.astype(np.complex64) + 1j  # a cast would drop the imaginary part
    with pytest.raises(InputError, match="dtype complex64; expected real numbers"):
        Stack.from_arrays(images, ref.lights)
    with pytest.raises(InputError, match="light directions have dtype complex"):
        Stack.from_arrays(ref.images, ref.lights.astype(np.complex128))
    with pytest.raises(InputError, match="light intensities have dtype complex"):
        Stack.from_arrays(ref.images, ref.lights, intensities=ref.intensities * (1 + 0j))


@pytest.mark.parametrize("value", [0.05, 255, -1.0, np.nan])
def test_masks_are_boolean_or_exactly_zero_and_one(value: float) -> None:
    ref = sphere_stack(n=6)
    mask = ref.mask.astype(np.float64)
    mask[0, 0] = value
    with pytest.raises(InputError, match=r"mask holds .* other than 0 and 1"):
        Stack.from_arrays(ref.images, ref.lights, mask=mask)
    ok = Stack.from_arrays(ref.images, ref.lights, mask=ref.mask.astype(np.uint8))
    np.testing.assert_array_equal(ok.mask, ref.mask)


def test_npz_masks_follow_the_same_rule(tmp_path: Path) -> None:
    ref = sphere_stack(n=6)
    path = tmp_path / "s.npz"
    np.savez(path, images=ref.images, lights=ref.lights, mask=ref.mask * 0.05)
    with pytest.raises(InputError, match="mask holds"):
        load_stack(path)


def test_one_minimum_light_count_everywhere() -> None:
    from msfnet.model.train_config import parse_curriculum
    from msfnet.runtime.stack import selection

    assert MIN_LIGHTS == 3
    ref = sphere_stack(n=MIN_LIGHTS - 1)
    with pytest.raises(InputError, match=f"at least {MIN_LIGHTS} lights"):
        ref.validate()
    with pytest.raises(InputError, match=f"at least {MIN_LIGHTS} lights"):
        selection(8, None, MIN_LIGHTS - 1)
    with pytest.raises(InputError, match=f"need {MIN_LIGHTS} <= LMIN"):
        parse_curriculum("0:2-4:16")  # 2-light training batches used to be accepted
    assert parse_curriculum("0:3-4:16")[0].lights_min == 3


def test_training_samples_need_the_minimum_light_count() -> None:
    pytest.importorskip("torch")
    from msfnet.model.data import make_sample

    stack = sphere_stack(n=8, h=32, w=32)
    rng = np.random.default_rng(0)
    with pytest.raises(InputError, match=f"needs at least {MIN_LIGHTS}"):
        make_sample(stack, 2, 16, rng)
    x, *_ = make_sample(stack, MIN_LIGHTS, 16, rng)
    assert x.shape[0] == MIN_LIGHTS


@pytest.mark.parametrize("threads", [0, 1025, 100_000])
def test_threads_are_bounded_by_one_validator(threads: int) -> None:
    import argparse

    from msfnet.common.cli import thread_count
    from msfnet.common.cpu import MAX_THREADS, check_threads
    from msfnet.runtime.options import ModelOptions

    with pytest.raises(argparse.ArgumentTypeError, match=f"1..{MAX_THREADS}"):
        thread_count(str(threads))
    with pytest.raises(InputError, match=f"1..{MAX_THREADS}"):
        check_threads(threads)
    with pytest.raises(InputError, match=f"1..{MAX_THREADS}"):
        ModelOptions(threads=threads)
    assert thread_count("8") == 8 and check_threads(MAX_THREADS) == MAX_THREADS


def test_bench_peaks_refuse_absurd_threads_before_measuring() -> None:
    from msfnet.bench.peak import engine_peaks

    with pytest.raises(InputError, match="threads must be"):
        engine_peaks([2, 100_000], {"onnxruntime"}, torch_peaks=False)


def test_bench_accuracy_refuses_absurd_threads() -> None:
    from msfnet.bench.accuracy import main

    with pytest.raises(SystemExit) as e:
        main(["--threads", "100000"])
    assert e.value.code == 2


def test_stack_validate_refuses_complex_lights_given_directly() -> None:
    ref = sphere_stack(n=6)
    stack = Stack("s", ref.images, ref.lights.astype(np.complex64), ref.intensities, ref.mask, None)
    with pytest.raises(InputError, match="expected real numbers"):
        stack.validate()


def test_load_options_still_load_a_plain_stack(tmp_path: Path) -> None:
    """The checks above leave ordinary stacks alone."""
    folder = save_stack(sphere_stack(n=6), tmp_path / "s")
    s = load_stack(folder, LoadOptions(max_memory_mb=64))
    assert s.num_lights == 6 and s.images.dtype == np.uint16


# -- round three (issue #48): a NUL byte in filenames.txt was an internal error (os.stat's
# ValueError "embedded null byte" from the output checks' look for linked inputs)


def test_a_nul_byte_in_filenames_txt_is_one_line(tmp_path: Path) -> None:
    folder = save_stack(sphere_stack(n=6, h=16, w=16), tmp_path / "s")
    names = (folder / "filenames.txt").read_text().splitlines()
    names[0] = names[0][:2] + "\0" + names[0][2:]
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, "-m", "msfnet.runtime.cli.run", str(folder), "-o", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "filenames.txt" in lines[0] and "NUL" in lines[0], lines
    assert not out.exists()


def test_msf_calib_refuses_one_capture_given_twice(tmp_path: Path, capsys) -> None:
    """`msf-calib directions A A/` averaged a capture with itself (weighed double beside a
    third), silently."""
    from msfnet.calib.cli import main as calib_main

    capture = tmp_path / "chrome"
    capture.mkdir()
    (tmp_path / "link").symlink_to(capture)
    for second in (f"{capture}/", str(tmp_path / "link")):
        out = tmp_path / "l.txt"
        assert calib_main(["directions", str(capture), second, "-o", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "given twice" in err[0], err
        assert not out.exists()


@pytest.mark.parametrize(
    ("extra", "words"),
    [
        (["--intrinsics", "100", "100", "1e308", "1e308"], "principal point"),
        (["--pixel-size", "1e-310"], "pixel size"),
    ],
    ids=["principal point 1e308", "subnormal pixel size"],
)
def test_settings_the_maps_cannot_use_are_refused_before_the_estimate(
    extra: list[str], words: str, tmp_path: Path, capsys, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Both passed the checks and ended in internal errors during the maps, after the whole
    run (a ZeroDivisionError, a singular factor)."""
    from msfnet.runtime.cli.run import main as run_main
    from msfnet.runtime.infer import estimators

    def never(*args: object, **kwargs: object) -> None:
        raise AssertionError("the estimate ran")

    monkeypatch.setattr(estimators.LeastSquaresEstimator, "estimate", never)
    folder = save_stack(sphere_stack(n=6, h=16, w=16), tmp_path / "s")
    out = tmp_path / "out"
    assert run_main([str(folder), "--method", "l2", "-o", str(out), *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("msf-run: error:") and words in err[0], err
    assert not out.exists()


def _l2_run(folder: Path, out: Path, **env: str) -> subprocess.CompletedProcess[bytes]:
    """msf-run --method l2 in a C locale (with ``env`` on top), names passed as bytes."""
    environ = {k: v for k, v in os.environ.items() if k != "PYTHONIOENCODING"}
    argv = [os.fsencode(folder), "--no-maps", "--method", "l2", "-o", os.fsencode(out)]
    return subprocess.run(
        [sys.executable, "-m", "msfnet.runtime.cli.run", *argv],
        capture_output=True,
        env={**environ, "LANG": "C", "LC_ALL": "C", **env},
        timeout=120,
    )


@pytest.mark.parametrize("name", [b"caf\xc3\xa9", LATIN1], ids=["utf-8", "latin-1"])
def test_any_name_prints_under_an_ascii_locale(name: bytes, tmp_path: Path) -> None:
    """Under LANG=C / PYTHONIOENCODING=ascii a non-ASCII name ended in a UnicodeEncodeError,
    once after the output was written (the summary line names the stack). Under LANG=C alone
    an undecodable name still prints as its own bytes (a script reads the path back)."""
    folder = save_stack(sphere_stack(n=6, h=16, w=16), _latin1(tmp_path, name))
    out = _latin1(tmp_path, name + b"_out")
    if name == LATIN1:
        proc = _l2_run(folder, out)
        assert proc.returncode == 0 and os.fsencode(out) in proc.stdout, proc.stdout[-300:]
        out = _latin1(tmp_path, name + b"_out2")
    proc = _l2_run(folder, out, PYTHONIOENCODING="ascii")
    assert proc.returncode == 0, proc.stderr[-500:]
    assert b"caf\\" in proc.stdout and b"Error" not in proc.stderr  # escaped, not raised
    assert (out / "normals.npy").is_file()


def test_an_objects_txt_entry_with_a_space_is_one_folder(tmp_path: Path) -> None:
    """Issue #48: a folder named with a space was read as a folder plus a selection."""
    from _runtime_helpers import png_stack

    from msfnet.runtime.evaluate.datasets import find_objects

    png_stack(tmp_path / "my part", 16)
    png_stack(tmp_path / "bear part 2", 16)
    (tmp_path / "objects.txt").write_text("my part\nbear part 2 2-7  # a selection\n")
    found = find_objects(tmp_path)
    assert [(o.folder.name, o.select) for o in found] == [("my part", None), ("bear part 2", "2-7")]
    (tmp_path / "objects.txt").write_text("my part\t1:3\n")  # a tab, a colon range
    assert [(o.folder.name, o.select) for o in find_objects(tmp_path)] == [("my part", "1:3")]
    (tmp_path / "objects.txt").write_text("no such part 1-4\n")
    with pytest.raises(InputError, match="'no such part' listed but not found"):
        find_objects(tmp_path)


def test_msf_eval_says_one_line_when_the_budget_cannot_hold_a_stack(
    ball_dir: Path, tmp_path: Path, capsys
) -> None:
    """Issue #48: msf-eval printed bear's protocol line before its one-line error (the budget
    was checked only when the first stack was decoded, after the notes)."""
    from msfnet.runtime.cli.eval import main as eval_main

    out = tmp_path / "e"
    assert eval_main([str(ball_dir.parent), "--max-memory", "100", "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "above --max-memory 100 MB" in err[0], err
    assert not out.exists()


def test_a_stack_without_shading_is_said(tmp_path: Path) -> None:
    """Issue #48: a flat stack (one frame for every light) ran silently, exit 0."""
    from dataclasses import replace

    stack = sphere_stack(n=8, h=24, w=24)
    flat = replace(stack, images=np.repeat(stack.images[:1], 8, axis=0))
    folder = save_stack(flat, tmp_path / "flat")
    out = tmp_path / "out"
    argv = [str(folder), "--method", "l2", "--no-maps", "-o", str(out)]
    proc = subprocess.run(
        [sys.executable, "-m", "msfnet.runtime.cli.run", *argv],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert "warning: every image is the same inside the mask" in proc.stderr
    assert json.loads((out / "profile.json").read_text())["warnings"]
    assert not stack.validate().warnings  # a shaded stack says nothing
