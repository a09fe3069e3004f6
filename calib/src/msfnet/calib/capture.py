"""Capture sessions: one frame per light, written to disk as it arrives, resumable.

Layout of ``out_dir``::

    raw/ambient.png, raw/001.png ...   frames as captured (written atomically, never modified)
    session.json                       camera/light settings and per-frame exposure checks
    001.png ... filenames.txt          the finished stack (ambient subtracted), DiLiGenT layout,
    light_directions.txt ...           plus lights, intensities and mask when known

Re-running with the same ``out_dir`` skips every frame already in ``raw/``: an interrupted
session (Ctrl-C, cable pulled, power cut) loses at most the frame being written.
"""

from __future__ import annotations

import contextlib
import json
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from msfnet.runtime.errors import InputError
from msfnet.runtime.files import write_atomic
from msfnet.runtime.imageio import read_image, read_mask, write_png
from msfnet.runtime.stack import read_vectors

SESSION = "session.json"


def exposure_check(frame: np.ndarray, white_level: float, mask: np.ndarray | None = None,
                   max_saturated: float = 0.01, min_level: float = 0.1) -> dict:
    """Share of saturated pixels and the bright end (99.5th percentile) of the frame."""
    g = frame.max(axis=-1) if frame.ndim == 3 else frame
    vals = g[mask] if mask is not None else g.ravel()
    sat = float(np.mean(vals >= 0.99 * white_level))
    p = float(np.percentile(vals, 99.5)) / white_level
    return {"saturated": sat, "p99_5": p, "too_bright": sat > max_saturated,
            "too_dark": p < min_level}


def _name(i: int) -> str:
    return f"{i + 1:03d}.png"


def _to_uint(frame: np.ndarray) -> np.ndarray:
    if frame.dtype in (np.uint8, np.uint16):
        return frame
    return np.clip(np.rint(frame), 0, 65535).astype(np.uint16)


def _write_rows(path: Path, rows: np.ndarray) -> None:
    text = "".join(" ".join(f"{v:.8f}" for v in r) + "\n" for r in rows)
    write_atomic(path, lambda tmp: tmp.write_text(text))


def _load_session(path: Path, count: int, overwrite: bool) -> dict:
    if not path.is_file():
        return {"count": count, "frames": {}}
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(f"session file is corrupt ({exc}); delete it to start over", path) \
            from exc
    if data.get("count") != count and not overwrite:
        raise InputError(f"existing session has {data.get('count')} lights, this one {count} "
                         "(use another folder or --overwrite)", path)
    return data


