"""Which effect is missing? Score (Lagrange-multiplier) tests at the null.

The base fit minimises ``||A x - b||^2`` at its optimum (``A``, ``b``: the whitened,
linearised graph; GTSAM's ``b = -error``). Adding an effect adds columns ``C`` (the
derivatives of every residual w.r.t. the effect's parameters at their null value, which the
kernel always returns) without moving the optimum. Eliminating the base variables:

    C~ = C - A (A^T A)^-1 A^T C      (what the base variables cannot explain)
    g  = C~^T b                      (the score: half the gradient of the cost)
    S  = C~^T C~                     (the effect's information with the base re-optimised)

The one-step (Gauss-Newton) estimate of the effect is ``delta = S^-1 g`` with covariance
``S^-1``, and the LM statistic ``g^T S^-1 g = delta^T S delta`` is the drop of the cost that
this step buys; under the null (effect absent, noise model right) it is ``chi2(dim)``
(Rao 1948; Engle 1984, "Wald, likelihood ratio and Lagrange multiplier tests"). A parameter
whose null sits on its bound (``thrust_lag.tau >= 0``, ``linear_drag.c >= 0``) is tested
one-sided: the statistic is taken at the best *feasible* step and its 1-D null law is
``0.5 chi2(0) + 0.5 chi2(1)``; for several parameters the plain ``chi2(dim)`` tail is used,
which is conservative for the chi-bar-square law.

A noise model that is only roughly right inflates or deflates every LM statistic alike. The
*robust* (sandwich) statistic replaces ``S`` by the empirical variance of the score summed
over time blocks, ``V = B/(B-1) sum_b (g_b - g/B)(g_b - g/B)^T``, and is valid whatever the
noise scale and its correlation within a block (White 1982; Wooldridge 1990 for the
regression-based LM form). Every term is a sum over residual rows, so a block bootstrap over
time (Kuensch 1989) of the ranking costs only small matrix sums.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from aqfg import distributions as dist


@dataclass
class LinearSystem:
    """The base fit's whitened linear system at its optimum, plus candidate columns.

    ``A`` (m, n) sparse: columns of the variables the base fit estimated; ``C`` (m, c)
    dense: one column per candidate effect parameter (``names``, full names such as
    ``thrust_lag.tau``), at the parameter's null value; ``b`` (m,) = -whitened residual;
    ``row_time`` (m,) s (NaN for rows without a time, e.g. priors); ``row_kind`` (m,)
    factor kind ("dynamics", "gnss", "usbl", "depth", "prior"). ``lower``/``upper``/
    ``null`` (c,) per candidate column: bounds and null value.
    """
    A: sp.csr_matrix
    C: np.ndarray
    b: np.ndarray
    names: tuple[str, ...]
    row_time: np.ndarray
    row_kind: np.ndarray
    null: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    scale: np.ndarray | None = None     # typical parameter magnitudes (for conditioning)
    knots: list | None = None           # per mission: knot times (K,) s
    knot_cols: list | None = None       # per mission: (K, 6) columns of A of each knot state
    param_cols: dict | None = None      # (mission, parameter name) -> column of A


@dataclass
class Projected:
    """``C~`` and ``b~`` of a :class:`LinearSystem` (rows kept for per-block sums)."""
    Ct: np.ndarray          # (m, c)
    bt: np.ndarray          # (m,)
    names: tuple[str, ...]
    row_time: np.ndarray
    null: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    dof: int                # m - n: residual degrees of freedom of the base fit
    cost: float             # ||b~||^2: the base fit's whitened cost


def factorise(N: sp.spmatrix):
    """Sparse LU of a symmetric positive definite normal matrix (no pivoting, symmetric
    mode: fill stays near Cholesky's; faster than the default, docs/diagnosis.md)."""
    return spla.splu(sp.csc_matrix(N), permc_spec="COLAMD", diag_pivot_thresh=0.0,
                     options=dict(SymmetricMode=True))


def project(sys: LinearSystem, ridge: float = 1e-9) -> Projected:
    """Eliminate the base variables: ``C~ = C - A (A^T A)^-1 A^T C`` and the same for ``b``.

    ``A^T A`` is factorised once (sparse LU); ``ridge`` x its diagonal guards against
    directions the base fit leaves unconstrained.
    """
    A = sys.A.tocsc()
    m, n = A.shape
    if sys.C.shape[0] != m or len(sys.b) != m:
        raise ValueError(f"linear system shapes disagree: A {A.shape}, C {sys.C.shape}, b {sys.b.shape}")
    N = (A.T @ A).tocsc()
    d = N.diagonal()
    N = N + sp.diags(ridge * np.maximum(d, 1e-12))
    lu = factorise(N)
    rhs = np.column_stack([A.T @ sys.C, A.T @ sys.b]) if n else np.zeros((0, sys.C.shape[1] + 1))
    Z = lu.solve(rhs) if n else rhs
    AZ = A @ Z
    Ct = sys.C - AZ[:, :-1]
    bt = sys.b - AZ[:, -1]
    return Projected(Ct, bt, sys.names, sys.row_time, sys.null, sys.lower, sys.upper,
                     int(m - n), float(bt @ bt))


@dataclass
class ScoreTest:
    """Score test of one effect at its null.

    ``statistic`` LM (model-based), ``p_value`` its tail; ``statistic_robust`` /
    ``p_value_robust`` the sandwich version over ``n_blocks`` time blocks; ``delta`` and
    ``sigma`` the one-step estimate of the effect's parameters (offset from the null and
    its 1-sigma, model-based); ``estimate`` null + delta.
    """
    effect: str
    params: tuple[str, ...]
    statistic: float
    p_value: float
    statistic_robust: float
    p_value_robust: float
    dof: int
    delta: np.ndarray
    sigma: np.ndarray
    estimate: np.ndarray
    n_blocks: int
    log10_p: float = float("nan")        # log10 of p_value (resolves p-values below 1e-300)
    gradient: np.ndarray | None = None   # the score g = C~^T b~ (which way the data pull)

    def to_json(self) -> dict:
        return {"effect": self.effect, "statistic": self.statistic, "p_value": self.p_value,
                "log10_p": self.log10_p, "statistic_robust": self.statistic_robust,
                "p_value_robust": self.p_value_robust, "dof": self.dof,
                "estimate": {n: {"value": float(v), "sigma": float(s)}
                             for n, v, s in zip(self.params, self.estimate, self.sigma)}}


def _box(null: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """Bounds of the step ``d`` from the null: ``lo - null <= d <= hi - null``."""
    return lo - null, hi - null


def _lm(g: np.ndarray, S: np.ndarray, dlo: np.ndarray, dhi: np.ndarray):
    """Best step ``d`` and the LM statistic ``max 2 g^T d - d^T S d`` over the box
    ``dlo <= d <= dhi`` (the parameters' physical bounds). Without binding bounds this is
    ``d = S^-1 g``, ``g^T S^-1 g``; otherwise every assignment of each coordinate to free /
    lower / upper is tried (3^dim, dim <= 3 here). A binding bound can only lower the
    statistic, so the chi-square p-value stays valid (conservative)."""
    try:
        d = np.linalg.solve(S, g)
    except np.linalg.LinAlgError:
        d = np.linalg.lstsq(S, g, rcond=None)[0]
    if np.all(d >= dlo - 1e-15) and np.all(d <= dhi + 1e-15):
        return d, float(2 * g @ d - d @ S @ d)
    k = len(g)
    best_d, best = np.zeros(k), 0.0
    for state in itertools.product((0, 1, 2), repeat=k):      # 0 free, 1 at lower, 2 at upper
        st = np.array(state)
        fixed = np.where(st == 1, dlo, np.where(st == 2, dhi, 0.0))
        if np.any(~np.isfinite(fixed[st > 0])):
            continue
        free = st == 0
        d = fixed.copy()
        if free.any():
            rhs = g[free] - S[np.ix_(free, ~free)] @ fixed[~free]
            try:
                d[free] = np.linalg.solve(S[np.ix_(free, free)], rhs)
            except np.linalg.LinAlgError:
                continue
        if np.any(d < dlo - 1e-12) or np.any(d > dhi + 1e-12):
            continue
        val = float(2 * g @ d - d @ S @ d)
        if val > best:
            best, best_d = val, d
    return best_d, best


def log_chi2_sf(x: float, k: int) -> float:
    """Natural log of the chi-square(k) upper tail, also far beyond float underflow
    (leading term of the incomplete gamma function: ``Gamma(s, y) ~ y^(s-1) e^-y``)."""
    lp = float(dist.chi2_logsf(x, k))
    if np.isfinite(lp):
        return lp
    s, y = k / 2.0, x / 2.0
    return float((s - 1) * np.log(y) - y - math.lgamma(s))


def _p_value(stat: float, dim: int, one_sided: bool) -> tuple[float, float]:
    """p-value and its log10 for an LM statistic (``0.5 chi2(1)`` for a 1-D one-sided test)."""
    stat = max(stat, 0.0)
    if one_sided and dim == 1:
        if stat <= 0:
            return 1.0, 0.0
        lp = log_chi2_sf(stat, 1) + np.log(0.5)
    else:
        lp = log_chi2_sf(stat, dim)
    return float(np.exp(lp)), float(lp / np.log(10))


def _log10_p(stat: np.ndarray, dim: int, one_sided: bool) -> np.ndarray:
    """:func:`_p_value`'s log10 p for an array of statistics (vectorised; statistics beyond
    the float range of the tail use its leading term, as :func:`log_chi2_sf`)."""
    stat = np.maximum(np.asarray(stat, float), 0.0)
    with np.errstate(divide="ignore"):
        lp = dist.chi2_logsf(stat, dim)
    bad = ~np.isfinite(lp)
    if bad.any():
        lp[bad] = [log_chi2_sf(float(x), dim) for x in stat[bad]]
    if one_sided and dim == 1:
        lp = np.where(stat > 0, lp + np.log(0.5), 0.0)
    return lp / np.log(10)


def time_blocks(row_time: np.ndarray, n_blocks: int) -> np.ndarray:
    """Block index (0..n_blocks-1) of each row by time quantile; -1 for rows without time."""
    out = np.full(len(row_time), -1, int)
    ok = np.isfinite(row_time)
    if not ok.any():
        return out
    edges = np.quantile(row_time[ok], np.linspace(0, 1, n_blocks + 1))
    out[ok] = np.clip(np.searchsorted(edges, row_time[ok], side="right") - 1, 0, n_blocks - 1)
    return out


def score_tests(proj: Projected, effects: dict[str, tuple[str, ...]],
                n_blocks: int = 20) -> list[ScoreTest]:
    """Score test of each effect (``{effect: its parameter names}``, each name a column of
    ``proj``), one effect at a time."""
    col = {n: i for i, n in enumerate(proj.names)}
    blk = time_blocks(proj.row_time, n_blocks)
    ok = blk >= 0
    nb = int(blk[ok].max()) + 1 if ok.any() else 0
    out = []
    for eff, pnames in effects.items():
        missing = [n for n in pnames if n not in col]
        if missing:
            raise KeyError(f"effect {eff!r}: no candidate column for {', '.join(missing)}")
        cols = np.array([col[n] for n in pnames])
        Ce = proj.Ct[:, cols]
        g = Ce.T @ proj.bt
        S = Ce.T @ Ce
        null, lo, hi = proj.null[cols], proj.lower[cols], proj.upper[cols]
        dlo, dhi = _box(null, lo, hi)
        one_sided = bool(np.any(dlo == 0) or np.any(dhi == 0))
        d, lm = _lm(g, S, dlo, dhi)
        p, lp = _p_value(lm, len(cols), one_sided)
        try:
            cov = np.linalg.inv(S)
        except np.linalg.LinAlgError:
            cov = np.linalg.pinv(S)
        sig = np.sqrt(np.maximum(np.diag(cov), 0.0))
        # sandwich: variance of the score from time blocks
        if nb >= 4:
            gb = np.zeros((nb, len(cols)))
            np.add.at(gb, blk[ok], Ce[ok] * proj.bt[ok, None])
            gc = gb - gb.mean(axis=0)
            V = nb / (nb - 1) * gc.T @ gc
            _, lmr = _lm(g, V, dlo, dhi)
            pr, _ = _p_value(lmr, len(cols), one_sided)
        else:
            lmr, pr = float("nan"), float("nan")
        out.append(ScoreTest(eff, tuple(pnames), float(lm), p, float(lmr), pr, len(cols), d,
                             sig, null + d, nb, lp, g.copy()))
    return out


def bootstrap_ranking(proj: Projected, effects: dict[str, tuple[str, ...]], n_boot: int = 200,
                      n_blocks: int = 20, seed: int = 0) -> dict[str, float]:
    """How often each effect ranks first (smallest p-value) when time blocks of residual
    rows are resampled with replacement (moving-block bootstrap over ``n_blocks`` blocks).

    Returns ``{effect: fraction of resamples in which it ranks first}``.
    """
    col = {n: i for i, n in enumerate(proj.names)}
    blk = time_blocks(proj.row_time, n_blocks)
    ok = blk >= 0
    nb = int(blk[ok].max()) + 1 if ok.any() else 0
    if nb < 2 or not effects:
        return {e: float("nan") for e in effects}
    # per-block sums of g and S for every candidate column
    c = proj.Ct.shape[1]
    Gb = np.zeros((nb, c))
    np.add.at(Gb, blk[ok], proj.Ct[ok] * proj.bt[ok, None])
    Sb = np.zeros((nb, c, c))
    np.add.at(Sb, blk[ok], proj.Ct[ok, :, None] * proj.Ct[ok, None, :])
    g0 = (proj.Ct[~ok] * proj.bt[~ok, None]).sum(axis=0)
    S0 = proj.Ct[~ok].T @ proj.Ct[~ok]
    info = []
    for eff, pn in effects.items():
        cols = np.array([col[n] for n in pn])
        null, lo, hi = proj.null[cols], proj.lower[cols], proj.upper[cols]
        dlo, dhi = _box(null, lo, hi)
        info.append((eff, cols, dlo, dhi, bool(np.any(dlo == 0) or np.any(dhi == 0))))
    rng = np.random.default_rng(seed)
    W = np.stack([np.bincount(rng.integers(0, nb, nb), minlength=nb).astype(float)
                  for _ in range(n_boot)])
    G = g0 + W @ Gb                                     # (n_boot, c)
    S = S0 + np.tensordot(W, Sb, axes=1)                # (n_boot, c, c)
    lp = np.empty((n_boot, len(info)))
    for j, (_eff, cols, flo, fhi, one) in enumerate(info):
        lm = np.array([_lm(G[r, cols], S[r][np.ix_(cols, cols)], flo, fhi)[1]
                       for r in range(n_boot)])
        lp[:, j] = _log10_p(lm, len(cols), one)
    first = np.argmin(lp, axis=1)
    return {eff: float(np.mean(first == j)) for j, (eff, *_rest) in enumerate(info)}


def covariance(A: sp.spmatrix, cols: np.ndarray, ridge: float = 1e-9) -> np.ndarray:
    """Joint marginal covariance of the variables in ``cols`` of a whitened system
    ``A`` at its optimum: the ``cols`` block of ``(A^T A)^-1`` (sparse LU, one solve per
    column)."""
    A = sp.csc_matrix(A)
    N = (A.T @ A).tocsc()
    N = N + sp.diags(ridge * np.maximum(N.diagonal(), 1e-12))
    lu = factorise(N)
    cols = np.asarray(cols, int)
    E = np.zeros((A.shape[1], len(cols)))
    E[cols, np.arange(len(cols))] = 1.0
    Z = lu.solve(E)
    S = Z[cols]
    return 0.5 * (S + S.T)


def shared_information(proj: Projected, a: tuple[str, ...], b: tuple[str, ...]) -> float:
    """Largest squared canonical correlation between the projected columns of the
    parameters ``a`` and ``b`` (0: the data tell the two effects apart completely; 1: one
    can stand in for the other). Fitting ``b`` jointly with ``a`` inflates the sigma of
    ``b``'s best-determined combination by ``1 / sqrt(1 - r2)``."""
    col = {n: i for i, n in enumerate(proj.names)}
    Ca = proj.Ct[:, [col[n] for n in a]]
    Cb = proj.Ct[:, [col[n] for n in b]]
    Saa, Sbb, Sab = Ca.T @ Ca, Cb.T @ Cb, Ca.T @ Cb
    try:
        M = np.linalg.solve(Sbb, Sab.T) @ np.linalg.solve(Saa, Sab)
    except np.linalg.LinAlgError:
        return float("nan")
    ev = np.linalg.eigvals(M).real
    return float(np.clip(ev.max(initial=0.0), 0.0, 1.0))


def holm_log(log10_p: np.ndarray) -> np.ndarray:
    """Holm-adjusted p-values from log10 p-values (exact for tiny p)."""
    m = len(log10_p)
    o = np.argsort(log10_p)
    adj = np.empty(m)
    run = -np.inf
    for k, i in enumerate(o):
        run = max(run, min(0.0, math.log10(m - k) + log10_p[i]))
        adj[i] = 10 ** run
    return adj
