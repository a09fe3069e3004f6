"""Every bad input of issue 3 part 6: one error line naming the file, exit 2, no partial outputs."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
from _runtime_helpers import sphere_stack

from msfnet.runtime.cli.run import main
from msfnet.runtime.stack import save_stack


@pytest.fixture
def stack_dir(tmp_path: Path) -> Path:
    return save_stack(sphere_stack(), tmp_path / "in" / "sphere")


def _replace_row(path: Path, row: int, text: str) -> None:
    lines = path.read_text().splitlines()
    lines[row] = text
    path.write_text("\n".join(lines) + "\n")


def _drop_last_row(path: Path) -> None:
    path.write_text("\n".join(path.read_text().splitlines()[:-1]) + "\n")


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _two_lights(d: Path) -> None:
    names = (d / "filenames.txt").read_text().split()[:2]
    (d / "filenames.txt").write_text("\n".join(names) + "\n")
    for f in ("light_directions.txt", "light_intensities.txt"):
        rows = (d / f).read_text().splitlines()[:2]
        (d / f).write_text("\n".join(rows) + "\n")


CASES: dict[str, tuple[Callable[[Path], None], str, str]] = {
    # name: (corrupt the folder, file named in the message, words in the message)
    "mismatched_counts": (
        lambda d: _drop_last_row(d / "light_directions.txt"),
        "light_directions.txt",
        "7 light directions for 8 images",
    ),
    "unreadable_image": (
        lambda d: (d / "003.png").write_bytes(b"not a png at all"),
        "003.png",
        "cannot decode",
    ),
    "truncated_image": (lambda d: _truncate(d / "005.png"), "005.png", "truncated"),
    "different_sizes": (
        lambda d: cv2.imwrite(str(d / "002.png"), np.zeros((20, 20, 3), np.uint16)),
        "002.png",
        "but 001.png is",
    ),
    "nan_light": (
        lambda d: _replace_row(d / "light_directions.txt", 2, "nan 0.1 0.9"),
        "light_directions.txt",
        "NaN",
    ),
    "zero_light": (
        lambda d: _replace_row(d / "light_directions.txt", 4, "0 0 0"),
        "sphere",
        "zero-length light direction",
    ),
    "two_lights": (_two_lights, "sphere", "at least 3 lights"),
    "zero_intensity": (
        lambda d: _replace_row(d / "light_intensities.txt", 1, "0 0 0"),
        "light_intensities.txt",
        "positive",
    ),
    "wrong_size_mask": (
        lambda d: cv2.imwrite(str(d / "mask.png"), np.full((10, 12), 255, np.uint8)),
        "mask.png",
        "mask is 12x10 but images are 44x36",
    ),
}


def _assert_one_line_error(capfd, must: list[str]) -> str:
    err = capfd.readouterr().err.strip()
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("msf-run: error: "), err
    for word in must:
        assert word in lines[0], (word, err)
    return lines[0]


def _no_outputs(out: Path) -> None:
    assert not out.exists()
    assert not [p for p in out.parent.iterdir() if ".partial-" in p.name]


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_stack(case: str, stack_dir: Path, tmp_path: Path, capfd) -> None:
    corrupt, filename, words = CASES[case]
    corrupt(stack_dir)
    out = tmp_path / "out" / "result"
    out.parent.mkdir()
    assert main(["--method", "l2", str(stack_dir), "-o", str(out)]) == 2
    _assert_one_line_error(capfd, [filename, words])
    _no_outputs(out)


def test_good_stack_runs(stack_dir: Path, tmp_path: Path, capfd) -> None:
    """The fixture itself is fine: the failures above come from the corruption."""
    out = tmp_path / "out"
    assert main(["--method", "l2", str(stack_dir), "-o", str(out)]) == 0
    assert (out / "normals.npy").is_file()


def _tiny_onnx(path: Path, with_meta: bool = False) -> Path:
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper

    graph = helper.make_graph(
        [helper.make_node("Identity", ["images"], ["normals"])],
        "not_msfnet",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, None)],
        [helper.make_tensor_value_info("normals", TensorProto.FLOAT, None)],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    if with_meta:  # claims to be msfnet but has the wrong inputs
        entry = model.metadata_props.add()
        entry.key, entry.value = "msfnet.format", "msfnet-normals-v1"
    onnx.save(model, str(path))
    return path


@pytest.mark.parametrize("kind", ["foreign", "foreign_with_meta", "garbage", "missing"])
def test_not_an_msfnet_model(kind: str, stack_dir: Path, tmp_path: Path, capfd) -> None:
    model = tmp_path / "model.onnx"
    if kind == "garbage":
        model.write_bytes(b"\x00\x01 this is not protobuf" * 10)
    elif kind != "missing":
        _tiny_onnx(model, with_meta=kind == "foreign_with_meta")
    out = tmp_path / "out" / "result"
    out.parent.mkdir()
    assert main(["--onnx", str(model), str(stack_dir), "-o", str(out)]) == 2
    words = {
        "foreign": "not an msfnet model",
        "foreign_with_meta": "not an msfnet model",
        "garbage": "cannot load ONNX model",
        "missing": "not found",
    }[kind]
    _assert_one_line_error(capfd, ["model.onnx", words])
    _no_outputs(out)


def test_outdir_refused_unless_overwrite(stack_dir: Path, tmp_path: Path, capfd) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("old result")
    assert main(["--method", "l2", str(stack_dir), "-o", str(out)]) == 2
    _assert_one_line_error(capfd, ["out", "--overwrite"])
    assert (out / "keep.txt").read_text() == "old result"
    # --overwrite never deletes what msfnet did not write
    assert main(["--method", "l2", str(stack_dir), "-o", str(out), "--overwrite"]) == 2
    _assert_one_line_error(capfd, ["out", "did not write", "keep.txt"])
    assert (out / "keep.txt").read_text() == "old result"
    # ... but replaces its own results
    (out / "keep.txt").unlink()
    assert main(["--method", "l2", str(stack_dir), "-o", str(out)]) == 0
    first = (out / "normals.npy").stat().st_ino
    assert main(["--method", "l2", str(stack_dir), "-o", str(out), "--overwrite"]) == 0
    assert (out / "normals.npy").stat().st_ino != first and (out / "normals_view.png").is_file()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out.")]


def test_outdir_inside_input_refused(stack_dir: Path, capfd) -> None:
    before = sorted(p.name for p in stack_dir.iterdir())
    assert main(["--method", "l2", str(stack_dir), "-o", str(stack_dir / "res")]) == 2
    _assert_one_line_error(capfd, ["inside the input folder"])
    assert sorted(p.name for p in stack_dir.iterdir()) == before


def test_bad_arguments(stack_dir: Path, tmp_path: Path, capfd) -> None:
    out = tmp_path / "o"
    assert main(["--method", "l2", str(stack_dir), "-o", str(out), "--select", "5-40"]) == 2
    _assert_one_line_error(capfd, ["--select", "outside 1..8"])
    assert main(["--method", "l2", "--onnx", "x.onnx", str(stack_dir), "-o", str(out)]) == 2
    _assert_one_line_error(capfd, ["needs no model"])
    assert main([str(tmp_path / "nothing_here"), "--method", "l2", "-o", str(out)]) == 2
    _assert_one_line_error(capfd, ["nothing_here", "not found"])
    _no_outputs(out)


# ---------------------------------------------------------------------------- issue 13
# Hostile and careless input at msf-run: each case must end in exit 2 with one line naming the
# problem, and nothing written. Every case here passed silently, wrote wrong numbers or raised a
# traceback before issue 13.


def _npz(tmp: Path, **change: object) -> Path:
    """sphere_stack as an .npz, with arrays replaced or dropped (value None)."""
    s = sphere_stack()
    arrays: dict[str, object] = {
        "images": s.images,
        "lights": s.lights,
        "intensities": s.intensities,
        "mask": s.mask,
        "normals": s.normals_gt,
    }
    for key, value in change.items():
        if value is None:
            arrays.pop(key)
        else:
            arrays[key] = value
    path = tmp / "stack.npz"
    np.savez(path, **arrays)  # type: ignore[arg-type]
    return path


def _images_with(value: float, dtype: type = np.float32) -> np.ndarray:
    images = sphere_stack().images.astype(dtype)
    images[2, 10, 12, 1] = value
    return images


def _eight_bit_among_sixteen(d: Path) -> list[str]:
    img = cv2.imread(str(d / "004.png"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(d / "004.png"), (img // 257).astype(np.uint8))
    return [str(d)]


def _write_rows(path: Path, rows: list[str]) -> Path:
    path.write_text("\n".join(rows) + "\n")
    return path


def _light_rows(d: Path, rows: list[str]) -> list[str]:
    _write_rows(d / "light_directions.txt", rows)
    return [str(d)]


def _intensity_rows(d: Path, value: str) -> list[str]:
    _write_rows(d / "light_intensities.txt", [value] * 8)
    return [str(d)]


def _black(d: Path) -> list[str]:
    for i in range(1, 9):
        cv2.imwrite(str(d / f"{i:03d}.png"), np.zeros((36, 44, 3), np.uint16))
    return [str(d)]


def _saturated(d: Path) -> list[str]:
    for i in range(1, 9):
        cv2.imwrite(str(d / f"{i:03d}.png"), np.full((36, 44, 3), 65535, np.uint16))
    return [str(d)]


def _lights_behind(d: Path) -> list[str]:
    rows = [r.split() for r in (d / "light_directions.txt").read_text().splitlines()]
    return _light_rows(d, [f"{x} {y} {-float(z)}" for x, y, z in rows])


def _zero_ground_truth(d: Path) -> list[str]:
    from scipy.io import savemat

    savemat(str(d / "Normal_gt.mat"), {"Normal_gt": np.zeros((36, 44, 3))})
    return [str(d)]


def _model_with(tmp: Path, d: Path, **meta: str) -> list[str]:
    from _runtime_helpers import tiny_msfnet_onnx

    return [str(d), "--onnx", str(tiny_msfnet_onnx(tmp / "crafted.onnx", **meta))]


def _random_bytes_npz(tmp: Path) -> list[str]:
    path = tmp / "random.npz"
    path.write_bytes(np.random.default_rng(0).bytes(4000))
    return [str(path)]


# name: (argv builder(tmp, stack_dir) -> argv, words in the message, words NOT in it)
HOSTILE: dict[str, tuple[Callable[[Path, Path], list[str]], list[str], list[str]]] = {
    # silently wrong numbers before
    "npz NaN pixel": (
        lambda t, d: [str(_npz(t, images=_images_with(np.nan)))],
        ["stack.npz", "NaN"],
        [],
    ),
    "npz inf pixel": (
        lambda t, d: [str(_npz(t, images=_images_with(np.inf)))],
        ["stack.npz", "infinite"],
        [],
    ),
    "npz negative pixel": (
        lambda t, d: [str(_npz(t, images=_images_with(-3.0)))],
        ["stack.npz", "negative"],
        [],
    ),
    "npz negative int16 pixel": (
        lambda t, d: [str(_npz(t, images=_images_with(-3, np.int16)))],
        ["negative"],
        [],
    ),
    "npz float64 beyond float32": (
        lambda t, d: [str(_npz(t, images=_images_with(1e300, np.float64)))],
        ["float32 range"],
        [],
    ),
    "npz string images": (lambda t, d: [str(_npz(t, images=np.array(["a", "b"])))], ["dtype"], []),
    "8-bit image among 16-bit": (
        lambda t, d: _eight_bit_among_sixteen(d),
        ["004.png", "uint8", "one bit depth"],
        [],
    ),
    "all lights equal": (lambda t, d: _light_rows(d, ["0.1 0.2 0.9"] * 8), ["do not span 3-D"], []),
    "lights in one plane": (
        lambda t, d: _light_rows(
            d, [f"{np.cos(a):.6f} {np.sin(a):.6f} 0" for a in np.linspace(0, 3, 8)]
        ),
        ["do not span 3-D"],
        [],
    ),
    "--select 1,1,1": (lambda t, d: [str(d), "--select", "1,1,1"], ["more than once"], []),
    "--select 2,3,2,4": (lambda t, d: [str(d), "--select", "2,3,2,4"], ["image 2"], []),
    "intensities 1e-40": (
        lambda t, d: _intensity_rows(d, "1e-40 1e-40 1e-40"),
        ["light intensity", "outside"],
        [],
    ),
    "intensities 1e30": (
        lambda t, d: _intensity_rows(d, "1e30 1e30 1e30"),
        ["light intensity", "outside"],
        [],
    ),
    "black stack": (lambda t, d: _black(d), ["black"], []),
    "ground truth all zero": (lambda t, d: _zero_ground_truth(d), ["ground-truth"], []),
    # tracebacks before
    "--select 5-3": (lambda t, d: [str(d), "--select", "5-3"], ["runs backwards"], []),
    "--select 1-99999999999": (
        lambda t, d: [str(d), "--select", "1-99999999999"],
        ["outside 1..8"],
        [],
    ),
    "--select x-y": (lambda t, d: [str(d), "--select", "x-y"], ["1-based"], []),
    "output under a file": (
        lambda t, d: [str(d), "-o", str(_write_rows(t / "f", ["x"]) / "o")],
        ["is a file, not a folder"],
        [],
    ),
    "--max-memory below the stack (l2)": (
        lambda t, d: [str(d), "--max-memory", "0.05"],
        ["--max-memory 0.05 MB", "loaded"],
        [],
    ),
    "model metadata train_lights 0": (
        lambda t, d: _model_with(t, d, **{"msfnet.train_lights": "0"}),
        ["crafted.onnx", "train_lights"],
        [],
    ),
    "model metadata train_lights 1e9": (
        lambda t, d: _model_with(t, d, **{"msfnet.train_lights": "1000000000"}),
        ["train_lights"],
        [],
    ),
    "model metadata input_multiple 8": (
        lambda t, d: _model_with(t, d, **{"msfnet.input_multiple": "8"}),
        ["multiples of 8"],
        [],
    ),
    "model metadata static shape 0": (
        lambda t, d: _model_with(t, d, **{"msfnet.static_shape": "8,0,0"}),
        ["static_shape"],
        [],
    ),
    "--threads 100000 (model)": (
        lambda t, d: [*_model_with(t, d), "--threads", "100000"],
        ["--threads"],
        [],
    ),
    "model is a folder": (lambda t, d: [str(d), "--onnx", str(d.parent)], ["not a file"], []),
    # misleading messages before
    "light rows of 2 numbers": (
        lambda t, d: _light_rows(d, ["0.1 0.9"] * 8),
        ["3 numbers per row", "2"],
        ["8 images"],
    ),
    "npz lights of 2 columns": (
        lambda t, d: [str(_npz(t, lights=np.ones((8, 2))))],
        ["3 numbers per row", "(8, 2)"],
        ["8 images but 8"],
    ),
    "npz of random bytes": (lambda t, d: _random_bytes_npz(t), ["not an .npz"], ["pickle"]),
    "empty lights file": (lambda t, d: _light_rows(d, []), ["no rows"], []),
    "count line disagrees": (
        lambda t, d: _light_rows(d, ["12", *["0.1 0.2 0.9"] * 8]),
        ["says 12 rows but 8 follow"],
        [],
    ),
    "lights file is a folder": (
        lambda t, d: [str(d), "--lights", str(d.parent)],
        ["not a regular file"],
        ["not found"],
    ),
    # accepted with exit 0 and nonsense normals before (review of the edge runtime)
    "every light behind the object (z-away file)": (
        lambda t, d: _lights_behind(d),
        ["light_directions.txt", "toward the camera"],
        [],
    ),
    "every pixel saturated": (lambda t, d: _saturated(d), ["sphere", "saturated"], []),
    # "stack folder not found" for a file that is there
    "an image as the stack": (
        lambda t, d: [str(d / "001.png")],
        ["001.png", "not a supported stack", ".npz"],
        ["not found"],
    ),
    "an .npy as the stack": (
        lambda t, d: [str(_npy(t))],
        ["stack.npy", "not a supported"],
        ["not found"],
    ),
    # options silently ignored, or the wrong message, before
    "--workers on one stack": (lambda t, d: [str(d), "--workers", "4"], ["--workers", "--ray"], []),
    "--maps with --no-maps": (
        lambda t, d: [str(d), "--maps", "height", "--no-maps"],
        ["--maps", "--no-maps"],
        [],
    ),
    "--white-level without linearising": (
        lambda t, d: [str(d), "--white-level", "200"],
        ["--white-level", "--srgb or --gamma"],
        [],
    ),
}


def _npy(tmp: Path) -> Path:
    np.save(tmp / "stack.npy", sphere_stack().images)
    return tmp / "stack.npy"


@pytest.mark.parametrize("case", sorted(HOSTILE))
def test_hostile_input(case: str, stack_dir: Path, tmp_path: Path, capfd) -> None:
    build, words, absent = HOSTILE[case]
    out = tmp_path / "out" / "result"
    out.parent.mkdir()
    argv = build(tmp_path, stack_dir)
    method = [] if "--onnx" in argv else ["--method", "l2"]
    capfd.readouterr()
    try:
        code = main([*method, *argv] + ([] if "-o" in argv else ["-o", str(out)]))
    except SystemExit as exc:  # refused by the option parser (e.g. --threads' one validator)
        code = exc.code
    assert code == 2
    line = _assert_one_line_error(capfd, words)
    for word in absent:
        assert word not in line, line
    _no_outputs(out)


# data loss before: an --overwrite that would delete or replace an input is refused
DATA_LOSS: dict[str, Callable[[Path, Path], list[str]]] = {
    "-o PARENT_OF_STACK --overwrite": lambda t, d: [str(d), "-o", str(d.parent), "--overwrite"],
    "-o STACK --overwrite": lambda t, d: [str(d), "-o", str(d), "--overwrite"],
    "-o LIGHTS_FILE --overwrite": lambda t, d: [
        str(d),
        "--lights",
        str(d / "lights2.txt"),
        "-o",
        str(d / "lights2.txt"),
        "--overwrite",
    ],
    "-o symlink to the stack": lambda t, d: [
        str(d),
        "-o",
        str(_link(t / "link", d)),
        "--overwrite",
    ],
}


def _link(link: Path, target: Path) -> Path:
    link.symlink_to(target)
    return link


@pytest.mark.parametrize("case", sorted(DATA_LOSS))
def test_overwrite_never_touches_an_input(
    case: str, stack_dir: Path, tmp_path: Path, capfd
) -> None:
    (stack_dir / "lights2.txt").write_text((stack_dir / "light_directions.txt").read_text())
    before = {p: p.read_bytes() for p in stack_dir.parent.rglob("*") if p.is_file()}
    assert main(["--method", "l2", *DATA_LOSS[case](tmp_path, stack_dir)]) == 2
    _assert_one_line_error(capfd, ["input"])
    assert {p: p.read_bytes() for p in stack_dir.parent.rglob("*") if p.is_file()} == before


def test_disk_full_while_writing_is_one_line_and_leaves_nothing(
    stack_dir: Path, tmp_path: Path, monkeypatch, capfd
) -> None:
    """ENOSPC during the write of normals.npy (after the inference): one line, exit 2, no
    output folder and no staging left."""
    import errno

    def full(*args: object, **kwargs: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("msfnet.runtime.results.outputs.np.save", full)
    out = tmp_path / "out" / "result"
    out.parent.mkdir()
    assert main(["--method", "l2", str(stack_dir), "-o", str(out)]) == 2
    _assert_one_line_error(capfd, ["No space left on device"])
    _no_outputs(out)


def test_msf_eval_duplicate_object_names(stack_dir: Path, tmp_path: Path, capfd) -> None:
    from msfnet.runtime.cli.eval import main as eval_main

    root = stack_dir.parent
    (root / "objects.txt").write_text("sphere\nsphere 1-4\n")
    out = tmp_path / "ev"
    assert eval_main([str(root), "--l2-only", "-o", str(out)]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "listed twice" in err[0], err
    assert not out.exists()


def test_max_memory_message_quotes_the_users_value(stack_dir: Path, tmp_path: Path, capfd) -> None:
    from _runtime_helpers import tiny_msfnet_onnx

    model = tiny_msfnet_onnx(tmp_path / "tiny.onnx")
    out = tmp_path / "out"
    assert main(["--onnx", str(model), str(stack_dir), "-o", str(out), "--max-memory", "151"]) == 2
    _assert_one_line_error(capfd, ["--max-memory 151 MB"])


def test_a_black_image_among_lit_ones_is_one_warning_line(
    stack_dir: Path, tmp_path: Path, capfd
) -> None:
    """A dead light (image 5 all zero) ran silently with the MAE up from 3.8 to 14.9 deg: now
    a warning names the image (not an error: the other lights may suffice), and profile.json
    keeps it."""
    cv2.imwrite(str(stack_dir / "005.png"), np.zeros((36, 44, 3), np.uint16))
    out = tmp_path / "out"
    assert main(["--method", "l2", "--no-maps", str(stack_dir), "-o", str(out)]) == 0
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("msf-run: warning: "), err
    assert str(stack_dir / "005.png") in err[0] and "black" in err[0]
    profile = json.loads((out / "profile.json").read_text())
    assert profile["warnings"] == [err[0].removeprefix("msf-run: warning: ")]
    assert (
        main(["--method", "l2", "--no-maps", str(stack_dir), "-o", str(tmp_path / "q"), "-q"]) == 0
    )
    assert capfd.readouterr().err == ""  # -q: errors only


@pytest.mark.parametrize("roi", [["--roi", "-5,0,10,10"], ["--roi=-5,0,10,10"]])
def test_a_negative_roi_gets_the_roi_message(
    roi: list[str], stack_dir: Path, tmp_path: Path, capfd
) -> None:
    """argparse took "-5,0,10,10" for an option: "--roi: expected one argument"."""
    with pytest.raises(SystemExit) as exit_:
        main(["--method", "l2", str(stack_dir), *roi, "-o", str(tmp_path / "o")])
    assert exit_.value.code == 2
    line = _assert_one_line_error(capfd, ["--roi", "x and y must be >= 0"])
    assert "expected one argument" not in line
    _no_outputs(tmp_path / "o")
