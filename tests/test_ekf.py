"""Unit tests of the update-error EKF: history, window pass (numpy vs C++), Eq. 13 anchors,
update nodes, USBL handling, bounds and bad input. Small synthetic missions (tests/ekf_synth.py)."""
from __future__ import annotations

import numpy as np
import pytest

from aqfg.ekf.estimator import UpdateErrorEstimator, fit_update_error
from aqfg.ekf.history import (DEPTH, GNSS, IMU_ACC, MOTOR, USBL, EkfConfig, build_history,
                              usbl_prefilter)
from aqfg.ekf.optim import Entry, Objective, Window, bounds, gradient_descent, minimise
from aqfg.ekf.window import (ACCEPTED, NOOP, REJECTED, HAVE_CPP_EKF, run_window,
                             usbl_to_position, window_ref)
from aqfg.data.mission import without_gnss
from aqfg.data.importers.frames import euler_to_quat
from aqfg.model.vehicle import Model
from aqfg.export import save_result
from aqfg.parameters_doc import per_mission_document
from aqfg.model.retrace import rollout
from ekf_synth import synth_mission

def _history(vehicle="asv", effects=(), config=None, **kw):
    m, p_true, tr = synth_mission(vehicle, **kw)
    model = Model.for_mission(m, effects)
    p = model.nominal(dict(zip(model.all_names, p_true)))
    return build_history(model, m, config), p, tr


def _full_pass(h, p, record=True, use_cpp=None):
    a = h.anchors[h.k_start]
    return run_window(h, p, a.x, a.P, h.k_start, len(h.knots) - 1, record=record, use_cpp=use_cpp)


# ---------------------------------------------------------------- numpy == C++
@pytest.mark.parametrize("vehicle", ["asv", "auv"])
@pytest.mark.parametrize("cov_model", ["kinematic", "full"])
def test_cpp_window_equals_numpy(vehicle, cov_model):
    assert HAVE_CPP_EKF, "aqfg._kernel.ekf_window is not built (pip install -e . rebuilds it)"
    eff = ("thrust_lag", "lever_arm", "usbl_range_scale", "usbl_bearing_bias")
    h, p, _ = _history(vehicle, eff, EkfConfig(cov_model=cov_model), imu_acc=True, usbl=True,
                       duration=40.0)
    mo = h.model
    for n, v in (("thrust_lag.tau", 0.4), ("lever_arm.x", 0.3), ("usbl_range_scale.scale", 1.01),
                 ("usbl_bearing_bias.bias", 0.02)):
        p[mo.index(n)] = v
    # a gross USBL outlier that passes the pre-filter is impossible to plant reliably, so
    # shift one fix inside the filter's reach of the gate instead: the gate must act the same
    u = np.nonzero(h.node_kind == USBL)[0]
    h.node_z[u[3], 0] += 6.0
    a = h.anchors[h.k_start]
    k0 = h.k_start + 23                      # not at an anchor: any start state works
    x0 = a.x + 0.1
    ref = window_ref(h, p, x0, a.P, k0, len(h.knots) - 1, record=True, rejects=1)
    cpp = run_window(h, p, x0, a.P, k0, len(h.knots) - 1, record=True, use_cpp=True, rejects=1)
    assert (ref.status == cpp.status).all()
    assert ref.rejects == cpp.rejects
    assert (ref.status == REJECTED).any()    # the gate was exercised
    for f in ("e", "nu", "nu_w", "s", "x", "P", "X", "Pn"):
        a_, b_ = getattr(ref, f), getattr(cpp, f)
        np.testing.assert_allclose(b_, a_, rtol=1e-10, atol=1e-11, err_msg=f)


