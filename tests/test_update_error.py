"""The update-error method on simulated missions with known truth (issue 3, "Done when").

Offline: k, k_x, k_yz recovered from two 10-minute missions of one vehicle (GNSS every 8 s,
or USBL only), and the dead-reckoning RMSE on a third mission with the estimates clearly
below that with the paper's "old" parameters (Table II). Online: a 30 deg heading error and
a current corrected. Tolerances come from a 6-seed Monte Carlo of each scenario (worst case
quoted per test) with a margin; the seeds here are fixed, not chosen.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np
import pytest

from aqfg.ekf.estimator import UpdateErrorEstimator
from aqfg.ekf.window import run_window
from aqfg.data.mission import with_gnss_every, without_gnss
from aqfg.model.vehicle import Model
from aqfg.model.params import OLD_PARAMS
from aqfg.model.retrace import inertial_track
from aqfg.sim.simulator import simulate

FIXED = ("k", "k_x", "k_yz")
VARIABLE = ("theta_e", "s_x", "s_y")
HEADING = {"theta_e": np.radians(30.0), "s_x": 0.1, "s_y": -0.05}


@lru_cache(maxsize=None)
def mission(vehicle: str, seed: int, fixes: str = "gnss", heading: bool = False):
    """A 10-minute mission with GNSS every 8 s ("gnss"), USBL only after the launch fix
    ("usbl") or GNSS at 1 Hz ("full", for test missions); and its truth."""
    m, tr = simulate(vehicle, seed=seed, duration=600.0, usbl=(fixes == "usbl"),
                     params=HEADING if heading else None)
    if fixes == "gnss":
        m = with_gnss_every(m, 8.0)
    elif fixes == "usbl":
        m = without_gnss(m, keep_first=True)
    return m, tr


def track_error(track, truth) -> np.ndarray:
    """Horizontal distance (m) from the truth at the track's times."""
    P = np.column_stack([np.interp(track.t, truth.t, truth.pos[:, i]) for i in range(2)])
    return np.linalg.norm(track.pos[:, :2] - P, axis=1)


def dead_reckoning_rmse(vehicle: str, seed: int, fixed: dict) -> float:
    """Inertial-track RMSE (m) on a test mission, with the test mission's true heading
    offset and current and the given fixed parameters (Table II protocol)."""
    m, tr = mission(vehicle, seed, "full")
    model = Model.for_mission(m)
    p = model.nominal({**{n: tr.params[n] for n in VARIABLE}, **fixed})
    return float(np.sqrt(np.mean(track_error(inertial_track(model, m, p), tr) ** 2)))


def offline(vehicle: str, fixes: str, seed: int = 1, **kw):
    ms = [mission(vehicle, s, fixes)[0] for s in (seed, seed + 100)]
    r = UpdateErrorEstimator(None, ms, **kw).run_offline()
    truth = mission(vehicle, seed, fixes)[1].params
    rel = {n: r.values[n] / truth[n] - 1.0 for n in FIXED}
    rmse_old = dead_reckoning_rmse(vehicle, seed + 200, OLD_PARAMS)
    rmse_est = dead_reckoning_rmse(vehicle, seed + 200, {n: r.values[n] for n in FIXED})
    return r, rel, rmse_old, rmse_est


# Monte Carlo, seeds 1-6 (train on seed and seed + 100, test on seed + 200), defaults:
# worst |relative error| of k, k_x, k_yz; worst |error| of k / k_x; worst RMSE ratio
# estimated / old; worst per-mission heading offset error (deg) and current error (m/s,
# seeds 1-4):
#   ASV GNSS 8 s   0.17 0.20 0.12  0.023  0.20  2.5  0.010
#   AUV GNSS 8 s   0.05 0.05 0.12  0.021  0.13  0.9  0.013
#   ASV USBL only  0.16 0.17 0.11  0.030  0.27  3.6  0.055
#   AUV USBL only  0.05 0.04 0.14  0.039  0.18  2.8  0.070
# (USBL-only currents carry a bias of the update-error metric itself: with
# metric="whitened" the current errors of the same runs fall to ~0.01 m/s.)
@pytest.mark.slow
@pytest.mark.parametrize("vehicle,fixes", [("asv", "gnss"), ("auv", "gnss"), ("asv", "usbl"),
                                           ("auv", "usbl")])