def capture_stack(camera, lights, out_dir: str | Path, *,
                  light_directions: np.ndarray | str | Path | None = None,
                  light_intensities: np.ndarray | str | Path | None = None,
                  mask: np.ndarray | str | Path | None = None, ambient: bool = True,
                  subtract_ambient: bool = True, overwrite: bool = False,
                  max_saturated: float = 0.01, min_level: float = 0.1, strict: bool = False,
                  progress: bool = True, log=print) -> Path:
    """Capture one frame per light (plus an ambient frame) into ``out_dir``; return it.

    camera: ``.capture() -> (H, W, 3) uint8/uint16``, ``.white_level``, ``.info()``;
    lights: ``.count``, ``.on(i)`` (0-based, only that light), ``.off()``.
    Frames already in ``out_dir/raw`` are kept and skipped (resume). ``strict`` turns exposure
    warnings into errors. Without light directions the images are still written (e.g. a
    chrome-sphere capture for ``msf-calib directions``); the folder is then not yet a stack.
    """
    out = Path(out_dir)
    raw = out / "raw"
    n = int(lights.count)
    if n < 1:
        raise InputError("the light back-end reports no lights")
    if overwrite and raw.is_dir():
        for p in raw.glob("*.png"):
            p.unlink()
    raw.mkdir(parents=True, exist_ok=True)
    sess_path = out / SESSION
    session = _load_session(sess_path, n, overwrite)
    session.update(count=n, camera=camera.info(), white_level=camera.white_level)
    mask_arr = None
    if mask is not None:
        mask_arr = read_mask(mask) if isinstance(mask, (str, Path)) else np.asarray(mask, bool)

    def save_session() -> None:
        text = json.dumps(session, indent=1, sort_keys=True)
        write_atomic(sess_path, lambda t: t.write_text(text))

    todo = ([("ambient.png", None)] if ambient else []) + [(_name(i), i) for i in range(n)]
    pending = [(name, i) for name, i in todo if not (raw / name).is_file()]
    if len(pending) < len(todo):
        log(f"resuming: {len(todo) - len(pending)} of {len(todo)} frames already in {raw}")
    problems = []
    try:
        for name, i in tqdm(pending, desc="capture", unit="frame", disable=not progress):
            if i is None:
                lights.off()
            else:
                lights.on(i)
            fname = name
            frame = _to_uint(np.asarray(camera.capture()))
            write_png(raw / fname, frame)  # atomic: a crash never leaves half a frame
            if i is not None:
                chk = exposure_check(frame, camera.white_level, mask_arr, max_saturated,
                                     min_level)
                chk["time"] = time.time()
                session["frames"][fname] = chk
                msg = []
                if chk["too_bright"]:
                    msg.append(f"{chk['saturated']:.1%} saturated")
                if chk["too_dark"]:
                    msg.append(f"under-exposed (brightest 0.5% at {chk['p99_5']:.0%} of range)")
                if msg:
                    problems.append(f"{fname}: " + ", ".join(msg))
                    log(f"warning: {problems[-1]}")
            save_session()
    finally:
        # never hide the original error behind a light-controller error
        with contextlib.suppress(Exception):
            lights.off()
    if strict and problems:
        raise InputError("exposure problems: " + "; ".join(problems), out)
    return finish_stack(out, light_directions, light_intensities, mask_arr, subtract_ambient)


def finish_stack(out: Path, light_directions=None, light_intensities=None,
                 mask: np.ndarray | None = None, subtract_ambient: bool = True) -> Path:
    """Build the DiLiGenT-layout stack in ``out`` from ``out/raw`` (idempotent)."""
    raw = out / "raw"
    session = json.loads((out / SESSION).read_text())
    n = int(session["count"])
    names = [_name(i) for i in range(n)]
    missing = [nm for nm in names if not (raw / nm).is_file()]
    if missing:
        raise InputError(f"session incomplete: {len(missing)} frame(s) missing, e.g. "
                         f"{missing[0]}; run the capture again to resume", raw)
    amb_path = raw / "ambient.png"
    amb = read_image(amb_path).astype(np.int64) if subtract_ambient and amb_path.is_file() \
        else None
    shape = None
    for nm in names:
        img = read_image(raw / nm)
        shape = img.shape[:2]
        if amb is not None:
            # Keep the camera's units; a 16-bit container holds the difference exactly.
            img = np.clip(img.astype(np.int64) - amb, 0, 65535).astype(np.uint16)
        write_png(out / nm, img)
    write_atomic(out / "filenames.txt", lambda t: t.write_text("\n".join(names) + "\n"))
    for arr, fname, what in ((light_directions, "light_directions.txt", "light directions"),
                             (light_intensities, "light_intensities.txt", "light intensities")):
        if arr is None:
            continue
        rows = read_vectors(Path(arr), what) if isinstance(arr, (str, Path)) else np.asarray(arr)
        if len(rows) != n:
            raise InputError(f"{len(rows)} {what} for {n} captured frames")
        _write_rows(out / fname, rows)
    if mask is not None:
        if mask.shape != shape:
            raise InputError(f"mask is {mask.shape} but frames are {shape}")
        write_png(out / "mask.png", mask.astype(np.uint8) * 255)
    return out


__all__ = ["capture_stack", "exposure_check", "finish_stack"]
