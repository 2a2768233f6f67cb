"""The one Levenberg-Marquardt loop (aqfg.fg.lm), the Huber loss (aqfg.fg.robust) and the
fleet's rounds handed out by a generator (aqfg.fg.schur.joint_lm, aqfg.fg.rounds)."""
from __future__ import annotations

import threading

import gtsam
import numpy as np
import pytest

from aqfg.fg.settings import FGSettings
from aqfg.fg.lm import LMParams, levenberg_marquardt
from aqfg.fg.robust import huber_cost, huber_cost_squared, huber_scalar, huber_weight
from aqfg.fg.schur import joint_lm


class Rosenbrock:
    """r = (10 (y - x^2), 1 - x), minimum 0 at (1, 1); ``lo``: a lower bound on x (an
    active set, as the batch's systems)."""

    def __init__(self, lo: float = -np.inf):
        self.lo = lo
        self.singular = 0

    def res(self, p):
        return np.array([10.0 * (p[1] - p[0] ** 2), 1.0 - p[0]])

    def cost(self, p) -> float:
        r = self.res(p)
        return 0.5 * float(r @ r)

    def linearize(self, p) -> None:
        self.J = np.array([[-20.0 * p[0], 10.0], [-1.0, 0.0]])
        self.r = self.res(p)

    def trial(self, p, lam):
        H = self.J.T @ self.J
        if lam < 1e-2 and self.singular < 2:        # two ill-posed systems: more damping
            self.singular += 1
            raise np.linalg.LinAlgError("singular")
        A, g = H + lam * np.diag(np.diag(H)), -self.J.T @ self.r
        d = np.linalg.solve(A, g)
        if p[0] + d[0] < self.lo:           # the bound active: x to it, y re-solved
            d[0] = self.lo - p[0]
            d[1] = (g[1] - A[1, 0] * d[0]) / A[1, 1]
        c = p + d
        return c, self.cost(c), self.cost(p)


def test_loop_reaches_the_minimum_and_records_its_iterates():
    sys_ = Rosenbrock()
    seen = []
    out = levenberg_marquardt(sys_, np.array([-1.2, 1.0]),
                              LMParams(100, 0.0, 1e-20),
                              lambda it, c, lam: seen.append((it, c, lam)))
    assert out.converged
    assert out.x == pytest.approx([1.0, 1.0], abs=1e-6)
    assert out.cost < 1e-12
    assert sys_.singular == 2 and out.trials > out.iterations
    costs = [c for _, c, _ in out.history]
    assert all(b <= a for a, b in zip(costs, costs[1:]))       # accepted steps only
    assert seen == out.history[1:] and out.history[0][0] == 0
    assert all(lam >= 1e-9 for _, _, lam in out.history)


def test_loop_stops_at_the_iteration_limit_and_at_a_bound():
    out = levenberg_marquardt(Rosenbrock(), np.array([-1.2, 1.0]), LMParams(3, 0.0, 0.0))
    assert out.iterations == 3 and not out.converged
    # x held at 2 or above: the constrained minimum (2, 4)
    out = levenberg_marquardt(Rosenbrock(lo=2.0), np.array([3.0, 0.0]), LMParams(100, 0.0, 1e-20))
    assert out.converged and out.x[0] == 2.0 and out.x[1] == pytest.approx(4.0, abs=1e-6)


def test_params_follow_the_settings():
    s = FGSettings().with_(solver={"max_iterations": 7, "rel_tol": 1e-4, "abs_tol": 2e-3})
    p = LMParams.of(s)
    assert (p.max_iterations, p.rel_tol, p.abs_tol) == (7, 1e-4, 2e-3)
    assert LMParams.of(s, max_iterations=2).max_iterations == 2


@pytest.mark.parametrize("k", [0.5, 1.345, 3.0])
def test_huber_is_gtsams(k):
    h = gtsam.noiseModel.mEstimator.Huber.Create(k)
    d = np.array([0.0, 0.3, k, 1.5 * k, 10.0 * k])
    assert huber_cost(d, k) == pytest.approx([h.loss(x) for x in d], rel=1e-12)
    assert huber_weight(d, k) == pytest.approx([h.weight(x) for x in d], rel=1e-12)
    for x in d:
        assert huber_scalar(float(x), k) == pytest.approx((h.weight(x), h.loss(x)), rel=1e-12)
    assert 2.0 * huber_cost_squared(d ** 2, k * k) == pytest.approx(2.0 * huber_cost(d, k),
                                                                    rel=1e-12)
    # None: the Gaussian loss
    assert huber_cost(d, None) == pytest.approx(0.5 * d ** 2)
    assert np.all(huber_weight(d, None) == 1.0) and huber_scalar(2.0, None) == (1.0, 2.0)


def _lm_threads():
    return [t for t in threading.enumerate() if t.name == "aqfg-rounds"]


def test_joint_lm_generator_closed_mid_run_stops_its_loop():
    gen = joint_lm(2, FGSettings())
    reqs = next(gen)
    assert [op for op, _ in reqs] == ["open", "open"]
    assert len(_lm_threads()) == 1
    gen.close()
    assert not _lm_threads()


def test_joint_lm_generator_raises_what_the_loop_raises():
    gen = joint_lm(1, FGSettings())
    next(gen)
    with pytest.raises(KeyError):
        gen.send([{}])              # an "open" reply without the layout
    assert not _lm_threads()


def test_a_start_where_the_cost_is_not_finite_is_not_a_minimum():
    """From a point where the model cannot be evaluated (NaN cost) the loop takes no step
    and does not call that point converged."""
    class Nowhere(Rosenbrock):
        def cost(self, p) -> float:
            return float("nan")
    out = levenberg_marquardt(Nowhere(), np.array([-1.2, 1.0]), LMParams(100, 0.0, 1e-20))
    assert not out.converged and out.iterations == 0 and np.isnan(out.cost)
