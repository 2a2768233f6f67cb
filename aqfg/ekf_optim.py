"""Minimising the update error over a window (paper Eqs. 14-15, §III-C), with optimiser presets.

:class:`Objective` evaluates ``E(P) = sum_i ||e_i||^2`` (Eq. 14) over one or several windows
(one per mission) for a vector ``theta`` of the estimated parameters, counting and timing
every evaluation. :func:`minimise` solves Eq. 15 under bounds with one of two presets:

``"physical"`` (default)
    :func:`scipy.optimize.least_squares` (trust-region reflective) on the *stacked* vector of
    update errors (every component of every ``e_i``), forward-difference Jacobian,
    ``x_scale`` from the parameter table; bounds only physical (thrust and drag constants
    positive, ``theta_e`` within +-190 deg, current within +-2 m/s; effect parameters per
    :mod:`aqfg.params`). Using the residual structure (Gauss-Newton) converges in a few
    iterations where a scalar objective needs many.

``"paper"``
    Behaves like the authors' public C++ (github aqurai/auv-state-estimation, read for facts):
    Ceres with ONE scalar residual (the window's error sum), forward numeric derivatives, at
    most 200 iterations, bounds heading offset +-190 deg, thrust constant [2, 14], drag
    constants [0.4, 1.9] x their value before the optimisation (clamped to [0.1, 5] for
    ``k_x`` and [0, 2.5] for ``k_yz`` as there), current +-2 m/s. Here: ``least_squares``
    (``trf``, ``x_scale="jac"`` like Ceres' Jacobi scaling) on the 1-vector ``[E]``,
    ``max_nfev=200``, Ceres' default tolerances (function 1e-6, gradient 1e-10, parameter
    1e-8). Differences from Ceres: scipy's trust-region reflective method instead of Ceres'
    Levenberg-Marquardt with a bounds projection, and ``max_nfev`` counts function
    evaluations rather than iterations (Ceres' failed steps are iterations too). With a
    single residual the Gauss-Newton model always predicts ``E = 0``, so steps keep being
    shortened: measured ~700 evaluations per online optimisation of three parameters
    (the paper reports 30-50) against ~55 for "physical", for similar estimates.

Metrics. ``metric="update"`` (default) is the paper's Eq. 14, the squared Kalman update
errors of every measurement node. The public code's cost is the sum of innovation *norms*
``||z - h||`` of the absolute fixes only (``metric="innovation"``, "paper" preset only). Not
in the paper: ``metric="whitened"`` minimises the squared innovations whitened by their
covariance ``S`` (the prediction-error / maximum-likelihood cost the paper names as future
work); on simulated USBL-only missions it removes the ~0.05 m/s current bias of the update
error (whose weights ``K^T K`` are not the inverse innovation covariance). A gated node
counts in every metric, scaled by ``(gate / m2)^(1/4)`` (``m2``: its squared Mahalanobis
distance): continuous at the gate and growing like ``sqrt(m2)`` beyond it, so pushing a fix
out of the gate never pays. Evaluation counts include those of the finite differences.
The code also resets the heading offset to 0 before each optimisation, and its EKF clamps
the relative speed to 2 m/s and damps the velocity; none of that is reproduced.

Parameter uncertainty (``sigma``): the update error is not a whitened residual, so its
Gauss-Newton covariance has no statistical meaning. :func:`gn_sigma` instead linearises the
*whitened innovations* ``S^-1/2 (z - h)`` of all measurement nodes at the optimum (forward
differences) and returns ``sqrt(diag((J^T J)^-1))``: the prediction-error (ML) approximation,
which ignores the dependence of ``S`` on ``P``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from .ekf_history import FIX_KINDS, MOTOR, USBL, History
from .ekf_window import ACCEPTED, REJECTED, WindowOut, run_window

PRESETS = ("physical", "paper")
METRICS = ("update", "innovation", "whitened")


@dataclass
class Window:
    """One mission's stretch: from the anchor ``(x0, P0)`` at knot ``k0`` to knot ``k1``,
    with the full parameter vector ``p`` (estimated entries are overwritten)."""
    hist: History
    k0: int
    k1: int
    x0: np.ndarray
    P0: np.ndarray
    p: np.ndarray
    rejects: int = 0         # consecutive USBL rejections at the anchor


@dataclass(frozen=True)
class Entry:
    """One estimated number: parameter ``name`` used by windows ``windows`` (indices)."""
    name: str
    windows: tuple[int, ...]


@dataclass
class Counter:
    """Evaluation count and wall times (s) per evaluation."""
    n: int = 0
    times: list[float] = field(default_factory=list)


class Objective:
    """``E(P)`` (Eq. 14) over windows, as a function of the estimated entries ``theta``."""

    def __init__(self, windows: list[Window], entries: list[Entry], metric: str = "update",
                 use_cpp: bool | None = None, counter: Counter | None = None):
        if metric not in METRICS:
            raise ValueError(f"unknown metric {metric!r}; choose one of {', '.join(METRICS)}")
        self.windows = windows
        self.entries = entries
        self.metric = metric
        self.use_cpp = use_cpp
        self.counter = counter or Counter()
        self._idx = [[w.hist.model.index(e.name) for w in windows] for e in entries]

    def params(self, theta: np.ndarray) -> list[np.ndarray]:
        ps = [w.p.copy() for w in self.windows]
        for i, e in enumerate(self.entries):
            for wi in e.windows:
                ps[wi][self._idx[i][wi]] = theta[i]
        return ps

    def run(self, theta: np.ndarray, record: bool = False) -> list[WindowOut]:
        t0 = time.perf_counter()
        outs = [run_window(w.hist, p, w.x0, w.P0, w.k0, w.k1, record=record, use_cpp=self.use_cpp,
                           rejects=w.rejects)
                for w, p in zip(self.windows, self.params(theta))]
        self.counter.n += 1
        self.counter.times.append(time.perf_counter() - t0)
        return outs

    def _kinds(self, w: Window, o: WindowOut) -> np.ndarray:
        return w.hist.node_kind[o.node_lo:o.node_hi]

    def residuals(self, theta: np.ndarray) -> np.ndarray:
        """Stacked residuals: update errors (every component of e_i for every measurement
        node) or, for ``metric="whitened"``, whitened innovations."""
        outs = self.run(theta)
        if self.metric == "whitened":
            parts = [self._whitened_saturated(w, o) for w, o in zip(self.windows, outs)]
        else:
            parts = [o.e[self._kinds(w, o) != MOTOR].ravel() for w, o in zip(self.windows, outs)]
        return np.concatenate(parts) if parts else np.zeros(0)

    def _whitened_saturated(self, w: Window, o: WindowOut) -> np.ndarray:
        kinds = self._kinds(w, o)
        sel = kinds != MOTOR
        v = np.nan_to_num(o.nu_w[sel])
        rej = o.status[sel] == REJECTED
        if rej.any():
            cfg = w.hist.config
            gate = np.where(kinds[sel][rej] == USBL, cfg.gate_usbl, cfg.gate_gnss)
            m2 = np.sum(v[rej] ** 2, axis=1)
            v[rej] *= ((gate / m2) ** 0.25)[:, None]
        return v.ravel()

    def scalar(self, theta: np.ndarray) -> float:
        """The window's error sum: E (Eq. 14) or, for ``metric="innovation"``, the public
        code's sum of innovation norms over the absolute fixes."""
        outs = self.run(theta)
        if self.metric == "update":
            return float(sum(o.error() for o in outs))
        if self.metric == "whitened":
            return float(sum(np.sum(self._whitened_saturated(w, o) ** 2)
                             for w, o in zip(self.windows, outs)))
        tot = 0.0
        for w, o in zip(self.windows, outs):
            kinds = self._kinds(w, o)
            sel = np.isin(kinds, FIX_KINDS)
            norm = np.sqrt(np.nansum(o.nu[sel] ** 2, axis=1))
            rej = o.status[sel] == REJECTED
            if rej.any():   # as for the other metrics: scaled to the gate boundary
                cfg = w.hist.config
                gate = np.where(kinds[sel][rej] == USBL, cfg.gate_usbl, cfg.gate_gnss)
                m2 = np.nansum(o.nu_w[sel][rej] ** 2, axis=1)
                norm[rej] *= (gate / m2) ** 0.25
            tot += float(np.sum(norm))
        return tot

    def whitened(self, theta: np.ndarray) -> np.ndarray:
        """Whitened innovations of every accepted measurement node (for :func:`gn_sigma`)."""
        outs = self.run(theta)
        parts = []
        for w, o in zip(self.windows, outs):
            sel = (self._kinds(w, o) != MOTOR) & (o.status == ACCEPTED)
            v = o.nu_w[sel]
            parts.append(v[np.isfinite(v)])
        return np.concatenate(parts) if parts else np.zeros(0)


