"""Parameter uncertainty and observability of an update-error fit (paper §III-F).

The update error (Eq. 14) is not a whitened residual, so the Gauss-Newton covariance of its
own sum of squares means nothing by itself. :func:`assess` linearises the fit at the
optimum (forward differences of every node's terms, in the parameters' own scales) and
returns, per estimated parameter, a finite 1-sigma or "not determined" with the reason:

* ``sandwich`` (default when the fit spans enough fixes): the M-estimator covariance of
  ``argmin sum ||r_i||^2`` (``r_i``: the metric's residual rows of node ``i``),
  ``A^-1 B A^-1`` with ``A = sum J_i^T J_i`` and ``B`` the covariance of the summed scores
  ``g_i = J_i^T r_i``, estimated from the scores themselves summed over ``G`` blocks of
  consecutive fixes (``G = max(MIN_BLOCKS, sqrt(n_fix))``, so blocks of ``~sqrt(n_fix)``
  fixes on long fits; a ``G / (G - 1)`` small-sample factor). It measures how much the estimate of *this*
  estimator moves with the data actually seen, so it stays honest when the noise levels
  are wrong, the innovations are correlated over a block, or the model is not the vehicle
  (then it is the spread around the best model-fit, not around an unknowable truth).
* ``model`` (fallback, fewer than two fixes per block, e.g. an online window, or the
  public code's scalar metric): the Gauss-Newton approximation on the whitened
  innovations (the maximum-likelihood Cramer-Rao approximation), inflated by the measured
  consistency ``c = sum nu_w^2 / (n - p)`` when ``c > 1``. It describes the efficient
  (ML) estimator, not the update-error one, and is too small for the weakly observed
  constants (measured in docs/update-error.md).

Observability: directions of the parameter space along which the metric does not change
(eigenvalues of ``A`` below ``RCOND`` times the largest, in scaled units) carry no
information; a parameter with weight on such a direction is "not determined" (its sigma
is not a number). Otherwise the verdict compares sigma with the parameter's magnitude
``m`` (:func:`magnitude`): "determined" when ``sigma <= 0.1 m``, "weakly determined" up to
``m``, "not determined" beyond (sigma not reported: the data do not pin it down better
than its plausible size). A parameter at a bound is reported as such (the local
approximation does not hold there).

A gated USBL fix whose accept/reject decision flips within a finite-difference step would
put a jump into the Jacobian; the step is then taken on the other side or 10x smaller.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aqfg.ekf.history import DEPTH, FIX_KINDS, IMU_ACC
from aqfg.ekf.optim import NodeTerms, Objective
from aqfg.ekf.window import ACCEPTED

RCOND = 1e-9          # relative eigenvalue below which a direction carries no information
MIN_BLOCKS = 10       # fewest fix blocks for the sandwich
DETERMINED = 0.1      # sigma / magnitude at or below which a parameter is "determined"
STEP = 1e-4           # finite-difference step, in units of the parameter's scale

VERDICTS = ("determined", "weakly determined", "not determined", "at bound")


@dataclass
class Uncertainty:
    """Per estimated number: ``sigma`` (finite, or NaN where ``note`` says why not),
    ``verdict`` (one of :data:`VERDICTS`) and ``note`` (None or the reason no sigma is
    given). ``method``: "sandwich" or "model"; ``consistency``: mean squared whitened
    innovation per degree of freedom (1 for a consistent filter); ``blocks``: fix blocks
    of the sandwich; ``cov``: covariance in the parameters' units (NaN rows/columns for
    the undetermined)."""
    sigma: np.ndarray
    verdict: list[str]
    note: list[str | None]
    method: str
    consistency: float
    blocks: int
    cov: np.ndarray

    def as_info(self, names: list[str]) -> dict:
        """Plain-JSON summary: ``{name: {"verdict", "sigma" (or None), "note"}}``."""
        return {n: {"verdict": v, "sigma": (float(s) if np.isfinite(s) else None),
                    **({"note": t} if t else {})}
                for n, s, v, t in zip(names, self.sigma, self.verdict, self.note)}


def magnitude(spec, value: float) -> float:
    """The size ``sigma`` is judged against: the parameter's typical magnitude
    (``spec.scale``), or ``|value|`` for a positive constant without an upper bound
    (thrust and drag constants, whose size differs by an order of magnitude between
    vehicles)."""
    if spec.lower > 0 and not np.isfinite(spec.upper):
        return max(abs(float(value)), 1e-12)
    return float(spec.scale)


def _dims(kind: np.ndarray) -> np.ndarray:
    return np.where(np.isin(kind, FIX_KINDS), 2, np.where(kind == DEPTH, 1,
                                                           np.where(kind == IMU_ACC, 3, 0)))


def _column(obj: Objective, theta: np.ndarray, i: int, h: float, lo, hi, t0: NodeTerms
            ) -> tuple[NodeTerms, float] | None:
    """Terms at ``theta + step e_i`` for the first step that keeps every gate decision and
    gives finite terms (a filter at the edge of its integration's stability can diverge
    a step away from the estimate)."""
    for step in (h, -h, 0.1 * h, -0.1 * h):
        th = theta.copy()
        th[i] += step
        if (lo is not None and th[i] < lo[i]) or (hi is not None and th[i] > hi[i]):
            continue
        t = obj.node_terms(th)
        if (np.array_equal(t.status, t0.status) and np.all(np.isfinite(t.rows))
                and np.all(np.isfinite(t.nu_w))):
            return t, step
    return None


def assess(obj: Objective, theta: np.ndarray, scales: np.ndarray, specs: list,
           lo: np.ndarray | None = None, hi: np.ndarray | None = None,
           sandwich: bool = True) -> Uncertainty:
    """Uncertainty and observability of the estimate ``theta`` (module doc). ``specs``: the
    :class:`aqfg.model.params.ParamSpec` of each entry; ``lo``/``hi``: the bounds used."""
    p = len(theta)
    scales = np.asarray(scales, float)
    t0 = obj.node_terms(theta)
    acc = t0.status == ACCEPTED
    Jr, Jw, flipped = _jacobians(obj, theta, scales, lo, hi, t0)
    Jw[~acc] = 0.0
    nw = int(_dims(t0.kind)[acc].sum())
    chi2 = float(np.sum(t0.nu_w[acc] ** 2))
    consistency = chi2 / max(nw - p, 1)

    A = np.einsum("ndi,ndj->ij", Jr, Jr)
    # information directions: of the metric (A) for the update error; a parameter that
    # moves no residual at all has a zero column
    lam, V = np.linalg.eigh(A)
    null = lam <= RCOND * max(lam.max(initial=0.0), 1e-300)
    load_null = np.sum(V[:, null] ** 2, axis=1) if null.any() else np.zeros(p)

    fixes = np.isin(t0.kind, FIX_KINDS)
    n_fix = int(fixes.sum())
    if sandwich and n_fix >= 2 * MIN_BLOCKS and obj.metric != "innovation":
        cov_s, blocks = _block_sandwich(t0, Jr, fixes, _pinv(lam, V, null))
        method = "sandwich"
    else:
        method, blocks = "model", 0
        Iw = np.einsum("ndi,ndj->ij", Jw, Jw)
        lw, Vw = np.linalg.eigh(Iw)
        nullw = lw <= RCOND * max(lw.max(initial=0.0), 1e-300)
        cov_s = _pinv(lw, Vw, nullw) * max(1.0, consistency)
        if nullw.any():
            load_null = np.maximum(load_null, np.sum(Vw[:, nullw] ** 2, axis=1))

    sig_s = np.sqrt(np.clip(np.diag(cov_s), 0.0, None))
    sigma = sig_s * scales
    verdict, note = _verdicts(theta, specs, scales, sigma, lo, hi, flipped, load_null)
    bad = np.array([t is not None for t in note])
    sigma = np.where(bad, np.nan, sigma)
    cov = cov_s * np.outer(scales, scales)
    cov[bad, :] = np.nan
    cov[:, bad] = np.nan
    return Uncertainty(sigma, verdict, note, method, float(consistency), blocks, cov)


def _jacobians(obj: Objective, theta: np.ndarray, scales: np.ndarray,
               lo: np.ndarray | None, hi: np.ndarray | None, t0
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Forward-difference derivatives, per unit of each parameter's scale, of the metric's
    rows (n, d, p) and of the whitened innovations (n, 3, p) at ``theta`` (terms ``t0``);
    and which parameters have no usable derivative (their columns zero: :func:`_column`)."""
    p = len(theta)
    n, d = t0.rows.shape
    Jr = np.zeros((n, d, p))
    Jw = np.zeros((n, 3, p))
    flipped = np.zeros(p, bool)
    for i in range(p):
        got = _column(obj, theta, i, STEP * scales[i], lo, hi, t0)
        if got is None:
            flipped[i] = True
            continue
        t, step = got
        # derivatives per unit of the parameter's scale (dimensionless columns)
        Jr[:, :, i] = (t.rows - t0.rows) / step * scales[i]
        Jw[:, :, i] = (t.nu_w - t0.nu_w) / step * scales[i]
    return Jr, Jw, flipped


