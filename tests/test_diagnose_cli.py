"""``aqfg diagnose``: outputs exactly as the format doc's "Outputs", report, errors."""
import json
import re

import numpy as np

from aqfg.cli import main
from aqfg.data.io import save_mission
from aqfg.sim.simulator import simulate


def test_diagnose_writes_json_report_and_summary(wind_mission_dir, tmp_path, capsys):
    out = tmp_path / "diag"
    assert main(["diagnose", str(wind_mission_dir), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    data = json.loads((out / "diagnosis.json").read_text())
    # the format doc's keys
    assert isinstance(data["missing"], bool) and isinstance(data["ranking"], list)
    for r in data["ranking"]:
        assert {"effect", "score", "p_value", "estimate", "rmse_before", "rmse_after"} <= set(r)
        for v in r["estimate"].values():
            assert set(v) == {"value", "sigma"}
    names = [r["effect"] for r in data["ranking"]]
    from aqfg.model.effects import BUILTIN
    assert set(names) <= set(BUILTIN) and "usbl_range_scale" not in names   # no USBL here
    assert data["missing"] and names[0] == "wind_drag"
    assert data["ranking"][0]["rmse_after"] < data["ranking"][0]["rmse_before"]
    est = data["ranking"][0]["estimate"]
    assert abs(est["wind_drag.a_n"]["value"] - 0.06) < 3 * est["wind_drag.a_n"]["sigma"] + 0.005
    assert "wind_drag" in printed and "rank" in printed
    # the held-out RMS distance beside its noise floor, never a clipped 0.00-m error
    top = data["ranking"][0]
    assert top["noise_floor"] > 0 and top["rmse_raw_after"] < top["rmse_raw_before"]
    assert top["heldout_gain"] >= data["settings"]["min_gain"] == 0.1
    assert "noise floor" in printed and "-100%" not in printed
    html = (out / "report.html").read_text()
    assert "noise floor" in html
    assert html.count("data:image/png;base64,") >= 5
    assert not re.search(r'(src|href)="(?!data:)', html)          # self-contained
    assert "wind_drag" in html
    # refuses to overwrite without --force
    assert main(["diagnose", str(wind_mission_dir), "--out", str(out)]) == 2


def test_diagnose_with_effect_compares_before_after(wind_mission_dir, tmp_path, capsys):
    out = tmp_path / "diag2"
    assert main(["diagnose", str(wind_mission_dir), "--effect", "wind_drag", "--out", str(out),
                 "--no-plots"]) == 0
    data = json.loads((out / "diagnosis.json").read_text())
    assert data["model_effects"] == ["wind_drag"] and data["added"] == ["wind_drag"]
    assert "wind_drag" not in [r["effect"] for r in data["ranking"]]
    b, a = data["before"], data["base"]
    assert a["rmse"] < 0.7 * b["rmse"]
    assert a["consistency"]["passed"]
    assert "wind_drag.a_n" in a["parameters"]
    printed = capsys.readouterr().out
    assert "Added wind_drag" in printed
    assert "data:image/png" not in (out / "report.html").read_text()


def test_diagnose_bad_input(wind_mission_dir, tmp_path, capsys):
    assert main(["diagnose", str(wind_mission_dir), "--effect", "no_such_effect",
                 "--out", str(tmp_path / "x")]) == 2
    assert "no_such_effect" in capsys.readouterr().err
    assert main(["diagnose", str(tmp_path / "missing_dir"), "--out", str(tmp_path / "y")]) == 3
    assert main(["diagnose", str(wind_mission_dir), "--effect", "usbl_range_scale",
                 "--out", str(tmp_path / "z")]) == 2
    assert "not applicable" in capsys.readouterr().err
    assert main(["diagnose", str(wind_mission_dir), "--min-gain", "1.5",
                 "--out", str(tmp_path / "g")]) == 2
    err = capsys.readouterr().err
    assert "--min-gain" in err and "1.5" in err


def test_diagnose_logs_the_base_fits_warnings_once(tmp_path, capsys):
    """The base model's fit warns (here: sigma inflated, outliers down-weighted, on the
    REMUS mission); the candidates' refits keep their warnings in their results instead
    of repeating them (each said "run `aqfg diagnose`" seven times inside it)."""
    from conftest import data_path
    assert main(["diagnose", str(data_path("remus-dev-a")), "--out", str(tmp_path / "d")]) == 0
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ": warning: fg:" in ln]
    assert lines and len(lines) == len(set(lines)), lines


def test_a_run_shorter_than_two_horizons_is_diagnosed_over_one(tmp_path, capsys):
    """A 50-s run (a real boat's runs are often this short) holds fewer fixes than two 60-s
    prediction horizons: its long held-out predictions are one window to the end of the
    run, not a refusal ("not enough fixes to hold some out")."""
    d = tmp_path / "short"
    m, truth = simulate("asv", seed=2, duration=50.0, gnss_period=1.0)
    save_mission(m, d, truth=truth)
    out = tmp_path / "diag"
    assert main(["diagnose", str(d), "--out", str(out)]) == 0, \
        capsys.readouterr().err
    data = json.loads((out / "diagnosis.json").read_text())
    assert isinstance(data["missing"], bool) and data["ranking"]