# ---------------------------------------------------------------- prediction = the model
def test_without_updates_the_filter_is_the_model():
    """No measurement after the first fix: the EKF mean is retrace.rollout exactly, and every
    node is a motor command with zero update error (Eq. 11, §III-B)."""
    m, p_true, _ = synth_mission("asv", duration=30.0)
    m = without_gnss(m, keep_first=True)
    model = Model.for_mission(m)
    h = build_history(model, m)
    p = model.nominal(dict(zip(model.all_names, p_true)))
    out = _full_pass(h, p)
    assert set(h.node_kind.tolist()) == {MOTOR}
    assert (out.status == NOOP).all() and not out.e.any() and out.error() == 0.0
    tr = rollout(model, m, p, h.anchors[h.k_start].x[:6], h.t_start, h.knots[h.k_start + 1:])
    np.testing.assert_allclose(out.X[1:, :3], tr.pos[1:], atol=1e-9)
    np.testing.assert_allclose(out.X[1:, 3:6], tr.vel[1:], atol=1e-9)


def test_motor_nodes_have_zero_error_and_E_sums_the_others():
    h, p, _ = _history("auv", imu_acc=True, usbl=True, duration=30.0)
    out = _full_pass(h, p)
    kinds = h.node_kind[out.node_lo:out.node_hi]
    assert (kinds == MOTOR).sum() > 100
    assert not out.e[kinds == MOTOR].any() and (out.status[kinds == MOTOR] == NOOP).all()
    for k in (GNSS, USBL, DEPTH, IMU_ACC):
        assert (out.status[kinds == k] != NOOP).all() and np.abs(out.e[kinds == k]).sum() > 0
    assert out.error() == pytest.approx(float(np.sum(out.e[kinds != MOTOR] ** 2)), rel=1e-14)
    # a window holding only motor commands has E = 0 whatever the parameters
    h, p, _ = _history("auv", duration=30.0)
    ks = h.node_knot[h.node_kind == MOTOR]
    a, b = next((int(a), int(b)) for a, b in zip(ks[:-1], ks[1:])
                if (h.node_kind[slice(*h.nodes_between(a, b))] == MOTOR).all() and b > a)
    for scale in (0.5, 2.0):
        q = p.copy()
        q[3] *= scale
        assert run_window(h, q, out.X[a - h.k_start], np.eye(9), a, b).error() == 0.0


# ---------------------------------------------------------------- anchors, Eq. 13
def test_state_recomputed_from_an_anchor_matches_the_forward_pass():
    m, p_true, _ = synth_mission("asv", duration=60.0, usbl=True)
    est = UpdateErrorEstimator(None, m, init={n: float(v) for n, v in
                                             zip(("theta_e", "s_x", "s_y", "k", "k_x", "k_yz"),
                                                 p_true[:6])})
    h = est.histories[0]
    p = est.p0[0]
    out = _full_pass(h, p)
    est.store_anchors(h, out, h.k_start, 0)
    fk = h.fix_knots()
    assert set(fk[1:].tolist()) <= set(h.anchors)          # an anchor after every fix
    k = int(fk[5]) + 7                                      # between two fixes
    t = float(h.knots[k])
    assert h.anchor_at_or_before(k).k == int(fk[5])
    x, P = est.state_at(t, p)                               # from the anchor at fk[5]
    np.testing.assert_allclose(x, out.X[k - h.k_start], atol=1e-9)
    # the same state from the start anchor (the whole chain of nodes) agrees too
    a0 = h.anchors[h.k_start]
    chain = run_window(h, p, a0.x, a0.P, h.k_start, k)
    x0, P0 = chain.x, chain.P
    np.testing.assert_allclose(x, x0, atol=1e-9)
    np.testing.assert_allclose(P, P0, atol=1e-12)
    # and the window error of Eq. 14 over the last stretch is that of the forward pass
    lo, hi = h.nodes_between(int(fk[5]), int(fk[8]))
    e_fwd = out.e[lo - out.node_lo:hi - out.node_lo]
    assert est.window_error(p, float(h.knots[fk[5]]), float(h.knots[fk[8]])) == \
        pytest.approx(float(np.sum(e_fwd ** 2)), rel=1e-12)


