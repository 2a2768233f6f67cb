"""Minimising the update error over a window (paper Eqs. 14-15, §III-C), with optimiser presets.

:class:`Objective` evaluates ``E(P) = sum_i ||e_i||^2`` (Eq. 14) over one or several windows
(one per mission) for a vector ``theta`` of the estimated parameters, counting and timing
every evaluation. :func:`minimise` solves Eq. 15 under the bounds of one of two presets,
with one of three optimisers ("trf", "ceres", "gradient"):

``"physical"`` (default)
    Bounds only physical (thrust and drag constants positive, ``theta_e`` within +-190 deg,
    current within +-2 m/s; effect parameters per :mod:`aqfg.model.params`). Batch fits use
    "trf": :func:`scipy.optimize.least_squares` (trust-region reflective) on the *stacked*
    vector of update errors (every component of every ``e_i``), forward-difference
    Jacobian, ``x_scale`` from the parameter table; using the residual structure
    (Gauss-Newton) converges in a few iterations where a scalar objective needs many.
    Online windows use "gradient", the paper's gradient descent (§V-F, at most 50 error
    evaluations, :func:`gradient_descent`): a short window often leaves a direction almost
    undetermined (heading offset against current on a straight leg), and a Gauss-Newton
    solver jumps along it to wherever the noise puts the minimum, where gradient descent
    from the previous estimate hardly moves (docs/update-error.md).

``"paper"``
    Optimiser "ceres", which behaves like the authors' public C++ (github
    aqurai/auv-state-estimation, read for facts):
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
    shortened: many more evaluations than "physical" for similar estimates (measured in
    docs/update-error.md).

Metrics. ``metric="update"`` (default) is the paper's Eq. 14, the squared Kalman update
errors of every measurement node. The public code's cost is the sum of innovation *norms*
``||z - h||`` of the absolute fixes only (``metric="innovation"``, "paper" preset only). Not
in the paper: ``metric="whitened"`` minimises the squared innovations whitened by their
covariance ``S`` (the prediction-error / maximum-likelihood cost the paper names as future
work). A gated node
counts in every metric at the gate boundary: scaled by ``sqrt(gate / m2)`` (``m2``: its
squared Mahalanobis distance), so its contribution is continuous at the gate and constant
beyond it (a truncated quadratic): pushing a fix out of the gate never pays, and a gross
outlier pulls no harder than a fix at the gate. Evaluation counts include those of the
finite differences.
The code also resets the heading offset to 0 before each optimisation, and its EKF clamps
the relative speed to 2 m/s and damps the velocity; none of that is reproduced.

Parameter uncertainty and observability: :mod:`aqfg.ekf.uncertainty`.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from aqfg.ekf.history import FIX_KINDS, MOTOR, USBL, History
from aqfg.ekf.window import REJECTED, WindowOut, run_window

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


@dataclass
class NodeTerms:
    """One evaluation's per-node terms (measurement nodes only): ``rows`` (n, d) the
    metric's residuals (update errors ``e_i``, d = 9, or saturated whitened innovations,
    d = 3), ``nu_w`` (n, 3) whitened innovations (0-padded), ``status`` (n,), ``tm`` (n,) s
    since the mission start, ``kind`` (n,), ``window`` (n,) index of the window."""
    rows: np.ndarray
    nu_w: np.ndarray
    status: np.ndarray
    tm: np.ndarray
    kind: np.ndarray
    window: np.ndarray


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
            v[rej] *= np.sqrt(gate / m2)[:, None]
        return v.ravel()

    def node_terms(self, theta: np.ndarray) -> NodeTerms:
        """Per measurement node (motor nodes left out, windows stacked): the metric's
        residual rows, whitened innovations, status, times and kinds (for
        :mod:`aqfg.ekf.uncertainty`)."""
        outs = self.run(theta)
        rows, nuw, status, tm, kind, win = [], [], [], [], [], []
        for wi, (w, o) in enumerate(zip(self.windows, outs)):
            kinds = self._kinds(w, o)
            sel = kinds != MOTOR
            if self.metric == "whitened":
                rows.append(self._whitened_saturated(w, o).reshape(-1, 3))
            else:
                rows.append(o.e[sel])
            nuw.append(np.nan_to_num(o.nu_w[sel]))
            status.append(o.status[sel])
            tm.append(w.hist.node_tm[o.node_lo:o.node_hi][sel])
            kind.append(kinds[sel])
            win.append(np.full(int(sel.sum()), wi))
        def cat(a: list[np.ndarray], shape: int | tuple[int, ...]) -> np.ndarray:
            return np.concatenate(a) if a else np.zeros(shape)
        return NodeTerms(cat(rows, (0, 9)), cat(nuw, (0, 3)), cat(status, 0).astype(np.int8),
                         cat(tm, 0), cat(kind, 0).astype(np.int32), cat(win, 0).astype(int))

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
                norm[rej] *= np.sqrt(gate / m2)
            tot += float(np.sum(norm))
        return tot


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
    status: int              # scipy's status (gradient: 1 converged, 0 budget spent)
    message: str
    optimiser: str = "trf"
    converged: bool = True   # stopped by a tolerance, not by the evaluation budget


OPTIMISERS = ("trf", "ceres", "gradient")
GRADIENT_BUDGET = 50         # error evaluations per optimisation: the paper's 30-50 (§V-F)


def default_optimiser(preset: str, mode: str) -> str:
    """Online windows use the paper's gradient descent; batch fits use "trf" ("physical")
    or the public code's Ceres-like solver ("paper")."""
    if preset == "paper":
        return "ceres"
    return "gradient" if mode == "online" else "trf"


