"""Factors of the graph: residuals and Jacobians against finite differences, the batched
(cached) dynamics factor against the stand-alone one, noise models, layout errors."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from aqfg.fg import factors as fc
from aqfg.model.effects import UserEffect
from aqfg.model.vehicle import Model, attitude_at
from aqfg.sim.simulator import simulate

FD_TOL = 1e-5        # relative: central differences at eps 1e-6 on smooth functions


@pytest.fixture(scope="module")
def asv():
    m, tr = simulate("asv", seed=4, duration=40.0, usbl=True)
    return m, tr


@pytest.fixture(scope="module")
def auv():
    m, tr = simulate("auv", seed=5, duration=40.0)
    return m, tr


def _values(items):
    v = gtsam.Values()
    for k, x in items:
        v.insert(k, np.asarray(x, float))
    return v


def _check_jacobians(factor, values, tol=FD_TOL):
    """Whitened Jacobians of ``factor.linearize`` vs central differences of whitenedError."""
    keys = list(factor.keys())
    A, b = factor.linearize(values).jacobian()
    assert np.allclose(-b, factor.whitenedError(values), atol=1e-10)
    col = 0
    for k in keys:
        x = values.atVector(k)
        fd = np.zeros((len(b), len(x)))
        for j in range(len(x)):
            eps = 1e-6 * max(1.0, abs(x[j]))
            for sgn in (1, -1):
                v2 = gtsam.Values(values)
                xx = x.copy(); xx[j] += sgn * eps
                v2.update(k, xx)
                fd[:, j] += sgn * factor.whitenedError(v2) / (2 * eps)
        an = A[:, col:col + len(x)]
        scale = max(1.0, np.abs(fd).max())
        assert np.abs(an - fd).max() < tol * scale * 10, (gtsam.DefaultKeyFormatter(k), an, fd)
        col += len(x)


def _dyn_setup(m, tr, effects=(), estimate=("k", "k_x", "k_yz", "theta_e", "s_x", "s_y")):
    model = Model.for_mission(m, effects)
    truth = {n: v for n, v in tr.params.items() if n in model.all_names and isinstance(v, float)}
    lay = fc.ParamLayout.build(model, estimate, truth)
    steps, off = model.steps(m, np.array([12.0, 13.0]))   # 1 s of 50 Hz IMU inputs
    X = np.interp(12.0, tr.t, tr.pos[:, 0]), np.interp(12.0, tr.t, tr.pos[:, 1])
    x0 = np.array([X[0], X[1], 0.3, 0.8, -0.4, 0.05])
    x1 = model.propagate(x0, lay.base, steps)[0] + 0.01
    k0, k1 = fc.state_key(0, 0), fc.state_key(0, 1)
    node_keys = tuple((g, fc.node_key(g)) for g in lay.dyn_groups())
    vals = _values([(k0, x0), (k1, x1)] + [(k, lay.initial(g) * 1.01) for g, k in node_keys])
    return model, lay, steps, k0, k1, node_keys, vals


@pytest.mark.parametrize("which", ["asv", "auv"])
def test_dynamics_factor_jacobians_match_finite_differences(which, asv, auv):
    m, tr = asv if which == "asv" else auv
    model, lay, steps, k0, k1, nk, vals = _dyn_setup(m, tr)
    noise = fc.ProcessNoise().noise_model(1.0)
    f = fc.dynamics_factor(model, lay, steps, k0, k1, nk, noise)
    assert len(f.keys()) == 4                      # x0, x1, fixed node, variable node
    _check_jacobians(f, vals)
    # residual is x1 - f(x0, p) with the kernel's prediction
    p = lay.full({g: vals.atVector(k) for g, k in nk})
    pred = model.propagate(vals.atVector(k0), p, steps)[0]
    assert np.allclose(f.unwhitenedError(vals), vals.atVector(k1) - pred, atol=1e-12)


def test_dynamics_factor_with_effects_and_user_effect(asv):
    """Effect parameters in both nodes (C++ kernel), and a Python user effect (numpy path)."""
    m, tr = asv
    est = ("k", "k_x", "thrust_lag.tau", "linear_drag.c_x", "theta_e", "heading_drift.rate",
           "wind_drag.a_n")
    model, lay, steps, k0, k1, nk, vals = _dyn_setup(m, tr, ("thrust_lag", "linear_drag",
                                                            "heading_drift", "wind_drag"), est)
    assert model.uses_cpp
    vals.update(nk[0][1], np.array([9.0, 1.8, 0.3, 0.2]))
    _check_jacobians(fc.dynamics_factor(model, lay, steps, k0, k1, nk,
                                        fc.ProcessNoise().noise_model(1.0)), vals)
    cubic = UserEffect("cubic_drag", ("c3",), null=(0.0,), lower=(0.0,), upper=(10.0,),
                       accel=lambda v, R, d, tm, q: -q[0] * R @ ((R.T @ v) ** 3))
    model, lay, steps, k0, k1, nk, vals = _dyn_setup(m, tr, (cubic,), ("k", "cubic_drag.c3",
                                                                       "theta_e"))
    assert not model.uses_cpp
    vals.update(nk[0][1], np.array([9.0, 0.5]))
    _check_jacobians(fc.dynamics_factor(model, lay, steps, k0, k1, nk,
                                        fc.ProcessNoise().noise_model(1.0)), vals, tol=1e-4)


def test_cached_dynamics_factor_equals_standalone(auv):
    """The batch smoother's factor (kernel results from one propagate_many call) gives the
    same residual and Jacobians as the factor that integrates in its own callback."""
    m, tr = auv
    model, lay, _, _, _, nk, _ = _dyn_setup(m, tr)
    knots = np.array([5.0, 5.7, 6.7, 7.7, 8.1])
    steps, off = model.steps(m, knots)
    rng = np.random.default_rng(1)
    X = rng.normal(0, 1, (len(knots), 6))
    keys = [fc.state_key(0, i) for i in range(len(knots))]
    vals = _values(list(zip(keys, X)) + [(k, lay.initial(g)) for g, k in nk])
    p = lay.full({g: vals.atVector(k) for g, k in nk})
    pred, Jx, Jp = model.propagate_many(X[:-1], p, steps, off)
    cache = fc.DynamicsCache(pred, Jx, Jp)
    noise = fc.ProcessNoise().noise_model(0.7)
    for i in range(len(knots) - 1):
        a = fc.cached_dynamics_factor(cache, i, lay, keys[i], keys[i + 1], nk, noise)
        b = fc.dynamics_factor(model, lay, steps.slice(int(off[i]), int(off[i + 1])), keys[i],
                               keys[i + 1], nk, noise)
        Aa, ba = a.linearize(vals).jacobian()
        Ab, bb = b.linearize(vals).jacobian()
        assert np.allclose(ba, bb, rtol=1e-12, atol=1e-12)
        assert np.allclose(Aa, Ab, rtol=1e-12, atol=1e-12)


def test_measurement_factor_jacobians(asv):
    """GNSS and USBL with the sensor node (range scale, bearing bias, lever arm) and the
    heading (which enters through the lever arm); depth."""
    m, tr = asv
    model = Model.for_mission(m, ("usbl_range_scale", "usbl_bearing_bias", "lever_arm"))
    est = ("theta_e", "usbl_range_scale.scale", "usbl_bearing_bias.bias", "lever_arm.x",
           "lever_arm.y")
    lay = fc.ParamLayout.build(model, est, {"theta_e": 0.4, "lever_arm.x": -0.3,
                                            "usbl_range_scale.scale": 1.01})
    assert lay.meas_groups("gnss") == ("variable", "sensor")
    assert lay.meas_groups("usbl") == ("variable", "sensor")
    t, R, kx, nk, x, vals, g = _gnss_at_usbl_fix(m, model, lay)
    u = fc.usbl_factor(model, lay, kx, nk, np.array([25.0, -0.6]), R, t, m.usbl_station,
                       gtsam.noiseModel.Diagonal.Sigmas(np.array([0.15, 0.026])))
    _check_jacobians(u, vals)
    # bearing residual wraps: measured just across +-pi from the prediction
    h = model.h_usbl(x[:3], R, t, lay.full({"variable": lay.initial("variable"),
                                             "sensor": lay.initial("sensor")}), m.usbl_station)[0]
    z = h + np.array([0.0, 2 * np.pi - 0.01])
    r = fc.usbl_factor(model, lay, kx, nk, z, R, t, m.usbl_station,
                       gtsam.noiseModel.Unit.Create(2)).unwhitenedError(vals)
    assert abs(r[1] - 0.01) < 1e-9
    d = fc.depth_factor(kx, 0.4, 0.3, gtsam.noiseModel.Isotropic.Sigma(1, 0.05))
    vals.update(kx, np.array([0, 0, 0.5, 0, 0, -0.2]))
    assert np.allclose(d.unwhitenedError(vals), [0.5 - 0.2 * 0.3 - 0.4])
    _check_jacobians(d, vals)


def _gnss_at_usbl_fix(m, model, lay):
    """A GNSS factor at the 4th USBL fix's time on knot 0 with the variable and sensor
    nodes, its Jacobians checked; returns (t, R, knot key, node keys, state, values, factor)."""
    t = float(m.usbl.t[3])
    R = attitude_at(m, np.array([t]))[0]
    kx = fc.state_key(0, 0)
    nk = (("variable", fc.node_key("variable")), ("sensor", fc.node_key("sensor")))
    x = np.array([20.0, -15.0, 0.0, 0.7, 0.2, 0.0])
    vals = _values([(kx, x), (nk[0][1], lay.initial("variable")), (nk[1][1], lay.initial("sensor"))])
    g = fc.gnss_factor(model, lay, kx, nk, np.array([20.5, -14.0]), R, t,
                       gtsam.noiseModel.Isotropic.Sigma(2, 1.0))
    _check_jacobians(g, vals)
    return t, R, kx, nk, x, vals, g


def test_time_offset_factor_jacobians(asv):
    """GNSS and USBL with their time offsets estimated (the sensor node) and a lever arm:
    the fix reads the knot's velocity, and every Jacobian matches finite differences."""
    m, tr = asv
    model = Model.for_mission(m, ("gnss_delay", "usbl_delay", "lever_arm"))
    est = ("theta_e", "gnss_delay.tau", "usbl_delay.tau", "lever_arm.x")
    lay = fc.ParamLayout.build(model, est, {"theta_e": 0.4, "gnss_delay.tau": 0.7,
                                            "usbl_delay.tau": 1.5, "lever_arm.x": -0.3})
    assert lay.meas_groups("gnss") == ("variable", "sensor")
    t, R, kx, nk, x, vals, g = _gnss_at_usbl_fix(m, model, lay)
    H = g.linearize(vals).jacobian()[0]
    assert np.abs(H[:, 3:5]).max() > 0.5       # the velocity enters through the offset
    _check_jacobians(fc.usbl_factor(model, lay, kx, nk, np.array([25.0, -0.6]), R, t,
                                    m.usbl_station,
                                    gtsam.noiseModel.Diagonal.Sigmas(np.array([0.15, 0.026]))),
                     vals)