def test_offline_recovers_fixed_parameters_and_beats_the_old_ones(vehicle, fixes):
    r, rel, rmse_old, rmse_est = offline(vehicle, fixes)
    tol = {"k": 0.25, "k_x": 0.25, "k_yz": 0.25}
    for n in FIXED:
        assert abs(rel[n]) < tol[n], f"{n}: estimate {r.values[n]:.3f}, relative error {rel[n]:+.2f}"
    # k / k_x sets the cruise speed: far better determined than either
    truth = mission(vehicle, 1, fixes)[1].params
    ratio = (r.values["k"] / r.values["k_x"]) / (truth["k"] / truth["k_x"])
    assert abs(ratio - 1) < 0.06
    assert rmse_est < 0.4 * rmse_old, (rmse_est, rmse_old)
    # per-mission heading offsets and currents are estimated alongside (§III-A)
    for s, mr in zip((1, 101), r.missions):
        tp = mission(vehicle, s, fixes)[1].params
        assert abs(np.degrees(mr.p[0] - tp["theta_e"])) < 5.0
        assert np.all(np.abs(mr.p[1:3] - [tp["s_x"], tp["s_y"]]) < (0.03 if fixes == "gnss" else 0.1))
    assert r.info["evaluations"] == len(r.timings["evaluation"]) > 10
    assert all(np.isfinite(r.sigma[n]) and r.sigma[n] > 0 for n in FIXED)


@pytest.mark.slow
def test_offline_paper_preset_also_beats_the_old_parameters():
    """The Ceres-like preset (one scalar residual, paper bounds) on the ASV: ~1900 error
    evaluations (200 iterations) instead of ~80, but as accurate here (seeds 1-3: |relative
    error| <= 0.13, RMSE ratio <= 0.18)."""
    r, rel, rmse_old, rmse_est = offline("asv", "gnss", preset="paper")
    assert r.info["preset"] == "paper"
    assert 2.0 <= r.values["k"] <= 14.0
    assert all(abs(rel[n]) < 0.25 for n in FIXED), rel
    assert rmse_est < 0.4 * rmse_old
    assert r.info["evaluations"] > 200


def _online(vehicle, fixes, seed, **kw):
    m, tr = mission(vehicle, seed, fixes, heading=True)
    init = {n: tr.params[n] for n in FIXED}
    est = UpdateErrorEstimator(None, m, init=init)
    h = est.histories[0]
    a = h.anchors[h.k_start]
    plain = run_window(h, est.p0[0], a.x, a.P, h.k_start, len(h.knots) - 1, record=True)
    t = h.knots[h.k_start:]
    from aqfg.result import Track
    err_plain = track_error(Track(t, plain.X[:, :3], plain.X[:, 3:6]), tr)
    r = est.run_online(**kw)
    err_filt = track_error(r.missions[0].filtered, tr)
    err_corr = track_error(r.missions[0].track, tr)
    late = t > 60.0
    return r, tr, err_plain[late].mean(), err_filt[late].mean(), err_corr[late].mean()


# Monte Carlo (seeds 1-6), online with the fixed parameters known, 30 deg heading error and a
# (0.1, -0.05) m/s current. Per seed, over the estimates after t = 100 s: median of the
# theta_e error, median of its absolute value (deg), current error of the medians (m/s);
# causal track error / that of the EKF without estimation, corrected / causal (t > 60 s).
# Mean over seeds (worst seed):
#   window     scenario   median dtheta  median |dtheta|  |ds|          causal/plain  corr/causal
#   3 fixes    ASV GNSS   6.2 (16.5)     22 (33)          0.03 (0.06)   0.80 (1.02)   0.52 (0.55)
#   (paper's)  AUV GNSS   9.4 (19.1)     22 (45)          0.03 (0.06)   0.90 (0.99)   0.53 (0.57)
#              ASV USBL   14 (33)        46 (67)          0.10 (0.26)   0.82 (1.53)   0.47 (0.51)
#   6 fixes    ASV GNSS   1.5 (2.9)      7.3 (11)         0.02 (0.04)   0.63 (0.81)   0.67 (0.72)
#              AUV GNSS   1.8 (3.6)      7.6 (13)         0.02 (0.04)   0.68 (0.84)   0.71 (0.76)
#   10 fixes   ASV USBL   1.8 (3.2)      7.0 (9.7)        0.04 (0.09)   0.66 (1.26)   0.57 (0.66)
#              AUV USBL   2.3 (9.6)      12 (31)          0.04 (0.08)   1.02 (2.30)   0.62 (0.74)
# On straight legs heading offset and current are nearly interchangeable over 24 s, so the
# paper's short window gives noisy estimates on these missions; longer windows fix that.
# Early on (few fixes, wild estimates) the causal track can be worse than without
# estimation; the corrected track (past-trajectory correction) is better in every run.
@pytest.mark.parametrize("vehicle,fixes,window_fixes", [("asv", "gnss", 6), ("auv", "gnss", 6),
                                                        ("asv", "usbl", 10)])
