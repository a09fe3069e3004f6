"""The chrome-sphere diagnostic picture: lights numbered as their files are, labels that do not
cover one another, and each label attached to its own mark."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from msfnet.calib.directions import light_labels, place_labels


def test_labels_are_the_numbers_in_the_file_names() -> None:
    psm = [f"chrome.{i}.tga" for i in (0, 1, 10, 11, 2, 3, 4, 5, 6, 7, 8, 9)]
    assert light_labels(psm) == ["0", "1", "10", "11", "2", "3", "4", "5", "6", "7", "8", "9"]
    assert light_labels(["001.png", "002.png", "096.png"]) == ["1", "2", "96"]
    # no numbers, or numbers that repeat: the 1-based position, as the printout counts them
    assert light_labels(["left.png", "right.png", "top.png"]) == ["1", "2", "3"]
    assert light_labels(["a1.png", "b1.png", "c2.png"]) == ["1", "2", "3"]


def _overlap(a: tuple[int, ...], b: tuple[int, ...]) -> int:
    return max(0, min(a[2], b[2]) - max(a[0], b[0])) * max(0, min(a[3], b[3]) - max(a[1], b[1]))


def _check(
    points: list[tuple[int, int]], boxes: list, shape: tuple[int, int], w: int, h: int
) -> None:
    assert len(boxes) == len(points)
    for i, box in enumerate(boxes):
        assert box[2] - box[0] == w and box[3] - box[1] == h
        assert min(box[0], box[1]) >= 0 and box[2] <= shape[1] and box[3] <= shape[0]
        for j, other in enumerate(boxes):
            if j != i:
                assert _overlap(box, other) == 0, (i, j, box, other)
        for x, y in points:  # no label hides a mark (5 px either way)
            assert _overlap(box, (x - 5, y - 5, x + 6, y + 6)) == 0, (i, box, (x, y))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_clustered_highlights_get_labels_that_do_not_overlap(seed: int) -> None:
    """Twelve highlights within ~40 px, as on psmImages' chrome sphere (their numbers used to
    print on top of one another)."""
    rng = np.random.default_rng(seed)
    points = [(int(x), int(y)) for x, y in rng.uniform(480, 560, (12, 2))]
    shape, (w, h) = (680, 1024), (16, 11)
    boxes = place_labels(points, [(w, h)] * 12, shape)
    _check(points, boxes, shape, w, h)
    # a label that stays next to a mark is nearer that mark than any other: no ambiguity
    # (the others are called out with a leader line)
    for i, box in enumerate(boxes):
        mid = np.array([(box[0] + box[2]) / 2, (box[1] + box[3]) / 2])
        dist = np.linalg.norm(np.asarray(points) - mid, axis=1)
        if dist[i] < 20:
            assert dist[i] * 1.5 < np.delete(dist, i).min()


def test_spread_out_highlights_keep_their_labels_beside_them() -> None:
    points = [(100 + 80 * i, 200 + 30 * (i % 2)) for i in range(8)]
    boxes = place_labels(points, [(16, 11)] * 8, (400, 800))
    _check(points, boxes, (400, 800), 16, 11)
    for (x, y), box in zip(points, boxes, strict=True):
        assert np.hypot((box[0] + box[2]) / 2 - x, (box[1] + box[3]) / 2 - y) < 20


def test_labels_stay_inside_the_picture_at_its_edge() -> None:
    points = [(2, 2), (8, 3), (3, 9)]
    boxes = place_labels(points, [(16, 11)] * 3, (120, 160))
    _check(points, boxes, (120, 160), 16, 11)


def test_psmimages_chrome_diagnostic_numbers_lights_from_0(
    psm_dir: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The printout names the files (chrome.0.tga ... chrome.11.tga); the picture uses the
    same numbers: one image, drawn with labels 0-11."""
    from msfnet.calib import cli, directions

    drawn: list[list[str]] = []
    real = directions.diagnostic_image

    def spy(*args: Any, labels: list[str] | None = None, **kw: Any) -> np.ndarray:
        drawn.append(list(labels or []))
        return real(*args, labels=labels, **kw)

    monkeypatch.setattr(cli, "diagnostic_image", spy)
    assert cli.main(["directions", str(psm_dir / "chrome"), "-o", str(tmp_path / "l.txt")]) == 0
    out = capsys.readouterr().out
    assert "chrome.0.tga" in out and "chrome.11.tga" in out
    assert len(drawn) == 1 and sorted(drawn[0], key=int) == [str(i) for i in range(12)]
    assert (tmp_path / "l_diagnostic.png").stat().st_size > 0
