"""The Blobby / Sculpture loader, on a tiny generated fake of that layout; samples of integer
stacks."""

from __future__ import annotations

import numpy as np
import pytest
from _runtime_helpers import as_float32, png_stack

pytest.importorskip("torch", reason="needs torch: the [train] extra")

from msfnet.common.errors import InputError
from msfnet.common.imageio import write_png
from msfnet.model.data import BlobbySource, find_blobby_samples, load_blobby_sample, make_sample
from msfnet.runtime.evaluate.metrics import deviation_deg
from msfnet.runtime.stack import load_stack
from msfnet.synth.shapes import sphere_normals


def _fake_root(root, shapes=("blob01", "blob02"), materials=("alum", "gold"), n=5):
    normals, mask = sphere_normals(16)
    rng = np.random.default_rng(0)
    for shape in shapes:
        folder = root / "Images" / shape
        folder.mkdir(parents=True)
        enc = np.where(mask[..., None], np.rint((normals + 1) / 2 * 255), 0).astype(np.uint8)
        write_png(folder / f"{shape}_normal.png", enc)
        for mat in materials:
            mdir = folder / f"{shape}_{mat}"
            mdir.mkdir()
            lines = []
            for i in range(n):
                d = rng.normal([0, 0, 3], 0.5)
                d /= np.linalg.norm(d)
                img = np.clip(np.einsum("hwc,c->hw", normals, d), 0, 1) * 200
                write_png(mdir / f"l_{i:03d}.png", np.repeat(img[..., None], 3, 2).astype(np.uint8))
                lines.append(f"l_{i:03d}.png {d[0]:.6f} {d[1]:.6f} {d[2]:.6f}")
            (mdir / f"{shape}_{mat}.txt").write_text("\n".join(lines) + "\n")
    return normals, mask


def test_blobby_layout_is_found_and_loaded(tmp_path):
    normals, mask = _fake_root(tmp_path)
    pairs = find_blobby_samples(tmp_path)
    assert len(pairs) == 4
    s = load_blobby_sample(*pairs[1])
    assert s.images.shape == (5, 16, 16, 3) and s.name == "blob01/blob01_gold"
    assert s.images.dtype == np.uint8  # held as decoded; make_sample casts each crop
    np.testing.assert_array_equal(s.mask, mask)
    assert deviation_deg(s.normals_gt, normals, mask)[1] < 1.0  # 8-bit encoding
    src = BlobbySource(tmp_path, cache=2)
    b = src.batch(3, 4, 8, np.random.default_rng(0))
    assert tuple(b.images.shape) == (3, 4, 3, 8, 8) and tuple(b.normals.shape) == (3, 3, 8, 8)


def test_blobby_errors_name_the_file(tmp_path):
    with pytest.raises(InputError, match=r"no '<shape>_normal\.png'"):
        find_blobby_samples(tmp_path)
    _fake_root(tmp_path, shapes=("s",), materials=("m",), n=3)
    lst = tmp_path / "Images" / "s" / "s_m" / "s_m.txt"
    lst.write_text("l_000.png 0 0\n")
    with pytest.raises(InputError, match=r"s_m\.txt"):
        load_blobby_sample(*find_blobby_samples(tmp_path)[0])


@pytest.mark.parametrize("bits", [8, 16])
def test_samples_of_an_integer_stack_equal_the_float32_ones(tmp_path, bits):
    """make_sample casts the crop before noise, jitter and normalisation: an integer stack
    gives the float32 copy's training sample."""
    held = load_stack(png_stack(tmp_path / "s", bits, n=10, h=40, w=48))
    assert held.images.dtype == (np.uint8 if bits == 8 else np.uint16)
    got = make_sample(held, 6, 32, np.random.default_rng(3))
    want = make_sample(as_float32(held), 6, 32, np.random.default_rng(3))
    for a, b in zip(got, want, strict=True):
        np.testing.assert_array_equal(a, b)
