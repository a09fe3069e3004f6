"""Capture sessions: one frame per light, written to disk as it arrives, resumable.

Layout of ``out_dir``::

    raw/ambient.png, raw/001.png ...   frames as captured (written atomically, never modified)
    session.json                       camera/light settings, linearisation, exposure checks
    001.png ... filenames.txt          the finished stack (ambient subtracted), DiLiGenT layout,
    light_directions.txt ...           plus lights, intensities, mask and ground truth when
                                       known, written by msfnet.runtime.stack's writers (the
                                       files save_stack writes; Normal_gt.npy of older captures
                                       is still read)

Re-running with the same ``out_dir`` skips every frame already in ``raw/``: an interrupted
session (Ctrl-C, cable pulled, power cut) loses at most the frame being written. A resume with
another light count or other camera settings (camera.info(): exposure, gain, mode, simulated
scene ...) is refused: one stack never mixes frames of two setups. A finished stack is kept as
it is (only light files, mask or linearisation given anew are updated). ``overwrite`` discards
the previous session: its frames (only the names msf-capture writes: other images in ``raw/``
stay), its session.json and the stack built from it. Everything given is checked before the
first frame: a bad lights file or mask must not cost a capture session.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from tqdm import tqdm

from msfnet.common.errors import InputError
from msfnet.common.files import folder_lock, remove_stale_staging_in, vectors_text, write_atomic
from msfnet.common.imageio import (
    image_header,
    list_images,
    mask_threshold,
    read_image,
    read_mask,
    write_png,
)
from msfnet.common.vocabulary import opt, verbatim
from msfnet.runtime.stack import (
    FILENAMES_FILE,
    INTENSITIES_FILE,
    LIGHTS_FILE,
    MASK_FILE,
    NORMALS_FILE,
    filenames_text,
    read_normals,
    read_vectors,
    unit_lights,
    write_filenames,
    write_intensities,
    write_lights,
    write_mask,
    write_normals,
)
from msfnet.runtime.stack.readers import unit_normals
from msfnet.runtime.stack.transforms import linearise, white_level
from msfnet.runtime.stack.types import check_intensities, check_lights

if TYPE_CHECKING:
    from msfnet.runtime.api import Model, Result
    from msfnet.runtime.stack import LoadOptions


SESSION = "session.json"
# Ground truth as earlier msf-capture versions wrote it: still read on resume, and kept while
# unchanged (the loader reads it too); new ground truth goes to Normal_gt.mat like save_stack's.
LEGACY_NORMALS_FILE = "Normal_gt.npy"
Log = Callable[[str], object]


@dataclass(frozen=True)
class Linearisation:
    """How the camera encodes values; the stack is written linear (16-bit) when not None."""

    srgb: bool = False
    gamma: float | None = None

    def __post_init__(self) -> None:
        if self.srgb and self.gamma is not None:
            raise InputError(
                f"{opt('srgb')} and {opt('gamma')} both linearise: give one of them", option="srgb"
            )
        if self.gamma is not None and not self.gamma > 0:
            raise InputError(
                f"{opt('gamma', verbatim(str(self.gamma)))}: must be a positive number",
                option="gamma",
            )

    @property
    def active(self) -> bool:
        return self.srgb or self.gamma is not None

    def record(self) -> dict[str, object] | None:
        """What session.json says (None: frames stored as the camera delivered them)."""
        if self.srgb:
            return {"kind": "srgb"}
        if self.gamma is not None:
            return {"kind": "gamma", "gamma": self.gamma}
        return None


@dataclass(frozen=True)
class Exposure:
    """One frame's exposure, as session.json records it."""

    saturated: float  # share of pixels at the white level
    p99_5: float  # the bright end (99.5th percentile) as a share of the white level
    too_bright: bool
    too_dark: bool

    @classmethod
    def judged(
        cls, saturated: float, p99_5: float, max_saturated: float, min_level: float
    ) -> Exposure:
        """The verdict for these measurements under these limits."""
        # A frame that reaches the white level anywhere (saturated > 0: a chrome sphere's
        # highlight) is not under-exposed, however dark the rest: more exposure would only
        # clip more.
        return cls(
            saturated, p99_5, saturated > max_saturated, p99_5 < min_level and not saturated > 0.0
        )

    @classmethod
    def from_record(cls, record: object, max_saturated: float, min_level: float) -> Exposure | None:
        """A frame's check as session.json recorded it, judged anew under this run's limits;
        None when there is no usable record."""
        if not isinstance(record, dict):
            return None
        try:
            sat, p = float(record["saturated"]), float(record["p99_5"])
        except (KeyError, TypeError, ValueError):
            return None
        if not (math.isfinite(sat) and math.isfinite(p)):
            return None
        return cls.judged(sat, p, max_saturated, min_level)

    def problems(self) -> list[str]:
        found = []
        if self.too_bright:
            found.append(f"{self.saturated:.1%} saturated")
        if self.too_dark:
            found.append(f"under-exposed (brightest 0.5% at {self.p99_5:.0%} of range)")
        return found


