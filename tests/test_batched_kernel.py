"""The lockstep kernel for models with a user effect (aqfg.model.batched) computes what the
per-step numpy reference computes: states, Jacobians (user derivatives by differences) and
the model-only re-trace, for user effects written per sample or vectorised."""
import numpy as np
import pytest

from aqfg.fg.common import knot_times
from aqfg.model import batched
from aqfg.model import reference as ref
from aqfg.model.effects import UserEffect
from aqfg.model.vehicle import Model
from aqfg.sim.simulator import simulate


def _cubic(v, R, d, tm, q):
    vb = R.T @ v
    return -R @ (np.array([q[0], q[1], q[1]]) * vb * np.abs(vb)) + [0.01 * q[0] * np.sin(tm), 0, 0]


def _cubic_vec(v, R, d, tm, q):
    vb = np.einsum("nji,nj->ni", R, v)
    out = -np.einsum("nij,nj->ni", R, np.array([q[0], q[1], q[1]]) * vb * np.abs(vb))
    out[:, 0] += 0.01 * q[0] * np.sin(tm)
    return out


PER_SAMPLE = UserEffect("cub", ("a", "b"), accel=_cubic, null=(0.0, 0.0))
VECTORISED = UserEffect("cub", ("a", "b"), accel=_cubic_vec, null=(0.0, 0.0), vectorized=True)
VALUES = {"k": 5.0, "k_x": 1.5, "thrust_lag.tau": 0.4, "reverse_thrust.ratio": 0.6,
          "cub.a": 0.3, "cub.b": 0.2, "theta_e": 0.3, "s_x": 0.1, "heading_drift.rate": 1e-3,
          "current_drift.ds_x": 1e-3, "linear_drag.c_x": 0.2, "wind_drag.a_n": 0.01,
          "ground_advance.c": 0.15}


@pytest.fixture(scope="module")
def mission():
    m, _ = simulate("asv", seed=2, duration=40.0)
    return m


@pytest.mark.parametrize("user", [PER_SAMPLE, VECTORISED], ids=["per-sample", "vectorised"])
def test_lockstep_equals_the_reference(mission, user):
    model = Model.for_mission(mission, ("thrust_lag", "reverse_thrust", "ground_advance", user))
    knots = knot_times(mission, 1.0)
    steps, off = model.steps(mission, knots)
    p = model.nominal(VALUES)
    rng = np.random.default_rng(0)
    X0 = rng.normal(size=(len(knots) - 1, 6))
    X0[:, 2] = X0[:, 5] = 0.0
    got = batched.propagate_many(X0, p, steps, off, model.geometry, model.user_layout())
    if user is PER_SAMPLE:
        want = ref.propagate_many(X0, p, steps, off, model.geometry, model.user_layout())
    else:       # the reference calls one sample at a time: through sample_accel
        want = ref.propagate_many(X0, p, steps, off, model.geometry,
                                  Model.for_mission(mission, ("thrust_lag", "reverse_thrust",
                                                              "ground_advance",
                                                              PER_SAMPLE)).user_layout())
    for a, b in zip(got, want):
        assert np.allclose(a, b, rtol=1e-8, atol=1e-8)
    # Model.propagate_many takes this road when a user effect is on
    assert np.allclose(model.propagate_many(X0, p, steps, off)[0], got[0], atol=1e-12)


@pytest.mark.parametrize("lag", [True, False])
def test_rollout_equals_the_segment_by_segment_integration(mission, lag):
    effects = (("thrust_lag",) if lag else ()) + ("reverse_thrust", "ground_advance", VECTORISED)
    model = Model.for_mission(mission, effects)
    p = model.nominal(VALUES if lag else {k: v for k, v in VALUES.items() if "lag" not in k})
    knots = np.arange(mission.t0 + 1.0, mission.t1, 0.5)
    steps, off = model.steps(mission, knots)
    x0 = np.array([1.0, -2.0, 0.0, 0.3, 0.1, 0.0])
    X = model.rollout_segments(x0, p, steps, off)
    x = x0.copy()
    for i in range(len(knots) - 1):
        x = model.propagate(x, p, steps.slice(off[i], off[i + 1]))[0]
        assert np.allclose(X[i + 1], x, atol=1e-9)
    # at its null the user effect vanishes: the built-in kernel's re-trace
    p0 = p.copy()
    p0[model.index("cub.a")] = p0[model.index("cub.b")] = 0.0
    base = Model.for_mission(mission, effects[:-1])
    want = base.rollout_segments(x0, p0[:base.n_full], steps, off)
    assert np.allclose(model.rollout_segments(x0, p0, steps, off), want, atol=1e-9)


def test_vectorised_effect_of_the_wrong_shape_is_named(mission):
    bad = UserEffect("bad", ("a",), accel=lambda v, R, d, tm, q: np.zeros(3), null=(0.0,),
                     vectorized=True)
    model = Model.for_mission(mission, (bad,))
    knots = knot_times(mission, 1.0)[:4]
    steps, off = model.steps(mission, knots)
    with pytest.raises(ValueError, match="user effect 'bad'"):
        model.propagate_many(np.zeros((3, 6)), model.nominal({"k": 5.0}), steps, off)


def test_an_effects_column_at_its_null_equals_the_references(mission):
    """The structural test reads every catalogue column of J_p at the effects' null values:
    the lockstep kernel's `ground_advance` column at c = 0 (nonzero: what the effect would
    do) equals the reference's."""
    model = Model.for_mission(mission, ("thrust_lag", PER_SAMPLE))
    knots = knot_times(mission, 1.0)
    steps, off = model.steps(mission, knots)
    p = model.nominal({k: v for k, v in VALUES.items() if k != "ground_advance.c"})
    X0 = np.random.default_rng(1).normal(size=(len(knots) - 1, 6))
    X0[:, 2] = X0[:, 5] = 0.0
    got = batched.propagate_many(X0, p, steps, off, model.geometry, model.user_layout())[2]
    want = ref.propagate_many(X0, p, steps, off, model.geometry, model.user_layout())[2]
    j = model.index("ground_advance.c")
    assert np.abs(want[:, :, j]).max() > 1e-3
    assert np.allclose(got[:, :, j], want[:, :, j], rtol=1e-8, atol=1e-10)
