"""--select and --max-lights: which images a run uses."""

from __future__ import annotations

import pytest

from msfnet.common.errors import InputError
from msfnet.runtime.stack import evenly_spaced, parse_select, selection

GOOD = [
    ("21-96", 96, list(range(20, 96))),
    ("1,3,5-7", 10, [0, 2, 4, 5, 6]),
    ("8-", 10, [7, 8, 9]),
    ("-3", 10, [0, 1, 2]),
    ("2:4", 10, [1, 2, 3]),
    (" 1 , 2 ,3 ", 5, [0, 1, 2]),
]
BAD = [
    ("5-3", 10, "backwards"),
    ("0", 10, "outside 1..10"),
    ("11", 10, "outside 1..10"),
    ("1,1,2", 10, "more than once"),
    ("a-b", 10, "expected 1-based"),
    (",", 10, "expected 1-based"),
    ("", 10, "an empty part"),  # not "all images"
    ("1,,3", 10, "an empty part"),  # a typo, not 1,3
    ("1,", 10, "an empty part"),
]


@pytest.mark.parametrize(("spec", "n", "want"), GOOD)
def test_parse_select(spec: str, n: int, want: list[int]) -> None:
    assert parse_select(spec, n) == want


@pytest.mark.parametrize(("spec", "n", "words"), BAD)
def test_parse_select_refuses(spec: str, n: int, words: str) -> None:
    with pytest.raises(InputError, match=words):
        parse_select(spec, n)


def test_max_lights_spreads_over_the_selection() -> None:
    assert evenly_spaced(96, 4) == [0, 32, 63, 95]
    assert selection(96, "21-96", 3) == [20, 58, 95]  # 76 kept: positions 0, 38, 75
    assert selection(10, None, None) == list(range(10))
    with pytest.raises(InputError, match="empty part"):
        selection(10, "", None)  # --select '' is refused, not read as no selection
    with pytest.raises(InputError, match="at least 3"):
        selection(10, None, 2)