def exposure_check(
    frame: np.ndarray,
    white_level: float,
    mask: np.ndarray | None = None,
    max_saturated: float = 0.01,
    min_level: float = 0.1,
) -> Exposure:
    """Share of saturated pixels and the bright end (99.5th percentile) of the frame."""
    g = frame.max(axis=-1) if frame.ndim == 3 else frame
    vals = g[mask] if mask is not None else g.ravel()
    at_white = vals >= 0.99 * white_level
    sat = float(np.mean(at_white))
    p = float(np.percentile(vals, 99.5)) / white_level
    return Exposure.judged(sat, p, max_saturated, min_level)


def _name(i: int) -> str:
    return f"{i + 1:03d}.png"


def _to_uint(frame: np.ndarray) -> np.ndarray:
    if frame.dtype in (np.uint8, np.uint16):
        return frame
    return np.clip(np.rint(frame), 0, 65535).astype(np.uint16)


def read_session(path: Path) -> dict:
    """session.json as a dict; a damaged or foreign file is refused in one line."""
    try:
        data = json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError, RecursionError) as exc:
        raise InputError(
            f"session file is damaged ({type(exc).__name__}); delete it to start over", path
        ) from exc
    if not isinstance(data, dict):
        raise InputError(
            "session file is not an msf-capture session; delete it to start over", path
        )
    count = data.get("count")
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        # (a missing count read as "existing session has None lights")
        raise InputError(
            f"session file records no light count (count: {json.dumps(count)}); it is damaged "
            "or not msf-capture's: delete it to start over",
            path,
        )
    return data


# Session keys saying which frames the stack images were built from and how; a session without
# them (new, overwritten, or given new frames since) has its stack images built anew.
_BUILT_KEYS = ("linearisation", "ambient_subtracted", "stack_white_level")


def _instead(overwrite_allowed: bool) -> str:
    """What to do instead, naming --overwrite only where the caller has it (msf-capture
    --loop refuses it)."""
    return (
        f"use another folder or {opt('overwrite')}" if overwrite_allowed else "use another folder"
    )


def _load_session(path: Path, count: int, camera: dict, overwrite_allowed: bool = True) -> dict:
    """The session to continue (a new one when there is none), refused when it was taken with
    another light count or other camera settings."""
    if not path.is_file():
        return {"count": count, "frames": {}}
    data = read_session(path)
    if data.get("discarding"):
        raise InputError(
            f"an earlier {opt('overwrite')} was interrupted while discarding this session: run "
            f"it with {opt('overwrite')} again to start over"
            + ("" if overwrite_allowed else ", or use another folder"),
            path,
        )
    if data.get("count") != count:
        raise InputError(
            f"existing session has {data.get('count')} lights, this one {count} "
            f"({_instead(overwrite_allowed)})",
            path,
        )
    recorded = data.get("camera")
    if isinstance(recorded, dict):
        # compared as session.json stores it (tuples become lists, keys strings)
        now = json.loads(json.dumps(camera))
        # a key only the new info has was not recorded by an older version: not a difference
        # (NaN, which a driver may report, is not equal to itself: compare its JSON text too)
        differ = sorted(
            k
            for k in recorded
            if k not in now
            or (now[k] != recorded[k] and json.dumps(now[k]) != json.dumps(recorded[k]))
        )
        if differ:

            def show(info: dict) -> str:
                return ", ".join(f"{k}={info.get(k, '(none)')}" for k in differ)

            raise InputError(
                f"existing session was taken with {show(recorded)}, this one with "
                f"{show(now)} ({_instead(overwrite_allowed)})",
                path,
            )
    return data


# What msf-capture writes: raw frames, stack images, and the stack's other files.
_FRAME = re.compile(r"^(ambient|\d{3,})\.png$")
_STACK_IMAGE = re.compile(r"^\d{3,}\.png$")
_STACK_FILES = (
    FILENAMES_FILE,
    LIGHTS_FILE,
    INTENSITIES_FILE,
    MASK_FILE,
    NORMALS_FILE,
    LEGACY_NORMALS_FILE,
)


