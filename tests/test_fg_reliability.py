"""The batch factor graph does not hand out confident nonsense: outlying fixes are
down-weighted and reported, parameters the data cannot determine are flagged, and an
optimiser that stops at its iteration limit says so."""
from __future__ import annotations

import copy

import numpy as np
import pytest

from aqfg.fg import FGSettings, fit_fg
from aqfg.sim import simulate


@pytest.fixture(scope="module")
def asv():
    return simulate("asv", seed=5, duration=600.0, gnss_period=1.0)


@pytest.fixture(scope="module")
def clean_fit(asv):
    return fit_fg([asv[0]])


def test_one_bad_gnss_fix_is_down_weighted_and_reported(asv, clean_fit):
    m = copy.deepcopy(asv[0])
    i = len(m.gnss.t) // 2
    m.gnss.ne[i] += np.array([1000.0, 0.0])          # one fix moved by 1 km
    res = fit_fg([m])
    for n in ("theta_e", "k", "k_x", "s_x", "s_y"):
        assert abs(res.values[n] - clean_fit.values[n]) < 2 * clean_fit.sigma[n], n
    flagged = res.outliers[m.name]["gnss"]
    assert any(abs(o["t"] - m.gnss.t[i]) < 1e-6 for o in flagged)
    assert any("outliers" in w for w in res.warnings)


def test_no_thrust_means_thrust_and_drag_not_determined(asv):
    m = copy.deepcopy(asv[0])
    m.motors.u[:] = 0.0
    res = fit_fg([m])
    obs = res.observability
    for n in ("k", "k_x"):
        assert obs[n]["verdict"] == "not determined", (n, obs[n])
        assert "commanded" in obs[n]["reason"]
    assert any("k is not determined" in w for w in res.warnings)


def test_a_rich_mission_determines_the_heading(clean_fit):
    assert clean_fit.observability["theta_e"]["verdict"] == "determined"


def test_iteration_limit_is_flagged(asv):
    two = FGSettings().with_(solver={"max_iterations": 2, "rel_tol": 0.0, "abs_tol": 0.0})
    res = fit_fg([asv[0]], settings=two)
    assert res.solve is not None and res.solve.hit_iteration_limit
    assert any("iteration limit" in w for w in res.warnings)


def test_sandwich_raises_a_variance_only_where_the_ratio_is_significant():
    """The sandwich is an estimate with dof degrees of freedom: a ratio a correct model
    reaches by chance keeps the Hessian variance, a significant one replaces it."""
    from aqfg.fg.covariance import honest_covariance, significant_ratio, t_tail_factor
    C = {1: np.diag([1.0, 4.0])}
    dof = 20
    thr = significant_ratio(dof)
    assert 1.3 < thr < 1.8                               # chi2(0.95, 20) / 20 = 1.57
    S = {1: np.diag([0.9 * thr, 4.0 * 3.0 * thr])}       # first not significant, second is
    out = honest_covariance(C, S, dof)[1]
    assert out[0, 0] == pytest.approx(1.0)
    # the raised one is the sandwich's, widened for the dof it was estimated from
    c = t_tail_factor(dof)
    assert 1.05 < c < 1.2
    assert out[1, 1] == pytest.approx(4.0 * 3.0 * thr * c ** 2)
    assert honest_covariance(C, S)[1][0, 0] == pytest.approx(0.9 * thr)   # no dof: max


def test_t_tail_factor_keeps_the_three_sigma_coverage():
    """A variance from dof blocks: (error / sigma) is Student-t, whose 3-sigma band covers
    less than a normal's; the factor restores the coverage (checked by sampling)."""
    from scipy.stats import norm
    from aqfg.fg.covariance import t_tail_factor
    assert t_tail_factor(None) == 1.0 and t_tail_factor(10_000) == pytest.approx(1.0, abs=1e-3)
    assert t_tail_factor(8) == pytest.approx(1.43, abs=0.01)
    rng = np.random.default_rng(0)
    dof, n = 8, 400_000
    err = rng.standard_normal(n)                              # true sigma 1
    sig = np.sqrt(rng.chisquare(dof, n) / dof)                 # its estimate
    plain = np.mean(np.abs(err) > 3 * sig)
    wide = np.mean(np.abs(err) > 3 * sig * t_tail_factor(dof))
    target = 2 * norm.sf(3.0)                                  # 0.27 %
    assert plain > 4 * target                                  # 1.7 % without the factor
    assert wide == pytest.approx(target, rel=0.15)


def test_a_start_the_model_cannot_evaluate_gives_way_to_the_next(asv):
    """Where the graph's cost is not finite at the best closed-form start (constants so
    stiff that the dynamics from its states diverge), the batch starts from the next
    candidate start where it is finite, and from the nominal constants where none is."""
    from aqfg.fg import factors as fc
    from aqfg.fg.batch import BatchSmoother
    from aqfg.fg.starts import evaluable_values
    bg = BatchSmoother().build([asv[0]])
    fixed = fc.node_key("fixed")
    names = bg.layout.names["fixed"]

    def k_of(vals):
        return float(vals.atVector(fixed)[names.index("k")])
    first = k_of(bg.values)
    assert evaluable_values(bg, lambda v: 1.0, {}) is bg.values
    nxt = evaluable_values(bg, lambda v: np.nan if k_of(v) == first else 1.0, {})
    assert k_of(nxt) == pytest.approx(bg.starts[0][1].fixed["k"])
    nominal = float(bg.layout.initial("fixed")[names.index("k")])
    last = evaluable_values(bg, lambda v: 1.0 if k_of(v) == nominal else np.nan, {})
    assert k_of(last) == nominal
