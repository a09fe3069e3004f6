"""Property: whatever stack, light file and options msf-run is given, it either succeeds with
finite outputs or refuses in exactly one line (exit 2) and writes nothing.

Hypothesis draws tiny stacks (folders of 8/16-bit PNGs, possibly mixed, or .npz arrays of any
dtype with NaN/inf/negatives), light files (wrong column counts, missing or extra rows,
duplicates, zero rows, NaN; txt or json), intensity files, masks, ground truth and option values.
Run with ``--method l2`` (no model) and with a tiny model that honours the msfnet contract.
Bounded and deterministic: derandomize=True, so CI sees the same examples every time.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pytest
from _runtime_helpers import tiny_msfnet_onnx
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from msfnet.common.files import STAGING_TAG
from msfnet.runtime.cli.run import main

SETTINGS = settings(
    max_examples=40,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[
        HealthCheck.function_scoped_fixture,
        HealthCheck.too_slow,
        HealthCheck.data_too_large,
    ],
)

# Hypothesis favours the first and last entries of a sampled_from list (boundary values), so
# every list below starts and ends with a sensible value and holds the broken ones inside.

# light counts: mostly enough for photometric stereo, sometimes not
COUNTS = st.sampled_from([3, 2, 0, 4, 5, 6, 8, 4])
# floats a careless or hostile file holds
WILD = st.one_of(
    st.floats(-2, 2),
    st.sampled_from([0.0, 1.0, -1.0, np.nan, np.inf, -np.inf, 1e-40, 1e30, 65535.0]),
)
PIXEL = st.one_of(st.floats(0, 60000), st.sampled_from([0.0, np.nan, np.inf, -5.0, 1e-30, 3e38]))


@st.composite
def light_rows(draw, n: int) -> np.ndarray:
    """Mostly plausible upper-hemisphere lights, sometimes broken."""
    rows = max(0, n + draw(st.sampled_from([0, -1, 1, *[0] * 7])))
    cols = draw(st.sampled_from([3, 2, 4, *[3] * 7]))
    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    arr = rng.normal(size=(rows, cols))
    if cols >= 3:
        arr[:, 2] = np.abs(arr[:, 2]) + 0.5
    breakage = draw(
        st.sampled_from(["none", "wild", "duplicate", "equal", "zero_row", *["none"] * 5])
    )
    if rows and breakage == "wild":
        arr[draw(st.integers(0, rows - 1)), draw(st.integers(0, cols - 1))] = draw(WILD)
    elif rows > 1 and breakage == "duplicate":
        arr[1] = arr[0]
    elif rows and breakage == "equal":
        arr[:] = arr[0]
    elif rows and breakage == "zero_row":
        arr[0] = 0.0
    return arr


def _write_vectors(path: Path, arr: np.ndarray, as_json: bool | str) -> Path:
    if as_json == "bytes":  # not text at all
        path.write_bytes(np.random.default_rng(len(arr)).bytes(200))
    elif as_json == "deep":  # nested beyond Python's recursion limit
        path = path.with_suffix(".json")
        path.write_text("[" * 100_000 + "]" * 100_000)
    elif as_json:
        # json.dumps writes NaN/Infinity tokens, which Python's json reads back
        path = path.with_suffix(".json")
        path.write_text(json.dumps({"lights": arr.tolist()}))
    else:
        path.write_text("".join(" ".join(repr(float(v)) for v in r) + "\n" for r in arr))
    return path


@st.composite
def folder_stacks(draw, root: Path) -> list[str]:
    n = draw(COUNTS)
    h, w = draw(st.integers(1, 9)), draw(st.integers(1, 9))
    folder = root / "stack"
    folder.mkdir()
    depth = draw(st.sampled_from([8, 16]))
    odd_one = draw(st.sampled_from([None, 0, *[None] * 4]))  # one image of the other depth
    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    names = []
    for i in range(n):
        d = (24 - depth) if i == odd_one else depth
        top = 255 if d == 8 else 65535
        scale = draw(st.sampled_from([top, 0, 1, top // 2, top]))
        img = (rng.random((h, w, 3)) * scale).astype(np.uint8 if d == 8 else np.uint16)
        names.append(f"{i + 1:03d}.png")
        cv2.imwrite(str(folder / names[-1]), img)
    if draw(st.booleans()):
        (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    as_json = draw(st.sampled_from([False, True, "bytes", "deep", False]))
    _write_vectors(folder / "light_directions.txt", draw(light_rows(n)), as_json)
    if draw(st.booleans()):
        ints = np.full((max(0, n + draw(st.sampled_from([0, 0, 1]))), 3), 1.0)
        if len(ints):
            ints[0] = draw(WILD)
        _write_vectors(folder / "light_intensities.txt", ints, False)
    if draw(st.booleans()):
        mh = h + draw(st.sampled_from([0, 1, 0]))  # sometimes the wrong size
        mask = (rng.random((mh, w)) < draw(st.sampled_from([1.0, 0.0, 0.5]))).astype(np.uint8)
        cv2.imwrite(str(folder / "mask.png"), mask * 255)
    if draw(st.booleans()):
        gt = rng.normal(size=(h, w, 3)) * draw(st.sampled_from([1.0, 0.0, 1.0]))
        np.save(folder / "Normal_gt.npy", gt)
    return [str(folder)]


@st.composite
def npz_stacks(draw, root: Path) -> list[str]:
    n = draw(COUNTS)
    h, w = draw(st.integers(1, 9)), draw(st.integers(1, 9))
    dtype = draw(st.sampled_from([np.float32, np.float64, np.uint8, np.uint16, np.int16]))
    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    shape = (n, h, w, 3) if draw(st.booleans()) else (n, h, w)
    images = rng.random(shape) * draw(st.sampled_from([1.0, 0.0, 200.0, 50000.0]))
    if images.size and draw(st.integers(0, 2)) == 0:
        images.flat[draw(st.integers(0, images.size - 1))] = draw(PIXEL)
    if np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        images = np.clip(
            np.nan_to_num(images, posinf=info.max, neginf=info.min), info.min, info.max
        )
    arrays = {"images": images.astype(dtype), "lights": draw(light_rows(n))}
    if draw(st.booleans()):
        arrays["intensities"] = np.abs(rng.normal(size=(n, 3))) * draw(
            st.sampled_from([1.0, 0.0, 1e-40, 1e30, 1.0])
        )
    if draw(st.booleans()):
        arrays["mask"] = rng.random((h, w)) < draw(st.sampled_from([1.0, 0.0, 0.5]))
    if draw(st.booleans()):
        arrays["normals"] = rng.normal(size=(h, w, 3)) * draw(st.sampled_from([1.0, 0.0, 1.0]))
    path = root / "stack.npz"
    np.savez(path, **arrays)
    return [str(path)]


@st.composite
def invocations(draw, root: Path) -> list[str]:
    argv = draw(st.one_of(folder_stacks(root), npz_stacks(root)))
    if draw(st.integers(0, 5)) == 0:  # a --lights override of its own
        argv += [
            "--lights",
            str(
                _write_vectors(
                    root / "override.txt", draw(light_rows(draw(COUNTS))), draw(st.booleans())
                )
            ),
        ]
    # each option: sometimes given, then mostly a sensible value
    options = {
        "--select": st.one_of(
            st.sampled_from(
                ["1-3", "1,1,1", "5-3", "0", "1-99999999999", "x", "", "2-", "-4", "1,3,4", "2-"]
            ),
            st.text("0123456789-,: ", max_size=6),
        ),
        "--max-lights": st.sampled_from(["3", "2", "0", "nan", "10", "4"]),
        "--max-memory": st.sampled_from(
            ["64", "0.5", "1e-3", "nan", "inf", "-1", "0", "1e12", "4096"]
        ),
        "--repeat": st.sampled_from(["1", "0", "2"]),
    }
    for flag, values in options.items():
        if draw(st.integers(0, 4)) == 0:
            argv += [f"{flag}={draw(values)}"]
    return argv


def _snapshot(root: Path) -> dict[str, bytes]:
    return {str(p): p.read_bytes() for p in root.rglob("*") if p.is_file()}


def _finite_json(path: Path) -> object:
    def refuse(token: str) -> float:
        raise AssertionError(f"{path.name} holds a bare {token}")

    return json.loads(path.read_text(), parse_constant=refuse)


def _numbers(value: object) -> list[float]:
    if isinstance(value, dict):
        return [x for v in value.values() for x in _numbers(v)]
    if isinstance(value, list):
        return [x for v in value for x in _numbers(v)]
    return [float(value)] if isinstance(value, (int, float)) and not isinstance(value, bool) else []


def _check_one_run(argv: list[str], root: Path, capfd, record: bool = True) -> int:
    out = root / "out" / "result"
    inputs = _snapshot(root)
    capfd.readouterr()
    try:
        code = main([*argv, "-o", str(out)])
    except SystemExit as exc:  # argparse refusals
        code = int(exc.code or 0)
    err = capfd.readouterr().err
    assert code in (0, 2), (code, err, argv)
    if record:
        event(f"exit {code}")
    for name, data in inputs.items():  # inputs are never touched
        assert Path(name).read_bytes() == data, name
    leftovers = [p for p in root.rglob("*") if STAGING_TAG in p.name]
    assert not leftovers, leftovers
    if code == 2:
        lines = err.strip().splitlines()
        assert len(lines) == 1, (err, argv)
        assert lines[0].startswith("msf-run: error: "), (err, argv)
        assert not (root / "out").exists(), (err, argv)
        return code
    normals = np.load(out / "normals.npy")
    assert normals.dtype == np.float32 and normals.ndim == 3 and normals.shape[2] == 3
    assert np.isfinite(normals).all(), argv
    norm = np.linalg.norm(normals, axis=2)
    assert np.all((np.abs(norm - 1) < 1e-3) | (norm == 0)), argv
    profile = _finite_json(out / "profile.json")
    assert all(np.isfinite(_numbers(profile)))
    if (out / "metrics.json").exists():
        metrics = _finite_json(out / "metrics.json")
        assert isinstance(metrics, dict) and all(
            isinstance(v, (int, float)) and np.isfinite(v) for v in metrics.values()
        ), metrics
        assert 0 <= metrics["mae_deg"] <= 180
    return code


@SETTINGS
@given(data=st.data())
def test_msf_run_least_squares_on_anything(data, capfd) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        argv = data.draw(invocations(root), label="argv")
        _check_one_run(["--method", "l2", *argv], root, capfd)


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tiny_msfnet_onnx(tmp_path_factory.mktemp("tiny") / "tiny.onnx")


@settings(SETTINGS, max_examples=25)
@given(data=st.data())
def test_msf_run_tiny_model_on_anything(data, tiny_model: Path, capfd) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        argv = data.draw(invocations(root), label="argv")
        tile = data.draw(st.sampled_from([None, "0", "48", "50", "-4", "96"]), label="tile")
        extra = [] if tile is None else [f"--tile={tile}"]
        _check_one_run(["--onnx", str(tiny_model), "--threads", "1", *extra, *argv], root, capfd)


def test_the_property_sees_both_outcomes(tmp_path: Path, capfd) -> None:
    """The generators reach both sides: a plain stack succeeds, a broken one is refused (so the
    property is not vacuously met by refusing everything)."""
    from _runtime_helpers import sphere_stack

    from msfnet.runtime.stack import save_stack

    good, bad = tmp_path / "good", tmp_path / "bad"
    for root in (good, bad):
        save_stack(sphere_stack(n=4, h=8, w=9), root / "stack")
    assert _check_one_run(["--method", "l2", str(good / "stack")], good, capfd, False) == 0
    (bad / "stack" / "light_directions.txt").write_text("1 2\n" * 4)
    assert _check_one_run(["--method", "l2", str(bad / "stack")], bad, capfd, False) == 2
