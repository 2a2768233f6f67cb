"""The README's tour runs as written, top to bottom: each command of its bash block, through
the command line's entry point, in a scratch directory holding a copy of examples/. Only
the missions are shorter (--duration 120) and the fleet uses one worker, for speed."""
from __future__ import annotations

import shlex
import shutil
from pathlib import Path

import pytest

from aqfg.cli import build_parser, main

ROOT = Path(__file__).resolve().parent.parent
FAST = {"--duration": "120", "--workers": "1"}


def tour_commands(readme: str) -> list[list[str]]:
    """The commands of the first bash block after the heading "## A tour"."""
    text = readme.split("\n## A tour", 1)[1]
    block = text.split("```bash\n", 1)[1].split("```", 1)[0]
    return [shlex.split(ln, comments=True) for ln in block.splitlines()
            if ln.strip() and not ln.lstrip().startswith("#")]


def fast(argv: list[str]) -> list[str]:
    """``argv`` with the FAST options' values (added to simulate where it has none)."""
    argv = list(argv)
    for opt, value in FAST.items():
        if opt in argv:
            argv[argv.index(opt) + 1] = value
        elif opt == "--duration" and argv[0] == "simulate":
            argv += [opt, value]
    return argv


def import_formats() -> list[str]:
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    fmt = next(a for a in sub.choices["import"]._actions if a.dest == "format")
    return list(fmt.choices)


def test_tour_commands_are_aqfg_commands():
    cmds = tour_commands((ROOT / "README.md").read_text())
    assert len(cmds) >= 10
    assert all(c[0] == "aqfg" for c in cmds)
    assert {c[1] for c in cmds} >= {"simulate", "info", "fit", "diagnose", "import", "fleet"}


@pytest.mark.slow
def test_readme_tour_runs_top_to_bottom(tmp_path, monkeypatch, capsys):
    pytest.importorskip("distributed")        # the tour ends with aqfg fleet
    shutil.copytree(ROOT / "examples", tmp_path / "examples",
                    ignore=shutil.ignore_patterns("missions"))
    monkeypatch.chdir(tmp_path)
    formats = import_formats()
    for cmd in tour_commands((ROOT / "README.md").read_text()):
        argv = fast(cmd[1:])
        if argv[0] == "import" and argv[1] not in formats:
            pytest.fail(f"the tour imports {argv[1]!r}, which aqfg import does not read")
        code = main(argv)
        err = capsys.readouterr().err
        assert code == 0, f"{shlex.join(cmd)} ended with {code}: {err[-2000:]}"
    assert (tmp_path / "learn3" / "model.json").is_file()
    assert (tmp_path / "season" / "fleet.json").is_file()