def test_online_corrects_a_30_degree_heading_error_and_a_current(vehicle, fixes, window_fixes):
    r, tr, e_plain, e_filt, e_corr = _online(vehicle, fixes, 2, window_fixes=window_fixes)
    H = r.history
    assert H.names == VARIABLE and len(H.t) > 40
    late = H.t > 100.0
    d_theta = np.degrees(np.angle(np.exp(1j * (H.values[late, 0] - tr.params["theta_e"]))))
    assert abs(np.median(d_theta)) < 10.0, np.median(d_theta)
    assert np.median(np.abs(d_theta)) < 20.0
    s_err = np.median(H.values[late, 1:3], axis=0) - [tr.params["s_x"], tr.params["s_y"]]
    assert np.all(np.abs(s_err) < 0.1), s_err
    # the causal track is better than the same EKF without estimation, and correcting the
    # past with the new parameters (§III-D) improves it further
    assert e_filt < 0.9 * e_plain, (e_filt, e_plain)
    assert e_corr < 0.8 * e_filt
    nc = np.array(r.info["nonconvergence"])
    assert nc.shape == (len(H.t), 3) and np.isfinite(nc[2:]).all()


def test_online_with_the_papers_three_fix_window():
    """Default settings (window = last 3 fixes, every fix): estimates are noisy (see the
    Monte Carlo above) but the heading offset still moves from 0 towards the truth and the
    corrected track beats the filter without estimation."""
    r, tr, e_plain, e_filt, e_corr = _online("asv", "gnss", 2)
    late = r.history.t > 100.0
    th = np.degrees(np.median(r.history.values[late, 0]))
    assert abs(th - 30.0) < 20.0, th
    assert e_corr < e_plain
    assert r.info["window_fixes"] == 3
    n = r.info["evaluations_per_optimisation"]
    assert len(n) == len(r.timings["optimisation"]) == len(r.history.t)
    assert sum(n) == r.info["evaluations"] == len(r.timings["evaluation"])


def test_whitened_metric_on_usbl_only():
    """metric="whitened" (not the paper's: squared innovations whitened by S) on the USBL-only
    ASV: currents within 0.03 m/s (the update error's outward current bias, which this metric
    never had, is fixed at its source: the USBL covariance's orientation)."""
    ms = [mission("asv", s, "usbl")[0] for s in (1, 101)]
    r = UpdateErrorEstimator(None, ms, metric="whitened").run_offline(sigma=False)
    assert r.info["metric"] == "whitened"
    for s, mr in zip((1, 101), r.missions):
        tp = mission("asv", s, "usbl")[1].params
        assert np.all(np.abs(mr.p[1:3] - [tp["s_x"], tp["s_y"]]) < 0.03)
    truth = mission("asv", 1, "usbl")[1].params
    assert all(abs(r.values[n] / truth[n] - 1) < 0.15 for n in FIXED)


# ---------------------------------------------------------------- defects found against the paper
def test_usbl_only_current_is_not_biased_outward_from_the_station():
    """The USBL covariance used to turn with the measured bearing: the update error then
    preferred a current pointing away from the station (0.02-0.06 m/s on every seed, 5-9
    sigma). Oriented at the predicted position the bias is gone (seeds 1-6: <= 0.007 m/s)."""
    m, tr = simulate("asv", seed=1, duration=600.0, usbl=True, usbl_outlier_rate=0.0)
    m = without_gnss(m, keep_first=True)
    r = UpdateErrorEstimator(None, m, init={n: tr.params[n] for n in FIXED}).run_offline(
        estimate=VARIABLE)
    err = np.array([r.values["s_x"] - tr.params["s_x"], r.values["s_y"] - tr.params["s_y"]])
    assert np.all(np.abs(err) < 0.02), err                # was (0.060, 0.056)
    for i, n in enumerate(("s_x", "s_y")):
        assert abs(err[i]) < 3 * r.sigma[n]


def test_usbl_outliers_move_the_estimates_by_less_than_their_sigma():
    """10 % gross USBL outliers (simulated USBL-only ASV): the estimates stay within 1.5
    reported sigma of the clean fit's (they moved k, k_x by 5 sigma when a gated outlier's
    pull grew with its size), and the clean fit is within 3 sigma of the truth."""
    fits = {}
    for rate in (0.0, 0.1):
        m, tr = simulate("asv", seed=9, duration=600.0, usbl=True, usbl_outlier_rate=rate)
        fits[rate] = UpdateErrorEstimator(None, without_gnss(m, keep_first=True)).run_offline()
    clean, dirty = fits[0.0], fits[0.1]
    for n in VARIABLE + FIXED:
        assert n in clean.sigma, (n, clean.sigma_notes)
        shift = (dirty.values[n] - clean.values[n]) / clean.sigma[n]
        assert abs(shift) < 1.5, (n, shift)
        z = (clean.values[n] - tr.params[n]) / clean.sigma[n]
        assert abs(z) < 3.0, (n, z)


