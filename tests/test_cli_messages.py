"""What the command line says: each warning once (with the action that follows, once),
help text that matches what the options do, and a suggestion for a mistyped option."""
from __future__ import annotations

import io
import json
import logging
import re

import pytest

from aqfg.cli import build_parser, main
from aqfg.commands import common
from aqfg.data.io import save_mission
from aqfg.sim.simulator import simulate


@pytest.fixture(scope="module")
def short(tmp_path_factory):
    d = tmp_path_factory.mktemp("short") / "m"
    m, tr = simulate("asv", seed=3, duration=120.0)
    save_mission(m, d, truth=tr)
    return d


def warning_lines(err: str, command: str) -> list[str]:
    return [ln for ln in err.splitlines() if ln.startswith(f"aqfg {command}: warning: ")]


# ---------------------------------------------------------------- warnings said once
def test_fit_of_the_otter_example_says_each_warning_once(otter, tmp_path, capsys):
    assert main(["fit", str(otter), "--out", str(tmp_path / "f"), "--no-plots"]) == 0
    cap = capsys.readouterr()
    warned = warning_lines(cap.err, "fit")
    assert warned, "the Otter's fit warns (its model lacks the Otter's physics)"
    assert len(set(warned)) == len(warned)
    # the advice that follows is said once, in the closing summary line
    text = cap.out + cap.err
    assert text.count("`aqfg diagnose") == 1
    last = cap.err.strip().splitlines()[-1]
    assert last.startswith("aqfg fit: ") and f"`aqfg diagnose {otter} --out DIR`" in last
    if len(warned) > 1:
        assert f"{len(warned)} warnings above" in last


def run_logged(command: str, emit) -> str:
    """stderr of the CLI's logging set-up for ``command`` while ``emit`` logs."""
    buf = io.StringIO()
    common.setup(command, 0)
    h = next(h for h in common.log.handlers if getattr(h, "_aqfg_cli", False))
    h.setStream(buf)
    try:
        emit(buf)
        common.summary()
    finally:
        common.log.removeHandler(h)
    return buf.getvalue()


def test_a_repeated_warning_is_said_once_and_advice_to_run_itself_never():
    lg = logging.getLogger("aqfg.fg.test")
    misfit = ("the model does not explain the fixes: sigma inflated 6x; run `aqfg diagnose` "
              "to find the missing physics")

    def emit(_buf):
        lg.warning("fg: %s", misfit)
        lg.warning("fg: %s", misfit)
        lg.warning("fg: the data call for the effect x (try --effect x, or `aqfg diagnose`)")

    err = run_logged("diagnose", emit)
    assert err.count("sigma inflated 6x") == 1
    assert "`aqfg diagnose" not in err                 # the command that runs: no advice
    assert "(try --effect x)" in err
    assert err.strip().splitlines()[-1] == "aqfg diagnose: 2 warnings above"

    err = run_logged("fit", emit)                      # another command: advice once, last
    assert err.count("sigma inflated 6x") == 1 and err.count("`aqfg diagnose") == 1
    assert err.strip().splitlines()[-1] == ("aqfg fit: 2 warnings above; `aqfg diagnose MISSION "
                                            "--out DIR` finds the physics the model is missing")


def test_a_warning_does_not_land_inside_the_progress_bar():
    def emit(buf):
        buf.isatty = lambda: True                # a terminal: the bar is drawn
        bar = common.Progress("fit", stream=buf)
        bar(0.4, "solving")
        logging.getLogger("aqfg.fg.test").warning("a warning")
        bar(1.0, "done")

    err = run_logged("fit", emit)
    lines = err.split("\n")
    assert any(ln == "aqfg fit: warning: a warning" for ln in lines)
    assert not any("warning" in ln and "[" in ln for ln in lines)


# ---------------------------------------------------------------- fit: refuse, then estimate
def test_fit_refuses_to_overwrite_before_estimating_and_estimates_the_fixes_it_uses(
        short, tmp_path, capsys):
    out = tmp_path / "f"
    assert main(["fit", str(short), "--out", str(out), "--gnss-every", "8", "--no-plots"]) == 0
    err = capsys.readouterr().err
    n = int(re.search(r"([\d,]+) fixes", err).group(1).replace(",", ""))
    assert n == 16                                     # 121 fixes at 1 Hz, one every 8 s
    assert main(["fit", str(short), "--out", str(out), "--gnss-every", "8"]) == 2
    err = capsys.readouterr().err
    assert "refusing to overwrite" in err and "estimate:" not in err


# ---------------------------------------------------------------- help and options
def subparser(name: str):
    ap = build_parser()
    sub = next(a for a in ap._actions if a.dest == "command")
    return sub.choices[name]


@pytest.mark.parametrize("command", ["fit", "diagnose"])
def test_every_option_of_fit_and_diagnose_has_help(command):
    p = subparser(command)
    missing = [a.option_strings[0] for a in p._actions if a.option_strings and not a.help]
    assert missing == []


@pytest.mark.parametrize("argv, suggestion", [
    (["fit", "m", "--gnss-evry", "8", "--out", "o"], "--gnss-every"),
    (["fit", "m", "--out", "o", "-force"], "--force"),
    (["simulate", "o", "--sed", "3"], "--seed"),
    (["diagnose", "m", "--out", "o", "--efect", "linear_drag"], "--effect"),
])
def test_a_mistyped_option_gets_the_commands_usage_and_the_close_option(argv, suggestion,
                                                                         capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert f"usage: aqfg {argv[0]}" in err
    assert f"did you mean {suggestion}?" in err


def test_an_option_like_nothing_names_the_commands_help(capsys):
    with pytest.raises(SystemExit):
        main(["fit", "m", "--out", "o", "--zzzz"])
    err = capsys.readouterr().err
    assert "unrecognized option --zzzz" in err and "aqfg fit --help" in err
    assert "did you mean" not in err


def test_estimate_defaults_are_what_the_help_says(short, tmp_path):
    """--estimate's help: online fg estimates theta_e, s_x, s_y, and k, k_x, k_yz unless
    one is given; online update-error theta_e, s_x, s_y; batch the six."""
    hlp = " ".join(next(a.help for a in subparser("fit")._actions
                        if "--estimate" in a.option_strings).split())
    assert "batch, the six base parameters" in hlp
    assert "online fg, theta_e,s_x,s_y" in hlp and "plus k,k_x,k_yz unless" in hlp
    assert "online update-error, theta_e,s_x,s_y" in hlp

    def estimated(*extra: str) -> set[str]:
        out = tmp_path / "-".join(extra).replace("=", "")
        assert main(["fit", str(short), "--out", str(out), "--no-plots", "-q", *extra]) == 0
        return set(json.loads((out / "parameters.json").read_text())["parameters"])

    six = {"theta_e", "s_x", "s_y", "k", "k_x", "k_yz"}
    assert estimated("--mode", "online") == six
    assert estimated("--mode", "online", "--init", "k=8") == {"theta_e", "s_x", "s_y"}
    assert estimated("--mode", "online", "--method", "update-error") == {"theta_e", "s_x", "s_y"}