def _block_sandwich(t0, Jr: np.ndarray, fixes: np.ndarray, Ai: np.ndarray
                    ) -> tuple[np.ndarray, int]:
    """Sandwich covariance ``A^-1 B A^-1`` (scaled units; ``Ai`` = ``A^-1``) with ``B``
    from the metric's gradient summed over blocks of consecutive fixes (about sqrt(n_fix)
    blocks, at least ``MIN_BLOCKS``, never across windows); and the number of blocks."""
    n = t0.rows.shape[0]
    p = Jr.shape[2]
    n_fix = int(fixes.sum())
    G = max(MIN_BLOCKS, int(np.sqrt(n_fix)))
    per = int(np.ceil(n_fix / G))
    # block id: window, then running fix count within it
    blk = np.zeros(n, int)
    base = 0
    for w in np.unique(t0.window):
        sel = t0.window == w
        cnt = np.cumsum(fixes[sel]) - fixes[sel]           # fixes before each node
        b = cnt // per
        blk[sel] = base + b
        base += int(b.max(initial=0)) + 1
    g = np.einsum("ndi,nd->ni", Jr, t0.rows)
    nb = int(blk.max()) + 1
    gb = np.zeros((nb, p))
    np.add.at(gb, blk, g)
    B = gb.T @ gb * nb / max(nb - 1, 1)
    return Ai @ B @ Ai, nb


