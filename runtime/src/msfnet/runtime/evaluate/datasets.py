"""Public benchmarks: their evaluation protocol and the published figures to compare against.

DiLiGenT (Shi et al., CVPR 2016): 96 lights per object; bear's first 20 images are corrupted and
the standard protocol (the MSF-Net paper's too) uses images 21-96. Published mean angular errors
(deg) for the objects we validate on, as listed in the data's SOURCE.md.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

from msfnet.common.errors import InputError
from msfnet.common.imageio import list_images
from msfnet.common.vocabulary import opt
from msfnet.runtime.stack import LIGHTS_NAMES, folder_name

PROTOCOL_SELECT = {"bearPNG": "21-96"}  # object folder -> the images the benchmark uses
PROTOCOL_WHY = {"bearPNG": "DiLiGenT's protocol: bear's first 20 images are corrupted"}


def protocol_note(folder: Path, select: str) -> str:
    """The line a command prints when a benchmark's selection applies by the folder's name."""
    why = PROTOCOL_WHY.get(known_object(folder), "the benchmark's protocol")
    return f"{folder_name(folder)}: using images {select} ({why}); {opt('select')} overrides"


PUBLISHED_MAE: dict[str, dict[str, float]] = {
    "ballPNG": {"L2 (paper)": 4.10, "PS-FCN": 2.67, "MSF-Net (paper)": 2.27},
    "bearPNG": {"L2 (paper)": 8.39, "PS-FCN": 7.72, "MSF-Net (paper)": 4.60},
    "harvestPNG": {"L2 (paper)": 30.62, "PS-FCN": 12.39, "MSF-Net (paper)": 10.80},
}
PUBLISHED_METHODS = ("PS-FCN", "MSF-Net (paper)")


def known_object(folder: Path) -> str:
    """The benchmark object a folder holds, for its protocol and published figures: its own
    name, or that of the folder it links to (``bear -> DiLiGenT/bearPNG``)."""
    name = folder_name(folder)
    if name in PROTOCOL_SELECT or name in PUBLISHED_MAE:
        return name
    return Path(os.path.realpath(folder)).name or name


def protocol_select(folder: Path) -> str | None:
    """The images the benchmark uses of this object folder (DiLiGenT bear: 21-96), if any."""
    return PROTOCOL_SELECT.get(known_object(folder))


@dataclass(frozen=True)
class BenchObject:
    folder: Path
    select: str | None  # the benchmark's image selection (e.g. bear 21-96)
    lights: Path | None = None  # a light file shared by the root's objects (psmImages)

    @property
    def name(self) -> str:
        return folder_name(self.folder)


def lights_file(folder: Path) -> Path | None:
    """The folder's own light file (light_directions.txt or lights.txt), if any."""
    return next((folder / n for n in LIGHTS_NAMES if (folder / n).is_file()), None)


def has_images(folder: Path) -> bool:
    return (folder / "filenames.txt").is_file() or bool(list_images(folder, strict=False))


def shared_lights_root(folder: Path) -> tuple[Path, list[Path]] | None:
    """(the shared light file, the stack sub-folders) when ``folder`` has a light file but no
    images of its own and sub-folders that hold images (psmImages: ``lights.txt`` at the top,
    one folder of TGA images per object); None otherwise. The one rule for msf-run's batches
    and msf-eval's benchmarks."""
    lights = lights_file(folder)
    if lights is None or has_images(folder):
        return None
    subs = [d for d in sorted(folder.iterdir()) if d.is_dir() and has_images(d)]
    return (lights, subs) if subs else None


def _check_listed_select(select: str, folder: Path, listing: Path) -> None:
    """An objects.txt selection checked up front, in objects.txt's words: checked later it
    read as a --select the user never gave, mid-batch."""
    from msfnet.runtime.stack.load import count_images
    from msfnet.runtime.stack.select import parse_select

    n = count_images(folder)
    if n == 0:
        return  # no images: the stack's own check says so
    try:
        parse_select(select, n)
    except InputError as exc:
        detail = exc.message.replace(f"{opt('select', select, quote=True)}: ", "")
        raise InputError(f"object {folder.name}: selection {select!r}: {detail}", listing) from exc