def test_usbl_noise_gives_tangential_error_growing_with_range():
    """Range sigma nearly constant, bearing sigma constant (paper Fig. 5): the position
    sigma across the line of sight is range x bearing sigma."""
    sn = fc.SensorNoise()
    s10, s100 = sn.usbl_sigmas(10.0), sn.usbl_sigmas(100.0)
    assert s100[0] < 1.2 * s10[0] + 0.05 and s10[1] == s100[1]
    assert 100 * s100[1] == pytest.approx(10 * (10 * s10[1]))


def test_robust_loss_downweights_outliers(asv):
    m, tr = asv
    model = Model.for_mission(m)
    lay = fc.ParamLayout.build(model, ("theta_e",))
    kx = fc.state_key(0, 0)
    t = float(m.usbl.t[0])
    R = attitude_at(m, np.array([t]))[0]
    x = np.array([20.0, -15.0, 0.0, 0, 0, 0])
    z_true = model.h_usbl(x[:3], R, t, lay.base, m.usbl_station)[0]
    vals = _values([(kx, x)])
    base = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.15, 0.026]))
    for kind in ("huber", "cauchy"):
        robust = fc.SensorNoise(robust=kind).wrap(base, "usbl")
        for dz, shrink in ((np.array([0.05, 0.0]), False), (np.array([30.0, 0.0]), True)):
            f_r = fc.usbl_factor(model, lay, kx, (), z_true + dz, R, t, m.usbl_station, robust)
            f_g = fc.usbl_factor(model, lay, kx, (), z_true + dz, R, t, m.usbl_station, base)
            br = np.linalg.norm(f_r.linearize(vals).jacobian()[1])
            bg = np.linalg.norm(f_g.linearize(vals).jacobian()[1])
            assert (br < 0.2 * bg) if shrink else br == pytest.approx(bg, rel=0.05)
    assert fc.SensorNoise().wrap(base, "depth") is base       # robust_on: gnss and usbl
    assert fc.SensorNoise().wrap(base, "gnss") is not base
    with pytest.raises(ValueError, match="robust loss"):
        fc.SensorNoise(robust="tukey")


