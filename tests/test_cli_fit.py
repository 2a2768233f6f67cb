"""``aqfg fit``: the output files of the format doc, plots, methods, modes and bad input."""
from __future__ import annotations

import json

import numpy as np
import pytest

from aqfg.cli import main
from aqfg.data.io import save_mission
from aqfg.sim.simulator import simulate

HEADER = "t,north,east,down,vn,ve,vd"


@pytest.fixture(scope="module")
def missions(tmp_path_factory):
    root = tmp_path_factory.mktemp("missions")
    out = []
    for seed in (1, 2):
        m, tr = simulate("asv", seed=seed, duration=150.0)
        d = root / f"m{seed}"
        save_mission(m, d, truth=tr)
        out.append((d, tr))
    return out


def read_track(path):
    lines = path.read_text().splitlines()
    assert lines[0] == HEADER
    return np.loadtxt(path, delimiter=",", skiprows=1)


def test_fit_batch_writes_outputs_and_plots(missions, tmp_path, capsys):
    (d, tr), _ = missions
    out = tmp_path / "fit"
    assert main(["fit", str(d), "--out", str(out), "--gnss-every", "8"]) == 0
    doc = json.loads((out / "parameters.json").read_text())
    params = doc["parameters"]
    assert list(params) == ["k", "k_x", "k_yz", "theta_e", "s_x", "s_y"]
    for n, e in params.items():
        assert set(e) == {"value", "sigma", "unit"} and e["sigma"] > 0
    assert params["theta_e"]["unit"] == "rad" and doc["fixed"] == {}
    assert abs(params["theta_e"]["value"] - tr.params["theta_e"]) < 3 * params["theta_e"]["sigma"]
    traj, inert = read_track(out / "trajectory.csv"), read_track(out / "inertial.csv")
    assert traj.shape[1] == inert.shape[1] == 7 and np.all(np.diff(traj[:, 0]) > 0)
    assert inert[0, 0] == pytest.approx(0.0) and inert[-1, 0] == pytest.approx(150.0, abs=0.1)
    assert (out / "map.png").stat().st_size > 10_000
    printed = capsys.readouterr().out
    assert "theta_e" in printed and "sigma" in printed and "map.png" in printed
    # the simulated vehicle is the model: its track keeps the nominal process noise
    assert list(doc["track"]["process_noise_scale"].values()) == [1.0]
    assert "trajectory smoothed with the process noise" not in printed
    # existing outputs are not replaced without --force
    assert main(["fit", str(d), "--out", str(out)]) == 2
    assert "refusing to overwrite" in capsys.readouterr().err
    assert main(["fit", str(d), "--out", str(out), "--force", "--no-plots",
                 "--estimate", "theta_e,s_x,s_y", "--init", "k=9.26"]) == 0
    doc = json.loads((out / "parameters.json").read_text())
    assert list(doc["parameters"]) == ["theta_e", "s_x", "s_y"]
    assert doc["fixed"]["k"]["value"] == 9.26 and set(doc["fixed"]) == {"k", "k_x", "k_yz"}
    assert not (out / "map.png").exists()          # --force replaced the whole set


