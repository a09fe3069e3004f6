"""Loaders hold images in the type they were stored in (uint8 / uint16) unless a value changes
(downscale, linearisation: float32); floats and other types become float32. --max-memory counts
the type actually held."""

from __future__ import annotations

import os
import tracemalloc
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from _runtime_helpers import as_float32, png_stack, sphere_stack, write_npz_bomb

from msfnet.common.errors import InputError
from msfnet.common.imageio import read_image
from msfnet.runtime.stack import (
    LoadOptions,
    Stack,
    check_stack_size,
    held_dtype,
    load_stack,
    prepare_stack,
    save_stack,
)


@pytest.mark.parametrize(("bits", "dtype"), [(8, np.uint8), (16, np.uint16)])
def test_png_stack_is_held_as_decoded(tmp_path: Path, bits: int, dtype: type) -> None:
    folder = png_stack(tmp_path / "s", bits, n=6)
    s = load_stack(folder)
    assert s.images.dtype == dtype
    assert s.images.nbytes == 6 * 36 * 44 * 3 * np.dtype(dtype).itemsize
    for name, img in zip(s.filenames, s.images, strict=True):
        np.testing.assert_array_equal(img, read_image(folder / name))
    assert int(s.images.max()) > (150 if bits == 8 else 30000)  # most of the range is used


def test_roi_alone_keeps_the_integer_type(tmp_path: Path) -> None:
    folder = png_stack(tmp_path / "s", 16, n=5)
    full = load_stack(folder)
    crop = load_stack(folder, roi=(4, 2, 30, 28))
    assert crop.images.dtype == np.uint16 and crop.shape == (28, 30)
    np.testing.assert_array_equal(crop.images, full.images[:, 2:30, 4:34])
    in_memory = prepare_stack(full, LoadOptions(roi=(4, 2, 30, 28)))
    assert in_memory.images.dtype == np.uint16
    np.testing.assert_array_equal(in_memory.images, crop.images)


@pytest.mark.parametrize(
    "options",
    [dict(downscale=2), dict(srgb=True), dict(gamma=2.2), dict(roi=(0, 0, 40, 30), downscale=2)],
)
def test_value_transforms_give_float32(tmp_path: Path, options: dict) -> None:
    """Block means and linear values are fractions: those stacks stay float32, computed from
    the stored integers exactly as before."""
    folder = png_stack(tmp_path / "s", 8, n=5)
    s = load_stack(folder, **options)
    assert s.images.dtype == np.float32
    from_float = prepare_stack(
        as_float32(load_stack(folder)), LoadOptions(**options, white_level=255.0)
    )
    np.testing.assert_array_equal(s.images, from_float.images)


def test_grey_pngs_become_rgb_of_their_type(tmp_path: Path) -> None:
    ref = sphere_stack(n=4)
    folder = tmp_path / "g"
    folder.mkdir()
    for i, img in enumerate(ref.images):
        cv2.imwrite(str(folder / f"{i:02d}.png"), np.rint(img[..., 0]).astype(np.uint16))
    np.savetxt(folder / "light_directions.txt", ref.lights)
    s = load_stack(folder)
    assert s.images.dtype == np.uint16 and s.images.shape == (4, 36, 44, 3)
    np.testing.assert_array_equal(s.images[..., 0], s.images[..., 2])
    np.testing.assert_array_equal(s.images[1, ..., 1], np.rint(ref.images[1, ..., 0]))


def test_float_tiff_stays_float32(tmp_path: Path) -> None:
    ref = sphere_stack(n=4)
    folder = tmp_path / "f"
    folder.mkdir()
    for i, img in enumerate(ref.images):
        assert cv2.imwrite(str(folder / f"{i:02d}.tiff"), (img / 65535)[:, :, ::-1])
    np.savetxt(folder / "light_directions.txt", ref.lights)
    s = load_stack(folder)
    assert s.images.dtype == np.float32
    np.testing.assert_array_equal(s.images, ref.images / np.float32(65535))


