"""Memory bombs (issue #27, part B, item 7): every array source is sized from its header before
anything is decoded or inflated, and least squares stays within --max-memory.

Each case runs in a fresh interpreter that reports its peak resident memory (VmHWM: the
child's own address space) before and after the action: a bomb refused from its header leaves
the peak where it was, give or take a tolerance for the refusal's own work."""

from __future__ import annotations

import json
import struct
import subprocess
import sys
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pytest
from _runtime_helpers import sphere_stack

from msfnet.runtime.stack import save_stack

resource = pytest.importorskip("resource", reason="peak memory via resource (POSIX)")

TOLERANCE_MB = 60  # the refusal's own work (headers, imports it triggers), far below any bomb

CHILD = """
import json, sys
from pathlib import Path

from msfnet.runtime.instrument import peak_rss_mb as peak_mb  # VmHWM: not the parent's

from msfnet.common.errors import InputError
from msfnet.runtime.stack import LoadOptions, load_stack
before = peak_mb()
try:
    load_stack(Path(sys.argv[1]), LoadOptions(max_memory_mb=float(sys.argv[2])))
    said = None
except InputError as exc:
    said = str(exc)
print(json.dumps({"before": before, "after": peak_mb(), "error": said}))
"""


def _load_in_child(path: Path, budget_mb: float = 256) -> dict:
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, str(path), str(budget_mb)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-800:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    body = kind + data
    return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))


