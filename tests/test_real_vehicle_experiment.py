"""experiments/real_vehicle.py end to end on two simulated runs of recorded-run shape (5-Hz
GNSS, no truth used): every section of the table and its checks are written, and a run
an estimator cannot fit is scored as failed instead of ending the experiment."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

from aqfg.data import save_mission
from aqfg.sim.simulator import simulate

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def _experiment():
    spec = importlib.util.spec_from_file_location("real_vehicle", ROOT / "experiments" / "real_vehicle.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["real_vehicle"] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    d = tmp_path_factory.mktemp("runs")
    for seed in (4, 5):      # run4's propellers push half as hard backwards
        m, _ = simulate("asv", seed=seed, duration=150.0, gnss_period=0.2, gnss_sigma=0.3,
                        effects={"reverse_thrust": 0.5} if seed == 4 else None)
        m.name = f"run{seed}"
        save_mission(m, d / m.name)
    return d


def test_the_table_has_every_section_and_check(runs, tmp_path):
    rv = _experiment()
    out = tmp_path / "table.md"
    assert rv.main([str(runs), "--out", str(out)]) == 0
    text = out.read_text()
    for head in ("## GNSS noise", "## Heading offset", "## Model-only prediction",
                 "## Online", "## Diagnosis", "## Wall times", "## Checks"):
        assert head in text
    for check in ("(a) theta_e", "(b) 60-s prediction (8 s)", "(b) re-trace (all fixes)",
                  "(c) online causal8", "(4) diagnosis: 2/2 runs diagnosed"):
        assert check in text
    assert "failed" not in text.split("## Checks")[1]
    # the diagnosis names the hidden effect, and the run is scored again with it
    diag = next(line for line in text.splitlines() if line.startswith("| run4 | reverse_thrust"))
    assert "ratio" in diag
    learned = text.split("## With the diagnosed model")[1].split("##")[0]
    assert "| run4 |" in learned and "| run5 |" not in learned


def test_a_run_the_fit_refuses_is_scored_as_failed(runs, tmp_path, monkeypatch):
    rv = _experiment()
    real = rv.batch_scores

    def refuse(method, m, *a):
        if method == "fg" and m.name == "run5":
            raise ValueError("refused")
        return real(method, m, *a)
    monkeypatch.setattr(rv, "batch_scores", refuse)
    out = tmp_path / "table.md"
    assert rv.main([str(runs), "--out", str(out), "--no-diagnosis"]) == 0
    text = out.read_text()
    assert "failed (scored as n/a, counted against the method): run5 fg: batch: ValueError" in text
    row = next(line for line in text.splitlines() if line.startswith("| run5 |") and "/" in line)
    assert "n/a" in row