@pytest.mark.parametrize(
    ("stored", "held"),
    [
        (np.uint8, np.uint8),
        (np.uint16, np.uint16),
        (np.float32, np.float32),
        (np.float64, np.float32),
        (np.int32, np.float32),
        (np.float16, np.float32),
    ],
)
def test_npz_keeps_uint8_and_uint16(tmp_path: Path, stored: type, held: type) -> None:
    ref = sphere_stack(n=5)
    images = np.rint(
        ref.images * np.float32(255 / 65535)
        if stored == np.uint8
        else ref.images / 64
        if stored == np.float16
        else ref.images
    )
    path = tmp_path / "s.npz"
    np.savez(path, images=images.astype(stored), lights=ref.lights, mask=ref.mask)
    s = load_stack(path)
    assert s.images.dtype == held == held_dtype(stored)
    np.testing.assert_array_equal(s.images, images.astype(stored).astype(held))


def test_from_arrays_holds_the_same_types() -> None:
    ref = sphere_stack(n=5)
    ints = np.rint(ref.images).astype(np.uint16)
    assert Stack.from_arrays(ints, ref.lights).images.dtype == np.uint16
    assert Stack.from_arrays(ints[..., 0], ref.lights).images.dtype == np.uint16  # grey
    as64 = Stack.from_arrays(ints.astype(np.float64), ref.lights).images
    assert as64.dtype == np.float32
    np.testing.assert_array_equal(as64, ints)
    assert Stack.from_arrays(ints.astype(np.int32), ref.lights).images.dtype == np.float32


@pytest.mark.parametrize(
    ("bits", "options", "said", "mb"),
    [
        (16, {}, "0.88", 0.879),  # 8 x 120 x 160 x 3 values of 2 bytes
        (8, {}, "0.44", 0.439),
        (8, {"gamma": 2.2}, "2", 1.758),  # linearised: float32
        (16, {"downscale": 2}, "0.44", 0.439),  # float32, a quarter of the pixels
    ],
)
def test_max_memory_counts_the_type_held(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, bits: int, options: dict, said: str, mb: float
) -> None:
    folder = png_stack(tmp_path / "s", bits, n=8, h=120, w=160)
    import msfnet.runtime.stack.load as load

    decoded: list[Path] = []
    real = load.read_image
    monkeypatch.setattr(load, "read_image", lambda p, *a: decoded.append(p) or real(p, *a))
    with pytest.raises(InputError, match=rf"take {said} MB loaded, above max_memory_mb=0.1 MB"):
        load_stack(folder, LoadOptions(max_memory_mb=0.1, **options))
    assert decoded == []  # refused from the headers, before decoding any image
    s = load_stack(folder, LoadOptions(max_memory_mb=mb * 1.01, **options))
    assert s.images.nbytes / 2**20 == pytest.approx(mb, abs=0.001)


def test_npz_header_is_counted_in_its_held_type(tmp_path: Path) -> None:
    """A 16-bit bomb is refused from the header at 2 bytes a value, without inflating it."""
    path = write_npz_bomb(tmp_path / "bomb16.npz", "<u2", (32, 2048, 2048, 3))
    with pytest.raises(InputError, match="take 768 MB loaded"):
        load_stack(path, LoadOptions(max_memory_mb=512))
    with pytest.raises(InputError, match="take 1536 MB loaded"):
        check_stack_size(32, 2048, 2048, 512, path)  # the float32 default
    with pytest.raises(InputError, match="take 384 MB loaded"):
        check_stack_size(32, 2048, 2048, 256, path, np.uint8)


def test_decoding_holds_one_stack_not_two(tmp_path: Path) -> None:
    """Each image is copied into the stack as it is decoded: no list of decoded images beside
    the stack (which doubled the peak), and no float32 copy (which tripled it)."""
    no_gt = replace(sphere_stack(n=24, h=120, w=160), normals_gt=None)  # images only
    folder = save_stack(no_gt, tmp_path / "s")
    tracemalloc.start()
    try:
        s = load_stack(folder, threads=1)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert s.images.dtype == np.uint16
    print(f"load peak {peak / 2**20:.2f} MB for a {s.images.nbytes / 2**20:.2f} MB stack")
    assert peak < 1.3 * s.images.nbytes