def _verdicts(theta: np.ndarray, specs: list, scales: np.ndarray, sigma: np.ndarray,
              lo: np.ndarray | None, hi: np.ndarray | None, flipped: np.ndarray,
              load_null: np.ndarray) -> tuple[list[str], list[str | None]]:
    """Each parameter's observability verdict and, where it has no usable sigma, why."""
    verdict: list[str] = []
    note: list[str | None] = []
    for i, spec in enumerate(specs):
        at_lo = lo is not None and abs(theta[i] - lo[i]) <= 1e-4 * scales[i]
        at_hi = hi is not None and abs(theta[i] - hi[i]) <= 1e-4 * scales[i]
        m = magnitude(spec, theta[i])
        if flipped[i]:
            verdict.append("not determined")
            note.append("no derivative at the estimate: a gated fix changes its "
                        "accept/reject decision there, or the filter diverges a step away")
        elif at_lo or at_hi:
            bound = lo if at_lo else hi
            assert bound is not None
            b = bound[i]
            verdict.append("at bound")
            note.append(f"at its {'lower' if at_lo else 'upper'} bound {b:.6g}: the fit "
                        "pushes it beyond, no interior value is supported")
        elif load_null[i] > 1e-3 or not np.isfinite(sigma[i]):
            verdict.append("not determined")
            note.append("the data carry no information on it (the error does not change "
                        "along a direction that moves it)")
        elif sigma[i] > m:
            verdict.append("not determined")
            note.append(f"1-sigma {sigma[i]:.3g} exceeds its magnitude {m:.3g}")
        else:
            verdict.append("determined" if sigma[i] <= DETERMINED * m else "weakly determined")
            note.append(None)
    return verdict, note


def _pinv(lam: np.ndarray, V: np.ndarray, null: np.ndarray) -> np.ndarray:
    inv = np.where(null, 0.0, 1.0 / np.where(null, 1.0, lam))
    return (V * inv) @ V.T


def no_motion_through_water(unc: Uncertainty, specs: list, thrust: bool) -> Uncertainty:
    """Without any thrust command in the data the vehicle only drifts with the water: the
    heading offset and every thrust or drag parameter (group "fixed") then act only on the
    filter's velocity noise, and whatever sigma the fit gives them is not a statement about
    the vehicle. Marks them "not determined" when ``thrust`` is False."""
    if thrust:
        return unc
    for i, spec in enumerate(specs):
        if spec.group == "fixed" or spec.name in ("theta_e", "heading_drift.rate"):
            unc.verdict[i] = "not determined"
            unc.note[i] = "no thrust command in the data: the vehicle never moved through the water"
            unc.sigma[i] = np.nan
            unc.cov[i, :] = np.nan
            unc.cov[:, i] = np.nan
    return unc
