"""The station's watch loop (inspection.watch, msf-inspect --watch): each complete part judged
exactly once across restarts, broken and incomplete parts recorded without stopping the loop,
one JSON line per part, a clean stop on SIGTERM."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from _runtime_helpers import staging_leftovers

from msfnet.runtime.cli.inspect import main as inspect_main
from msfnet.runtime.inspection.defects import DefectOptions
from msfnet.runtime.inspection.station import Station
from msfnet.runtime.inspection.watch import JOURNAL, READY, WatchOptions, watch
from msfnet.runtime.options import ModelOptions
from msfnet.runtime.stack import save_stack
from msfnet.synth.plates import PlateOptions, render_plate

ONCE = WatchOptions(once=True)


@pytest.fixture(scope="module")
def line(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """golden/ and parts/p0..p3 (p1 and p3 with relief defects)."""
    root = tmp_path_factory.mktemp("line")
    save_stack(render_plate(PlateOptions(seed=7, relief=False)).stack, root / "golden")
    for i in range(4):
        plate = render_plate(PlateOptions(seed=7, relief=i % 2 == 1, noise=1e-3 * (1 + i)))
        save_stack(plate.stack, root / "parts" / f"p{i}")
    return root


@pytest.fixture(scope="module")
def station(line: Path) -> Station:
    return Station(DefectOptions(depth=0.1), ModelOptions(method="l2"), reference=line / "golden")


def _journal(out: Path) -> list[dict]:
    return [json.loads(x) for x in (out / JOURNAL).read_text().splitlines()]


def _parts(line: Path, tmp_path: Path, names: tuple[str, ...] = ("p0", "p1", "p2", "p3")) -> Path:
    folder = tmp_path / "incoming"
    folder.mkdir()
    for n in names:
        shutil.copytree(line / "parts" / n, folder / n)
    return folder


def test_each_part_is_judged_once_across_restarts(line, station, tmp_path: Path) -> None:
    folder, out = _parts(line, tmp_path, ("p0", "p1")), tmp_path / "station"
    first = watch(station, folder, out, ONCE)
    assert (first.passed, first.failed, first.errors, first.exit_code) == (1, 1, 0, 1)
    shutil.copytree(line / "parts" / "p2", folder / "p2")
    again = watch(station, folder, out, ONCE)  # only the new part
    assert (again.earlier, again.parts) == (2, 1)
    records = _journal(out)
    assert [r["part"] for r in records] == ["p0", "p1", "p2"]
    assert [r["verdict"] for r in records] == ["pass", "fail", "pass"]
    assert records[1]["defects"] == len(records[1]["regions"]) >= 1
    assert set(records[0]["times_ms"]) >= {"decode", "normals", "maps", "judge", "write"}
    for name in ("p0", "p1", "p2"):
        written = {p.name for p in (out / name).iterdir()}
        assert {"overlay.png", "deviation.png", "verdict.json", "regions.csv"} <= written
    summary = json.loads((out / "station.json").read_text())
    assert summary["parts"] == 1 and summary["earlier_parts"] == 2
    assert {s["stage"] for s in summary["stages_ms"]} >= {"decode", "normals", "total"}


def test_a_kill_between_folder_and_line_neither_repeats_nor_loses_a_part(
    line, station, tmp_path: Path
) -> None:
    folder, out = _parts(line, tmp_path, ("p0", "p1", "p2")), tmp_path / "station"
    watch(station, folder, out, ONCE)
    lines = (out / JOURNAL).read_text().splitlines(keepends=True)
    # p1's line lost (killed after its folder was written), p2's cut in the middle
    (out / JOURNAL).write_text(lines[0] + lines[2][:20])
    shutil.rmtree(out / "p2")
    again = watch(station, folder, out, ONCE)
    assert again.parts == 1  # p2 only: p1's folder stood for it
    assert [r["part"] for r in _journal(out)] == ["p0", "p1", "p2"]
    assert _journal(out)[1]["verdict"] == "fail"


def test_a_broken_part_is_recorded_and_the_next_one_judged(line, station, tmp_path: Path) -> None:
    folder, out = _parts(line, tmp_path, ("p0", "p1")), tmp_path / "station"
    (folder / "p0" / "003.png").write_bytes(b"not a png")
    (folder / "empty").mkdir()
    summary = watch(station, folder, out, ONCE)
    assert (summary.errors, summary.failed, summary.exit_code) == (2, 1, 2)
    by_part = {r["part"]: r for r in _journal(out)}
    assert by_part["p0"]["verdict"] == "error" and "003.png" in by_part["p0"]["error"]
    assert by_part["empty"]["verdict"] == "error"
    assert not (out / "p0").exists() and not staging_leftovers(out)
    shutil.copy(line / "parts" / "p0" / "003.png", folder / "p0" / "003.png")  # mended
    again = watch(station, folder, out, ONCE)  # errors are taken again; p1 is done
    assert (again.passed, again.failed, again.errors) == (1, 0, 1)
    assert [(r["part"], r["verdict"]) for r in _journal(out)][3:] == [
        ("empty", "error"),
        ("p0", "pass"),
    ]


def test_an_incomplete_part_waits_until_it_is_complete_or_stale(line, station, tmp_path):
    from msfnet.runtime.inspection.watch import Journal, PartFinder

    folder = _parts(line, tmp_path, ("p0",))
    (folder / "p0" / "light_directions.txt").unlink()
    (tmp_path / "out").mkdir()
    finder = PartFinder(folder, WatchOptions(stale_s=5.0), Journal(tmp_path / "out"), ())
    assert finder.ready(0.0) == []  # first look: it may still be being written
    (path,) = finder.ready(0.5)  # unchanged: offered
    from msfnet.common.errors import InputError

    assert not finder.failed(path, InputError("no lights"), 0.5)  # still waiting
    assert finder.ready(1.0) == [] and finder.stale(1.0) == []  # not offered again unchanged
    assert [p.name for p, _ in finder.stale(5.1)] == ["p0"]  # given up on
    assert finder.stale(9.0) == [] and finder.ready(9.0) == []  # once per state
    shutil.copy(line / "parts" / "p0" / "light_directions.txt", folder / "p0")
    assert finder.ready(6.0) == []  # changed: looked at again once it settles
    assert [p.name for p in finder.ready(6.5)] == ["p0"]
    (folder / "p0" / READY).write_text("")
    assert [p.name for p in finder.ready(7.0)] == ["p0"]  # a marker: taken at once


def _cli(*argv: str) -> int:
    return inspect_main(list(argv))


@pytest.mark.parametrize(
    ("extra", "words"),
    [
        (("--watch", "{missing}"), "no such folder"),
        (("{parts}", "--watch", "{parts}"), "give one"),
        (("--watch", "{parts}", "--overwrite"), "never replaced"),
        (("--watch", "{parts}", "--reference", "{missing}"), "no such file"),
    ],
)
def test_bad_station_settings_are_one_line(line, tmp_path, capsys, extra, words) -> None:
    folder = _parts(line, tmp_path, ("p0",))
    given = [a.format(missing=tmp_path / "nope", parts=folder) for a in extra]
    code = _cli(*given, "--depth", "0.1", "--method", "l2", "-o", str(tmp_path / "out"))
    err = capsys.readouterr().err.strip()
    assert code == 2 and words in err and len(err.splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_a_folder_holding_other_files_is_not_taken_as_a_station(line, tmp_path, capsys) -> None:
    folder = _parts(line, tmp_path, ("p0",))
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "notes.txt").write_text("mine")
    code = _cli(
        "--watch", str(folder), "--depth", "0.1", "--method", "l2", "-o", str(tmp_path / "out")
    )
    assert code == 2 and "parts.jsonl" in capsys.readouterr().err
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["notes.txt"]


@pytest.mark.skipif(sys.platform == "win32", reason="SIGTERM")
def test_a_running_station_takes_new_parts_and_stops_cleanly_on_sigterm(line, tmp_path) -> None:
    folder, out = _parts(line, tmp_path, ("p0",)), tmp_path / "station"
    argv = ["--watch", str(folder), "--reference", str(line / "golden"), "--depth", "0.1"]
    argv += ["--method", "l2", "--poll", "0.05", "-o", str(out)]
    code = "import sys\nfrom msfnet.runtime.cli.inspect import main\nsys.exit(main(sys.argv[1:]))"
    proc = subprocess.Popen(
        [sys.executable, "-c", code, *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 60

        def judged() -> list[str]:
            text = (out / JOURNAL).read_text() if (out / JOURNAL).is_file() else ""
            return [json.loads(x)["part"] for x in text.splitlines()]

        while judged() != ["p0"] and time.monotonic() < deadline:
            time.sleep(0.05)
        shutil.copytree(line / "parts" / "p1", folder / "p1")  # a new part, written meanwhile
        while judged() != ["p0", "p1"] and time.monotonic() < deadline:
            time.sleep(0.05)
        assert judged() == ["p0", "p1"]
        os.kill(proc.pid, signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == 0, stderr
    assert "p0: PASS" in stdout and "p1: FAIL" in stdout and "judged 2 part(s)" in stdout
    assert (out / "station.json").is_file() and not staging_leftovers(out)


def test_a_folder_name_used_again_is_another_part_and_temporaries_wait(line, station, tmp_path):
    """review-session25 4, 9, 15: a new folder under a judged name is judged as name~2; a
    folder being written as p.tmp is not a part; a part named like the station's journal gets
    its own output name."""
    folder, out = _parts(line, tmp_path, ("p0",)), tmp_path / "station"
    watch(station, folder, out, ONCE)
    shutil.rmtree(folder / "p0")
    shutil.copytree(line / "parts" / "p1", folder / "p0")  # a defective part, same name
    shutil.copytree(line / "parts" / "p2", folder / "p2.tmp")  # still being written
    shutil.copytree(line / "parts" / "p2", folder / JOURNAL)
    again = watch(station, folder, out, ONCE)
    records = _journal(out)[1:]
    assert [(r["part"], r.get("folder"), r["verdict"]) for r in records] == [
        ("p0~2", "p0", "fail"),
        ("parts.jsonl~2", "parts.jsonl", "pass"),
    ]
    assert again.exit_code == 1 and (out / "p0~2" / "verdict.json").is_file()
    assert watch(station, folder, out, ONCE).parts == 0  # each judged once


def test_once_exits_by_every_part_in_the_folder_not_only_this_runs(line, station, tmp_path):
    folder, out = _parts(line, tmp_path, ("p0", "p1")), tmp_path / "station"
    assert watch(station, folder, out, ONCE).exit_code == 1
    rerun = watch(station, folder, out, ONCE)  # after a kill, say: nothing new to judge
    assert rerun.parts == 0 and rerun.exit_code == 1  # p1 failed, and is still there
    shutil.rmtree(folder / "p1")
    assert watch(station, folder, out, ONCE).exit_code == 0


def test_a_part_the_tool_fails_on_is_recorded_and_the_line_goes_on(
    line, station, tmp_path, monkeypatch
) -> None:
    folder, out = _parts(line, tmp_path, ("p0", "p1")), tmp_path / "station"
    judge = station.judge

    def flaky(stack, name, decode_s=0.0):
        if name == "p0":
            raise ValueError("a bug on this part")
        return judge(stack, name, decode_s)

    monkeypatch.setattr(station, "judge", flaky)
    summary = watch(station, folder, out, ONCE)
    verdicts = {r["part"]: r for r in _journal(out)}
    assert "internal error: ValueError" in verdicts["p0"]["error"]
    assert verdicts["p1"]["verdict"] == "fail" and summary.exit_code == 2


def test_two_stations_of_one_process_never_share_an_output(line, station, tmp_path) -> None:
    import threading

    from msfnet.common.errors import InputError
    from msfnet.runtime.inspection import watch as watching

    folder, out = _parts(line, tmp_path, ("p0",)), tmp_path / "station"
    started, release = threading.Event(), threading.Event()
    judge = station.judge

    def slow(stack, name, decode_s=0.0):
        started.set()
        release.wait(30)
        return judge(stack, name, decode_s)

    station.judge = slow  # type: ignore[method-assign]
    try:
        first = threading.Thread(target=watching.watch, args=(station, folder, out, ONCE))
        first.start()
        assert started.wait(30)
        with pytest.raises(InputError, match="another station of this process"):
            watching.watch(station, folder, out, ONCE)
        release.set()
        first.join(30)
    finally:
        del station.judge
    assert [r["part"] for r in _journal(out)] == ["p0"]


def test_the_loops_flags_without_a_loop_are_refused(line, tmp_path, capsys) -> None:
    part = str(line / "parts" / "p0")
    code = _cli(part, "--depth", "0.1", "--once", "-o", str(tmp_path / "v"))
    err = capsys.readouterr().err
    assert code == 2 and "--once: for a station's loop, with --watch DIR" in err


def test_a_station_folder_resumed_with_another_rule_is_refused(line, station, tmp_path) -> None:
    """review-session25 16: verdicts of one station folder are all made alike."""
    from msfnet.common.errors import InputError

    folder, out = _parts(line, tmp_path, ("p0",)), tmp_path / "station"
    watch(station, folder, out, ONCE)
    other = Station(DefectOptions(depth=0.2), ModelOptions(method="l2"), reference=line / "golden")
    with pytest.raises(InputError, match=r"other settings \(rule\)"):
        watch(other, folder, out, ONCE)
    assert watch(station, folder, out, ONCE).parts == 0  # the same settings resume


def test_a_folder_that_cannot_be_listed_for_a_moment_is_looked_at_again(
    line, tmp_path, monkeypatch
) -> None:
    """review-session25 16: a network share's ESTALE ends no station; with --once it is one
    line."""
    import errno

    from msfnet.common.errors import InputError
    from msfnet.runtime.inspection import watch as watching

    folder = _parts(line, tmp_path, ("p0",))
    (tmp_path / "out").mkdir()
    finder = watching.PartFinder(folder, WatchOptions(), watching.Journal(tmp_path / "out"), ())
    real = os.scandir

    def stale(path):
        raise OSError(errno.ESTALE, "Stale file handle")

    monkeypatch.setattr(watching.os, "scandir", stale)
    with pytest.warns(UserWarning, match="trying again"):
        assert finder.candidates() == []
    once = watching.PartFinder(folder, ONCE, finder.journal, ())
    with pytest.raises(InputError, match="cannot list"):
        once.candidates()
    monkeypatch.setattr(watching.os, "scandir", real)
    assert [p.name for p in finder.candidates()] == ["p0"]