@pytest.mark.parametrize("name", ["001.png", "stack.npy", "notes.txt"])
def test_a_file_that_is_no_stack_is_named_as_such(tmp_path: Path, name: str) -> None:
    """It exists: "stack folder not found" sent users looking for a typo."""
    folder = save_stack(sphere_stack(n=4), tmp_path / "s")
    path = folder / "001.png" if name == "001.png" else tmp_path / name
    if name == "stack.npy":
        np.save(path, sphere_stack(n=4).images)
    elif name == "notes.txt":
        path.write_text("x")
    with pytest.raises(InputError, match=r"not a supported stack: expected a folder .* \.npz"):
        load_stack(path)
    with pytest.raises(InputError, match="stack folder not found"):
        load_stack(tmp_path / "missing")


def test_only_an_image_named_like_a_mask_is_the_mask(tmp_path: Path) -> None:
    """Without mask.png a file like ``cat.mask.tga`` is the mask; a text file or a macOS
    ``._mask.png`` with "mask" in the name is not (it failed as "cannot decode image")."""
    stack = sphere_stack(n=4)
    folder = save_stack(stack, tmp_path / "s")
    (folder / "mask.png").rename(folder / "obj.mask.png")
    (folder / "mask_notes.txt").write_text("threshold 127")
    (folder / "._mask.png").write_bytes(b"\x00\x05\x16\x07 AppleDouble")
    np.testing.assert_array_equal(load_stack(folder).mask, stack.mask)
    (folder / "obj.mask.png").unlink()
    assert load_stack(folder).mask.all()  # no mask: every pixel


def test_a_folder_load_parses_its_mat_ground_truth_once(
    tmp_path: Path, mat_parses: list[Path]
) -> None:
    """The header check before the read hands its parse to read_normals: one parse of the
    .mat headers per load (there were four: two in the check, two in the read)."""
    folder = png_stack(tmp_path / "s", 8, n=4)
    gt = folder / "Normal_gt.mat"
    assert gt.is_file()
    mat_parses.clear()  # writing the stack did not parse; from here on, the load
    stack = load_stack(folder)
    assert mat_parses == [gt]
    assert stack.normals_gt is not None and stack.normals_gt.shape == (36, 44, 3)


