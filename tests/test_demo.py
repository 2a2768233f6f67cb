"""The main job end to end: `aqfg demo` simulates, fits the model as given, diagnoses,
and fits both methods with and without the missing effect. Asserts on what it writes, and
that what it prints is what it wrote."""
import json

import numpy as np
import pytest

from aqfg.cli import main
from aqfg.commands.demo import DEMO_EFFECT, table_lines
from aqfg.data.io import load_mission, load_truth

SIX = {"theta_e", "s_x", "s_y", "k", "k_x", "k_yz"}


@pytest.mark.slow
def test_demo_finds_the_hidden_effect_and_the_error_falls(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out)]) == 0
    mission = load_mission(out / "mission")
    truth = load_truth(out / "mission")
    hidden = next(iter(DEMO_EFFECT))
    assert hidden in truth.params["effects"]

    for method in ("fg", "update-error"):
        doc = json.loads((out / f"fit-{method}" / "parameters.json").read_text())
        params = doc["parameters"]
        assert set(params) == SIX and doc["provenance"]["method"] == method
        assert all(np.isfinite(v["value"]) for v in params.values())
        tr = np.loadtxt(out / f"fit-{method}" / "trajectory.csv", delimiter=",", skiprows=1)
        assert tr.shape[1] == 7 and tr[0, 0] <= mission.gnss.t[0] + 1.0

    diag = json.loads((out / "diagnosis" / "diagnosis.json").read_text())
    assert diag["provenance"]["aqfg"]
    assert diag["missing"] is True
    top = diag["ranking"][0]
    assert top["effect"] == hidden
    assert top["rmse_after"] < 0.7 * top["rmse_before"]

    after = json.loads((out / f"diagnosis-with-{hidden}" / "diagnosis.json").read_text())
    assert after["consistency"]["passed"] is True
    assert (out / "diagnosis" / "report.html").stat().st_size > 10_000
    with_eff = json.loads((out / f"fit-fg-with-{hidden}" / "parameters.json").read_text())[
        "parameters"]
    name = f"{hidden}.ratio"
    assert abs(with_eff[name]["value"] - truth.params[name]) < 3 * with_eff[name]["sigma"] + 0.02
    # one story: the console's table and its numbers are demo.json's, whose values are
    # each fit's parameters.json
    printed = capsys.readouterr()
    demo = json.loads((out / "demo.json").read_text())
    assert demo["missing"] == hidden == top["effect"]
    for line in table_lines(demo["rows"]):
        assert line in printed.out
    fits = [r for r in demo["rows"] if r.get("dir")]
    assert {(r["model"], r["method"]) for r in fits} == {
        (m, k) for m in ("as given", f"with {hidden}") for k in ("fg", "update-error")}
    for r in fits:
        params = json.loads((out / r["dir"] / "parameters.json").read_text())["parameters"]
        for n, v in r["values"].items():
            assert params[n]["value"] == pytest.approx(v, rel=1e-9)
    # the effect brings both methods' model-only tracks close to the truth's
    rmse = {(r["model"], r["method"]): r["track_rmse_m"] for r in fits}
    for k in ("fg", "update-error"):
        assert rmse[(f"with {hidden}", k)] < 0.6 * rmse[("as given", k)]
    # the fit's own words come once, in the story, not as stderr warnings
    for w in demo["fit_warnings"]:
        assert printed.out.count(w) == 1 and w not in printed.err
    assert "aqfg diagnose`" not in printed.out + printed.err
    # a second run into the same directory is refused, nothing overwritten
    assert main(["demo", "--out", str(out)]) == 2
    assert "refusing" in capsys.readouterr().err