def minimise(obj: Objective, theta0: np.ndarray, lo: np.ndarray, hi: np.ndarray,
             preset: str = "physical", scales: np.ndarray | None = None,
             max_nfev: int | None = None, optimiser: str | None = None) -> Solution:
    """Solve Eq. 15 from ``theta0`` (clipped into the bounds). ``optimiser`` (default by
    ``preset``: "trf" for "physical", "ceres" for "paper"):

    * "trf": trust-region reflective Gauss-Newton on the stacked residuals (module doc);
    * "ceres": the public code's one scalar residual (module doc, preset "paper");
    * "gradient": the paper's gradient descent (§V-F), see :func:`gradient_descent`.
    """
    if optimiser is None:
        optimiser = default_optimiser(preset, "batch")
    if optimiser not in OPTIMISERS:
        raise ValueError(f"unknown optimiser {optimiser!r}; choose one of {', '.join(OPTIMISERS)}")
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    x0 = np.clip(np.asarray(theta0, float), lo, hi)
    # a start on a bound is fine for trf, but strictly inside avoids a zero first step
    span = hi - lo
    eps = np.where(np.isfinite(span), 1e-9 * span, 1e-9)
    x0 = np.minimum(np.maximum(x0, lo + eps), hi - eps)
    sc = np.asarray(scales, float) if scales is not None else np.ones(len(x0))
    n0 = obj.counter.n
    t0 = time.perf_counter()
    if optimiser == "gradient":
        x, E, status, msg = gradient_descent(obj.scalar, x0, lo, hi, sc,
                                             max_nfev or GRADIENT_BUDGET)
        return Solution(x, E, obj.counter.n - n0, time.perf_counter() - t0, status, msg,
                        optimiser, status > 0)
    if optimiser == "ceres":
        res = least_squares(lambda th: np.array([obj.scalar(th)]), x0, jac="2-point",
                            bounds=(lo, hi), method="trf", x_scale="jac",
                            ftol=1e-6, gtol=1e-10, xtol=1e-8, max_nfev=max_nfev or 200)
        E = float(res.fun[0])
    else:
        if obj.metric == "innovation":
            raise ValueError("metric='innovation' (a sum of norms) needs preset='paper'")
        res = least_squares(obj.residuals, x0, jac="2-point", bounds=(lo, hi), method="trf",
                            x_scale=sc, ftol=1e-8, xtol=1e-8, gtol=1e-10,
                            max_nfev=max_nfev or 100)
        E = float(np.sum(res.fun ** 2))
    return Solution(res.x, E, obj.counter.n - n0, time.perf_counter() - t0, int(res.status),
                    str(res.message), optimiser, int(res.status) > 0)


def gradient_descent(f, x0: np.ndarray, lo: np.ndarray, hi: np.ndarray, scales: np.ndarray,
                     budget: int = GRADIENT_BUDGET, ftol: float = 1e-6
                     ) -> tuple[np.ndarray, float, int, str]:
    """Steepest descent on ``f`` (the paper's optimiser, §V-F) within bounds.

    In units of each parameter's scale: forward-difference gradient (step 1e-4), trial steps
    along ``-g`` of at most one scale unit (the first exactly one, later ones twice the last
    accepted), Armijo backtracking (halving, c = 1e-4), iterates clipped into the
    bounds. Stops when a step lowers ``f`` by less than ``ftol`` relative (status 1), no
    descent step is found (status 2), or after ``budget`` evaluations of ``f`` (status 0).

    Along a direction in which ``f`` hardly changes (a heading offset traded for a current
    on a straight leg) the gradient is tiny, so the estimate stays near its start instead
    of being carried by the noise to wherever the flat valley's minimum happens to lie.
    Returns ``(x, f(x), status, message)``."""
    p = len(x0)

    def fs(y: np.ndarray) -> float:
        return f(np.clip(y * scales, lo, hi))

    y = np.asarray(x0, float) / scales
    fy = fs(y)
    n = 1
    alpha = None
    h = 1e-4
    while True:
        if n + p > budget:
            return np.clip(y * scales, lo, hi), fy, 0, "evaluation budget spent"
        g = np.array([(fs(y + h * np.eye(p)[i]) - fy) / h for i in range(p)])
        n += p
        gn = float(np.linalg.norm(g))
        if not gn > 0:
            return np.clip(y * scales, lo, hi), fy, 1, "zero gradient"
        a = 1.0 / gn if alpha is None else min(alpha, 1.0 / gn)
        while True:
            if n >= budget:
                return np.clip(y * scales, lo, hi), fy, 0, "evaluation budget spent"
            yn = np.clip(y - a * g, lo / scales, hi / scales)
            fn = fs(yn)
            n += 1
            if fn <= fy - 1e-4 * float(g @ (y - yn)) and fn < fy:
                break
            a *= 0.5
            if a * gn < 1e-6:
                return np.clip(y * scales, lo, hi), fy, 2, "no descent step"
        dec = fy - fn
        y, fy = yn, fn
        alpha = 2.0 * a
        if dec <= ftol * max(abs(fy), 1e-300):
            return np.clip(y * scales, lo, hi), fy, 1, "relative decrease below ftol"
