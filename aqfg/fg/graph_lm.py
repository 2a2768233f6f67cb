"""Levenberg-Marquardt on a built batch graph (:class:`aqfg.fg.graph.BuiltGraph`).

:func:`levenberg_marquardt` runs :func:`aqfg.fg.lm.levenberg_marquardt` either on GTSAM's
linearisation (:class:`GraphLM`: Marquardt's damping on every key, the parameter bounds by
an active set, :func:`damped_step`) or on the graph's numpy form
(:mod:`aqfg.fg.fastlm`); :func:`fast_covariance` gives the parameter nodes' Hessian and
sandwich covariances from the numpy system.
"""
from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from aqfg.fg import factors as fc
from aqfg.fg import lm
from aqfg.fg.fastlm import FastSystem, levenberg_marquardt_fast
from aqfg.fg.graph import BuiltGraph
from aqfg.fg.lm import diagonal_floor
from aqfg.fg.settings import FGSettings


@dataclass
class LMOutcome:
    """Result of one Levenberg-Marquardt solve of a built graph."""
    values: gtsam.Values
    cost: float
    gfg: gtsam.GaussianFactorGraph | None   # linearised at ``values`` (GTSAM path)
    iterations: int
    trials: int
    converged: bool
    it_times: list[float]
    fast: dict | None = None               # numpy path: its evaluation at ``values``


def fast_covariance(fs: FastSystem, ev: dict, node_list, layout, key_time, s: FGSettings):
    """Hessian and sandwich covariances of the parameter nodes from the numpy system
    (the same quantities as the Bayes tree's marginals and :func:`block_sandwich`)."""
    D, E, Hsp, Hpp, gs, gp = fs.normal(ev)
    try:
        fac = fs.factor(D, E, Hsp, Hpp)
        C = fs.param_covariance(fac)
    except np.linalg.LinAlgError:
        cov = {k: np.diag(np.full(layout.dim(g), np.inf)) for g, k, _ in node_list}
        return cov, None
    cov = {}
    for _, k, _ in node_list:
        o, d = fs.node_off[k]
        cov[k] = C[o:o + d, o:o + d].copy()
    sw = fs.sandwich(ev, fac, key_time, s.batch.sandwich_block) if s.batch.sandwich_block else None
    return cov, sw


def finish_fast(fs: FastSystem, prev: LMOutcome, X: np.ndarray, th: np.ndarray,
                 s: FGSettings) -> LMOutcome:
    """LM on the numpy system from ``(X, th)`` to convergence (after the process-noise
    factor changed); iteration counts and times add to ``prev``'s."""
    X, th, cost, ev, n_it, n_trials, conv, it_times = levenberg_marquardt_fast(
        fs, None, s, start=(X, th))
    return LMOutcome(fs.to_values(X, th, prev.values), cost, None, prev.iterations + n_it,
                     prev.trials + n_trials, conv, prev.it_times + it_times, ev)


class GraphLM:
    """:class:`aqfg.fg.lm.LMSystem` of a built graph on GTSAM's linearisation: a point is
    a ``gtsam.Values``. Marquardt's damping on every key, the bounds of the parameter nodes
    ``bounded`` by an active set (:func:`damped_step`); a candidate is ``project`` of the
    retracted values. ``pin``: a factor added to every step's system (a node held)."""

    def __init__(self, bg: BuiltGraph, ordering: gtsam.Ordering, bounded, project,
                 pin: gtsam.JacobianFactor | None = None):
        self.bg, self.ordering, self.bounded, self.project, self.pin = \
            bg, ordering, bounded, project, pin
        self.key_dims = bg.key_dims()
        self.evaluated: tuple[gtsam.Values | None, float] = (None, np.nan)   # in the cache
        self.lin_at: gtsam.Values | None = None

    def cost(self, x: gtsam.Values) -> float:
        """The cost at ``x``; the dynamics cache then holds ``x``."""
        self.evaluated = (x, self.bg.error(x))
        return self.evaluated[1]

    def linearize(self, x: gtsam.Values) -> None:
        if self.evaluated[0] is not x:
            self.cost(x)
        self.gfg = self.bg.graph.linearize(x)       # the cache holds the dynamics at x
        self.lin_at, self.base = x, self.evaluated[1]
        self.hdiag = hessian_diagonal(self.gfg, self.key_dims)
        self.system = self.gfg
        if self.pin is not None:
            self.system = self.gfg.clone()
            self.system.add(self.pin)

    def trial(self, x: gtsam.Values, lam: float) -> tuple[gtsam.Values, float, float]:
        try:
            delta = damped_step(self.system, self.ordering, self.key_dims, self.hdiag, lam,
                                self.bg.layout, self.bounded, x)
        except RuntimeError as e:   # GTSAM's indeterminate system: an ill-conditioned one
            raise np.linalg.LinAlgError(str(e)) from e
        cand = self.project(x.retract(delta))
        return cand, self.cost(cand), self.base

    def settle(self, x: gtsam.Values) -> gtsam.GaussianFactorGraph:
        """The linearisation at ``x`` (the loop's end), the dynamics cache holding ``x``."""
        if self.lin_at is not x:
            self.linearize(x)
        elif self.evaluated[0] is not x:
            self.bg.fill(x)
        return self.gfg