def test_fit_online_and_two_missions(missions, tmp_path, capsys, monkeypatch):
    (d1, tr1), (d2, _) = missions
    out = tmp_path / "online"
    fixed = tmp_path / "fixed.json"
    fixed.write_text(json.dumps({n: {"value": tr1.params[n], "sigma": 0.0}   # earlier layout
                                 for n in ("k", "k_x", "k_yz")}))
    import aqfg.outputs
    reads: list[str] = []
    real_read = aqfg.outputs.read_json
    monkeypatch.setattr(aqfg.outputs, "read_json", lambda p, *a: reads.append(str(p)) or
                        real_read(p, *a))
    assert main(["fit", str(d1), "--out", str(out), "--mode", "online", "--window", "24",
                 "--gnss-every", "8", "--params-from", str(fixed)]) == 0
    assert reads.count(str(fixed)) == 1                  # the file is read once
    doc = json.loads((out / "parameters.json").read_text())
    assert set(doc["parameters"]) == {"theta_e", "s_x", "s_y"}
    # the online run's record: its batch re-initialisations (the heading was not given)
    rec = doc["online"]
    assert rec["reinit_batches"] and all({"t", "theta_e", "restarted", "reference"} <= set(b)
                                         for b in rec["reinit_batches"])
    assert any(e["event"].startswith("re-initialised") for e in rec["events"])
    assert rec["process_noise_scale"] >= 1.0
    assert "online: re-initialised from a batch solve of the fixes so far: " in capsys.readouterr().out
    assert {n: e["value"] for n, e in doc["fixed"].items()} == \
        {n: tr1.params[n] for n in ("k", "k_x", "k_yz")}      # the fixed values it used
    assert (out / "parameters.png").stat().st_size > 10_000
    traj = read_track(out / "trajectory.csv")
    assert traj[-1, 0] == pytest.approx(150.0, abs=0.1)
    # the causal track: the real-time estimate, on the same clock, not the corrected one
    causal = read_track(out / "causal.csv")
    assert causal.shape[1] == traj.shape[1] and np.all(np.diff(causal[:, 0]) > 0)
    assert 150.0 - 8.0 - 1e-6 <= causal[-1, 0] <= traj[-1, 0] + 1e-6    # to the last fix
    at = np.column_stack([np.interp(causal[:, 0], traj[:, 0], traj[:, c]) for c in (1, 2)])
    assert np.max(np.hypot(*(causal[:, 1:3] - at).T)) > 0.01
    out2 = tmp_path / "two"
    assert main(["fit", str(d1), str(d2), "--out", str(out2), "--gnss-every", "8",
                 "--no-plots"]) == 0
    subdirs = sorted(p.name for p in out2.iterdir() if p.is_dir())
    assert len(subdirs) == 2
    for s in subdirs:
        assert (out2 / s / "trajectory.csv").exists() and (out2 / s / "inertial.csv").exists()


def test_fit_update_error_method(missions, tmp_path):
    (d, _), _ = missions
    out = tmp_path / "ue"
    assert main(["fit", str(d), "--out", str(out), "--method", "update-error",
                 "--estimate", "theta_e,s_x,s_y", "--gnss-every", "8", "--no-plots"]) == 0
    assert set(json.loads((out / "parameters.json").read_text())["parameters"]) == \
        {"theta_e", "s_x", "s_y"}


def test_fit_bad_input(missions, tmp_path, capsys):
    (d, _), _ = missions
    assert main(["fit", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]) == 3   # data
    assert main(["fit", str(d), "--out", str(tmp_path / "o"), "--estimate", "k,bogus"]) == 2
    assert "bogus" in capsys.readouterr().err
    assert main(["fit", str(d), "--out", str(tmp_path / "o"), "--init", "k=abc"]) == 2
    assert "'k' must be a number" in capsys.readouterr().err
    assert main(["fit", str(d), "--out", str(tmp_path / "o"), "--effect", "warp_drive"]) == 2
    assert "warp_drive" in capsys.readouterr().err
    assert main(["fit", str(d), "--out", str(tmp_path / "o"), "--params-from",
                 str(tmp_path / "missing.json")]) == 3
    assert not (tmp_path / "o").exists()


def fit_online_with_true_constants(m, tr, tmp_path, capsys, *extra: str) -> str:
    """``aqfg fit --mode online`` of ``m`` with its true thrust/drag constants
    (``--params-from``) and the ``extra`` arguments; the printed output."""
    d = tmp_path / "m"
    save_mission(m, d, truth=tr)
    fixed = tmp_path / "fixed.json"
    fixed.write_text(json.dumps({"parameters": {n: {"value": tr.params[n], "sigma": 0.0}
                                                for n in ("k", "k_x", "k_yz")}}))
    assert main(["fit", str(d), "--out", str(tmp_path / "o"), "--mode", "online",
                 "--params-from", str(fixed), "--no-plots", "-q", *extra]) == 0
    return capsys.readouterr().out


