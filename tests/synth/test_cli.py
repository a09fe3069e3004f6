"""msf-synth on careless input: the root appears whole or not at all, --overwrite replaces only
an msf-synth root, errors and Ctrl-C are one line."""

from __future__ import annotations

from pathlib import Path

import pytest

from msfnet.common.files import MANIFEST, STAGING_TAG
from msfnet.synth import cli
from msfnet.synth.cli import main

SMALL = ["--objects", "2", "--lights", "4", "--size", "16", "--no-shadows"]


def _one_line(capfd, words: list[str]) -> None:
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("msf-synth: "), err
    for word in words:
        assert word in err[0], (word, err)


def test_root_is_written_whole_and_replaced_only_with_overwrite(tmp_path: Path, capfd) -> None:
    out = tmp_path / "syn"
    assert main([str(out), *SMALL, "-q"]) == 0
    names = (out / "objects.txt").read_text().split()
    assert sorted(p.name for p in out.iterdir()) == sorted([MANIFEST, "objects.txt", *names])
    assert main([str(out), *SMALL]) == 2
    _one_line(capfd, ["--overwrite"])
    assert main([str(out), *SMALL, "--seed", "5", "--overwrite", "-q"]) == 0
    assert (out / "objects.txt").read_text().split() != [] and not _staging(tmp_path)


def _staging(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if STAGING_TAG in p.name]


def test_overwrite_never_deletes_a_foreign_folder(tmp_path: Path, capfd) -> None:
    out = tmp_path / "mydata"
    out.mkdir()
    (out / "precious.png").write_bytes(b"the user's capture")
    assert main([str(out), *SMALL, "--overwrite"]) == 2
    _one_line(capfd, ["precious.png", "did not write"])
    assert (out / "precious.png").read_bytes() == b"the user's capture"


@pytest.mark.parametrize("failure", [KeyboardInterrupt, OSError])
def test_interrupted_render_leaves_nothing(
    failure: type[BaseException], tmp_path: Path, monkeypatch, capfd
) -> None:
    """Ctrl-C or a full disk on the second object: no root with one object in it."""
    real = cli.save_stack
    calls = []

    def second_fails(stack, folder, bit_depth=16):
        calls.append(folder)
        if len(calls) == 2:
            raise failure(28, "No space left on device") if failure is OSError else failure()
        return real(stack, folder, bit_depth=bit_depth)

    monkeypatch.setattr(cli, "save_stack", second_fails)
    out = tmp_path / "new" / "syn"
    assert main([str(out), *SMALL]) == (130 if failure is KeyboardInterrupt else 2)
    _one_line(capfd, ["interrupted" if failure is KeyboardInterrupt else "No space"])
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["--shapes", "cube"], ["--shapes", "cube"]),
        (["--materials", ""], ["--materials"]),
    ],
)
def test_bad_names(argv: list[str], words: list[str], tmp_path: Path, capfd) -> None:
    assert main([str(tmp_path / "x"), *argv]) == 2
    _one_line(capfd, words)
    assert list(tmp_path.iterdir()) == []


def test_overwrite_replaces_only_what_msf_synth_wrote(tmp_path: Path, capfd) -> None:
    """The help says "only one msf-synth wrote", but any msfnet folder was replaced (an
    msf-run result too): the manifest did not say which command wrote it."""
    import json

    from _runtime_helpers import sphere_stack

    from msfnet.runtime.cli.run import main as run_main
    from msfnet.runtime.stack import save_stack

    stack = save_stack(sphere_stack(n=4), tmp_path / "in")
    result = tmp_path / "result"
    assert run_main(["--method", "l2", "--no-maps", "-q", str(stack), "-o", str(result)]) == 0
    before = sorted(p.name for p in result.iterdir())
    assert main([str(result), *SMALL, "--overwrite"]) == 2
    _one_line(capfd, ["result", "msf-run's output, not msf-synth's"])
    assert sorted(p.name for p in result.iterdir()) == before
    # a root from before the manifest named its writer is replaced as it always was
    old = tmp_path / "old"
    assert main([str(old), *SMALL, "-q"]) == 0
    manifest = json.loads((old / MANIFEST).read_text())
    assert manifest.pop("command") == "msf-synth"
    (old / MANIFEST).write_text(json.dumps(manifest))
    assert main([str(old), *SMALL, "--overwrite", "-q"]) == 0


@pytest.mark.parametrize(("materials", "dark"), [("diffuse", 0.0), ("diffuse,dark", 0.1)])
def test_the_hard_presets_dark_objects_follow_materials(
    materials: str, dark: float, tmp_path: Path, monkeypatch
) -> None:
    """--preset hard --materials diffuse still drew ~10 % of its objects glossy and dark."""
    seen = []
    real = cli.render_set

    def spy(seed, count, options, **kwargs):  # type: ignore[no-untyped-def]
        seen.append(options)
        return real(seed, count, options, **kwargs)

    monkeypatch.setattr(cli, "render_set", spy)
    argv = [str(tmp_path / "s"), *SMALL, "--preset", "hard", "--materials", materials]
    assert main(argv) == 0
    assert seen[0].very_dark == dark


def test_plates_preset_renders_a_line_with_its_truth(tmp_path: Path, capfd) -> None:
    """--preset plates: 5 good parts to learn from, and parts whose odd ones carry the relief
    defects truth.json lists; a station judges them as the truth says."""
    import json

    from msfnet.runtime.cli.inspect import main as inspect_main

    out = tmp_path / "line"
    assert main([str(out), "--preset", "plates", "--objects", "4", "--size", "96"]) == 0
    assert sorted(p.name for p in (out / "good").iterdir()) == [f"g{i}" for i in range(1, 6)]
    truth = json.loads((out / "truth.json").read_text())
    assert [bool(truth[f"p00{i}"]) for i in range(1, 5)] == [False, True, False, True]
    goods = [str(p) for p in sorted((out / "good").iterdir())]
    assert inspect_main(["--train-good", *goods, "--method", "l2", "-o", str(out / "m")]) == 0
    argv = ["--watch", str(out / "parts"), "--reference", str(out / "m"), "--once"]
    code = inspect_main([*argv, "--depth", "0.05", "--method", "l2", "-o", str(tmp_path / "s")])
    assert code == 1  # two parts with defects
    verdicts = {
        r["part"]: r["verdict"]
        for r in map(json.loads, (tmp_path / "s" / "parts.jsonl").read_text().splitlines())
    }
    assert verdicts == {p: "fail" if truth[p] else "pass" for p in truth}
    assert main([str(tmp_path / "small"), "--preset", "plates", "--size", "64"]) == 2
    assert "at least 96 px" in capfd.readouterr().err


@pytest.mark.parametrize(
    ("extra", "words"),
    [(["--lights", "65"], "3-64 lights"), (["--shapes", "sphere"], "not plates")],
)
def test_plates_refuse_what_plates_cannot_be(tmp_path: Path, capfd, extra, words) -> None:
    assert main([str(tmp_path / "x"), "--preset", "plates", *extra]) == 2
    _one_line(capfd, [words])
    assert not (tmp_path / "x").exists()
