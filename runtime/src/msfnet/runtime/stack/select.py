"""Choosing which images of a stack to use: ``--select`` specs and ``--max-lights``."""

from __future__ import annotations

import numpy as np

from msfnet.common.errors import InputError
from msfnet.common.vocabulary import opt
from msfnet.runtime.stack.types import MIN_LIGHTS


def parse_select(spec: str, n: int) -> list[int]:
    """1-based image selection like ``21-96``, ``1,3,5-9`` or ``90-`` -> 0-based indices.

    Ranges must run upwards and every index must exist; an index may not repeat (a repeated
    image adds no information but skews the normalisation over lights).
    """
    out: list[int] = []
    given = opt("select", spec, quote=True)
    usage = f"{given}: expected 1-based indices like 21-96 or 1,3,5-9"
    for part in spec.split(","):
        part = part.strip()
        if not part:  # "" or "1,,3": a typo, not "all images" (omit --select for that)
            raise InputError(
                f"{usage} (an empty part; leave out {opt('select')} for all images)",
                option="select",
            )
        try:
            if "-" in part or ":" in part:
                a, b = part.replace(":", "-").split("-", 1)
                lo, hi = int(a) if a.strip() else 1, int(b) if b.strip() else n
                if hi < lo:
                    raise InputError(f"{given}: range {part} runs backwards", option="select")
                # check the ends before expanding: "1-999999999999" must not fill the memory
                for end in (lo, hi):
                    if not 1 <= end <= n:
                        raise InputError(f"{given}: index {end} is outside 1..{n}", option="select")
                out.extend(range(lo - 1, hi))
            else:
                out.append(int(part) - 1)
        except ValueError as exc:
            raise InputError(usage, option="select") from exc
        if len(out) > n:  # more picks than images: some image repeats
            break
    if not out:
        raise InputError(usage, option="select")
    bad = [i + 1 for i in out if not 0 <= i < n]
    if bad:
        raise InputError(f"{given}: index {bad[0]} is outside 1..{n}", option="select")
    seen: set[int] = set()
    for i in out:
        if i in seen:
            raise InputError(f"{given}: image {i + 1} is selected more than once", option="select")
        seen.add(i)
    return out


def evenly_spaced(n: int, k: int) -> list[int]:
    """k indices spread evenly over n (for --max-lights)."""
    return sorted({round(float(i)) for i in np.linspace(0, n - 1, k)})


def selection(n: int, select: str | None, max_lights: int | None) -> list[int]:
    """--select (1-based spec), then --max-lights evenly spread over what is left."""
    keep = parse_select(select, n) if select is not None else list(range(n))
    if max_lights is not None and max_lights < len(keep):
        if max_lights < MIN_LIGHTS:
            raise InputError(
                f"{opt('max_lights', max_lights)}: at least {MIN_LIGHTS} lights are needed",
                option="max_lights",
            )
        keep = [keep[i] for i in evenly_spaced(len(keep), max_lights)]
    return keep
