"""Effects own their terms: the parameter table, the dynamics/measurement split and the
measurement functions derive from them; an effect outside the catalogue plugs into the model
through its term alone."""
from __future__ import annotations

import numpy as np
import pytest

from aqfg.model import frames, measurements, params
from aqfg.model import reference as ref
from aqfg.model.effects import (
    BUILTIN,
    BuiltinEffect,
    Effect,
    GroundForceTerm,
    HeadingTerm,
    UserEffect,
    resolve,
)
from aqfg.model.retrace import usbl_positions
from aqfg.model.vehicle import Model, quat_to_rot
from aqfg.sim.simulator import simulate


def test_table_and_split_derive_from_the_effects():
    assert all(isinstance(e, BuiltinEffect) for e in BUILTIN.values())
    dyn = [n for e in BUILTIN.values() if e.kind == "dynamics" for n in e.params]
    meas = [n for e in BUILTIN.values() if e.kind == "measurement" for n in e.params]
    assert params.NAMES == params.BASE_NAMES + tuple(dyn) + tuple(meas)
    assert params.N_DYN == len(params.BASE_NAMES) + len(dyn)
    for e in BUILTIN.values():
        for s in e.specs():
            assert params.SPEC[s.name] == s and s.lower <= s.null <= s.upper
            assert s.typical is None or s.lower <= s.typical <= s.upper
        assert params.NAMES[params.SLICE[e.name]] == e.params
    assert isinstance(UserEffect("u", ("a",), accel=lambda *a: np.zeros(3), null=(0.0,)), Effect)
    assert frames.HEADING_PARAMS == ("theta_e", "heading_drift.rate")


def _fd(f, x, eps):
    x = np.asarray(x, float)
    cols = []
    for i in range(len(x)):
        e = np.zeros(len(x)); e[i] = eps * max(1.0, abs(x[i]))
        cols.append((f(x + e) - f(x - e)) / (2 * e[i]))
    return np.column_stack(cols)


@pytest.mark.parametrize("sensor", ["gnss", "usbl"])
def test_measurement_jacobians_match_finite_differences(sensor):
    rng = np.random.default_rng(3)
    p = params.vector({"theta_e": 0.4, "heading_drift.rate": 2e-3, "usbl_range_scale.scale": 1.03,
                       "usbl_bearing_bias.bias": 0.07, "lever_arm.x": -0.4,
                       "lever_arm.y": 0.2, "lever_arm.z": 0.3})
    R = quat_to_rot(rng.normal(size=(1, 4)))[0]
    pos, st, tm = np.array([30.0, -12.0, 2.0]), np.array([1.0, 2.0, 1.5]), 40.0
    h = {"gnss": lambda x, q: measurements.h_gnss(x, R, tm, q),
         "usbl": lambda x, q: measurements.h_usbl(x, R, tm, q, st)}[sensor]
    _, Jx, Jp = h(pos, p)
    np.testing.assert_allclose(Jx, _fd(lambda x: h(x, p)[0], pos, 1e-6), atol=1e-7)
    np.testing.assert_allclose(Jp, _fd(lambda q: h(pos, q)[0], p, 1e-6), atol=1e-7)
    touched = {params.NAMES[i] for i in np.flatnonzero(np.abs(Jp).max(axis=0))}
    want = {"theta_e", "heading_drift.rate", "lever_arm.x", "lever_arm.y", "lever_arm.z"}
    if sensor == "usbl":
        want |= {"usbl_range_scale.scale", "usbl_bearing_bias.bias"}
    assert touched == want