# ---------------------------------------------------------------- USBL
def test_usbl_covariance_is_stretched_tangentially_with_range():
    p = Model.for_mission(synth_mission("asv", duration=5.0)[0]).nominal()
    st = np.array([0.0, 0.0, 0.0])
    for r, b in ((20.0, 0.3), (100.0, 2.0)):
        pos, R = usbl_to_position(np.array([r, b, 0.0]), st, p, 0.2, 0.02)
        np.testing.assert_allclose(pos, [r * np.cos(b), r * np.sin(b)], atol=1e-12)
        radial = np.array([np.cos(b), np.sin(b)])
        tang = np.array([-np.sin(b), np.cos(b)])
        assert radial @ R @ radial == pytest.approx(0.2 ** 2)
        assert tang @ R @ tang == pytest.approx((r * 0.02) ** 2)
        assert radial @ R @ tang == pytest.approx(0.0, abs=1e-12)
    # the range scale and bearing bias parameters correct the measurement first
    from aqfg.model.params import INDEX
    q = p.copy()
    q[INDEX["usbl_range_scale.scale"]] = 1.1
    q[INDEX["usbl_bearing_bias.bias"]] = 0.1
    pos, _ = usbl_to_position(np.array([110.0, 0.6, 0.0]), st, q, 0.2, 0.02)
    np.testing.assert_allclose(pos, [100 * np.cos(0.5), 100 * np.sin(0.5)], atol=1e-9)


def test_usbl_gate_rejects_an_outlier_without_lowering_E_and_gives_up_after_max_rejects():
    h, p, _ = _history("asv", usbl=True, duration=60.0, gnss_period=100.0)
    u = np.nonzero(h.node_kind == USBL)[0]
    h.node_z[u[4], 0] += 8.0                 # an 8 m range outlier, past the pre-filter
    out = _full_pass(h, p)
    r = u[4] - out.node_lo
    assert out.status[r] == REJECTED
    assert (out.status[u - out.node_lo] == ACCEPTED).sum() == len(u) - 1
    # rejected = not applied: the pass equals one where that node is a no-op
    h.node_kind[u[4]] = MOTOR
    same = _full_pass(h, p)
    h.node_kind[u[4]] = USBL
    np.testing.assert_allclose(same.X, out.X, atol=1e-12)
    # the rejected node's error sits at the gate boundary: |nu_w|^2 > gate, and its
    # error is K nu shrunk by sqrt(gate / m2), i.e. more than zero
    m2 = float(np.nansum(out.nu_w[r] ** 2))
    assert m2 > h.config.gate_usbl and np.linalg.norm(out.e[r]) > 0
    # with an impossibly tight gate every fix is rejected except after max_rejects in a row
    cfg = EkfConfig(gate_usbl=1e-9, max_rejects=3)
    h2, p2, _ = _history("asv", config=cfg, usbl=True, duration=60.0, gnss_period=100.0)
    o2 = _full_pass(h2, p2)
    st = o2.status[h2.node_kind[o2.node_lo:o2.node_hi] == USBL]
    assert st.tolist()[:8] == [REJECTED] * 3 + [ACCEPTED] + [REJECTED] * 3 + [ACCEPTED]
    assert o2.rejects == (len(st) % 4 if st[-1] == REJECTED else 0)


def test_a_gated_fix_pulls_no_harder_than_one_at_the_gate_whatever_its_size():
    """A rejected fix counts in E with its update error scaled to the gate boundary, so an
    outlier 4x larger contributes the same (it used to grow like sqrt(|nu|), which let a
    few gated outliers carry half of E and move the parameters by several sigma)."""
    sizes = (8.0, 32.0)
    norms, whitened = [], []
    for d in sizes:
        h, p, _ = _history("asv", usbl=True, duration=60.0, gnss_period=100.0)
        u = np.nonzero(h.node_kind == USBL)[0]
        h.node_z[u[4], 0] += d                  # a range outlier, past the pre-filter
        out = _full_pass(h, p)
        r = u[4] - out.node_lo
        assert out.status[r] == REJECTED
        norms.append(np.linalg.norm(out.e[r]))
        m2 = float(np.nansum(out.nu_w[r] ** 2))
        # update error = (K nu) sqrt(gate / m2): K nu itself is that of the accepted update
        whitened.append(m2)
    assert whitened[1] > 8 * whitened[0]               # the second one is much further out
    assert norms[1] == pytest.approx(norms[0], rel=0.05)
    # the same for the whitened metric: a gated node's residual has norm sqrt(gate)
    h, p, _ = _history("asv", usbl=True, duration=60.0, gnss_period=100.0)
    u = np.nonzero(h.node_kind == USBL)[0]
    h.node_z[u[4], 0] += 20.0
    a = h.anchors[h.k_start]
    obj = Objective([Window(h, h.k_start, len(h.knots) - 1, a.x, a.P, p.copy())],
                    [Entry("theta_e", (0,))], metric="whitened")
    t = obj.node_terms(np.array([p[0]]))
    rej = t.status == REJECTED
    assert rej.sum() == 1
    assert np.linalg.norm(t.rows[rej]) == pytest.approx(np.sqrt(h.config.gate_usbl))


