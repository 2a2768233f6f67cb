"""The kinematic floor of the online causal track: a constant-velocity Kalman filter on the
fixes alone.

Online without a given heading offset, the fixed-lag smoother holds the parameters at
their start values until a batch of the fixes so far has estimated them
(:class:`aqfg.fg.fixed_lag.FixedLagSmoother`). Until then the model's prediction rests on a
heading offset no data has chosen (a start value, or a closed form of three or four
fixes), and on a model of another vehicle where the constants are the defaults: between
fixes it ran the causal track 5-15 m off where a filter that knows no model stays within
2-3 m (docs/independent-vehicle.md). While the parameters are held the causal track
therefore follows this filter, and the model from the fix at which they are first
released. The smoother itself, and every estimate, are untouched.

State ``[north, east, v_north, v_east]`` (m, m/s, NED), white acceleration of power
spectral density ``q`` per horizontal axis (m^2/s^3); fixes are horizontal positions with
an isotropic per-axis variance (:func:`aqfg.fg.common.robust_fix_table`: a USBL fix its
tangential variance at its range). A fix whose innovation is beyond the chi-square(2)
quantile ``gate`` is left out, unless the ``max_rejects`` fixes before it were (a track
that is off must not refuse every fix).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from aqfg.model.process import white_acceleration

if TYPE_CHECKING:                       # common imports nothing from here; keep it so
    from aqfg.fg.settings import FGSettings

FLOOR_CHOICE_FIXES = 3      # fixes whose prediction errors choose the floor or the model
FLOOR_Z = 2.0               # the filter's advantage, in sigma of the fixes' noise, to choose it

_H = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]])


def transition(dt: float, q: float) -> tuple[np.ndarray, np.ndarray]:
    """State transition ``F`` (4x4) and process noise ``Q`` (4x4) over ``dt`` s of the
    constant-velocity model with white acceleration of PSD ``q`` (m^2/s^3) per axis
    (exact for the double integrator)."""
    F = np.eye(4)
    F[0, 2] = F[1, 3] = dt
    b = white_acceleration(q, dt)
    Q = np.zeros((4, 4))
    Q[np.ix_([0, 2], [0, 2])] = b
    Q[np.ix_([1, 3], [1, 3])] = b
    return F, Q


@dataclass
class KinematicFilter:
    """Constant-velocity filter on horizontal fixes (see the module docstring). Feed fixes
    in time order with :meth:`update`; :meth:`at` predicts the state at a later time."""
    q: float = 0.1                  # m^2/s^3, white-acceleration PSD per horizontal axis
    gate: float = 13.8              # chi-square(2) quantile (p = 0.999)
    max_rejects: int = 3
    vel_sigma: float = 1.0          # m/s, the first fix's velocity prior (per axis)
    t: float = float("nan")
    x: np.ndarray = field(default_factory=lambda: np.zeros(4))
    P: np.ndarray = field(default_factory=lambda: np.eye(4))
    rejects: int = 0

    @classmethod
    def from_settings(cls, s: FGSettings) -> KinematicFilter:
        """The filter of the settings' causal floor (``online.kinematic_q``, the USBL
        gate's quantile and rejects rule): the floor's and the baseline's are this one."""
        return cls(q=s.online.kinematic_q, gate=s.online.gate_usbl,
                   max_rejects=s.online.max_rejects)

    @property
    def started(self) -> bool:
        return bool(np.isfinite(self.t))

    def update(self, t: float, pos: np.ndarray, var: float) -> bool:
        """Take the fix at ``t`` s (horizontal NED position ``pos`` (2,) m, per-axis
        variance ``var`` m^2); returns False where the gate left it out."""
        pos = np.asarray(pos, float)[:2]
        if not self.started:
            self.t, self.x = float(t), np.array([pos[0], pos[1], 0.0, 0.0])
            self.P = np.diag([var, var, self.vel_sigma ** 2, self.vel_sigma ** 2])
            return True
        self.x, self.P = self._predict(t)
        self.t = float(t)
        Si = np.linalg.inv(_H @ self.P @ _H.T + var * np.eye(2))
        nu = pos - self.x[:2]
        if float(nu @ Si @ nu) > self.gate and self.rejects < self.max_rejects:
            self.rejects += 1
            return False
        self.rejects = 0
        K = self.P @ _H.T @ Si
        self.x = self.x + K @ nu
        # Joseph form: stays symmetric positive definite
        A = np.eye(4) - K @ _H
        self.P = A @ self.P @ A.T + var * (K @ K.T)
        return True

    def _predict(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        dt = max(float(t) - self.t, 0.0)
        if dt == 0.0:
            return self.x.copy(), self.P.copy()
        F, Q = transition(dt, self.q)
        return F @ self.x, F @ self.P @ F.T + Q

    def at(self, t: float) -> np.ndarray:
        """The predicted state ``[north, east, v_north, v_east]`` at ``t`` s (at or after the
        last fix)."""
        return self._predict(t)[0]


def track_from(log_t: np.ndarray, log_x: np.ndarray, t: np.ndarray) -> np.ndarray:
    """States (n, 4) at times ``t`` predicted causally from the filter states ``log_x``
    (m, 4) recorded right after the fixes at ``log_t`` (m,) s: each from the last record at
    or before it (constant velocity); times before the first record take the first."""
    j = np.clip(np.searchsorted(log_t, np.asarray(t, float) + 1e-9) - 1, 0, len(log_t) - 1)
    dt = np.maximum(np.asarray(t, float) - log_t[j], 0.0)
    out = log_x[j].copy()
    out[:, :2] += out[:, 2:] * dt[:, None]
    return out


def baseline_tracks(fixes: tuple, t: np.ndarray, kf: KinematicFilter
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The kinematic baseline a motion model has to beat: the constant-velocity filter
    ``kf`` (fresh; :meth:`KinematicFilter.from_settings` for the causal floor's) on the fix
    table ``fixes`` (times, horizontal positions (m, 2), per-axis variances, ...;
    :func:`aqfg.fg.common.robust_fix_table`), at the times ``t`` (n,) s.
    Returns its causal states (n, 4: each predicted from the fixes at or before it, as
    :func:`track_from`) and its smoothed ones (Rauch-Tung-Striebel over all the fixes).
    Times before the first fix take the first fix's state."""
    tf, pf, vf = np.asarray(fixes[0], float), np.asarray(fixes[1], float), fixes[2]
    t = np.asarray(t, float)
    # events in time order; at equal times the fixes first (the output sees them)
    ev = sorted([(float(x), 0, i) for i, x in enumerate(tf)]
                + [(float(x), 1, j) for j, x in enumerate(t)])
    if kf.started:
        raise ValueError("baseline_tracks: the filter must be fresh")
    # per filter node: time, predicted and updated state and covariance
    nt: list[float] = []
    xp: list[np.ndarray] = []
    Pp: list[np.ndarray] = []
    xu: list[np.ndarray] = []
    Pu: list[np.ndarray] = []
    out_node = np.full(len(t), -1)
    causal = np.zeros((len(t), 4))
    for tk, kind, i in ev:
        if not kf.started:
            if kind == 1:
                continue
            kf.update(tk, pf[i], float(vf[i]))
            a, A = kf.x.copy(), kf.P.copy()
        else:
            a, A = kf._predict(tk)
            if kind == 0:
                kf.update(tk, pf[i], float(vf[i]))
            else:
                kf.x, kf.P, kf.t = a.copy(), A.copy(), tk
        nt.append(tk)
        xp.append(a)
        Pp.append(A)
        xu.append(kf.x.copy())
        Pu.append(kf.P.copy())
        if kind == 1:
            out_node[i] = len(nt) - 1
            causal[i] = kf.x
    if not nt:
        raise ValueError("baseline_tracks: no fixes")
    xs = [np.zeros(4)] * len(nt)
    xs[-1] = xu[-1]
    for k in range(len(nt) - 2, -1, -1):
        F, _ = transition(nt[k + 1] - nt[k], kf.q)
        C = np.linalg.solve(Pp[k + 1], F @ Pu[k]).T       # Pu F^T Pp^-1 (symmetric Pp)
        xs[k] = xu[k] + C @ (xs[k + 1] - xp[k + 1])
    smooth = np.array([xs[n] if n >= 0 else xs[0] for n in out_node]).reshape(len(t), 4)
    causal[out_node < 0] = xu[0]
    return causal, smooth


def advantage_z(diff: np.ndarray, gap_sq: np.ndarray, var: np.ndarray) -> float:
    """How many standard deviations of the fixes' noise one predictor's advantage over
    another is: ``diff`` (m^2) its squared horizontal error minus the other's at each fix,
    ``gap_sq`` (m^2) the squared distance between the two predictions, ``var`` (m^2) the
    fix's per-axis variance. Each fix's log-likelihood ratio ``diff / (2 var)`` varies with
    the fix's noise only along the gap (standard deviation ``sqrt(gap_sq / var)``); their
    sum over the fixes, in units of its standard deviation (0 where the predictions
    coincide)."""
    diff, gap_sq, var = (np.asarray(a, float) for a in (diff, gap_sq, var))
    sd = math.sqrt(float(np.sum(gap_sq / var)))
    return float(np.sum(diff / (2.0 * var)) / sd) if sd > 0 else 0.0


@dataclass
class CausalFloor:
    """The kinematic floor of an online causal track (see the module docstring): the
    filter's state recorded after each fix while the parameters are held, and the fix time
    from which the track follows the model (``until``; inf while held, the first fix where
    there is no hold)."""
    filt: KinematicFilter
    until: float = math.inf
    t: list[float] = field(default_factory=list)          # fix times while held
    x: list[np.ndarray] = field(default_factory=list)     # the filter's state right after
    z: list[np.ndarray] = field(default_factory=list)     # the fix taken last at each
    v: list[float] = field(default_factory=list)          # and its per-axis variance
    next_row: int = 0                                     # next row of the fix table

    def step(self, t_fix: float, fixes: tuple, held: bool) -> bool:
        """The update at the fix ``t_fix``: the filter takes the fixes of the table
        ``fixes`` (times, horizontal positions, per-axis variances, ...; time order) up to
        it. ``held``: the parameters are still held after this update; if not, the track
        follows the model from here, and True is returned (once)."""
        if t_fix >= self.until:
            return False
        t, pos, var = fixes[0], fixes[1], fixes[2]
        i = self.next_row
        while i < len(t) and t[i] <= t_fix + 1e-9:
            self.filt.update(float(t[i]), pos[i], float(var[i]))
            i += 1
        self.next_row = i
        if held:
            self.t.append(float(t_fix))
            self.x.append(self.filt.at(t_fix))
            self.z.append(np.asarray(pos[i - 1], float)[:2] if i > 0 else
                          np.full(2, np.nan))
            self.v.append(float(var[i - 1]) if i > 0 else np.nan)
            return False
        self.until = float(t_fix)
        return bool(self.t)

    def chosen(self, predicted: tuple | None, last: int = FLOOR_CHOICE_FIXES) -> np.ndarray:
        """Per held fix, whether the floor (True) or the model (False) carries the causal
        track after it: the floor where its predictions of the ``last`` fixes up to it were
        closer than the model's beyond what the fixes' own noise explains (squared
        horizontal errors, each predicted from the fix before: the filter's at constant
        velocity, the model's ``predicted`` = (fix times, states (m, 6) predicted there
        before the update), weighed by the fixes' variances: :func:`advantage_z` above
        ``FLOOR_Z``). Errors the fixes cannot
        tell apart leave the model, which knows the thrust (a boat starting from rest
        left the floor 9 m behind 4 s later); so does the first fix, which no prediction
        has tested yet (a real ASV throttling up in its first 8-s gap: the floor 5 m
        behind, the model 0.5 m). Causal: a fix's choice uses fixes up to it. Every
        later fix without a model prediction in its last ``last`` takes the floor, and
        all do where there is no model prediction at all."""
        n = len(self.t)
        out = np.ones(n, bool)
        if predicted is None or n < 2:
            return out
        pt, px = np.asarray(predicted[0], float), np.asarray(predicted[1], float)
        if not len(pt):
            return out
        t, x, z, v = np.array(self.t), np.array(self.x), np.array(self.z), np.array(self.v)
        p_f = np.full((n, 2), np.nan)           # each fix predicted from the one before
        p_m = np.full((n, 2), np.nan)
        p_f[1:] = x[:-1, :2] + x[:-1, 2:] * np.diff(t)[:, None]
        j = np.clip(np.searchsorted(pt, t - 1e-6), 0, len(pt) - 1)
        ok = np.abs(pt[j] - t) < 1e-6
        p_m[ok] = px[j[ok], :2]
        out[0] = False                          # no evidence yet: the model
        e_f = np.sum((p_f - z) ** 2, axis=1)
        e_m = np.sum((p_m - z) ** 2, axis=1)
        gap = np.sum((p_m - p_f) ** 2, axis=1)
        for k in range(1, n):
            sl = slice(max(1, k - last + 1), k + 1)
            a, b, w, g = e_f[sl], e_m[sl], v[sl], gap[sl]
            good = np.isfinite(a) & np.isfinite(b) & np.isfinite(w)
            out[k] = not good.any() or advantage_z(b[good] - a[good], g[good], w[good]) > FLOOR_Z
        return out

    def apply(self, knots: np.ndarray, X: np.ndarray, predicted: tuple | None = None) -> None:
        """Knot states ``X`` (n, 6: NED position, velocity) of the causal track at ``knots``
        (n,) s, in place: before ``until``, horizontally the filter's (each knot from the
        last fix at or before it), after the held fixes at which the filter predicted the
        fixes better than the model (:meth:`chosen`; ``predicted`` None: after every one)."""
        knots = np.asarray(knots, float)
        use = knots < self.until - 1e-9
        if not self.t or not use.any():
            return
        rec = np.clip(np.searchsorted(np.array(self.t), knots + 1e-9) - 1, 0, len(self.t) - 1)
        use &= self.chosen(predicted)[rec]
        if not use.any():
            return
        K = track_from(np.array(self.t), np.array(self.x), knots[use])
        X[use, 0:2], X[use, 3:5] = K[:, :2], K[:, 2:]