def _discard(out: Path) -> None:
    """``overwrite``: remove the previous session, and only what msf-capture wrote (the
    session's own frame names in raw/, its stack images, the stack files), so that nothing of
    it is read with the new frames.

    session.json is first marked as being discarded and removed last: a kill midway leaves a
    folder that a plain re-run refuses (no old frame is resumed into a new session) and that
    --overwrite, still seeing msf-capture's session, finishes discarding.
    """
    sess = out / SESSION
    if not sess.is_file():
        return  # nothing of msf-capture's here (check_folder made sure none of its names are)
    count = _session_count(sess)
    if count is not None:
        text = json.dumps({"count": count, "discarding": True}, indent=1, sort_keys=True)
        write_atomic(sess, lambda t: t.write_text(text))
    own = {_name(i) for i in range(count)} | {"ambient.png"} if count else None

    def ours(p: Path, pattern: re.Pattern[str]) -> bool:
        # the session's own frame names; by pattern only when its count is unreadable
        return bool(pattern.match(p.name)) and (own is None or p.name in own)

    for name in _STACK_FILES:
        (out / name).unlink(missing_ok=True)
    for p in out.iterdir():
        if ours(p, _STACK_IMAGE) and p.is_file() and not p.is_symlink():
            p.unlink()
    raw = out / "raw"
    if raw.is_dir():
        for p in raw.iterdir():
            if ours(p, _FRAME) and p.is_file() and not p.is_symlink():
                p.unlink()
    sess.unlink()


def _check_new_names(out: Path, count: int) -> None:
    """``overwrite`` of a session: _discard removes only the old session's frame names, so
    a file under a name only the new, longer session writes is someone else's."""
    old = _session_count(out / SESSION)
    if old is None:
        return  # unreadable count: _discard removes every frame name, as msf-capture's
    for i in range(old, count):
        for p in (out / _name(i), out / "raw" / _name(i)):
            if os.path.lexists(p):
                raise InputError(
                    f"{opt('overwrite')}: {p.relative_to(out)} is not the previous session's "
                    f"(it had {old} lights) and a {count}-light session would replace it: move "
                    "it away or use another folder",
                    out,
                    option="overwrite",
                )


def _session_count(path: Path) -> int | None:
    try:
        return int(read_session(path)["count"])
    except InputError:
        return None


def _capture_names(out: Path) -> list[Path]:
    """What lies in ``out`` under a name msf-capture writes (frames in raw/, stack images,
    the stack's other files)."""
    raw = out / "raw"
    found = [p for p in (out / n for n in _STACK_FILES) if os.path.lexists(p)]
    found += sorted(p for p in out.iterdir() if _STACK_IMAGE.match(p.name))
    if raw.is_dir():
        found += sorted(p for p in raw.iterdir() if _FRAME.match(p.name))
    return found


def _written_here(out: Path, path: Path) -> bool:
    """Whether ``path`` is (resolved) one of the files msf-capture writes in ``out``."""
    root, target = out.resolve(), path.resolve()
    if target.parent == root:
        return target.name in _STACK_FILES or bool(_STACK_IMAGE.match(target.name))
    return target.parent == root / "raw" and bool(_FRAME.match(target.name))


def check_inputs(out: Path, inputs: Iterable[object]) -> None:
    """Refuse an input file (light directions, intensities, mask) lying in ``out`` under a
    name msf-capture writes there (``light_directions.txt``, ``mask.png``, ``raw/001.png``
    ...): the capture would replace its own input. Arrays and None are skipped."""
    for value in inputs:
        if isinstance(value, (str, Path)) and _written_here(out, Path(value)):
            raise InputError(
                f"is inside the capture folder under a name msf-capture writes, so the capture "
                f"would replace it: give a copy outside {out}",
                value,
            )


def check_folder(
    out: Path, overwrite: bool, overwrite_allowed: bool = True, count: int | None = None
) -> None:
    """Refuse a folder msf-capture did not capture into (no session.json) when it holds a file
    under a name msf-capture writes (001.png, light_directions.txt, mask.png, raw/001.png ...),
    with or without ``overwrite``: it would be replaced. Other images (which could be
    mistaken for frames) are refused too; ``overwrite`` captures beside them. In a session's
    folder, ``overwrite`` with ``count`` lights refuses a file under a frame name the new
    session writes and the old one did not (its 013.png beside a 12-light session)."""
    if not out.is_dir():
        return
    if (out / SESSION).is_file():
        if overwrite and count is not None:
            _check_new_names(out, count)
        return
    clash = _capture_names(out)
    if clash:
        raise InputError(
            f"{opt('overwrite') + ': ' if overwrite else ''}{clash[0].relative_to(out)} is not "
            "msf-capture's (the folder has no session.json) and would be replaced; "
            "msf-capture replaces only what it captured: move it away or use another folder",
            out,
        )
    if overwrite:
        return
    raw = out / "raw"
    theirs = list_images(out, strict=False)
    if raw.is_dir():
        theirs += list_images(raw, strict=False)
    if theirs:
        example = theirs[0].name
        how = f", or {opt('overwrite')} to capture into it anyway" if overwrite_allowed else ""
        raise InputError(
            f"the folder holds images msf-capture did not take (e.g. {example}, "
            f"and no session.json): use another folder{how}",
            out,
        )


