"""A user's own effect (Python, vectorised, finite-difference derivatives) works in fitting
and diagnosis.

The user writes a linear drag (in the body frame, on the ground velocity: the mission has
no current, so this is the physics the simulator hides as ``linear_drag``) without
derivatives; the diagnosis must rank it first among the candidates, confirm it by a refit
(a batch fit with the user effect: its estimate within 3 sigma of the truth), and the
held-out error must fall when it is added. User effects run on the numpy kernel (all
dynamics factors in lockstep); the mission is long enough (300 s) for the effect to be
clearly detectable.
"""
import numpy as np
import pytest

from aqfg.diagnose.workflow import diagnose
from aqfg.model.effects import BUILTIN, UserEffect
from aqfg.sim.simulator import simulate


def _linear_drag(v, R, d, tm, q):
    """All samples at once: v (n, 3), R (n, 3, 3) -> (n, 3)."""
    vb = np.einsum("nji,nj->ni", R, v)                     # R^T v per sample
    return -np.einsum("nij,nj->ni", R, np.array([q[0], q[1], q[1]]) * vb)


USER = UserEffect("my_linear_drag", ("c_x", "c_yz"), accel=_linear_drag, null=(0.0, 0.0),
                  lower=(0.0, 0.0), upper=(10.0, 10.0), units=("1/s", "1/s"), scale=(0.3, 0.3),
                  description="linear drag written by a user", vectorized=True)
TRUE = {"linear_drag.c_x": 1.0, "linear_drag.c_yz": 0.5}


@pytest.fixture(scope="module")
def mission():
    m, _ = simulate("asv", seed=1, duration=300.0, effects=dict(TRUE),
                    params={"s_x": 0.0, "s_y": 0.0})
    return m


def test_user_effect_is_diagnosed(mission):
    cands = [BUILTIN[n] for n in ("thrust_asymmetry", "wind_drag", "current_drift")] + [USER]
    d = diagnose([mission], candidates=cands, n_refit=1, max_refit=1, n_boot=50)
    top = d.ranking[0]
    assert top.effect == "my_linear_drag" and top.confirmed and d.missing
    assert top.refit.rmse < d.base.rmse
    est = top.estimate()["my_linear_drag.c_x"]          # from the refit
    assert "my_linear_drag.c_x" in top.refit.full.estimated
    assert 0 < est["sigma"] < 0.6 and abs(est["value"] - 1.0) < 3 * est["sigma"] + 0.1
    assert "my_linear_drag" in d.to_json()["ranking"][0]["effect"]