def test_usbl_covariance_axes_follow_the_predicted_position():
    """With the filter's prediction given, the radial/tangential axes and the tangential
    spread are those of the predicted position, not of the measured (noisy) bearing."""
    p = Model.for_mission(synth_mission("asv", duration=5.0)[0]).nominal()
    st = np.array([0.0, 0.0, 0.0])
    z = np.array([100.0, 0.3, 0.0])
    pred = np.array([80.0 * np.cos(0.2), 80.0 * np.sin(0.2)])
    pos, R = usbl_to_position(z, st, p, 0.2, 0.02, predicted=pred)
    np.testing.assert_allclose(pos, [100 * np.cos(0.3), 100 * np.sin(0.3)], atol=1e-12)
    radial = np.array([np.cos(0.2), np.sin(0.2)])
    tang = np.array([-np.sin(0.2), np.cos(0.2)])
    assert radial @ R @ radial == pytest.approx(0.2 ** 2)
    assert tang @ R @ tang == pytest.approx((80.0 * 0.02) ** 2)
    assert radial @ R @ tang == pytest.approx(0.0, abs=1e-12)


def test_usbl_prefilter_drops_gross_outliers_only():
    rng = np.random.default_rng(3)
    t = np.arange(1.0, 200.0, 4.5)
    truth = np.column_stack([30 + 0.8 * t, 20 + 0.3 * t])
    pos = truth + rng.normal(0, 1.0, truth.shape)
    bad = [5, 17, 30]
    pos[bad] += [[40.0, 0.0], [0.0, -60.0], [25.0, 25.0]]
    keep = usbl_prefilter(t, pos, np.full(len(t), 1.0), 0.0, truth[0] - [0.8, 0.3], 1.0,
                          2.5, 3.0)
    assert not keep[bad].any()
    assert keep.sum() == len(t) - len(bad)


def test_imu_acceleration_nodes_remove_gravity_with_the_reported_attitude():
    m, _, _ = synth_mission("auv", duration=10.0)
    # a vehicle at rest, tilted: the accelerometer reads -g along the body's "up"
    from aqfg.model.vehicle import attitude_at
    Rb = attitude_at(m, m.imu.t)
    m.imu.acc = -9.80665 * Rb[:, 2, :]                  # f = R^T (0 - g e_z)
    m.motors.u[:] = 0.0
    h = build_history(Model.for_mission(m), m)
    z = h.node_z[h.node_kind == IMU_ACC, :3]
    assert len(z) > 50
    np.testing.assert_allclose(z, 0.0, atol=1e-9)