def test_process_noise_is_the_white_noise_acceleration_model():
    pn = fc.ProcessNoise(sigma_a=0.1, pos_rate=0.0, vel_rate=0.0)
    Q = pn.cov(2.0)
    assert Q[0, 0] == pytest.approx(0.01 * 8 / 3)
    assert Q[0, 3] == pytest.approx(0.01 * 2)
    assert Q[3, 3] == pytest.approx(0.01 * 2)
    assert np.all(np.linalg.eigvalsh(fc.ProcessNoise().cov(0.05)) > 0)


def test_surface_bound_and_layout(asv):
    m, _ = asv
    model = Model.for_mission(m)
    kx = fc.state_key(0, 3)
    f = fc.surface_factor(kx, 0.01, 0.02)
    v = _values([(kx, np.array([1, 2, 0.03, 0.5, 0.5, -0.04]))])
    assert f.error(v) == pytest.approx(0.5 * (3.0 ** 2 + 2.0 ** 2))
    lay = fc.ParamLayout.build(model, ("k", "k_x", "theta_e"))
    b = fc.bound_factor(lay, "fixed", fc.node_key("fixed"))
    assert b.error(_values([(fc.node_key("fixed"), np.array([5.0, 1.0]))])) == 0.0
    assert b.error(_values([(fc.node_key("fixed"), np.array([-1.0, 1.0]))])) > 1e3
    assert np.all(lay.project("fixed", np.array([-3.0, 2.0])) > 0)
    assert lay.estimated == ("k", "k_x", "theta_e")
    with pytest.raises(ValueError, match=r"thrust_lag.tau.*--effect thrust_lag"):
        fc.ParamLayout.build(model, ("k", "thrust_lag.tau"))