def check_vectors(
    value: np.ndarray | str | Path | None, count: int, what: str
) -> np.ndarray | None:
    """Light directions or intensities for ``count`` lights, validated (and directions made
    unit length), or None."""
    if value is None:
        return None
    src = Path(value) if isinstance(value, (str, Path)) else None
    rows = read_vectors(src, what) if src is not None else np.asarray(value, np.float32)
    if rows.ndim != 2 or rows.shape[1] != 3:
        raise InputError(f"{what} must have 3 numbers per row, got shape {rows.shape}", src)
    if len(rows) != count:
        raise InputError(
            f"{len(rows)} {what} for {count} lights: the file does not belong to this rig", src
        )
    if what == "light directions":
        rows = unit_lights(rows, src)
        check_lights(rows, src)
    else:
        check_intensities(rows, src)
    return rows


def check_mask(
    mask: np.ndarray | str | Path | None, shape: tuple[int, int] | None
) -> np.ndarray | None:
    """The object mask, readable, not empty and (when the frame size is known) of that size."""
    if mask is None:
        return None
    src = Path(mask) if isinstance(mask, (str, Path)) else None
    arr = read_mask(src) if src is not None else np.asarray(mask, bool)
    if not arr.any():
        what = f"no pixel above {mask_threshold(src)}" if src is not None else "no True pixel"
        raise InputError(f"the mask is empty ({what})", src)
    if shape is not None and arr.shape != tuple(shape):
        raise InputError(
            f"mask is {arr.shape[1]}x{arr.shape[0]} but the camera delivers "
            f"{shape[1]}x{shape[0]} frames",
            src,
        )
    return arr


def _frame_shape(camera: Any, raw: Path) -> tuple[int, int] | None:
    """The frame size before capturing: from the camera when it can tell, else from a frame
    already on disk (a resumed session)."""
    shape = getattr(camera, "frame_shape", None)
    if shape:
        return int(shape[0]), int(shape[1])
    if raw.is_dir():
        frames = sorted(raw.glob("[0-9][0-9][0-9].png"))
        if frames:
            return tuple(read_image(frames[0]).shape[:2])  # type: ignore[return-value]
    return None


def _check_frames(raw: Path, names: Iterable[str], shape: tuple[int, int] | None = None) -> None:
    """The frames of ``names`` on disk in ``raw`` are of one size and bit depth (and of
    ``shape``, the camera's, when known): a damaged or replaced frame crashed the stack build
    halfway (a broadcast error, some stack images written)."""
    first: tuple[str, Any] | None = None
    retake = "delete it and run the capture again to retake it"
    for name in names:
        path = raw / name
        head = image_header(path) if path.is_file() else None
        if head is None:
            continue
        if shape is not None and head.shape != tuple(shape):
            raise InputError(
                f"frame is {head.width}x{head.height} but the camera delivers "
                f"{shape[1]}x{shape[0]} frames: {retake}",
                path,
            )
        if first is None:
            first = (name, head)
        elif (head.shape, head.bits) != (first[1].shape, first[1].bits):

            def desc(h: Any) -> str:
                return f"{h.width}x{h.height}, {h.bits}-bit"

            raise InputError(
                f"frame is {desc(head)} but {first[0]} is {desc(first[1])}: {retake}", path
            )