@pytest.mark.parametrize("sensor", ["gnss", "usbl"])
def test_time_offset_jacobians_match_finite_differences(sensor):
    """Given the state [pos, vel], a stream's time offset moves its fix back along the
    velocity (``p - tau v``), the other stream's offset does not enter."""
    rng = np.random.default_rng(5)
    p = params.vector({"theta_e": 0.3, "lever_arm.x": -0.4, "lever_arm.y": 0.1,
                       "gnss_delay.tau": 0.8, "usbl_delay.tau": -1.3,
                       "usbl_range_scale.scale": 1.02})
    R = quat_to_rot(rng.normal(size=(1, 4)))[0]
    x, st, tm = np.array([30.0, -12.0, 2.0, 1.1, -0.6, 0.05]), np.array([1.0, 2.0, 1.5]), 40.0
    h = {"gnss": lambda x, q: measurements.h_gnss(x, R, tm, q),
         "usbl": lambda x, q: measurements.h_usbl(x, R, tm, q, st)}[sensor]
    _, Jx, Jp = h(x, p)
    assert Jx.shape == (2, 6)
    np.testing.assert_allclose(Jx, _fd(lambda y: h(y, p)[0], x, 1e-6), atol=1e-7)
    np.testing.assert_allclose(Jp, _fd(lambda q: h(x, q)[0], p, 1e-6), atol=1e-7)
    mine, other = ("gnss_delay.tau", "usbl_delay.tau")[::1 if sensor == "gnss" else -1]
    assert np.abs(Jp[:, params.INDEX[mine]]).max() > 0.1
    assert np.abs(Jp[:, params.INDEX[other]]).max() == 0.0
    tau = p[params.INDEX[mine]]
    ps = measurements.sensor_position(x, R, tm, p, sensor)[0]
    np.testing.assert_allclose(ps, measurements.sensor_position(x[:3] - tau * x[3:], R, tm, p)[0])


def test_usbl_inverse_undoes_the_measurement():
    p = params.vector({"usbl_range_scale.scale": 0.97, "usbl_bearing_bias.bias": -0.1})
    st = np.array([5.0, -3.0, 1.5])
    pts = np.array([[40.0, 25.0, 3.0], [-60.0, 10.0, 0.0], [2.0, -80.0, 7.0]])
    z = np.array([measurements.h_usbl(x, np.eye(3), 0.0, p, st)[0] for x in pts])
    pos, r, rh, b = measurements.usbl_inverse(z[:, 0], z[:, 1], pts[:, 2], st, p)
    np.testing.assert_allclose(pos, pts, atol=1e-9)
    np.testing.assert_allclose(r, np.linalg.norm(pts - st, axis=1), rtol=1e-12)
    one = measurements.usbl_inverse(z[0, 0], z[0, 1], pts[0, 2], st, p)[0]
    np.testing.assert_allclose(one, pts[0], atol=1e-9)


def test_usbl_positions_remove_scale_and_bias():
    m, tr = simulate("asv", seed=2, duration=120.0, gnss_period=None, usbl=True,
                     usbl_outlier_rate=0.0, usbl_sigma_range=0.0, usbl_sigma_bearing=0.0,
                     effects={"usbl_range_scale": 1.05, "usbl_bearing_bias": 0.08})
    true = np.column_stack([np.interp(m.usbl.t, tr.t, tr.pos[:, i]) for i in range(3)])
    p = params.vector({n: v for n, v in tr.params.items() if n in params.INDEX})
    err_nominal = np.abs(usbl_positions(m) - true)[:, :2].max()
    err_true = np.abs(usbl_positions(m, p=p) - true)[:, :2].max()
    assert err_nominal > 2.0 and err_true < 0.05, (err_nominal, err_true)


class SquareWind(GroundForceTerm):
    """A ground-frame force growing with the square of the time: not a UserEffect, an
    Effect of the term library with analytic derivatives."""
    name = "square_wind"
    description = "test effect"

    def specs(self):
        return (params.ParamSpec("square_wind.c", "m/s^4", 0.0, -1.0, 1.0, "fixed", 1e-4, ""),)

    def ground_accel(self, v, R, d, tm, q):
        return np.array([q[0] * tm * tm, 0.0, 0.0])

    def ground_jacobians(self, v, R, d, tm, q, eps=1e-6):
        return np.zeros((3, 3)), np.array([[tm * tm], [0.0], [0.0]]), np.zeros(3)


