"""msf-bench against the reliability rules: options are checked by argparse, and a missing
torch is found, before any benchmarking or writing."""

from __future__ import annotations

import pytest

pytest.importorskip("torch")

from msfnet.bench import cli


@pytest.mark.parametrize(
    "option",
    [
        ["--max-memory", "nan"],
        ["--max-memory", "-1"],
        ["--threads", "x"],
        ["--threads", "0"],
        ["--threads", "100000"],  # once refused only when the peaks started, after minutes
        ["--threads", "2,1025"],
    ],
)
def test_options_are_refused_before_benchmarking(
    option: list[str], tmp_path, monkeypatch, capfd
) -> None:
    def reached(args: object) -> None:
        raise AssertionError(f"{option} reached the benchmark unchecked")

    monkeypatch.setattr(cli, "bench", reached)
    with pytest.raises(SystemExit) as exc:
        cli.main([*option, "--report-dir", str(tmp_path / "r")])
    assert exc.value.code == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and option[0] in err[0], err


def test_without_torch_nothing_is_written_or_printed_but_one_line(tmp_path) -> None:
    from _runtime_helpers import run_without_torch

    done = run_without_torch(
        "msfnet.bench.cli", ["--quick", "--report-dir", str(tmp_path / "r")], cwd=tmp_path
    )
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "needs the Python package 'torch'" in lines[0], lines
    assert done.stdout == "" and list(tmp_path.iterdir()) == []


def test_thread_counts_share_the_one_bound() -> None:
    from msfnet.common.cpu import MAX_THREADS

    assert cli.thread_counts(f"{MAX_THREADS},1") == [MAX_THREADS, 1]
    with pytest.raises(Exception, match=f"1..{MAX_THREADS}"):
        cli.thread_counts(str(MAX_THREADS + 1))