def capture_stack(
    camera,
    lights,
    out_dir: str | Path,
    *,
    light_directions: np.ndarray | str | Path | None = None,
    light_intensities: np.ndarray | str | Path | None = None,
    mask: np.ndarray | str | Path | None = None,
    ambient: bool = True,
    subtract_ambient: bool = True,
    overwrite: bool = False,
    max_saturated: float = 0.01,
    min_level: float = 0.1,
    strict: bool = False,
    progress: bool | None = None,
    log: Log = print,
    linearisation: Linearisation | None = None,
    normals_gt: np.ndarray | None = None,
    overwrite_allowed: bool = True,
) -> Path:
    """Capture one frame per light (plus an ambient frame) into ``out_dir``; return it.

    camera: ``.capture() -> (H, W, 3) uint8/uint16``, ``.white_level``, ``.info()``, and
    optionally ``.frame_shape`` (H, W); lights: ``.count``, ``.on(i)`` (0-based, only that
    light), ``.off()``. Frames already in ``out_dir/raw`` are kept and skipped (resume, refused
    when ``.info()`` differs from the session's); a finished stack is kept; ``overwrite``
    discards the previous session and its stack first. ``strict`` turns exposure warnings into
    errors. Without light directions the images are still written (e.g. a chrome-sphere
    capture for ``msf-calib directions``); the folder is then not yet a stack.
    ``linearisation``: the camera's encoding, undone when the stack is built (recorded in
    session.json). ``progress``: False hides the bar; otherwise it shows on a terminal only.
    ``normals_gt``: known normals (simulated scenes). ``overwrite_allowed=False``: messages
    do not advise --overwrite (msf-capture --loop has none).

    The folder is held for the whole session (:func:`folder_lock`): a second capture into it
    is refused at once instead of both reporting success with one's frames gone.
    """
    out = Path(out_dir)
    with folder_lock(out, "msf-capture"):
        # what a capture killed with kill -9 was writing (it cannot clean up after itself)
        remove_stale_staging_in(out)
        remove_stale_staging_in(out / "raw")
        given = _check_given(
            camera,
            lights,
            out,
            light_directions=light_directions,
            light_intensities=light_intensities,
            mask=mask,
            overwrite=overwrite,
            overwrite_allowed=overwrite_allowed,
            linearisation=linearisation,
        )
        n = given.count
        if overwrite:
            _discard(out)
        session = _load_session(out / SESSION, n, given.camera_info, overwrite_allowed)
        if not isinstance(session.get("frames"), dict):
            session["frames"] = {}
        sess = _Session(out, session, camera, n, given.mask, max_saturated, min_level, log)
        frames = _frames(sess, ambient, given.shape)

        def finish() -> Path:
            sess.judge_all(strict)
            return finish_stack(
                out,
                given.light_directions,
                given.light_intensities,
                given.mask,
                subtract_ambient,
                given.linearisation,
                normals_gt,
                log=log,
            )

        nothing_new = not frames.pending and not frames.unchecked
        if nothing_new and _finished(out, n) and sess.path.is_file():
            log(
                f"stack complete: all {n} frames are already in {out / 'raw'}; nothing to capture "
                f"(kept as it is; {opt('overwrite')} captures again)"
            )
            return finish()
        _start(sess, frames, given.camera_info)
        _take(sess, lights, frames.pending, progress)
        return finish()


@dataclass(frozen=True)
class _Given:
    """What :func:`capture_stack` was given, checked before the first frame."""

    count: int  # lights
    linearisation: Linearisation
    light_directions: np.ndarray | None
    light_intensities: np.ndarray | None
    shape: tuple[int, int] | None  # the frames' (H, W), when known before capturing
    mask: np.ndarray | None
    camera_info: dict


def _check_given(
    camera: Any,
    lights: Any,
    out: Path,
    *,
    light_directions: np.ndarray | str | Path | None,
    light_intensities: np.ndarray | str | Path | None,
    mask: np.ndarray | str | Path | None,
    overwrite: bool,
    overwrite_allowed: bool,
    linearisation: Linearisation | None,
) -> _Given:
    """Everything given, checked before the first frame (and before anything is discarded):
    a bad lights file or mask must not cost a capture session."""
    n = int(lights.count)
    if n < 1:
        raise InputError("the light back-end reports no lights")
    lin = linearisation or Linearisation()
    check_inputs(out, (light_directions, light_intensities, mask))
    check_folder(out, overwrite, overwrite_allowed, count=n)
    dirs = check_vectors(light_directions, n, "light directions")
    ints = check_vectors(light_intensities, n, "light intensities")
    shape = _frame_shape(camera, out / "raw")
    mask_arr = check_mask(mask, shape)
    info = camera.info()  # before discarding anything: a device failing here costs nothing
    return _Given(n, lin, dirs, ints, shape, mask_arr, info)