# ---------------------------------------------------------------- optimisation
def test_bounds_of_the_presets_and_that_they_are_respected():
    h, p, _ = _history("asv", duration=60.0, gnss_period=2.0)
    model = h.model
    ents = [Entry(n, (0,)) for n in ("theta_e", "k", "k_x", "k_yz", "s_x")]
    cur = np.array([0.1, 6.0, 1.5, 0.2, 0.0])
    lo, hi = bounds("paper", ents, model, cur)
    np.testing.assert_allclose(lo, [-np.radians(190), 2.0, 0.6, 0.08, -2.0])
    np.testing.assert_allclose(hi, [np.radians(190), 14.0, 2.85, 0.38, 2.0])
    lo, hi = bounds("physical", ents, model, cur)
    assert lo[1] > 0 and np.isinf(hi[1]) and hi[0] == pytest.approx(np.radians(190))
    # the truth (k = 6) lies outside a user bound: the estimate stops on the bound
    a = h.anchors[h.k_start]
    win = Window(h, h.k_start, len(h.knots) - 1, a.x, a.P, p.copy())
    ents = [Entry("k", (0,)), Entry("theta_e", (0,))]
    obj = Objective([win], ents)
    lo, hi = bounds("physical", ents, model, np.array([4.0, 0.0]),
                    {"k": (2.0, 5.0), "theta_e": (0.0, 0.1)})
    for preset in ("physical", "paper"):
        sol = minimise(obj, np.array([4.0, 0.0]), lo, hi, preset, np.array([5.0, 0.5]))
        assert np.all(sol.theta >= lo) and np.all(sol.theta <= hi)
        assert sol.theta == pytest.approx([5.0, 0.1], abs=1e-3)   # truth: k = 6, theta = 0.2
        assert sol.evaluations > 0 and sol.seconds > 0
    with pytest.raises(ValueError, match="empty bounds"):
        bounds("physical", ents, model, np.array([4.0, 0.0]), {"k": (5.0, 2.0)})


def test_gradient_descent_does_not_wander_along_a_flat_direction():
    """The paper's optimiser: a well-determined direction converges, a nearly flat one
    (a heading offset traded for a current, in a short window) stays at its start, where a
    Gauss-Newton solver jumps to the flat direction's exact minimum."""
    def f(x):
        return (x[0] - 1.0) ** 2 + 1e-6 * (x[1] - 3.0) ** 2 + 0.5
    lo, hi = np.array([-5.0, -5.0]), np.array([5.0, 5.0])
    x, fx, status, _ = gradient_descent(f, np.array([0.0, 0.0]), lo, hi, np.ones(2))
    assert x[0] == pytest.approx(1.0, abs=1e-2)
    assert abs(x[1]) < 0.05
    assert fx == pytest.approx(f(x)) and status in (0, 1, 2)
    # bounds hold and the evaluation budget is respected
    n = [0]

    def g(x):
        n[0] += 1
        return (x[0] - 10.0) ** 2 + x[1] ** 2
    x, _, _, _ = gradient_descent(g, np.array([0.0, 1.0]), lo, hi, np.ones(2), budget=30)
    assert x[0] == pytest.approx(5.0) and n[0] <= 30


def test_the_online_window_holds_three_fixes_of_every_active_stream():
    from aqfg.ekf.estimator import window_start
    tg = np.arange(0.0, 200.0, 8.0)                     # GNSS every 8 s
    tu = np.arange(2.0, 200.0, 4.5)                     # USBL every 4.5 s
    t = np.unique(np.concatenate([tg, tu]))
    streams = {GNSS: np.nonzero(np.isin(t, tg))[0], USBL: np.nonzero(np.isin(t, tu))[0]}
    n = int(np.searchsorted(t, 160.0))                  # a GNSS fix
    j = window_start(t, streams, n, 3)
    assert t[n] - t[j] == pytest.approx(24.0)            # 3 GNSS intervals, not 3 fixes (~9 s)
    i = int(np.nonzero(tg == 160.0)[0][0])
    assert window_start(tg, {GNSS: np.arange(len(tg))}, i, 3) == i - 3   # one stream: 3 fixes
    # a stream that has stopped (GNSS before a dive) does not stretch the window
    stop = {GNSS: streams[GNSS][t[streams[GNSS]] < 60.0], USBL: streams[USBL]}
    n = len(t) - 1
    j = window_start(t, stop, n, 3)
    assert t[n] - t[j] == pytest.approx(13.5, abs=1e-9)   # 3 USBL intervals
    assert window_start(t, streams, 2, 3) == 0           # too few fixes yet: from the start