def project_nodes(layout: fc.ParamLayout, nodes, values: gtsam.Values) -> gtsam.Values:
    """``values`` with the parameter ``nodes`` projected onto their bounds (in place)."""
    for g, k, _ in nodes:
        v = values.atVector(k)
        pv = layout.project(g, v)
        if np.any(pv != v):
            values.update(k, pv)
    return values


def levenberg_marquardt(bg: BuiltGraph, values: gtsam.Values, ordering: gtsam.Ordering | None,
                        s: FGSettings, progress=None, fs: FastSystem | None = None) -> LMOutcome:
    """:func:`aqfg.fg.lm.levenberg_marquardt` of the graph driven from Python (GTSAM's
    optimizers copy all Values into every CustomFactor call, :class:`GraphLM`), the
    stopping rule of :class:`FGSettings` (an accepted step lowering the cost by less than
    ``max(rel_tol x cost, abs_tol)``). With ``fs`` the same algorithm runs on the numpy
    form of the graph (:mod:`aqfg.fg.fastlm`); ``gfg`` is then None."""
    if fs is not None:
        X, th, cost, ev, n_it, n_trials, conv, it_times = levenberg_marquardt_fast(
            fs, values, s, progress)
        return LMOutcome(fs.to_values(X, th, values), cost, None, n_it, n_trials, conv,
                         it_times, ev)
    if ordering is None:
        ordering = gtsam.Ordering.MetisGaussianFactorGraph(bg.linearize(values))
    system = GraphLM(bg, ordering, bg.nodes,
                     lambda vals: project_nodes(bg.layout, bg.nodes, vals))
    out = lm.levenberg_marquardt(system, values, lm.LMParams.of(s),
                                 lm.batch_progress(progress, s.solver.max_iterations))
    return LMOutcome(out.x, out.cost, system.settle(out.x), out.iterations, out.trials,
                     out.converged, out.it_times)


def damped_step(gfg: gtsam.GaussianFactorGraph, ordering: gtsam.Ordering, key_dims,
                hdiag: dict, lam: float, layout: fc.ParamLayout, nodes, values: gtsam.Values
                ) -> gtsam.VectorValues:
    """One Levenberg-Marquardt step of the linear system ``gfg`` at ``values``.

    Marquardt's damping ``lam * diag(J^T J)`` (``hdiag`` from :func:`hessian_diagonal`) on
    every key of ``key_dims``, and an active set for the bounds of the parameter ``nodes``:
    parameters pushed through a bound go exactly to it and the rest of the step is re-solved
    consistently (a bare projection made LM crawl: 59 iterations with a drag term pinned at
    zero).
    """
    damped = gfg.clone()
    for k, d in key_dims:
        damped.add(gtsam.JacobianFactor(k, np.diag(np.sqrt(lam * hdiag[k])),
                                        np.zeros(d), gtsam.noiseModel.Unit.Create(d)))
    delta = damped.eliminateMultifrontal(ordering).optimize()
    clamps = active_bounds(layout, nodes, values, delta)
    if clamps:
        for k, A, b in clamps:
            damped.add(gtsam.JacobianFactor(k, A, b, gtsam.noiseModel.Unit.Create(len(b))))
        delta = damped.eliminateMultifrontal(ordering).optimize()
    return delta


def active_bounds(layout, node_list, values, delta, weight: float = 1e8) -> list:
    """Constraints ``(key, A, b)`` fixing the step of parameters that it would push
    beyond their bounds: ``delta_j = bound_j - v_j`` (whitened by ``weight``)."""
    out = []
    for g, k, _ in node_list:
        v = values.atVector(k)
        d = delta.at(k)
        lo, hi = layout.bounds(g)
        new = v + d
        hit = (new < lo) | (new > hi)
        if not np.any(hit):
            continue
        idx = np.flatnonzero(hit)
        A = np.zeros((len(idx), len(v)))
        A[np.arange(len(idx)), idx] = weight
        target = np.where(new[idx] < lo[idx], lo[idx], hi[idx]) - v[idx]
        out.append((k, A, weight * target))
    return out


def hessian_diagonal(gfg: gtsam.GaussianFactorGraph, key_dims, floor: bool = True) -> dict:
    """Diagonal of the Gauss-Newton Hessian A^T A per key (Marquardt's damping scale),
    from the whitened sparse Jacobian (columns in sorted key order, then b); with ``floor``
    at least 1e-9 x the key's largest entry (or 1e-9)."""
    ij = gfg.sparseJacobian_()
    col = ij[1].astype(np.int64) - 1
    d = np.bincount(col, weights=ij[2] ** 2)
    out, c = {}, 0
    for k, n in sorted(key_dims):
        v = d[c:c + n] if c + n <= len(d) else np.zeros(n)
        out[k] = diagonal_floor(v) if floor else v.copy()
        c += n
    return out