@dataclass
class _Session:
    """A session being captured into ``out``: session.json's contents, and the exposure
    check of each frame recorded in them."""

    out: Path
    data: dict[str, Any]  # session.json's contents; "frames": the exposure records
    camera: Any
    count: int
    mask: np.ndarray | None
    max_saturated: float
    min_level: float
    log: Log

    @property
    def path(self) -> Path:
        return self.out / SESSION

    @property
    def records(self) -> dict[str, Any]:
        return self.data["frames"]

    def save(self) -> None:
        text = json.dumps(self.data, indent=1, sort_keys=True)
        write_atomic(self.path, lambda t: t.write_text(text))

    def fits(self, frame: np.ndarray) -> None:
        """Refuse a frame that is not of the mask's size."""
        if self.mask is not None and self.mask.shape != frame.shape[:2]:
            raise InputError(
                f"mask is {self.mask.shape[1]}x{self.mask.shape[0]} but the "
                f"camera delivers {frame.shape[1]}x{frame.shape[0]} frames"
            )

    def check(self, name: str, frame: np.ndarray) -> None:
        """Record the frame's exposure in the session; problems are logged as warnings."""
        self.fits(frame)
        chk = exposure_check(
            frame, self.camera.white_level, self.mask, self.max_saturated, self.min_level
        )
        self.records[name] = {**asdict(chk), "time": time.time()}
        if chk.problems():
            self.log(f"warning: {name}: " + ", ".join(chk.problems()))

    def recorded(self, name: str) -> Exposure | None:
        """The frame's recorded exposure, judged under this run's limits (None: no record)."""
        return Exposure.from_record(self.records.get(name), self.max_saturated, self.min_level)

    def judge_all(self, strict: bool) -> None:
        """``strict``: every frame's recorded exposure judged, those taken before an
        interruption included, as an uninterrupted run judges them."""
        if not strict:
            return
        problems = []
        for i in range(self.count):
            chk = self.recorded(_name(i))
            if chk is not None and chk.problems():
                problems.append(f"{_name(i)}: " + ", ".join(chk.problems()))
        if problems:
            raise InputError("exposure problems: " + "; ".join(problems), self.out)


@dataclass(frozen=True)
class _Frames:
    """The session's frames (name, light index; None: the ambient frame) and which of them
    are still to capture or, on disk without an exposure record, to check."""

    todo: list[tuple[str, int | None]]
    pending: list[tuple[str, int | None]]
    unchecked: list[str]


def _frames(sess: _Session, ambient: bool, shape: tuple[int, int] | None) -> _Frames:
    """What is left to do, a resume's frames on disk checked (size, bit depth) first."""
    raw = sess.out / "raw"
    todo: list[tuple[str, int | None]] = [("ambient.png", None)] if ambient else []
    todo += [(_name(i), i) for i in range(sess.count)]
    _check_frames(raw, [name for name, _ in todo], shape)  # a resume's frames, before capturing
    pending = [(name, i) for name, i in todo if not (raw / name).is_file()]
    # frames on disk without a usable exposure record (a frame written before its record):
    # checked again from raw/ below
    on_disk = [name for name, i in todo if i is not None and (raw / name).is_file()]
    unchecked = [name for name in on_disk if sess.recorded(name) is None]
    return _Frames(todo, pending, unchecked)


def _start(sess: _Session, frames: _Frames, camera_info: dict) -> None:
    """Make the folder the session's: session.json records the setup (and forgets a stack
    built before new frames), a resume is reported and frames without a record checked."""
    raw = sess.out / "raw"
    log = sess.log
    raw.mkdir(parents=True, exist_ok=True)
    sess.data.update(count=sess.count, camera=camera_info, white_level=sess.camera.white_level)
    if frames.pending:  # new frames: a stack built before no longer shows them
        for key in _BUILT_KEYS:
            sess.data.pop(key, None)
    todo, pending = frames.todo, frames.pending
    if not pending:  # every frame is on disk but the stack was never built (killed then)
        log(f"all {len(todo)} frames already in {raw}; building the stack")
    elif len(pending) < len(todo):
        log(f"resuming: {len(todo) - len(pending)} of {len(todo)} frames already in {raw}")
    if frames.unchecked:
        log(
            f"checking the exposure of {len(frames.unchecked)} frame(s) in {raw} that have "
            "no record"
        )
        for name in frames.unchecked:
            sess.check(name, read_image(raw / name))
    sess.save()  # from here on the folder is msf-capture's (check_folder)


def _take(
    sess: _Session, lights: Any, pending: list[tuple[str, int | None]], progress: bool | None
) -> None:
    """Capture the pending frames, each recorded in the session before it is written."""
    raw = sess.out / "raw"
    try:
        # disable=None: a bar on a terminal, nothing in a log file
        for name, i in tqdm(
            pending, desc="capture", unit="frame", disable=True if progress is False else None
        ):
            if i is None:
                lights.off()
            else:
                lights.on(i)
            frame = _to_uint(np.asarray(sess.camera.capture()))
            sess.fits(frame)
            if i is not None:
                sess.check(name, frame)
            # The record first, then the frame: an interruption between the two leaves a
            # record without its frame, which the resume captures (and records) again; never
            # a frame on disk that nothing has checked.
            sess.save()
            write_png(raw / name, frame)  # atomic: a crash never leaves half a frame
    finally:
        # never hide the original error behind a light-controller error
        with contextlib.suppress(Exception):
            lights.off()