def test_a_frame_replaced_after_the_header_check_is_refused_before_decoding(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Headers are all read before any frame is decoded; a frame swapped for one of another
    size in between must be refused from its own header, not decoded into the stack."""
    import msfnet.runtime.stack.load as load_module

    folder = png_stack(tmp_path / "s", 16)
    frames = sorted(folder.glob("0*.png"))
    assert len(frames) >= 2
    original = load_module.check_headers

    def check_then_swap(*args, **kwargs):  # type: ignore[no-untyped-def]
        stored = original(*args, **kwargs)
        cv2.imwrite(str(frames[1]), np.zeros((20, 30, 3), np.uint16))
        return stored

    import msfnet.common.imageio as imageio

    decoded: list[Path] = []
    decode = imageio._decode_with_opencv

    def recording_decode(data: bytes, path: Path, listen: bool = False) -> np.ndarray | None:
        decoded.append(Path(path))
        return decode(data, path, listen)

    monkeypatch.setattr(load_module, "check_headers", check_then_swap)
    monkeypatch.setattr(imageio, "_decode_with_opencv", recording_decode)
    with pytest.raises(InputError) as err:
        load_stack(folder)
    line = str(err.value)
    assert "\n" not in line and frames[1].name in line and "30x20" in line
    assert frames[0] in decoded and frames[1] not in decoded  # refused from its header


def test_an_npz_member_declaring_a_huge_npy_header_is_refused_before_it_inflates(
    tmp_path: Path,
) -> None:
    """A zip member of a few KB can inflate to the 4 GB of header its length field declares;
    numpy's reader would inflate it all before refusing it. Refused from the field, with no
    more than a small buffer ever inflated."""
    import struct
    import zipfile

    path = tmp_path / "bomb.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        with z.open("images.npy", "w", force_zip64=True) as f:
            f.write(b"\x93NUMPY\x02\x00" + struct.pack("<I", 2**32 - 1))
            for _ in range(64):
                f.write(b" " * 2**20)  # 64 MB of "header": about 64 KB deflated
        with z.open("lights.npy", "w") as f:
            np.save(f, np.eye(3, dtype=np.float32))
    tracemalloc.start()
    try:
        with pytest.raises(InputError, match=r"a header of 4,294,967,295 bytes declared") as e:
            load_stack(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert "\n" not in str(e.value) and str(e.value).startswith(str(path))
    assert peak < 16 * 2**20, peak  # numpy's reader: the 64 MB inflated, twice (bytes, str)


@pytest.mark.parametrize("name", ["light_intensities.txt", "mask.png", "filenames.txt"])
@pytest.mark.parametrize("kind", ["dangling", "folder", "fifo"])
def test_a_stack_file_that_is_there_but_unreadable_is_refused(
    tmp_path: Path, name: str, kind: str
) -> None:
    """Found with is_file(), a moved intensities file (a dangling link) ran with unit
    intensities (4.5 -> 12.5 deg, no word) and a dangling mask as no mask."""
    import os

    folder = png_stack(tmp_path / "s", 16)
    target = folder / name
    if target.exists():
        target.unlink()
    if kind == "dangling":
        target.symlink_to(tmp_path / "moved" / name)
    elif kind == "folder":
        target.mkdir()
    else:
        os.mkfifo(target)
    with pytest.raises(InputError, match=r"dangling link|is a folder|not a regular file") as e:
        load_stack(folder)
    assert name in str(e.value)


@pytest.mark.parametrize("entry", ["../other/003.png", "/tmp/003.png", "sub/../../003.png"])
def test_filenames_txt_may_not_reach_outside_the_stack(tmp_path: Path, entry: str) -> None:
    """An image read from outside the folder is an input no output check knows of: an
    --overwrite could delete the image just read."""
    folder = png_stack(tmp_path / "s", 16)
    names = (folder / "filenames.txt").read_text().splitlines()
    names[2] = entry
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    with pytest.raises(InputError, match="outside the stack folder"):
        load_stack(folder)


def test_an_empty_mask_file_is_named(tmp_path: Path) -> None:
    """An all-black --mask was reported as the stack's problem, not the mask file's."""
    folder = png_stack(tmp_path / "s", 16)
    black = tmp_path / "black.png"
    cv2.imwrite(str(black), np.zeros((36, 44), np.uint8))
    with pytest.raises(InputError, match="mask is empty") as e:
        load_stack(folder, LoadOptions(mask=black))
    assert "black.png" in str(e.value)


def test_load_options_describe_the_files_given_in_place_of_the_stacks_own() -> None:
    """profile.json's ``input`` had no trace of LoadOptions(lights=...): a result computed
    with a mirrored light file did not say which file it used."""
    opts = LoadOptions(lights="rig/lights.txt", intensities=Path("rig/ints.txt"), mask="m.png")
    info = opts.describe()
    assert (info["lights"], info["intensities"], info["mask"]) == (
        "rig/lights.txt",
        "rig/ints.txt",
        "m.png",
    )
    assert not {"lights", "intensities", "mask"} & set(LoadOptions(select="1-3").describe())


def test_load_options_constructor_hints_take_str_paths() -> None:
    """``LoadOptions(lights="rig/lights.txt")`` (the README's line) works, but its hints said
    Path: a type error for mypy and pyright. The hints a checker reads are the constructor
    written out under TYPE_CHECKING; it must stay the fields' list, in order, with their
    defaults."""
    import ast
    import dataclasses
    import inspect

    from msfnet.runtime.stack import load as module

    tree = ast.parse(inspect.getsource(module))
    cls = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "LoadOptions")
    guarded = next(n for n in cls.body if isinstance(n, ast.If))
    assert ast.unparse(guarded.test) == "TYPE_CHECKING"
    init = next(n for n in guarded.body if isinstance(n, ast.FunctionDef))
    args = init.args.args[1:]
    fields = dataclasses.fields(LoadOptions)
    assert [a.arg for a in args] == [f.name for f in fields]
    assert [ast.literal_eval(d) for d in init.args.defaults] == [f.default for f in fields]
    hints = {a.arg: ast.unparse(a.annotation) for a in args if a.annotation is not None}
    for name in ("lights", "intensities", "mask"):
        assert hints[name] == "str | PathLike[str] | None"
        assert isinstance(getattr(LoadOptions(**{name: "x.txt"}), name), Path)  # held as Path
    assert all(
        hints[f.name] == f.type for f in fields if f.name not in ("lights", "intensities", "mask")
    )


# ------------------------------------------------- review-stack23.md: inputs read wrongly


def test_a_json_light_file_brings_its_intensities(tmp_path: Path) -> None:
    """They were dropped without a word (unit intensities: 4 deg off on a coloured rig), and
    all-zero ones were accepted."""
    import json

    folder = png_stack(tmp_path / "s", 16)
    lights = np.loadtxt(folder / "light_directions.txt")
    ints = np.loadtxt(folder / "light_intensities.txt")
    ints[:, 0] *= 2.0  # a coloured rig
    (folder / "light_intensities.txt").unlink()
    (folder / "light_directions.txt").unlink()
    own = {"lights": lights.tolist(), "intensities": ints.tolist()}
    (folder / "lights.json").write_text(json.dumps(own))
    stack = load_stack(folder)
    np.testing.assert_allclose(stack.intensities, ints, rtol=1e-6)

    (folder / "light_intensities.txt").write_text("1 1 1\n" * len(ints))  # given twice
    with pytest.raises(InputError, match="intensities are given twice"):
        load_stack(folder)
    # named with --lights, the JSON overrides the folder's files, intensities included
    (folder / "lights.json").rename(tmp_path / "rig.json")
    (folder / "light_directions.txt").write_text("0 0 1\n" * len(ints))
    stack = load_stack(folder, LoadOptions(lights=tmp_path / "rig.json"))
    np.testing.assert_allclose(stack.intensities, ints, rtol=1e-6)
    (folder / "light_directions.txt").unlink()
    (tmp_path / "rig.json").rename(folder / "lights.json")
    (folder / "light_intensities.txt").unlink()

    zero = {"lights": lights.tolist(), "intensities": [[0, 0, 0]] * len(ints)}
    (folder / "lights.json").write_text(json.dumps(zero))
    with pytest.raises(InputError, match="positive"):
        load_stack(folder)


def test_an_npz_member_of_no_known_name_is_refused(tmp_path: Path) -> None:
    """'light_intensities' for 'intensities' ran on unit intensities, 4 deg off, exit 0."""
    s = sphere_stack()
    arrays = {"images": s.images, "lights": s.lights, "mask": s.mask}
    np.savez(tmp_path / "typo.npz", **arrays, light_intensities=s.intensities)
    with pytest.raises(InputError, match="'light_intensities' is not one of a stack's"):
        load_stack(tmp_path / "typo.npz")
    np.savez(tmp_path / "wide.npz", images=s.images, lights=np.c_[s.lights, np.ones(8)])
    with pytest.raises(InputError, match="3 numbers per row"):
        load_stack(tmp_path / "wide.npz")
    np.savez(tmp_path / "ok.npz", **arrays, intensities=s.intensities)
    assert load_stack(tmp_path / "ok.npz").num_lights == 8


def test_one_grey_image_among_colour_ones_is_refused(tmp_path: Path) -> None:
    """It was spread over R, G and B: a coloured object's normals 0.7 deg off, no word."""
    folder = png_stack(tmp_path / "s", 16)
    third = folder / sorted(p.name for p in folder.glob("0*.png"))[2]
    grey = cv2.cvtColor(cv2.imread(str(third), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGR2GRAY)
    cv2.imwrite(str(third), grey)
    with pytest.raises(InputError, match=r"image is grey but .* is colour"):
        load_stack(folder)


def test_a_link_loop_in_filenames_txt_is_one_error(tmp_path: Path) -> None:
    """It was "internal error: RuntimeError: Symlink loop", exit 1."""
    folder = png_stack(tmp_path / "s", 16)
    names = (folder / "filenames.txt").read_text().split()
    (folder / names[2]).unlink()
    (folder / names[2]).symlink_to(names[2])
    with pytest.raises(InputError) as err:
        load_stack(folder)
    assert err.value.path is not None and Path(err.value.path).name == names[2]


def test_a_stack_given_as_dot_has_its_folders_name(tmp_path: Path, monkeypatch) -> None:
    folder = png_stack(tmp_path / "part", 16)
    monkeypatch.chdir(folder)
    assert load_stack(Path(".")).name == "part"


def test_a_linked_duplicate_photo_is_refused_with_or_without_filenames_txt(
    tmp_path: Path,
) -> None:
    folder = png_stack(tmp_path / "s", 16, n=8)
    names = (folder / "filenames.txt").read_text().split()
    lights = (folder / "light_directions.txt").read_text().splitlines()
    (folder / "light_directions.txt").write_text("\n".join([*lights, lights[0]]) + "\n")
    (folder / "light_intensities.txt").unlink()
    (folder / "zz.png").symlink_to(names[0])
    (folder / "filenames.txt").write_text("\n".join([*names, "zz.png"]) + "\n")
    with pytest.raises(InputError, match=f"{names[0]} and zz.png are the same photo \\(lines 1"):
        load_stack(folder)
    (folder / "filenames.txt").unlink()
    with pytest.raises(InputError, match=f"is the same file as {names[0]}") as err:
        load_stack(folder)
    assert Path(str(err.value.path)).name == "zz.png"


# ------------------------------------------------ review-stack23.md 1: reads through links


def _old_output(tmp_path: Path) -> Path:
    from _runtime_helpers import msfnet_folder

    return msfnet_folder(tmp_path / "out", ("mask.png", "normals.png"))


def test_what_a_stack_reads_through_links_is_an_input_of_the_output_checks(
    tmp_path: Path,
) -> None:
    """A stack whose mask.png linked into an earlier output lost it to that output's
    --overwrite (exit 0); a linked image was replaced."""
    from msfnet.common.files import check_output
    from msfnet.runtime.stack import linked_reads

    out = _old_output(tmp_path)
    stack = png_stack(tmp_path / "stk", 16)
    (stack / "mask.png").unlink()
    (stack / "mask.png").symlink_to(out / "mask.png")
    assert linked_reads(stack) == [stack / "mask.png"]
    with pytest.raises(InputError, match=r"contains the input .*stk/mask\.png \(reached"):
        check_output(out, [stack], overwrite=True, folder=True, reads=linked_reads(stack))
    check_output(tmp_path / "new", [stack], folder=True, reads=linked_reads(stack))

    (stack / "mask.png").unlink()
    names = (stack / "filenames.txt").read_text().split()
    (stack / "sub").symlink_to(out)  # filenames.txt reads through a linked sub-folder
    (stack / "filenames.txt").write_text("\n".join([*names[:-1], "sub/normals.png"]) + "\n")
    assert linked_reads(stack) == [stack / "sub/normals.png"]
    with pytest.raises(InputError, match=r"contains the input .*sub/normals\.png"):
        check_output(out, [stack], overwrite=True, folder=True, reads=linked_reads(stack))

    (stack / "filenames.txt").write_text("\n".join(names) + "\n")
    os.link(out / "mask.png", stack / "mask.png")  # a hard link: another name of it
    assert linked_reads(stack) == [stack / "mask.png"]
    with pytest.raises(InputError, match=r"contains the input .*stk/mask\.png"):
        check_output(out, [stack], overwrite=True, folder=True, reads=linked_reads(stack))


def test_a_link_the_stack_never_reads_is_no_input(tmp_path: Path) -> None:
    """review-today23.md 3: a ``results`` link to the output, or a profile kept beside the
    photos, blocked every --overwrite re-run."""
    from msfnet.common.files import check_output
    from msfnet.runtime.stack import linked_reads

    out = _old_output(tmp_path)
    stack = png_stack(tmp_path / "stk", 16)
    (stack / "results").symlink_to(out)
    (stack / "last_profile.json").symlink_to(out / "normals.png")
    assert linked_reads(stack) == []
    check_output(out, [stack], overwrite=True, folder=True, reads=linked_reads(stack))
