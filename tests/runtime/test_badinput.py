"""Every bad input of issue 3 part 6: one error line naming the file, exit 2, no partial outputs."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
from _runtime_helpers import sphere_stack

from msfnet.runtime.run_cli import main
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
    "mismatched_counts": (lambda d: _drop_last_row(d / "light_directions.txt"),
                          "light_directions.txt", "7 light directions for 8 images"),
    "unreadable_image": (lambda d: (d / "003.png").write_bytes(b"not a png at all"),
                         "003.png", "cannot decode"),
    "truncated_image": (lambda d: _truncate(d / "005.png"), "005.png", "truncated"),
    "different_sizes": (lambda d: cv2.imwrite(str(d / "002.png"),
                                              np.zeros((20, 20, 3), np.uint16)),
                        "002.png", "but 001.png is"),
    "nan_light": (lambda d: _replace_row(d / "light_directions.txt", 2, "nan 0.1 0.9"),
                  "light_directions.txt", "NaN"),
    "zero_light": (lambda d: _replace_row(d / "light_directions.txt", 4, "0 0 0"),
                   "sphere", "zero-length light direction"),
    "two_lights": (_two_lights, "sphere", "at least 3 lights"),
    "zero_intensity": (lambda d: _replace_row(d / "light_intensities.txt", 1, "0 0 0"),
                       "light_intensities.txt", "positive"),
    "wrong_size_mask": (lambda d: cv2.imwrite(str(d / "mask.png"),
                                              np.full((10, 12), 255, np.uint8)),
                        "mask.png", "mask is 12x10 but images are 44x36"),
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
        [helper.make_node("Identity", ["images"], ["normals"])], "not_msfnet",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, None)],
        [helper.make_tensor_value_info("normals", TensorProto.FLOAT, None)])
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
    words = {"foreign": "not an msfnet model", "foreign_with_meta": "not an msfnet model",
             "garbage": "cannot load ONNX model", "missing": "not found"}[kind]
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
    assert (out / "normals.npy").stat().st_ino != first and (out / "normals.png").is_file()
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