def _finished(out: Path, n: int) -> bool:
    return (out / FILENAMES_FILE).is_file() and all((out / _name(i)).is_file() for i in range(n))


def _text_changed(path: Path, text: str, log: Log) -> bool:
    """Whether a text file of the stack must be (re)written to hold ``text``; says so when an
    existing one is updated."""
    if path.is_file() and path.read_text() == text:
        return False
    if path.is_file():
        log(f"updated {path.name}")
    return True


def _mask_changed(path: Path, mask: np.ndarray, log: Log) -> bool:
    if path.is_file() and np.array_equal(read_mask(path), mask):
        return False
    if path.is_file():
        log(f"updated {path.name}")
    return True


def _normals_changed(out: Path, normals: np.ndarray) -> bool:
    """Whether the ground truth on disk (Normal_gt.mat, or an older capture's Normal_gt.npy)
    loads other than ``normals`` would once written: compared as the stack reader reads it."""
    for old in (out / NORMALS_FILE, out / LEGACY_NORMALS_FILE):
        if old.is_file():
            try:
                return not np.array_equal(read_normals(old), unit_normals(normals))
            except InputError:  # unreadable: write it anew
                return True
    return True


def finish_stack(
    out: Path,
    light_directions: np.ndarray | str | Path | None = None,
    light_intensities: np.ndarray | str | Path | None = None,
    mask: np.ndarray | None = None,
    subtract_ambient: bool = True,
    linearisation: Linearisation | None = None,
    normals_gt: np.ndarray | None = None,
    log: Log = print,
) -> Path:
    """Build the DiLiGenT-layout stack in ``out`` from ``out/raw``.

    Images are (re)built unless session.json says they were built from these frames the same
    way (the raw frames are the record); light files, mask and ground truth are written when
    given and different, by the stack writers of msfnet.runtime.stack (the files save_stack
    writes).
    """
    raw = out / "raw"
    sess_path = out / SESSION
    session = read_session(sess_path)
    n = int(session["count"])
    lin = linearisation or Linearisation()
    names = [_name(i) for i in range(n)]
    missing = [nm for nm in names if not (raw / nm).is_file()]
    if missing:
        raise InputError(
            f"session incomplete: {len(missing)} frame(s) missing, e.g. "
            f"{missing[0]}; run the capture again to resume",
            raw,
        )
    # no record (a new or overwritten session, or new frames): images on disk are not these
    # frames' (an earlier session's, or the user's), whatever they look like
    built = all(k in session for k in _BUILT_KEYS) and _finished(out, n)
    same = (session.get("linearisation"), session.get("ambient_subtracted"))
    if built and same == (lin.record(), subtract_ambient):
        shape = read_image(out / names[0]).shape[:2]
    else:
        if built:
            log("rebuilding the stack images from raw/ (linearisation or ambient changed)")
        shape = _build_images(out, names, subtract_ambient, lin)
        session.update(
            linearisation=lin.record(),
            ambient_subtracted=subtract_ambient,
            stack_white_level=65535.0 if lin.active else session.get("white_level"),
        )
        text = json.dumps(session, indent=1, sort_keys=True)
        write_atomic(sess_path, lambda t: t.write_text(text))
    if _text_changed(out / FILENAMES_FILE, filenames_text(names), log):
        write_filenames(out, names)
    dirs = check_vectors(light_directions, n, "light directions")
    ints = check_vectors(light_intensities, n, "light intensities")
    if dirs is not None and _text_changed(out / LIGHTS_FILE, vectors_text(dirs), log):
        stale = (out / LIGHTS_FILE).is_file() and (out / INTENSITIES_FILE).is_file()
        write_lights(out, dirs)
        if stale and ints is None:
            # intensities are fitted to (or, for the simulated rig, belong to) the directions
            # they came with: kept beside new ones they would be read as theirs
            (out / INTENSITIES_FILE).unlink()
            log(
                f"removed {INTENSITIES_FILE}: it was for the previous light directions "
                f"(give {opt('light_intensities')} to add new ones)"
            )
    if ints is not None and _text_changed(out / INTENSITIES_FILE, vectors_text(ints), log):
        write_intensities(out, ints)
    if mask is not None:
        if mask.shape != shape:
            raise InputError(f"mask is {mask.shape} but frames are {shape}")
        if _mask_changed(out / MASK_FILE, mask, log):
            write_mask(out, mask)
    if normals_gt is not None:
        gt = np.asarray(normals_gt, np.float32)
        if _normals_changed(out, gt):
            write_normals(out, gt)
            # one ground truth in the folder (the loader would prefer the new one anyway)
            (out / LEGACY_NORMALS_FILE).unlink(missing_ok=True)
    return out