def test_fit_online_says_which_usbl_fixes_the_gate_left_out(tmp_path, capsys):
    import dataclasses
    m, tr = simulate("asv", seed=3, duration=150.0, usbl=True, usbl_outlier_rate=0.0,
                     gnss_period=8.0)
    rng = m.usbl.range.copy()
    rng[15] += 12.0                       # one range outlier (80 sigma)
    m = dataclasses.replace(m, usbl=dataclasses.replace(m.usbl, range=rng))
    out = fit_online_with_true_constants(m, tr, tmp_path, capsys)
    assert f"1 USBL fixes left out by the innovation gate (at {m.usbl.t[15]:.1f} s)" in out


def test_fit_online_says_what_the_gtsam_engine_leaves_out(tmp_path, capsys):
    """A measurement effect (a lever arm) runs on the GTSAM engine, which keeps the current
    and the heading offset constant in the window's past: the command says so."""
    m, tr = simulate("auv", seed=6, duration=60.0, usbl=True, gnss_period=8.0)
    out = fit_online_with_true_constants(m, tr, tmp_path, capsys, "--effect", "lever_arm")
    assert "online: GTSAM engine" in out and "online.heading_walk needs the numpy engine" in out


def test_fit_batch_says_the_track_needed_more_process_noise(tmp_path, capsys):
    """On an Otter mission (not the model) the trajectory is smoothed with the process noise
    the evidence chooses, recorded in parameters.json and said."""
    from conftest import data_path
    from aqfg.data import load_truth
    d = data_path("otter-dev-calm-a")
    out = tmp_path / "fit"
    assert main(["fit", str(d), "--out", str(out), "--gnss-every", "8", "--no-plots"]) == 0
    doc = json.loads((out / "parameters.json").read_text())
    q = doc["track"]["process_noise_scale"]["otter-dev-calm-a"]
    assert q > 1.0
    assert f"trajectory smoothed with the process noise x{q:g} (otter-dev-calm-a)" in \
        capsys.readouterr().out
    traj, truth = read_track(out / "trajectory.csv"), load_truth(d)
    e = np.hypot(*(traj[:, 1:3] - np.column_stack([np.interp(traj[:, 0], truth.t, truth.pos[:, a])
                                                   for a in range(2)])).T)
    assert np.sqrt(np.mean(e ** 2)) < 1.0          # 1.4 m with the nominal noise


def test_fit_batch_writes_and_says_the_structural_sigma(tmp_path, capsys):
    """On the Otter (linear drag missing from the model) parameters.json carries the
    effect the data call for, the shift and the sigma before it, and its sigma is the
    combination; the warning names the effect and how to add it."""
    from conftest import data_path
    out = tmp_path / "fit"
    assert main(["fit", str(data_path("otter-example")), "--out", str(out), "--no-plots",
                 "--no-auto-effect"]) == 0
    doc = json.loads((out / "parameters.json").read_text())
    assert "auto_effect" not in doc and doc["provenance"]["effects"] == []
    st = doc["sigma_structure"]
    assert st["effect"] == "linear_drag" and st["p_value_robust"] < 1e-3
    # ... the fit again with it, whose move of each estimate the sigma holds where it
    # exceeds the first-order shift (aqfg.fg.fit.refit_structure)
    move = st["refit"]["move"]
    assert set(move) >= set(st["shift"]) and st["refit"]["cost"] > 0
    for n, d in st["shift"].items():
        assert doc["parameters"][n]["sigma"] == pytest.approx(
            np.hypot(st["sigma_before"][n], max(d, move[n])))
    assert "try --effect linear_drag" in capsys.readouterr().err


def test_update_error_batch_with_an_undetermined_parameter_completes(tmp_path, capsys):
    """A 40-s Otter crop: the update-error method cannot determine s_y and k_yz (sigma null
    in parameters.json); the command still ends with its table, not an internal error."""
    from conftest import data_path
    out = tmp_path / "ue"
    assert main(["fit", str(data_path("otter-heldout-93-40s")), "--method", "update-error",
                 "--out", str(out), "--no-plots"]) == 0
    doc = json.loads((out / "parameters.json").read_text())
    assert doc["parameters"]["k_yz"]["sigma"] is None and "internal error" not in \
        capsys.readouterr().err


