"""Parameter covariance that stays honest when the model is wrong.

The Hessian (Laplace) covariance ``H^-1`` of the MAP estimate assumes that the factors'
noise models are right. On a vehicle that is not the model the dynamics residuals are
large and correlated over tens of seconds, and ``H^-1`` is far too small. The sandwich
(Huber/White) covariance ``H^-1 M H^-1`` replaces the assumed information by the measured
spread of the score: ``M = sum_b g_b g_b^T`` with ``g_b = A_b^T r_b`` the gradient of the
whitened cost contributed by the factors of time block ``b`` (a block-HAC "meat", so that
correlation within a block is counted). Parameter priors enter the bread, not the meat.
Blocks come from the state knots a factor touches; the result is scaled by B / (B - n_p)
for the few blocks of one mission.

The sandwich's own estimate is noisy: with ``B`` blocks and ``n_p`` parameters each
variance is, on a correct model, the Hessian's times ``chi2(dof)/dof`` (``dof = B - n_p``).
A variance is therefore raised to the sandwich's only where the ratio is significant at
5 % (one-sided) -- so a model that fits keeps its Hessian sigma and a misspecified one gets
the sandwich's, instead of every fit drawing a random inflation.
"""
from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from aqfg import distributions as dist

SANDWICH_ALPHA = 0.05


@dataclass
class BlockGradients:
    """The whitened linear system ``A x = b`` of a linearised graph (columns in sorted key
    order, ``col0[key]`` the first of each key), and the gradient of the cost contributed
    by each time block ``G[:, j] = A_j^T b_j`` (n x len(ids)) over the rows of factors
    touching a state; ``ids``: the block numbers that hold rows, counted from ``t0``."""
    A: sp.csr_matrix
    col0: dict[int, int]
    G: np.ndarray
    ids: np.ndarray


def block_gradients(gfg: gtsam.GaussianFactorGraph, key_dims: list[tuple[int, int]],
                    key_time: dict[int, float], t0: float, block: float) -> BlockGradients:
    """Per-block score gradients of a linearised graph (the sandwich's meat, before any
    solve): a factor's rows belong to the block of the newest state it touches."""
    col0, c = {}, 0
    for k, d in sorted(key_dims):
        col0[k] = c
        c += d
    n = c
    ij = gfg.sparseJacobian_()
    rows = ij[0].astype(np.int64) - 1
    cols = ij[1].astype(np.int64) - 1
    vals = ij[2]
    is_b = cols == n
    m = int(rows.max()) + 1 if len(rows) else 0
    b = np.zeros(m)
    b[rows[is_b]] = vals[is_b]
    A = sp.csr_matrix((vals[~is_b], (rows[~is_b], cols[~is_b])), shape=(m, n))
    row_block = np.full(m, -1, np.int64)
    r = 0
    for i in range(gfg.size()):
        f = gfg.at(i)
        if f is None:
            continue
        assert isinstance(f, (gtsam.JacobianFactor, gtsam.HessianFactor))
        nr = f.rows()
        ts = [key_time[k] for k in f.keys() if k in key_time]
        if ts:
            row_block[r:r + nr] = int((max(ts) - t0) // block)
        r += nr
    keep = row_block >= 0
    ids, local = np.unique(row_block[keep], return_inverse=True)   # blocks holding rows
    nk = int(keep.sum())
    Ab = A.multiply(b[:, None]).tocsr()[keep]
    onehot = sp.csr_matrix((np.ones(nk), (np.arange(nk), local)), shape=(nk, len(ids)))
    return BlockGradients(A, col0, (Ab.T @ onehot).toarray(), ids)


def block_sandwich(gfg: gtsam.GaussianFactorGraph, key_dims: list[tuple[int, int]],
                   key_time: dict[int, float], param_keys: list[int], block: float
                   ) -> tuple[dict[int, np.ndarray], int] | None:
    """Sandwich covariance of the ``param_keys`` blocks of a linearised graph.

    ``key_dims``: (key, dim) of every variable; ``key_time``: time (s) of the state keys;
    factors touching no state key (priors on parameters) are left out of the meat;
    ``block``: length (s) of the time blocks. Returns the covariances and the degrees of
    freedom ``B - n_p`` of the estimate; None when there are too few blocks.
    """
    bg = block_gradients(gfg, key_dims, key_time, min(key_time.values()), block)
    nb = len(bg.ids)
    n_p = sum(d for k, d in key_dims if k in set(param_keys))
    if nb < n_p + 2:
        return None
    H = (bg.A.T @ bg.A).tocsc()
    try:
        lu = spla.splu(H, permc_spec="COLAMD")
        Z = lu.solve(bg.G)
    except RuntimeError:
        return None
    scale = nb / max(nb - n_p, 1)
    out = {}
    dims = dict(key_dims)
    for k in param_keys:
        zk = Z[bg.col0[k]:bg.col0[k] + dims[k]]
        zk = zk - zk.mean(axis=1, keepdims=True)
        out[k] = scale * zk @ zk.T
    return out, nb - n_p


def significant_ratio(dof: int, alpha: float = SANDWICH_ALPHA) -> float:
    """Variance ratio sandwich/Hessian that a correct model exceeds with probability
    ``alpha`` when the sandwich has ``dof`` degrees of freedom."""
    return float(dist.chi2_ppf(1.0 - alpha, max(int(dof), 1)) / max(int(dof), 1))


def honest_covariance(cov_model: dict[int, np.ndarray], cov_sw: dict[int, np.ndarray] | None,
                      dof: int | None = None) -> dict[int, np.ndarray]:
    """Model covariance with each variance raised to the sandwich's where that is larger
    and, given the sandwich's ``dof``, significantly so (``D C D``,
    ``D = diag(max(1, c sigma_sw / sigma_model))`` with ``c`` = :func:`t_tail_factor` of the
    dof: correlations kept, never smaller than the model's)."""
    if not cov_sw:
        return dict(cov_model)
    thr = significant_ratio(dof) if dof is not None else 1.0
    # a raised variance is the sandwich's, itself estimated from dof blocks: reported wider
    # so that its 3-sigma band keeps a normal 3-sigma band's coverage (t_dof quantile)
    tail = t_tail_factor(dof)
    out = {}
    for k, C in cov_model.items():
        S = cov_sw.get(k)
        if S is None:
            out[k] = C
            continue
        sm = np.sqrt(np.maximum(np.diag(C), 1e-300))
        ss = np.sqrt(np.maximum(np.diag(S), 0.0))
        d = np.where((ss / sm) ** 2 > thr, np.maximum(1.0, tail * ss / sm), 1.0)
        out[k] = C * np.outer(d, d)
    return out


def t_tail_factor(dof: int | None, n_sigma: float = 3.0) -> float:
    """How much wider a variance estimated with ``dof`` degrees of freedom must be reported
    for its ``n_sigma`` band to cover what a known variance's covers: Student's t quantile
    over the normal one at the same two-sided level (t_8: 4.4 / 3 = 1.47; 1 for large or
    unknown dof)."""
    if dof is None or dof <= 0:
        return 1.0
    p = float(dist.norm_cdf(n_sigma))
    return float(dist.t_ppf(p, int(dof)) / n_sigma)


def sigma_inflation(sigma: dict[str, float], sigma_model: dict[str, float]) -> dict[str, float]:
    """Per parameter, the reported (honest) sigma over the model's (Hessian) one; 1 where
    the model has none (``Result.sigma_inflation`` of a batch result)."""
    return {n: float(v / max(sigma_model.get(n, v), 1e-300)) for n, v in sigma.items()}
