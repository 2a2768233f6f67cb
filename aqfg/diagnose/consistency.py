"""Is the model consistent with its noise? Normalised-innovation chi-square tests.

Each measurement ``j`` contributes ``nis_j = r_j^T S_j^-1 r_j`` (the squared whitened
residual: the sum of squared normalised components) with ``dof_j`` components. Under a
consistent model ``nis_j ~ chi2(dof_j)`` independently, so the sum over a time window
is ``chi2(sum dof)`` (the NIS test of Bar-Shalom, Li & Kirubarajan, *Estimation with
Applications to Tracking and Navigation*, §5.4). Smoothed (fitted) residuals have lost
the degrees of freedom spent on the fit: ``expected`` gives ``E[nis_j]`` when it is not
``dof_j`` (e.g. ``dof_j (1 - leverage)``), and the chi-square is scaled to that mean
(Satterthwaite: ``nis ~ (E/dof) chi2(dof)``).

The test is one-sided: residuals *larger* than their noise say the model misses
something; residuals smaller than their noise only say the noise model is conservative.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats


@dataclass
class ConsistencyTest:
    """Windowed and overall NIS test of one residual series.

    Per window ``w`` (``t0[w] <= t < t1[w]``): ``nis`` summed, its ``dof``, the chi-square
    ``upper``/``lower`` bounds at level ``alpha`` (two-sided band) and its upper-tail
    ``p_value``. ``fails[w]``: the window lies above the upper bound.
    Overall: ``total`` NIS over ``total_dof`` with upper-tail ``p_value_total``;
    ``n_fail`` windows above the bound out of ``n_windows``, with ``p_value_windows`` the
    binomial probability of that many or more by chance (``alpha / 2`` each).
    ``passed``: neither the overall nor the window count test rejects at ``level``.
    ``ratio``: total NIS / its expectation (1 = consistent; 4 = errors twice their sigma).
    """
    t0: np.ndarray
    t1: np.ndarray
    nis: np.ndarray
    dof: np.ndarray
    expected: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    p_value: np.ndarray
    fails: np.ndarray
    total: float
    total_dof: float
    total_expected: float
    p_value_total: float
    n_fail: int
    n_windows: int
    p_value_windows: float
    alpha: float
    level: float
    passed: bool

    @property
    def ratio(self) -> float:
        return float(self.total / self.total_expected) if self.total_expected > 0 else float("nan")

    def summary(self) -> str:
        verdict = "consistent" if self.passed else "NOT consistent"
        return (f"{verdict} with the noise model: NIS/expected = {self.ratio:.2f}, "
                f"overall p = {self.p_value_total:.3g}; {self.n_fail} of {self.n_windows} "
                f"windows above the {100 * (1 - self.alpha / 2):.1f}% bound "
                f"(p = {self.p_value_windows:.3g})")

    def to_json(self) -> dict:
        return {"passed": bool(self.passed), "nis_ratio": self.ratio,
                "p_value": float(self.p_value_total), "windows_failing": int(self.n_fail),
                "windows": int(self.n_windows), "p_value_windows": float(self.p_value_windows)}


def _scaled_chi2_sf(x, dof, expected):
    """Upper tail of ``(expected/dof) chi2(dof)`` at ``x``."""
    dof = np.maximum(np.asarray(dof, float), 1e-12)
    c = np.asarray(expected, float) / dof
    return stats.chi2.sf(np.asarray(x, float) / np.maximum(c, 1e-300), dof)


def _scaled_chi2_ppf(q, dof, expected):
    dof = np.maximum(np.asarray(dof, float), 1e-12)
    c = np.asarray(expected, float) / dof
    return c * stats.chi2.ppf(q, dof)


def nis_test(t: np.ndarray, nis: np.ndarray, dof: np.ndarray, window: float = 60.0,
             expected: np.ndarray | None = None, alpha: float = 0.05,
             level: float = 0.01) -> ConsistencyTest:
    """NIS test over consecutive windows of ``window`` seconds and over the whole series.

    ``t`` (n,) s; ``nis`` (n,) squared whitened residual per measurement; ``dof`` (n,)
    its number of components; ``expected`` (n,) its mean under the model (default
    ``dof``). Windows with no measurement are skipped.
    """
    t = np.asarray(t, float)
    nis = np.asarray(nis, float)
    dof = np.broadcast_to(np.asarray(dof, float), nis.shape).astype(float)
    exp = dof if expected is None else np.broadcast_to(np.asarray(expected, float), nis.shape)
    if not (len(t) == len(nis)):
        raise ValueError(f"nis_test: t has {len(t)} entries but nis has {len(nis)}")
    if not len(t):
        raise ValueError("nis_test: no residuals to test")
    if window <= 0:
        raise ValueError(f"nis_test: window must be positive, got {window}")
    ok = np.isfinite(nis)
    t, nis, dof, exp = t[ok], nis[ok], dof[ok], exp[ok]
    edges = np.arange(t.min(), t.max() + window, window)
    if len(edges) < 2:
        edges = np.array([t.min(), t.min() + window])
    idx = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, len(edges) - 2)
    nw = len(edges) - 1
    s_nis = np.bincount(idx, nis, nw)
    s_dof = np.bincount(idx, dof, nw)
    s_exp = np.bincount(idx, exp, nw)
    keep = s_dof > 0
    t0, t1 = edges[:-1][keep], edges[1:][keep]
    s_nis, s_dof, s_exp = s_nis[keep], s_dof[keep], s_exp[keep]
    upper = _scaled_chi2_ppf(1 - alpha / 2, s_dof, s_exp)
    lower = _scaled_chi2_ppf(alpha / 2, s_dof, s_exp)
    pw = _scaled_chi2_sf(s_nis, s_dof, s_exp)
    fails = s_nis > upper
    total, tdof, texp = float(nis.sum()), float(dof.sum()), float(exp.sum())
    p_tot = float(_scaled_chi2_sf(total, tdof, texp))
    n_fail, n_w = int(fails.sum()), int(len(s_nis))
    p_win = float(stats.binom.sf(n_fail - 1, n_w, alpha / 2)) if n_w else 1.0
    passed = bool(p_tot >= level and p_win >= level)
    return ConsistencyTest(t0, t1, s_nis, s_dof, s_exp, lower, upper, pw, fails, total, tdof,
                           texp, p_tot, n_fail, n_w, p_win, alpha, level, passed)
