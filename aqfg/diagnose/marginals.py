"""Joint marginal covariances of knot states and parameters, without inverting the graph.

The held-out predictions need, for each anchor knot ``a``, the joint covariance of its state
``x_a`` (6) and the estimated parameters ``theta``: a few small blocks of ``N^-1`` with
``N = A^T A`` the whitened normal matrix of a fit. Solving ``N Z = E`` for every anchor's
six unit columns costs one sparse solve per column (hundreds of them on a 15-minute mission).

The graph has an arrow structure: the states of one mission form a block-tridiagonal chain
(a dynamics factor links consecutive knots; every measurement touches one knot), and every
other column (parameter nodes, other missions' states) couples to the chain only through
the parameter columns ``P``. With ``T`` the chain's block of ``N`` and ``B`` its coupling
to ``P`` (block inverse, e.g. Golub & Van Loan, *Matrix Computations*, §3.2):

    Sigma_XP = -T^-1 B Sigma_PP,    Sigma_XX = T^-1 + Sigma_XP Sigma_PP^-1 Sigma_PX

so one solve per parameter column gives ``Sigma_XP`` and ``Sigma_PP``, and the diagonal
blocks of ``T^-1`` come from the block-tridiagonal recursion of a Rauch-Tung-Striebel
smoother (forward Schur complements, backward covariances; O(K) 6x6 operations).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from aqfg.fg.score import LinearSystem, covariance, factorise


def _chain_blocks(N: sp.csr_matrix, kc: np.ndarray):
    """Diagonal ``D`` (K, 6, 6) and upper off-diagonal ``E`` (K-1, 6, 6) blocks of ``N``
    on the knot columns ``kc`` (K, 6); None if the block is not tridiagonal."""
    K = len(kc)
    sub = N[kc.ravel()][:, kc.ravel()].tocoo()
    # rows/cols of ``sub`` are in kc.ravel() order: knot = idx // 6, comp = idx % 6
    kr, cr = sub.row // 6, sub.row % 6
    kk, ck = sub.col // 6, sub.col % 6
    d = kk - kr
    if np.any(np.abs(d) > 1):
        return None
    D = np.zeros((K, 6, 6))
    E = np.zeros((max(K - 1, 0), 6, 6))
    s = d == 0
    np.add.at(D, (kr[s], cr[s], ck[s]), sub.data[s])
    s = d == 1
    np.add.at(E, (kr[s], cr[s], ck[s]), sub.data[s])
    return D, E


def _tridiag_inverse_diag(D: np.ndarray, E: np.ndarray) -> np.ndarray:
    """Diagonal blocks (K, 6, 6) of the inverse of the SPD block-tridiagonal matrix with
    diagonal blocks ``D`` and upper blocks ``E`` (``T[i, i+1] = E[i]``)."""
    K = len(D)
    Sinv = np.empty_like(D)
    S = D[0]
    Sinv[0] = np.linalg.inv(S)
    for i in range(1, K):
        S = D[i] - E[i - 1].T @ Sinv[i - 1] @ E[i - 1]
        Sinv[i] = np.linalg.inv(S)
    G = np.empty_like(D)
    G[-1] = Sinv[-1]
    for i in range(K - 2, -1, -1):
        F = Sinv[i] @ E[i]                  # S_i^-1 E_i
        G[i] = Sinv[i] + F @ G[i + 1] @ F.T
    return 0.5 * (G + np.transpose(G, (0, 2, 1)))


def anchor_covariances(lin: LinearSystem, mission_index: int, knots: np.ndarray,
                       pcols: np.ndarray, ridge: float = 1e-9) -> np.ndarray:
    """Joint covariance (n, 6 + p, 6 + p) of ``[x_k, theta]`` for each knot index in
    ``knots`` of mission ``mission_index``, ``theta`` the columns ``pcols`` of ``lin.A``
    (the fit's own marginal covariance at its optimum, same ridge as
    :func:`aqfg.fg.score.covariance`, to which it falls back when the states are not
    a chain)."""
    assert lin.knot_cols is not None, "a LinearSystem from aqfg.diagnose.linearise"
    A = sp.csc_matrix(lin.A)
    kc_all = np.asarray(lin.knot_cols[mission_index], int)
    knots = np.asarray(knots, int)
    pcols = np.asarray(pcols, int)
    N = (A.T @ A).tocsr()
    N = N + sp.diags(ridge * np.maximum(N.diagonal(), 1e-12))
    N = sp.csr_matrix(N)
    n = N.shape[0]
    state = np.zeros(n, bool)
    for kc in lin.knot_cols:
        state[np.asarray(kc, int).ravel()] = True
    P = np.flatnonzero(~state)
    blocks = _chain_blocks(N, kc_all)
    p = len(pcols)
    out = np.zeros((len(knots), 6 + p, 6 + p))
    if blocks is None:                                   # not a chain: direct solves
        for i, k in enumerate(knots):
            out[i] = covariance(A, np.concatenate([kc_all[k], pcols]), ridge)
        return out
    D, E = blocks
    lu = factorise(N.tocsc())
    Ep = np.zeros((n, len(P)))
    Ep[P, np.arange(len(P))] = 1.0
    Z = lu.solve(Ep) if len(P) else Ep                  # Sigma[:, P]
    Spp = 0.5 * (Z[P] + Z[P].T)
    Gd = _tridiag_inverse_diag(D, E)
    pos_in_P = {int(c): j for j, c in enumerate(P)}
    tp = np.array([pos_in_P[int(c)] for c in pcols], int)
    try:
        Spp_inv = np.linalg.inv(Spp)
    except np.linalg.LinAlgError:
        Spp_inv = np.linalg.pinv(Spp)
    for i, k in enumerate(knots):
        W = Z[kc_all[k]]                                 # (6, |P|) = Sigma_xP
        Sxx = Gd[k] + W @ Spp_inv @ W.T
        out[i, :6, :6] = 0.5 * (Sxx + Sxx.T)
        out[i, :6, 6:] = W[:, tp]
        out[i, 6:, :6] = W[:, tp].T
        out[i, 6:, 6:] = Spp[np.ix_(tp, tp)]
    return out