def test_an_effect_outside_the_catalogue_enters_through_its_term():
    m, _ = simulate("asv", seed=1, duration=20.0)
    base = Model.for_mission(m)
    model = base.with_effects(SquareWind())
    assert not model.uses_cpp and model.all_names[-1] == "square_wind.c"
    steps, _ = model.steps(m, np.array([5.0, 7.0]))
    x0 = np.array([0.0, 0.0, 0.0, 0.5, 0.1, 0.0])
    p0 = model.nominal({"k": 9.0})
    p1 = model.nominal({"k": 9.0, "square_wind.c": 1e-3})
    x_null, _, Jp = model.propagate(x0, p0, steps)
    np.testing.assert_allclose(x_null, base.propagate(x0, p0[:params.N_PARAMS], steps)[0],
                               atol=1e-12)
    x1 = model.propagate(x0, p1, steps)[0]
    assert x1[3] - x_null[3] > 5e-3                                 # pushed north
    e = 1e-6
    fd = (model.propagate(x0, model.nominal({"k": 9.0, "square_wind.c": e}), steps)[0]
          - model.propagate(x0, model.nominal({"k": 9.0, "square_wind.c": -e}), steps)[0]) / (2 * e)
    np.testing.assert_allclose(Jp[:, -1], fd, rtol=1e-6, atol=1e-9)


def test_effects_outside_the_catalogue_are_checked():
    m, _ = simulate("asv", seed=1, duration=5.0)
    model = Model.for_mission(m)

    class Odd(Effect):
        name = "odd"

        def specs(self):
            return ()
    with pytest.raises(ValueError, match="ground-force term"):
        model.with_effects(Odd())
    clash = UserEffect("linear_drag", ("c_x",), accel=lambda *a: np.zeros(3), null=(0.0,))
    with pytest.raises(ValueError, match="built-in parameters"):
        model.with_effects(clash)
    with pytest.raises(KeyError, match="unknown effect"):
        resolve("no_such_effect")

    class Half(HeadingTerm):          # its term without the Jacobian
        name = "half"

        def specs(self):
            return ()

        def heading(self, tm, q):
            return 0.0
    with pytest.raises(TypeError, match="heading_jacobian"):
        Half()


def test_thrust_gains_and_lag_come_from_their_effects():
    p = params.vector({"k": 5.0, "thrust_asymmetry.ratio": 0.8, "reverse_thrust.ratio": 0.5,
                       "thrust_lag.tau": 0.3})
    g = ref.thrust_gains(p, np.array([-1.0, 1.0, 1.0]), np.array([0.2, 0.3, -0.4]))
    np.testing.assert_allclose(g, [5.0, 4.0, 2.0])
    assert ref.lag_time_constant(p) == 0.3


def test_a_model_that_crosses_a_process_keeps_its_catalogue_effects_built_in():
    """Pickled (a fleet worker's reply) or copied, a model with catalogue effects still
    tells them from user effects (by identity), so its parameter layout and propagation
    are the original's: a copy once put linear_drag's parameters after the table as a user
    effect's, and the dead-reckoning refinement failed on the fleet."""
    import copy
    import pickle
    m, _ = simulate("asv", seed=1, duration=20.0)
    model = Model.for_mission(m).with_effects("linear_drag", SquareWind())
    for other in (pickle.loads(pickle.dumps(model)), copy.deepcopy(model)):
        assert other.effects[0] is BUILTIN["linear_drag"]
        assert [e.name for e in other.user_effects] == ["square_wind"]
        assert other.user_layout()[0][1] == model.user_layout()[0][1]
        assert other.n_full == model.n_full
        steps, _ = other.steps(m, np.array([5.0, 7.0]))
        p = model.nominal({"k": 9.0, "linear_drag.c_x": 2.0, "square_wind.c": 1e-3})
        x0 = np.array([0.0, 0.0, 0.0, 0.5, 0.1, 0.0])
        np.testing.assert_array_equal(other.propagate(x0, p, steps)[0],
                                      model.propagate(x0, p, steps)[0])
