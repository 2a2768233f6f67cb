"""Model-vs-measurement comparison, fit/held-out split and conditions, on simulated truth."""
import numpy as np
import pytest

from aqfg.diagnose.compare import (fixes_of, predict_measurements, sensor_series, split_fixes)
from aqfg.diagnose.conditions import condition_signals
from aqfg.model.vehicle import Model
from aqfg.model.params import vector
from aqfg.result import MissionResult, Track
from aqfg.sim.simulator import simulate


@pytest.fixture(scope="module")
def sim():
    m, truth = simulate("asv", seed=3, duration=240.0, usbl=True)
    return m, truth


def _truth_result(m, truth):
    """A MissionResult built from the truth (what a perfect fit would return)."""
    model = Model.for_mission(m)
    p = vector({k: v for k, v in truth.params.items() if isinstance(v, (int, float))
                and k in model.all_names})
    tr = Track(truth.t, truth.pos, truth.vel)
    res = predict_measurements(model, m, tr, p, gnss_sigma=1.0,
                               usbl_sigma=(0.15, np.radians(1.5)))
    return model, p, MissionResult(m.name, tr, tr, p, res)


def test_truth_predicts_the_measurements_within_their_noise(sim):
    m, truth = sim
    model, p, mres = _truth_result(m, truth)
    ss = {s.sensor: s for s in sensor_series(mres)}
    g = ss["gnss"]
    assert g.labels == ("north", "east") and g.measured.shape == g.predicted.shape
    # the simulator's GNSS noise is 1 m: normalised residuals have unit variance
    assert abs(np.mean(g.normalised ** 2) - 1.0) < 0.2
    assert np.allclose(g.sigma(), 1.0)
    u = ss["usbl"]
    ok = np.all(np.abs(u.normalised) < 8, axis=1)   # acoustic outliers aside
    assert ok.mean() > 0.9
    assert abs(np.mean(u.normalised[ok] ** 2) - 1.0) < 0.35


def test_split_holds_out_fixes_and_fixes_have_covariances(sim):
    m, _ = sim
    sp = split_fixes(m, 8.0)
    assert np.all(np.diff(sp.fit.gnss.t) >= 8.0 - 1e-6)
    assert len(sp.fit.gnss.t) + len(sp.heldout.gnss.t) == len(m.gnss.t)
    assert not set(sp.fit.gnss.t) & set(sp.heldout.gnss.t)
    assert len(sp.fit.usbl.t) + len(sp.heldout.usbl.t) == len(m.usbl.t)
    assert abs(len(sp.fit.usbl.t) - len(sp.heldout.usbl.t)) <= 1
    fx = fixes_of(m)
    assert np.all(np.diff(fx.t) >= 0)
    u = fx.source == "usbl"
    # USBL: radial sigma 0.15 m, tangential range x 1.5 deg, so the larger eigenvalue grows with range
    ev = np.sqrt(np.linalg.eigvalsh(fx.cov[u]))
    rng = np.linalg.norm(fx.ne[u] - m.usbl_station[:2], axis=1)
    far = rng > 10.0
    assert far.sum() > 10
    assert np.allclose(ev[far, 0], 0.15, rtol=1e-6)
    assert np.allclose(ev[far, 1], rng[far] * np.radians(1.5), rtol=1e-6)


def test_held_out_fixes_take_the_sigma_given(sim):
    """The held-out fixes' sigma (their noise floor) is the one given; the fit's fixes keep
    theirs."""
    m, _ = sim
    plain = split_fixes(m, 8.0)
    sp = split_fixes(m, 8.0, 0.07)
    assert np.all(sp.heldout.gnss.sigma == 0.07)
    np.testing.assert_array_equal(sp.heldout.gnss.t, plain.heldout.gnss.t)
    assert sp.fit.gnss.sigma is plain.fit.gnss.sigma or np.array_equal(sp.fit.gnss.sigma,
                                                                        plain.fit.gnss.sigma)
    assert m.gnss.sigma is None or not np.all(m.gnss.sigma == 0.07)    # the mission kept


def test_conditions_follow_the_truth(sim):
    m, truth = sim
    sig = condition_signals(m, Track(truth.t, truth.pos, truth.vel), theta_e=0.0)
    # turn rate from the IMU attitude vs the true yaw rate
    yaw = np.unwrap(truth.yaw)
    true_rate = np.abs(np.gradient(yaw, truth.t))
    est = np.interp(truth.t, sig.t, sig.values["turn_rate"])
    assert np.corrcoef(est, true_rate)[0, 1] > 0.8
    spd = np.interp(truth.t, sig.t, sig.values["speed"])
    assert np.allclose(spd, np.linalg.norm(truth.vel[:, :2], axis=1), atol=1e-6)
    assert sig.values["thrust"].max() <= 1.0 and "station_distance" in sig.values
    # window means: the mean of a constant is the constant; of elapsed time over [t-8, t], t-4
    t = np.array([50.0, 100.0])
    assert np.allclose(sig.mean_before("elapsed", t, 8.0), t - m.t0 - 4.0, atol=0.1)
