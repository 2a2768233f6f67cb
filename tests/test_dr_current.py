"""The current a dead reckoning drifts with (aqfg.fg.dr_current): a wrong current is
re-estimated by prediction error and replaces it for the model-only predictions, with the
truth within tolerance; on a
vehicle that is the model the smoother's current stays; short missions are left alone and
every decision is reported."""
from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest

from aqfg.data.mission import between
from aqfg.evaluate import inertial_rmse
from aqfg.fg import fit_fg
from aqfg.fg.dr_current import CURRENT, refine_current
from aqfg.parameters_doc import parameters_document
from aqfg.sim.simulator import simulate

TRUE_CURRENT = (0.15, -0.10)          # m/s north, east


@pytest.fixture(scope="module")
def asv():
    m, truth = simulate("asv", seed=3, duration=480.0, gnss_period=8.0,
                        params={"s_x": TRUE_CURRENT[0], "s_y": TRUE_CURRENT[1]})
    return m, truth, fit_fg([m])


def _with_current(result, s):
    """A copy of ``result`` whose current is ``s`` (the record of the refinement reset)."""
    r = copy.deepcopy(result)
    idx = [r.model.index(n) for n in CURRENT]
    r.missions[0].p = r.missions[0].p.copy()
    r.missions[0].p[idx] = s
    r.values.update(dict(zip(CURRENT, s)))
    r.dead_reckoning = dataclasses.replace(r.dead_reckoning, current=())
    return r


def test_a_vehicle_that_is_the_model_keeps_the_smoothers_current(asv):
    m, _, r = asv
    c = r.dead_reckoning.current[0]
    assert c.mission == m.name and c.blocks >= 2 and not c.applied
    assert c.cost_after >= c.cost_before
    for n, v in zip(CURRENT, c.before):
        assert r.values[n] == v
    # the prediction-error estimate is consistent where the model is right
    assert np.allclose(c.after, TRUE_CURRENT, atol=0.03), c.after


def test_a_wrong_current_is_replaced_and_the_retrace_improves(asv, capsys):
    m, truth, r = asv
    wrong = (TRUE_CURRENT[0] - 0.12, TRUE_CURRENT[1] + 0.10)
    bad = _with_current(r, wrong)
    before = inertial_rmse(bad.model, m, bad.missions[0].p, truth)
    out = refine_current(bad, [m], 60.0)
    idx = [out.model.index(n) for n in CURRENT]
    assert np.array_equal(bad.missions[0].p[idx], wrong) and bad.dead_reckoning.current == ()
    c = out.dead_reckoning.current[0]
    assert c.applied and c.cost_after < c.cost_before, c
    assert c.before == pytest.approx(wrong)
    assert np.allclose(c.after, TRUE_CURRENT, atol=0.03), c.after
    for n, v, s in zip(CURRENT, wrong, c.sigma):
        assert out.values[n] == v and s > 0      # the reported current: the smoother's
    assert np.array_equal(out.missions[0].p[idx], c.after)
    # the model-only re-trace is redone with the current reported, and is closer
    after = inertial_rmse(out.model, m, out.missions[0].p, truth)
    tr = out.missions[0].inertial
    pt = np.column_stack([np.interp(tr.t, truth.t, truth.pos[:, a]) for a in range(2)])
    assert np.sqrt(np.mean(np.sum((tr.pos[:, :2] - pt) ** 2, axis=1))) == pytest.approx(after, rel=0.05)
    assert after < 0.5 * before, (before, after)
    doc = parameters_document(out)["dead_reckoning"]["current"][m.name]
    assert doc["applied"] is True
    assert doc["refined"]["s_x"]["value"] == pytest.approx(c.after[0])
    assert doc["smoother"]["s_y"] == pytest.approx(wrong[1])
    from aqfg.commands.fit import _print_summary  # what `aqfg fit` says of it
    _print_summary(out)
    assert f"{m.name}: the model-only re-trace drifts with the current refined" in capsys.readouterr().out


def test_too_little_data_keeps_the_smoothers_current(asv):
    m, _, _ = asv
    short = between(m, m.t0, m.t0 + 50.0)           # predictions within one block of 60 s
    r = fit_fg([short])
    c = r.dead_reckoning.current[0]
    assert not c.applied and "too little data" in c.reason
    assert (r.values["s_x"], r.values["s_y"]) == c.before
    assert "reason" in parameters_document(r)["dead_reckoning"]["current"][short.name]