def test_a_still_vehicle_gives_not_determined_not_nan():
    """All motor commands zero and the fixes scattered around one point: the current is
    determined (zero), the heading offset and the thrust/drag constants are not; no sigma
    is NaN, each missing one has a reason, and an optimiser that ran out of evaluations
    says so."""
    import json
    m, _, _ = synth_mission("asv", duration=60.0, gnss_period=1.0)
    m.motors.u[:] = 0.0
    rng = np.random.default_rng(1)
    m.gnss.ne = rng.normal(0.0, 0.5, m.gnss.ne.shape)
    r = fit_update_error([m], mode="batch")
    assert all(np.isfinite(v) for v in r.sigma.values())
    assert set(r.sigma) == {"s_x", "s_y"}
    obs = r.observability
    for n in ("theta_e", "k", "k_x", "k_yz"):
        assert obs[n] == "not determined" and r.sigma_notes[n]
    for n in ("s_x", "s_y"):
        assert obs[n] in ("determined", "weakly determined")
        assert abs(r.values[n]) < 3 * r.sigma[n]
    assert isinstance(r.converged, bool)
    if not r.converged:
        assert any("without converging" in w for w in r.warnings)
    json.dumps({"warnings": r.warnings, "converged": r.converged,
                "observability": r.observability, "sigma_notes": r.sigma_notes,
                "per_mission": per_mission_document(r.per_mission),
                "consistency": r.info["consistency"]},
               allow_nan=False)
    on = fit_update_error([m], mode="online")
    assert all(np.isfinite(v) for v in on.sigma.values())
    assert on.observability["theta_e"] == "not determined"


def test_fit_update_error_returns_a_complete_result(tmp_path):
    m, p_true, _ = synth_mission("asv", duration=60.0, usbl=True, imu_acc=True)
    init = {"s_x": p_true[1], "s_y": p_true[2], "k_x": p_true[4], "k_yz": p_true[5]}
    r = fit_update_error([m], mode="batch", estimate=("theta_e", "k"), init=init)
    assert r.method == "update-error" and r.mode == "batch" and r.estimated == ("theta_e", "k")
    assert abs(r.values["k"] - p_true[3]) < 0.2 * p_true[3]
    assert set(r.sigma) == {"theta_e", "k"} and all(np.isfinite(list(r.sigma.values())))
    mr = r.missions[0]
    assert {"gnss", "usbl", "imu_acc"} <= set(mr.residuals)
    g = mr.residuals["gnss"]
    np.testing.assert_allclose(g.measured - g.predicted, g.raw)
    assert 0.2 < np.nanstd(g.normalised) < 5
    assert len(mr.track.t) == len(mr.track.pos) and mr.inertial.t[0] == m.gnss.t[0]
    assert r.info["evaluations"] == len(r.timings["evaluation"]) > 0
    assert len(r.timings["optimisation"]) == 1
    save_result(r, tmp_path)
    assert (tmp_path / "parameters.json").exists() and (tmp_path / "trajectory.csv").exists()
    on = fit_update_error([m], mode="online", estimate=("theta_e",), init={"k": p_true[3]})
    assert on.mode == "online" and len(on.history.t) == len(on.timings["optimisation"]) > 3
    assert on.missions[0].filtered is not None
    assert len(on.info["nonconvergence"]) == len(on.history.t)
    assert np.isnan(on.info["nonconvergence"][0][0]) and np.isfinite(on.info["nonconvergence"][-1][0])


def test_bad_input_is_named():
    m, _, _ = synth_mission("asv", duration=10.0)
    m.gnss = None
    with pytest.raises(ValueError, match="synth-asv-0.*no absolute fix"):
        fit_update_error([m])
    m2, _, _ = synth_mission("asv", duration=10.0)
    with pytest.raises(ValueError, match="thrust_lag.tau.*not estimable"):
        fit_update_error([m2], estimate=("thrust_lag.tau",))
    with pytest.raises(KeyError, match="bogus"):
        fit_update_error([m2], init={"bogus": 1.0})
    with pytest.raises(ValueError, match="preset"):
        fit_update_error([m2], preset="ceres")
    with pytest.raises(ValueError, match="mode"):
        fit_update_error([m2], mode="smooth")
    with pytest.raises(ValueError, match="cov_model"):
        EkfConfig(cov_model="exact")
    m3, _, _ = synth_mission("auv", duration=10.0)
    with pytest.raises(ValueError, match="vehicle types"):
        fit_update_error([m2, m3])