def _online_heading_errors(seed: int, **kw):
    m, tr = simulate("asv", seed=seed, duration=600.0, params={"theta_e": np.radians(30.0)})
    m = with_gnss_every(m, 8.0)
    r = UpdateErrorEstimator(None, m, init={n: tr.params[n] for n in FIXED}).run_online(**kw)
    H = r.history
    d = np.degrees(np.angle(np.exp(1j * (H.values[:, 0] - tr.params["theta_e"]))))
    return r, H, d


@pytest.mark.slow
def test_online_paper_window_with_the_papers_gradient_descent_does_not_wander():
    """The paper's 3-fix window, GNSS every 8 s, 30 deg initial heading error (the
    experiments' Figs. 7/8 setting). With the Gauss-Newton solver the heading and current
    wandered along the flat valley of a straight leg (median |heading error| after 120 s
    11-45 deg, currents up to the 2 m/s bound); with the paper's gradient descent from the
    previous estimate they stay near the truth as far as a 24 s window can tell (median
    4-10 deg, currents below 0.6 m/s, seeds 1001-1006)."""
    meds = []
    for seed in (1001, 1002, 1003):
        r, H, d = _online_heading_errors(seed)
        assert r.info["optimiser"] == "gradient"
        late = H.t > H.t[0] + 120.0
        meds.append(np.median(np.abs(d[late])))
        assert np.max(np.abs(H.values[:, 1:])) < 1.0       # no 1-2 m/s "current"
        assert max(r.info["evaluations_per_optimisation"]) <= 50     # the paper's 30-50
    assert np.mean(meds) < 12.0, meds                        # Gauss-Newton: 28


@pytest.mark.slow
def test_online_on_an_independent_vehicle_with_fixed_parameters_from_another_mission():
    """Otter (not the model), GNSS every 8 s plus USBL every 4.5 s, fixed parameters from a
    batch fit of another mission of the same vehicle: the heading offset stays within 10
    deg (median after 120 s; it was 47 deg, ending 95 deg off) and the causal track beats
    the filter's 2.4 m."""
    from aqfg.data.io import load_mission, load_truth
    from conftest import data_path
    fixed = UpdateErrorEstimator(None, with_gnss_every(load_mission(data_path("otter-dev-calm-b")),
                                                       8.0)).run_offline(sigma=False)
    m = with_gnss_every(load_mission(data_path("otter-dev-calm-a")), 8.0)
    tr = load_truth(data_path("otter-dev-calm-a"))
    r = UpdateErrorEstimator(None, m, init={n: fixed.values[n] for n in FIXED}).run_online()
    H = r.history
    assert r.info["window_fixes"] == 3
    d = np.degrees(np.angle(np.exp(1j * (H.values[:, 0] - tr.params["theta_e"]))))
    late = H.t > H.t[0] + 120.0
    assert np.median(np.abs(d[late])) < 10.0
    f = r.missions[0].filtered
    P = np.column_stack([np.interp(f.t, tr.t, tr.pos[:, i]) for i in range(2)])
    rmse = float(np.sqrt(np.mean(np.sum((f.pos[:, :2] - P) ** 2, axis=1))))
    assert rmse < 1.8, rmse
    assert all(np.isfinite(v) for v in r.sigma.values())


def test_batch_sigma_survives_a_gate_flip_on_an_independent_vehicle():
    """otter-dev-calm-a at one GNSS fix per 4 s: a USBL fix sits at the gate, so a finite-
    difference step flipped its decision and every sigma came out NaN. Now each parameter
    has a finite sigma or is "not determined" with a reason (here k_yz: the Otter's sway
    drag is so large that E no longer changes with it), and theta_e is right."""
    from aqfg.data.io import load_mission, load_truth
    from conftest import data_path
    m = with_gnss_every(load_mission(data_path("otter-dev-calm-a")), 4.0)
    tr = load_truth(data_path("otter-dev-calm-a"))
    r = UpdateErrorEstimator(None, m).run_offline()
    for n in r.estimated:
        if n in r.sigma:
            assert np.isfinite(r.sigma[n]) and r.sigma[n] > 0
        else:
            assert r.observability[n] in ("not determined", "at bound")
            assert r.sigma_notes[n]
    assert {"theta_e", "s_x", "s_y"} <= set(r.sigma)
    d = np.degrees(np.angle(np.exp(1j * (r.values["theta_e"] - tr.params["theta_e"]))))
    assert abs(d) < 3.0 and abs(np.radians(d)) < 3 * r.sigma["theta_e"]
    assert r.info["sigma_method"].startswith("sandwich")
