"""Multi-step predictions of the fixes from the smoothed states: the residuals that the
dead-reckoning refinements (:mod:`aqfg.fg.dead_reckoning`, :mod:`aqfg.fg.dr_current`)
minimise, and their exact Jacobian.

A segment starts at a fix at the smoothed state (NED position and velocity, m, m/s) and
rolls the model forward without corrections to every fix within ``horizon`` s; starts are
at least ``horizon / STRIDE_DIV`` s apart. Each horizontal error (m) is divided by its lead
time (leads under ``MIN_LEAD`` s count as that): the mean velocity error since the start,
m/s.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from aqfg.data.mission import Mission
from aqfg.model.reference import Steps
from aqfg.model.retrace import fixes
from aqfg.model.vehicle import Model
from aqfg.result import Result
from aqfg.threads import both

STRIDE_DIV = 4.0      # starts at least horizon / STRIDE_DIV s apart
MIN_LEAD = 1.0        # s, the shortest lead time a residual is divided by
HUBER_C = 1.5         # the refinements' Huber threshold, in robust scales of the residuals


@dataclass
class Segment:
    """One prediction: from the smoothed state at ``t0`` to the fixes in its horizon."""
    mission: int
    t0: float
    x0: np.ndarray          # smoothed [pos, vel] at t0
    steps: Steps
    offsets: np.ndarray
    rows: np.ndarray        # knot index of each target fix
    z: np.ndarray           # (n, 2) target fix positions (north, east), m
    lead: np.ndarray        # (n,) s from t0 to each target fix


def segments(model: Model, missions: list[Mission], result: Result, horizon: float
              ) -> list[Segment]:
    """Starts at fixes at least ``horizon / 4`` s apart, each predicting the fixes within
    ``horizon`` s after it."""
    stride = horizon / STRIDE_DIV
    out: list[Segment] = []
    for i, (m, mr) in enumerate(zip(missions, result.missions)):
        tf, pf = fixes(m, mr.p)
        if len(tf) < 3:
            continue
        tr = mr.track
        # the kernel steps between all fixes at once, sliced per segment (a segment's knots
        # are consecutive fixes; building them per segment took 40 % of the refinement);
        # with a lookback (warm-up steps) each segment builds its own
        u = np.unique(tf)
        whole = model.steps(m, u) if model.lookback <= 0 else None
        last = -np.inf
        for t0 in tf:
            if t0 - last < stride or t0 < tr.t[0] or t0 > tr.t[-1]:
                continue
            js = np.nonzero((tf > t0 + 1e-6) & (tf <= t0 + horizon))[0]
            if len(js) < 2:
                continue
            last = t0
            x0 = np.array([np.interp(t0, tr.t, tr.pos[:, c]) for c in range(3)]
                          + [np.interp(t0, tr.t, tr.vel[:, c]) for c in range(3)])
            knots = np.concatenate([[t0], np.unique(tf[js])])
            if whole is not None:
                a = int(np.searchsorted(u, t0 - 1e-9))
                b = a + len(knots) - 1
                off_all = whole[1]
                steps = whole[0].slice(int(off_all[a]), int(off_all[b]))
                off = off_all[a:b + 1] - off_all[a]
            else:
                steps, off = model.steps(m, knots)
            rows = np.searchsorted(knots, tf[js] - 1e-9)
            out.append(Segment(i, float(t0), x0, steps, off, rows, pf[js, :2], tf[js] - t0))
    return out


class Predictions:
    """The prediction errors of every segment as functions of the fit's variables ``x``
    (the constants at ``idx`` of each mission's parameter vector, the ``logs`` ones by
    their logarithm); the states of the last ``x`` kept for its Jacobian."""

    def __init__(self, model: Model, segs: list[Segment], p_missions: list[np.ndarray],
                 idx: np.ndarray, logs: np.ndarray):
        self.model, self.segs, self.p_missions, self.idx, self.logs = \
            model, segs, p_missions, idx, logs
        self._last: tuple[np.ndarray, list] | None = None
        dyn = list(model.dyn_columns())
        self.cols = [dyn.index(i) for i in idx] if all(i in dyn for i in idx) else None
        self.analytic = (model.uses_cpp and model.lookback <= 0 and self.cols is not None
                         and bool(segs))
        # each error divided by its lead time (module docstring)
        self.per_lead = (np.concatenate([np.repeat(1.0 / np.maximum(s.lead, MIN_LEAD), 2)
                                         for s in segs]) if segs else np.zeros(0))

    def states(self, x: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each segment's parameter vector and predicted states at its knots."""
        if self._last is not None and np.array_equal(self._last[0], x):
            return self._last[1]
        v = to_v(x, self.logs)

        def roll(segs: list[Segment]) -> list[tuple[np.ndarray, np.ndarray]]:
            out = []
            for s in segs:
                p = self.p_missions[s.mission].copy()
                p[self.idx] = v
                out.append((p, self.model.rollout_segments(s.x0, p, s.steps, s.offsets)))
            return out
        h = len(self.segs) // 2           # two halves in two threads (the kernel's)
        a, b = both(lambda: roll(self.segs[:h]), lambda: roll(self.segs[h:]))
        self._last = (np.array(x, float), a + b)
        return a + b

    def errors(self, x: np.ndarray) -> np.ndarray:
        """Horizontal prediction errors at the target fixes, m (north, east per fix)."""
        return np.concatenate([(X[s.rows, :2] - s.z).ravel()
                               for s, (_, X) in zip(self.segs, self.states(x))])

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """The errors divided by their lead times, m/s."""
        r = self.errors(x) * self.per_lead
        return np.where(np.isfinite(r), r, 1e6)

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """The exact Jacobian of :meth:`residuals` (where :attr:`analytic`): each
        prediction's state sensitivity to the constants chained along its knot intervals,
        ``D_{k+1} = J_x,k D_k + J_p,k`` (the kernel's interval Jacobians at the predicted
        states; ``D_0 = 0``, the start is the smoothed state), times ``dv/dx``."""
        assert self.cols is not None
        segs, n_x = self.segs, len(self.idx)
        n_k = max(len(s.offsets) - 1 for s in segs)
        # every prediction's interval Jacobians, padded to n_k intervals (identity, zero)
        JX = np.tile(np.eye(6), (len(segs), n_k, 1, 1))
        JP = np.zeros((len(segs), n_k, 6, n_x))
        sts = self.states(x)

        def fill(js: range) -> None:
            for j in js:
                s, (p, X) = segs[j], sts[j]
                _, jx, jp = self.model.propagate_many(X[:-1], p, s.steps, s.offsets)
                JX[j, :len(jx)] = jx
                JP[j, :len(jp)] = jp[:, :, self.cols]
        h = len(segs) // 2
        both(lambda: fill(range(h)), lambda: fill(range(h, len(segs))))
        D = np.zeros((len(segs), n_k + 1, 6, n_x))
        for k in range(n_k):
            D[:, k + 1] = JX[:, k] @ D[:, k] + JP[:, k]
        rows = np.concatenate([np.repeat(s.rows, 2) for s in segs])
        seg_of = np.repeat(np.arange(len(segs)), [2 * len(s.rows) for s in segs])
        comp = np.concatenate([np.tile([0, 1], len(s.rows)) for s in segs])
        J = (D[seg_of, rows, comp] * np.where(self.logs, to_v(x, self.logs), 1.0)
             * self.per_lead[:, None])
        return np.where(np.isfinite(J), J, 0.0)



def robust_scale(r: np.ndarray) -> float:
    """The residuals' robust scale (m/s): 1.4826 x their median absolute value, at least
    1e-3 (the normal's sigma for normal residuals)."""
    return max(1.4826 * float(np.median(np.abs(r))), 1e-3)


def to_x(v: np.ndarray, logs: np.ndarray) -> np.ndarray:
    """Constants to the fit's variables (the ``logs`` ones by their logarithm)."""
    return np.where(logs, np.log(np.maximum(v, 1e-12)), v)


def to_v(x: np.ndarray, logs: np.ndarray) -> np.ndarray:
    return np.where(logs, np.exp(np.clip(x, -300.0, 300.0)), x)


def forward_jacobian(residuals: Callable[[np.ndarray], np.ndarray], x: np.ndarray,
                     r: np.ndarray) -> np.ndarray:
    """Forward-difference Jacobian of ``residuals`` at ``x`` (residuals ``r`` there)."""
    J = np.empty((len(r), len(x)))
    for c in range(len(x)):
        h = 1e-5 * max(1.0, abs(x[c]))
        e = np.zeros(len(x))
        e[c] = h
        J[:, c] = (residuals(x + e) - r) / h
    return J