def test_a_user_effect_runs_on_the_numpy_path():
    """A Python UserEffect is evaluated by the numpy window (the C++ one cannot call it):
    at its null value the pass equals the built-in model's C++ pass; away from it, E moves."""
    from aqfg.model.effects import UserEffect
    cubic = UserEffect("cubic_drag", ("c3",), null=(0.0,), lower=(0.0,), upper=(10.0,),
                       accel=lambda v, R, d, tm, q: -q[0] * R @ ((R.T @ v) ** 3))
    m, p_true, _ = synth_mission("asv", duration=20.0, usbl=True)
    base = Model.for_mission(m)
    model = base.with_effects(cubic)
    vals = dict(zip(base.all_names, p_true))
    h0, h1 = build_history(base, m), build_history(model, m)
    p0, p1 = base.nominal(vals), model.nominal(vals)
    o0, o1 = _full_pass(h0, p0, use_cpp=True), _full_pass(h1, p1)
    np.testing.assert_allclose(o1.X, o0.X, atol=1e-9)
    np.testing.assert_allclose(o1.e, o0.e, atol=1e-9)
    p1[model.index("cubic_drag.c3")] = 0.5
    assert _full_pass(h1, p1).error() != pytest.approx(o0.error(), rel=1e-3)
    est = UpdateErrorEstimator(model, m, init=vals)
    r = est.run_offline(estimate=("cubic_drag.c3",), sigma=False)
    assert 0.0 <= r.values["cubic_drag.c3"] < 0.3


def test_the_public_codes_innovation_metric_with_the_paper_preset():
    m, p_true, _ = synth_mission("asv", duration=60.0)
    init = dict(zip(("theta_e", "s_x", "s_y", "k", "k_x", "k_yz"), map(float, p_true[:6])))
    init["k"] = 8.0
    est = UpdateErrorEstimator(None, m, preset="paper", metric="innovation", init=init)
    r = est.run_offline(estimate=("k",), sigma=False)
    assert r.info["metric"] == "innovation"
    assert abs(r.values["k"] / p_true[3] - 1) < 0.1
    with pytest.raises(ValueError, match="needs preset='paper'"):
        UpdateErrorEstimator(None, m, metric="innovation")
    with pytest.raises(ValueError, match="unknown metric"):
        UpdateErrorEstimator(None, m, metric="likelihood")


def test_a_model_with_a_fix_time_offset_is_refused():
    """The EKF's fix model has no velocity: it refuses a time offset instead of ignoring it."""
    m = synth_mission("asv", duration=20.0)[0]
    with pytest.raises(ValueError, match="does not model fix time offsets .gnss_delay."):
        UpdateErrorEstimator(None, m, effects=("gnss_delay",))


def test_a_derivative_step_where_the_filter_diverges_is_not_used():
    """The uncertainty's finite differences skip a step whose filter terms are not finite
    (a stiff filter can diverge a step from the estimate) and use the next; with none
    finite the parameter has no derivative (column zero) rather than NaN everywhere."""
    from types import SimpleNamespace

    from aqfg.ekf.uncertainty import _column, _jacobians

    def terms(th):
        bad = th[0] > 1.0                     # diverges above the estimate 1.0
        r = np.array([[np.nan if bad else 2.0 * th[0] + th[1]]])
        return SimpleNamespace(status=np.array([ACCEPTED]), rows=r, nu_w=np.zeros((1, 3)))
    obj = SimpleNamespace(node_terms=terms)
    theta = np.array([1.0, 0.5])
    t0 = terms(theta)
    t, step = _column(obj, theta, 0, 1e-3, None, None, t0)
    assert step < 0 and np.isfinite(t.rows).all()
    Jr, _, none = _jacobians(obj, theta, np.ones(2), None, None, t0)
    assert Jr[0, 0] == pytest.approx([2.0, 1.0]) and not none.any()
    obj = SimpleNamespace(node_terms=lambda th: SimpleNamespace(
        status=np.array([ACCEPTED]), rows=np.array([[np.nan if th[0] != 1.0 else 0.0]]),
        nu_w=np.zeros((1, 3))))
    Jr, _, none = _jacobians(obj, theta, np.ones(2), None, None, obj.node_terms(theta))
    assert none[0] and np.isfinite(Jr).all()
