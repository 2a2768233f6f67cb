"""aqfg.distributions: the chi-square, normal and Student's t functions a fit uses, from
scipy.special, equal to scipy.stats' (which a fit no longer imports)."""
import numpy as np
import pytest
from scipy import stats

from aqfg import distributions as dist

X = np.concatenate([[-1.0, 0.0, 1e-12, 0.3, 1.0, 5.0, 30.0, 100.0, 700.0, 1500.0, np.inf,
                     np.nan], np.linspace(0.0, 50.0, 101)])
Q = np.array([0.0, 1e-300, 1e-10, 0.01, 0.5, 0.99, 0.995, 1.0 - 1e-12, 1.0, np.nan])


@pytest.mark.parametrize("df", [1, 2, 3, 5, 8, 17, 100])
def test_equal_to_scipy_stats(df):
    with np.errstate(all="ignore"):
        np.testing.assert_array_equal(dist.chi2_sf(X, df), stats.chi2.sf(X, df))
        np.testing.assert_array_equal(dist.chi2_logsf(X, df), stats.chi2.logsf(X, df))
    np.testing.assert_array_equal(dist.chi2_ppf(Q, df), stats.chi2.ppf(Q, df))
    np.testing.assert_array_equal(dist.t_ppf(Q, df), stats.t.ppf(Q, df))
    for d in (df, df + 0.37):
        np.testing.assert_array_equal(dist.t_cdf(X, d), stats.t.cdf(X, d))
        np.testing.assert_array_equal(dist.t_sf(X, d), stats.t.sf(X, d))
    assert float(dist.chi2_sf(3.3, df)) == float(stats.chi2.sf(3.3, df))


def test_normal_equal_to_scipy_stats():
    xx = np.concatenate([-X, X])
    np.testing.assert_array_equal(dist.norm_cdf(xx), stats.norm.cdf(xx))
    np.testing.assert_array_equal(dist.norm_ppf(Q), stats.norm.ppf(Q))