def test_fit_with_heading_drift_says_the_offset_at_the_end(tmp_path, capsys):
    """With heading_drift, theta_e is the offset at the mission start: the table says so and
    gives the drifted offset at the end, within 3 deg of otter-dev-yawdrift's truth there
    (-10 deg + 0.02 deg/s)."""
    import re

    from conftest import data_path
    from aqfg.data import load_truth
    d = data_path("otter-dev-yawdrift")
    out = tmp_path / "fit"
    assert main(["fit", str(d), "--out", str(out), "--gnss-every", "8", "--no-plots",
                 "--effect", "heading_drift", "--no-auto-effect"]) == 0
    said = re.search(r"with the drift it is (-?[\d.]+) deg at the end, t0 \+ (\d+) s",
                     capsys.readouterr().out)
    assert said, "no offset at the end"
    P = load_truth(d).params
    truth_end = np.degrees(P["theta_e"] + P["heading_drift.rate"] * float(said[2]))
    assert abs(float(said[1]) - truth_end) < 3.0


def test_params_from_takes_the_vehicle_not_the_other_missions_heading(tmp_path, capsys):
    """The paper's protocol on the command line: online with ``--params-from`` a batch fit
    of another mission. That file also holds the other mission's heading offset and
    current; taken as given, the online fit started from otter-dev-calm-b's -35 deg on a
    mission at +30 deg and ran no batch initialisation (on a fresh Otter mission it ended
    142 deg off with a 0.75 m/s current). Only the vehicle's values are taken: the heading
    offset and the current are estimated afresh, from a batch initialisation."""
    from conftest import data_path
    from aqfg.data import load_truth
    donor = tmp_path / "donor"
    assert main(["fit", str(data_path("otter-dev-calm-b")), "--out", str(donor),
                 "--gnss-every", "8", "--no-plots"]) == 0
    params = json.loads((donor / "parameters.json").read_text())
    assert {"theta_e", "s_x", "s_y"} <= set(params["parameters"])
    capsys.readouterr()
    d = data_path("otter-dev-calm-a")
    out = tmp_path / "online"
    assert main(["fit", str(d), "--out", str(out), "--mode", "online", "--gnss-every", "8",
                 "--params-from", str(donor / "parameters.json"), "--no-plots"]) == 0
    said = capsys.readouterr()
    assert "theta_e, s_x, s_y of the mission it was fitted on are estimated afresh" in said.err
    # no heading_drift in this model: the table says nothing of a drifted offset
    assert "theta_e" in said.out and "with the drift" not in said.out
    doc = json.loads((out / "parameters.json").read_text())
    assert doc["online"]["reinit_batches"], "no batch initialisation: the heading was taken"
    # the donor's constants, as its file gave them
    for n in ("k", "k_x"):
        assert doc["fixed"][n]["value"] == pytest.approx(params["parameters"][n]["value"])
    err = np.degrees(abs(np.angle(np.exp(1j * (doc["parameters"]["theta_e"]["value"]
                                               - load_truth(d).params["theta_e"])))))
    assert err < 5.0, err


def test_the_gnss_noise_measured_on_dense_fixes_travels_with_params_from(missions, tmp_path):
    """A batch fit of 1-s fixes writes the GNSS noise it measured (white simulated noise of
    1 m: sigma about 1, tau below the spacing); an online fit of 8-s fixes with
    ``--params-from`` that file weighs its fixes by it and says so."""
    (d, _), _ = missions
    a, b = tmp_path / "batch", tmp_path / "online"
    assert main(["fit", str(d), "--out", str(a), "--no-plots", "--no-auto-effect"]) == 0
    gn = json.loads((a / "parameters.json").read_text())["gnss_noise"]
    assert gn["sigma"] == pytest.approx(1.0, rel=0.2) and gn["tau"] < 1.0
    assert gn["n_fixes"] > 100 and gn["spacing"] == pytest.approx(1.0)
    assert main(["fit", str(d), "--out", str(b), "--no-plots", "--mode", "online",
                 "--gnss-every", "8", "--params-from", str(a / "parameters.json")]) == 0
    assert json.loads((b / "parameters.json").read_text())["gnss_noise"] == gn
