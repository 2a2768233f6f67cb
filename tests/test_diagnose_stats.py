"""The statistics of the diagnosis on problems with known answers (fast, no fitting)."""
import numpy as np
import pytest
import scipy.sparse as sp
from scipy import stats

from aqfg.diagnose.conditions import (ConditionSignals, circular_linear, effective_n, holm,
                                      in_words, relate, adjust, spearman_autocorr)
from aqfg.diagnose.consistency import nis_test
from aqfg.fg.score import (LinearSystem, bootstrap_ranking, covariance, log_chi2_sf,
                                 project, score_tests)


def _regression(rng, n, beta_z, null=0.0, lower=-np.inf, upper=np.inf):
    """y = X b + beta_z z + noise: base columns X, candidate columns z1 (true), z2 (decoy)."""
    t = np.linspace(0, 100, n)
    X = np.column_stack([np.ones(n), t / 100])
    z1 = np.sin(t / 7.0)
    z2 = np.cos(t / 3.0)
    y = X @ np.array([1.0, -2.0]) + beta_z * z1 + rng.normal(0, 1, n)
    # the base fit's residual at its optimum
    b = y - X @ np.linalg.lstsq(X, y, rcond=None)[0]
    C = np.column_stack([z1, z2])
    return LinearSystem(sp.csr_matrix(X), C, b, ("e1.a", "e2.a"), t, np.full(n, "fix"),
                        np.array([null, null]), np.array([lower, lower]),
                        np.array([upper, upper]))


def test_score_test_is_chi2_under_the_null_and_finds_the_effect():
    rng = np.random.default_rng(0)
    stats_null = []
    for _ in range(300):
        pr = project(_regression(rng, 200, 0.0))
        stats_null.append(score_tests(pr, {"e1": ("e1.a",)})[0].statistic)
    # LM ~ chi2(1) under the null: mean 1, 95% quantile 3.84 (tolerances ~ 4 standard errors)
    assert abs(np.mean(stats_null) - 1.0) < 0.35
    assert abs(np.mean(np.array(stats_null) > 3.84) - 0.05) < 0.05
    pr = project(_regression(rng, 200, 0.8))
    tests = {s.effect: s for s in score_tests(pr, {"e1": ("e1.a",), "e2": ("e2.a",)})}
    assert tests["e1"].p_value < 1e-6 and tests["e2"].p_value > 1e-3
    # the one-step estimate is the regression coefficient, within 3 sigma
    assert abs(tests["e1"].estimate[0] - 0.8) < 3 * tests["e1"].sigma[0]
    boot = bootstrap_ranking(pr, {"e1": ("e1.a",), "e2": ("e2.a",)}, n_boot=50)
    assert boot["e1"] > 0.9


def test_one_sided_null_on_a_bound():
    rng = np.random.default_rng(1)
    # effect pushes the parameter below its lower bound (= null): no evidence, p = 1
    pr = project(_regression(rng, 200, -0.5, null=0.0, lower=0.0))
    s = score_tests(pr, {"e1": ("e1.a",)})[0]
    assert s.statistic == 0.0 and s.p_value == 1.0
    pr = project(_regression(rng, 200, +0.5, null=0.0, lower=0.0))
    s = score_tests(pr, {"e1": ("e1.a",)})[0]
    assert s.p_value < 1e-6 and s.estimate[0] > 0


def test_covariance_matches_dense_inverse():
    rng = np.random.default_rng(2)
    A = rng.normal(size=(40, 6))
    full = np.linalg.inv(A.T @ A)
    cols = np.array([1, 4, 5])
    assert np.allclose(covariance(sp.csr_matrix(A), cols), full[np.ix_(cols, cols)], rtol=1e-6)


def test_log_chi2_tail_beyond_underflow():
    assert np.isclose(log_chi2_sf(10.0, 2), np.log(stats.chi2.sf(10.0, 2)))
    far = log_chi2_sf(5000.0, 2)
    assert np.isfinite(far) and np.isclose(far, -2500.0, rtol=1e-3)


def test_nis_test_calibrated_and_detects_inflation():
    rng = np.random.default_rng(3)
    t = np.arange(2000.0)
    passes = [nis_test(t, stats.chi2.rvs(2, size=2000, random_state=rng), 2.0, 60.0).passed
              for _ in range(40)]
    assert np.mean(passes) > 0.85               # two tests at 1%: false alarms rare
    nis = stats.chi2.rvs(2, size=2000, random_state=rng)
    nis[600:900] *= 3.0                         # a stretch where errors are sqrt(3) too large
    ct = nis_test(t, nis, 2.0, 60.0)
    assert not ct.passed
    bad = (ct.t0 >= 600) & (ct.t1 <= 900)
    assert ct.fails[bad].mean() > 0.5 and ct.fails[~bad].mean() < 0.2


def test_holm_and_effective_n():
    assert np.allclose(holm(np.array([0.01, 0.04, 0.03])), [0.03, 0.06, 0.06])
    rng = np.random.default_rng(4)
    white = rng.normal(size=2000)
    assert effective_n(white, rng.normal(size=2000)) > 1500
    smooth = np.convolve(rng.normal(size=2100), np.ones(50) / 50, "valid")[:2000]
    smooth2 = np.convolve(rng.normal(size=2100), np.ones(50) / 50, "valid")[:2000]
    assert effective_n(smooth, smooth2) < 200
    # two independent smooth series: naive correlation tests reject far too often,
    # the effective-n test keeps its level
    rej = 0
    for _ in range(100):
        a = np.convolve(rng.normal(size=1100), np.ones(40) / 40, "valid")[:1000]
        b = np.convolve(rng.normal(size=1100), np.ones(40) / 40, "valid")[:1000]
        rej += spearman_autocorr(a, b)[1] < 0.05
    assert rej < 15


def test_conditions_found_and_said_in_words():
    rng = np.random.default_rng(5)
    tg = np.arange(0, 1000, 0.1)
    turn = np.abs(np.sin(tg / 30.0)) ** 4
    speed = 1 + 0.3 * np.sin(tg / 47.0)
    sig = ConditionSignals(tg, {"turn_rate": turn, "speed": speed, "elapsed": tg,
                                "heading": np.mod(tg / 20.0, 2 * np.pi)})
    t = np.arange(0, 1000, 1.0)
    nis = stats.chi2.rvs(2, size=len(t), random_state=rng) * (1 + 4 * sig.mean_before("turn_rate", t, 5.0))
    eff = adjust(relate("fixes", t, nis / 2, sig, memory=5.0))
    by = {e.condition: e for e in eff}
    assert by["turn_rate"].rho > 0.3 and by["turn_rate"].p_adjusted < 1e-3
    assert by["speed"].p_adjusted > 0.05 and by["elapsed"].p_adjusted > 0.05
    assert in_words(eff) == "Errors grow in turns."
    # circular-linear: residuals peaking on one heading
    th = rng.uniform(0, 2 * np.pi, 3000)
    y = stats.chi2.rvs(2, size=3000, random_state=rng) * (1 + np.cos(th - 2.0))
    R, p, _, peak = circular_linear(th, y)
    assert p < 1e-6 and abs(np.angle(np.exp(1j * (peak - 2.0)))) < 0.3