def write_png_bomb(path: Path, width: int, height: int) -> Path:
    """A valid 1-bit grey PNG of ``width`` x ``height`` black pixels: a few hundred KB on
    disk, ``width * height`` bytes once OpenCV decodes it (to 8 bits)."""
    row = b"\0" * (1 + (width + 7) // 8)  # filter byte + packed pixels
    deflate = zlib.compressobj(9)
    parts = [deflate.compress(row * 500) for _ in range(height // 500)]
    parts += [deflate.compress(row * (height % 500)), deflate.flush()]
    ihdr = struct.pack(">IIBBBBB", width, height, 1, 0, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + _png_chunk(b"IHDR", ihdr)
        + _png_chunk(b"IDAT", b"".join(parts))
        + _png_chunk(b"IEND", b"")
    )
    return path


def write_mat_bomb(path: Path, name: str, dims: tuple[int, ...]) -> Path:
    """A MATLAB v5 file holding one compressed double array of zeros of ``dims``: inflated by
    scipy.io.loadmat to 8 bytes a value."""
    count = int(np.prod(dims))

    def element(kind: int, data: bytes) -> bytes:
        return struct.pack("<II", kind, len(data)) + data + b"\0" * (-len(data) % 8)

    flags = element(6, struct.pack("<II", 6, 0))  # miUINT32: mxDOUBLE_CLASS, no flags
    shape = element(5, struct.pack(f"<{len(dims)}i", *dims))  # miINT32
    label = element(1, name.encode())  # miINT8
    head = flags + shape + label + struct.pack("<II", 9, count * 8)  # miDOUBLE, its size
    matrix_tag = struct.pack("<II", 14, len(head) + count * 8 + (-(count * 8) % 8))
    deflate = zlib.compressobj(6)
    parts = [deflate.compress(matrix_tag + head)]
    block = bytes(2**22)
    left = count * 8
    while left > 0:
        parts.append(deflate.compress(block[: min(left, len(block))]))
        left -= len(block)
    parts.append(deflate.flush())
    body = b"".join(parts)
    header = b"MATLAB 5.0 MAT-file, hostile test".ljust(116) + bytes(8)
    header += struct.pack("<H", 0x0100) + b"IM"
    path.write_bytes(header + struct.pack("<II", 15, len(body)) + body)
    return path


def test_mat_bomb_writer_writes_what_scipy_reads(tmp_path: Path) -> None:
    """The bomb below is a real .mat file: the same writer, small, reads back in scipy."""
    scipy_io = pytest.importorskip("scipy.io")
    got = scipy_io.loadmat(str(write_mat_bomb(tmp_path / "a.mat", "Normal_gt", (4, 5, 3))))
    assert got["Normal_gt"].shape == (4, 5, 3) and not got["Normal_gt"].any()


@pytest.fixture
def small_stack(tmp_path: Path) -> Path:
    return save_stack(sphere_stack(n=6, h=36, w=44), tmp_path / "s")


def _assert_refused_flat(result: dict, words: str) -> None:
    assert result["error"] is not None and words in result["error"], result
    grew = result["after"] - result["before"]
    assert grew < TOLERANCE_MB, f"peak grew {grew:.0f} MB before the refusal: {result}"


@pytest.mark.slow
def test_a_huge_mask_png_is_refused_before_decoding(small_stack: Path) -> None:
    """248 MP mask (under the 250 MP image limit): decoded to 248 MB, then compared."""
    write_png_bomb(small_stack / "mask.png", 16_500, 15_000)
    _assert_refused_flat(_load_in_child(small_stack), "mask is 16500x15000 but images are 44x36")


@pytest.mark.slow
def test_a_huge_ground_truth_png_is_refused_before_decoding(small_stack: Path) -> None:
    for old in small_stack.glob("Normal_gt.*"):
        old.unlink()
    write_png_bomb(small_stack / "Normal_gt.png", 16_500, 15_000)
    _assert_refused_flat(_load_in_child(small_stack), "ground truth is 16500x15000")


@pytest.mark.slow
def test_a_compressed_ground_truth_mat_is_refused_before_inflating(small_stack: Path) -> None:
    """600 MB of doubles in 0.6 MB of file; scipy.io.loadmat inflates all of it."""
    for old in small_stack.glob("Normal_gt.*"):
        old.unlink()
    write_mat_bomb(small_stack / "Normal_gt.mat", "Normal_gt", (5000, 5000, 3))
    _assert_refused_flat(_load_in_child(small_stack), "ground truth is 5000x5000")


@pytest.mark.slow
def test_large_frames_after_a_small_first_are_refused_before_decoding(tmp_path: Path) -> None:
    """The old loader decoded frame 1, checked the budget with its size, then decoded the
    rest in threads before comparing sizes: four 240 MP frames at once."""
    folder = save_stack(sphere_stack(n=6, h=36, w=44), tmp_path / "s")
    big = write_png_bomb(tmp_path / "big.png", 16_000, 15_000)
    for i in range(2, 7):
        (folder / f"{i:03d}.png").unlink()
        (folder / f"{i:03d}.png").hardlink_to(big)
    result = _load_in_child(folder, budget_mb=100_000)  # the budget is not what stops it
    _assert_refused_flat(result, "image is 16000x15000 but 001.png is 44x36")


@pytest.mark.slow
def test_an_npz_member_other_than_images_is_sized_before_inflating(tmp_path: Path) -> None:
    """'normals' of 600 MB zeros, compressed: np.load inflates a member when it is read."""
    ref = sphere_stack(n=6, h=36, w=44)
    path = tmp_path / "s.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        for key, arr in (("images", ref.images), ("lights", ref.lights)):
            with z.open(f"{key}.npy", "w") as f:
                np.lib.format.write_array(f, np.asarray(arr))
        with z.open("normals.npy", "w", force_zip64=True) as f:
            shape = (5000, 5000, 3)
            np.lib.format.write_array_header_1_0(
                f, {"descr": "<f8", "fortran_order": False, "shape": shape}
            )
            block = bytes(2**22)
            left = 5000 * 5000 * 3 * 8
            while left > 0:
                f.write(block[: min(left, len(block))])
                left -= len(block)
    _assert_refused_flat(_load_in_child(path), "npz array 'normals' is (5000, 5000, 3)")


LEAST_SQUARES = """
import json, sys
import numpy as np
from msfnet.runtime.stack import Stack
from msfnet.runtime.infer.least_squares import least_squares_normals

budget, n, h, w = float(sys.argv[1]), 32, 500, 540
rng = np.random.default_rng(0)
lights = rng.normal(size=(n, 3))
lights[:, 2] = np.abs(lights[:, 2]) + 1.0
images = np.empty((n, h, w, 3), np.float32)  # 104 MB, filled a light at a time
for i in range(n):
    images[i] = rng.uniform(100.0, 60000.0, (h, w, 1)).astype(np.float32)
stack = Stack.from_arrays(images, lights)
del images
out = least_squares_normals(stack, trim_shadows=0.2, max_memory_mb=budget)
# VmHWM on Linux: ru_maxrss would count the test runner's size at fork time (kept over exec)
from msfnet.runtime.instrument import peak_rss_mb
peak = peak_rss_mb()
print(json.dumps({"peak": peak, "stack": stack.images.nbytes / 2**20, "ok": bool(out.any())}))
"""


@pytest.mark.slow
@pytest.mark.parametrize("budget_mb", [330, 380])
def test_least_squares_keeps_the_whole_process_within_max_memory(budget_mb: float) -> None:
    """The budget is the process's: the interpreter, the stack and the output count too (the
    old bands took the budget minus the stack alone, so the process ran over it)."""
    proc = subprocess.run(
        [sys.executable, "-c", LEAST_SQUARES, str(budget_mb)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-800:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["ok"]
    assert result["peak"] <= budget_mb, result