def bounds(preset: str, entries: list[Entry], model, current: np.ndarray,
           user: dict[str, tuple[float, float]] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bounds of ``theta`` for a preset (``current``: values before the
    optimisation, for the paper's relative drag bounds); ``user`` overrides per name."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    lo = np.empty(len(entries))
    hi = np.empty(len(entries))
    for i, e in enumerate(entries):
        s = model.spec(e.name)
        lo[i], hi[i] = s.lower, s.upper
        if preset == "paper":
            c = float(current[i])
            if e.name == "theta_e":
                lo[i], hi[i] = -np.radians(190.0), np.radians(190.0)
            elif e.name == "k":
                lo[i], hi[i] = 2.0, 14.0
            elif e.name == "k_x":
                lo[i], hi[i] = max(0.4 * c, 0.1), min(1.9 * c, 5.0)
            elif e.name == "k_yz":
                lo[i], hi[i] = max(0.4 * c, 0.0), min(1.9 * c, 2.5)
            elif e.name in ("s_x", "s_y"):
                lo[i], hi[i] = -2.0, 2.0
        if user and e.name in user:
            lo[i], hi[i] = user[e.name]
        if not lo[i] < hi[i]:
            raise ValueError(f"empty bounds [{lo[i]}, {hi[i]}] for parameter {e.name!r}")
    return lo, hi


@dataclass
class Solution:
    theta: np.ndarray
    E: float                 # the objective value at theta (Eq. 14 or the scalar metric)
    evaluations: int         # error evaluations in this optimisation (Jacobian ones included)
    seconds: float           # wall time of the optimisation
    status: int              # scipy's status
    message: str


def minimise(obj: Objective, theta0: np.ndarray, lo: np.ndarray, hi: np.ndarray,
             preset: str = "physical", scales: np.ndarray | None = None,
             max_nfev: int | None = None) -> Solution:
    """Solve Eq. 15 from ``theta0`` (clipped into the bounds) with a preset (module doc)."""
    x0 = np.clip(np.asarray(theta0, float), lo, hi)
    # a start on a bound is fine for trf, but strictly inside avoids a zero first step
    span = hi - lo
    eps = np.where(np.isfinite(span), 1e-9 * span, 1e-9)
    x0 = np.minimum(np.maximum(x0, lo + eps), hi - eps)
    n0 = obj.counter.n
    t0 = time.perf_counter()
    if preset == "paper":
        res = least_squares(lambda th: np.array([obj.scalar(th)]), x0, jac="2-point",
                            bounds=(lo, hi), method="trf", x_scale="jac",
                            ftol=1e-6, gtol=1e-10, xtol=1e-8, max_nfev=max_nfev or 200)
        E = float(res.fun[0])
    elif preset == "physical":
        if obj.metric == "innovation":
            raise ValueError("metric='innovation' (a sum of norms) needs preset='paper'")
        res = least_squares(obj.residuals, x0, jac="2-point", bounds=(lo, hi), method="trf",
                            x_scale=scales if scales is not None else 1.0,
                            ftol=1e-8, xtol=1e-8, gtol=1e-10, max_nfev=max_nfev or 100)
        E = float(np.sum(res.fun ** 2))
    else:
        raise ValueError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    return Solution(res.x, E, obj.counter.n - n0, time.perf_counter() - t0, int(res.status),
                    str(res.message))


def gn_sigma(obj: Objective, theta: np.ndarray, scales: np.ndarray,
             lo: np.ndarray | None = None, hi: np.ndarray | None = None) -> np.ndarray:
    """1-sigma of ``theta`` from the Gauss-Newton approximation on the whitened innovations
    (module doc); forward differences with steps ``1e-4 * scales`` (backward at an upper
    bound). NaN where the information is singular."""
    r0 = obj.whitened(theta)
    J = np.zeros((len(r0), len(theta)))
    for i in range(len(theta)):
        h = 1e-4 * scales[i]
        if hi is not None and theta[i] + h > hi[i]:
            h = -h
        th = theta.copy()
        th[i] += h
        r = obj.whitened(th)
        if len(r) != len(r0):      # a gate flipped: the innovation set changed
            return np.full(len(theta), np.nan)
        J[:, i] = (r - r0) / h
    try:
        C = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return np.full(len(theta), np.nan)
    d = np.diag(C)
    return np.where(d > 0, np.sqrt(np.abs(d)), np.nan)