def _listed_object(entry: str, root: Path) -> tuple[str, str | None]:
    """(folder name, image selection or None) of one objects.txt entry: the whole entry where
    it names a folder (``my part`` was read as the folder ``my`` and the selection ``part``),
    else the name before a trailing selection (``bearPNG 21-96``)."""
    split = re.fullmatch(r"(.*?)\s+([\d,:\-]+)", entry)
    if (root / entry).is_dir() or split is None:
        return entry, None
    return split.group(1), split.group(2)


def find_objects(root: Path, *, select_given: bool = False) -> list[BenchObject]:
    """The objects of a benchmark root in benchmark order: those listed in objects.txt (one
    folder per line, optionally followed by an image selection), the root itself when it is a
    stack, the sub-folders of a root whose light file they share (psmImages), or every
    sub-folder holding a stack. Known benchmark objects get their protocol's selection
    (DiLiGenT bear: 21-96) unless objects.txt says otherwise. ``select_given``: the user's
    own selection overrides objects.txt's, which is then not checked."""
    if not root.is_dir():
        if root.exists():  # e.g. an .npz stack, which msf-run reads but a benchmark is not
            raise InputError(
                "a file, not a benchmark: expected a folder with objects.txt, "
                "object sub-folders, or one object folder (images + "
                "light_directions.txt); msf-run takes .npz stacks",
                root,
            )
        raise InputError("benchmark root or object folder not found", root)
    listing = root / "objects.txt"
    if listing.is_file():
        out = []
        for line in listing.read_text(encoding="utf-8-sig").splitlines():
            name, select = _listed_object(line.split("#", 1)[0].strip(), root)
            if not name:
                continue
            folder = root / name
            if not folder.is_dir():
                raise InputError(f"object folder {name!r} listed but not found", listing)
            if select is not None and not select_given:
                _check_listed_select(select, folder, listing)
            out.append(BenchObject(folder, select))
        if not out:
            raise InputError("objects.txt lists no objects", listing)
        return out
    if (shared := shared_lights_root(root)) is not None:
        lights, subs = shared
        # a sub-folder with a light file of its own keeps it; resolved: the objects may be
        # read from another working directory (Ray workers)
        common = lights.resolve()
        return [
            BenchObject(d, protocol_select(d), None if lights_file(d) else common) for d in subs
        ]
    if lights_file(root) is not None or has_images(root):  # one object (or --lights)
        return [BenchObject(root, protocol_select(root))]
    found = [
        BenchObject(d, protocol_select(d))
        for d in sorted(root.iterdir())
        if d.is_dir() and any((d / n).is_file() for n in LIGHTS_NAMES)
    ]
    if not found:
        raise InputError(
            "no object folders (with light_directions.txt or lights.txt) and no objects.txt", root
        )
    return found


def check_unique(objects: list[BenchObject]) -> None:
    names = [o.name for o in objects]
    dup = next((n for n in names if names.count(n) > 1), None)
    if dup is not None:
        where = [o.folder for o in objects if o.name == dup]
        same = len({p.resolve() for p in where}) == 1
        raise InputError(
            f"object {dup!r} is listed twice (its results would clash)"
            if same
            else f"two objects are named {dup!r} ({where[0]} and {where[1]}): their results "
            "would clash; evaluate them in separate runs or rename one"
        )


__all__ = [
    "PROTOCOL_SELECT",
    "PROTOCOL_WHY",
    "PUBLISHED_MAE",
    "PUBLISHED_METHODS",
    "BenchObject",
    "check_unique",
    "find_objects",
    "has_images",
    "lights_file",
    "protocol_note",
    "shared_lights_root",
]