def _build_images(
    out: Path, names: list[str], subtract_ambient: bool, lin: Linearisation
) -> tuple[int, int]:
    raw = out / "raw"
    amb_path = raw / "ambient.png"
    use_amb = subtract_ambient and amb_path.is_file()
    _check_frames(raw, [*names, amb_path.name] if use_amb else names)  # before writing any
    amb = read_image(amb_path) if use_amb else None
    shape: tuple[int, int] = (0, 0)
    for nm in names:
        img = read_image(raw / nm)
        shape = img.shape[:2]  # type: ignore[assignment]
        if lin.active:
            # linearise first: the ambient light adds in linear units, not encoded ones
            white = white_level(img.dtype)
            val = linearise(img, white, lin.srgb, lin.gamma) / white
            if amb is not None:
                val = val - linearise(amb, white, lin.srgb, lin.gamma) / white
            # 16 bits: an 8-bit encoded frame spreads over far more than 256 linear levels
            img = np.clip(np.rint(val * 65535.0), 0, 65535).astype(np.uint16)
        elif amb is not None:
            # Keep the camera's units; a 16-bit container holds the difference exactly.
            img = np.clip(img.astype(np.int64) - amb, 0, 65535).astype(np.uint16)
        write_png(out / nm, img)
    return shape


@dataclass
class LoopStep:
    """One pass of :func:`capture_loop`."""

    index: int  # 1, 2, ...
    stack: Path  # the captured stack folder
    output: Path | None = None  # where the model's results went
    result: Result | None = None


_NUMBERED = re.compile(r"^\d{3,}$")


RUN_PENDING = ".run-pending"  # beside a loop's takes: ".NNN.run-pending"


def next_take(root: Path, has_result: Callable[[Path], bool] | None = None) -> Path:
    """``root/001``, ``root/002``, ...: an unfinished last take is resumed (and, given
    ``has_result``, a finished one without its result: its run was interrupted), otherwise
    the number after the highest."""
    found = root.iterdir() if root.is_dir() else ()
    taken = sorted((int(p.name), p) for p in found if p.is_dir() and _NUMBERED.match(p.name))
    if taken:
        last = taken[-1][1]
        sess = last / SESSION
        if sess.is_file():
            count = int(read_session(sess).get("count", 0))
            if not _finished(last, count) or (has_result is not None and not has_result(last)):
                return last
        return root / f"{taken[-1][0] + 1:03d}"
    return root / "001"


def capture_loop(
    camera,
    lights,
    root: str | Path,
    *,
    iterations: int | None = None,
    model: Model | None = None,
    load: LoadOptions | None = None,
    out_root: Path | None = None,
    interval: float = 0.0,
    **capture: Any,
) -> Iterator[LoopStep]:
    """Capture stack after stack into ``root/001``, ``root/002``, ... (``iterations`` times,
    or until the caller stops iterating / Ctrl-C) and, with a ``model`` (loaded once), run
    each: results in ``out_root/NNN`` (default ``root/NNN-normals``). Yields each step.
    ``capture``: keyword options of :func:`capture_stack`."""
    root = Path(root)

    def result_of(take: Path) -> Path:
        return (out_root / take.name) if out_root is not None else root / f"{take.name}-normals"

    def pending(take: Path) -> Path:
        # marks a take whose run was asked for and has not finished: only such a take is run
        # again (a take captured without a model is not owed a result)
        return root / f".{take.name}{RUN_PENDING}"

    def owed(take: Path) -> bool:
        return pending(take).exists() and not result_of(take).exists()

    done = 0
    while iterations is None or done < iterations:
        if done and interval > 0:
            time.sleep(interval)
        # with a model, a take whose run was stopped is run again (results are written whole)
        folder = next_take(root, (lambda t: not owed(t)) if model is not None else None)
        if model is not None:
            root.mkdir(parents=True, exist_ok=True)
            pending(folder).touch()
        stack = capture_stack(camera, lights, folder, **capture)
        step = LoopStep(int(folder.name), stack)
        if model is not None:
            out = result_of(folder)
            step.result = model(stack, load)
            step.result.save(out, inputs=tuple(load.inputs()) if load else ())
            step.output = out
            pending(folder).unlink(missing_ok=True)
        done += 1
        yield step


__all__ = [
    "SESSION",
    "Exposure",
    "Linearisation",
    "LoopStep",
    "capture_loop",
    "capture_stack",
    "check_folder",
    "check_inputs",
    "check_mask",
    "check_vectors",
    "exposure_check",
    "finish_stack",
    "next_take",
]
