"""The kinematic floor of the online causal track: a constant-velocity Kalman filter on the
fixes alone.

Online without a given heading offset, the fixed-lag smoother holds the parameters at
their start values until a batch of the fixes so far has estimated them
(:class:`aqfg.fg.fixed_lag.FixedLagSmoother`). Until then the model's prediction rests on a
heading offset no data has chosen (a start value, or a closed form of three or four
fixes), and on a model of another vehicle where the constants are the defaults: between
fixes it ran the causal track 5-15 m off where a filter that knows no model stays within
2-3 m (docs/independent-vehicle.md). While the parameters are held the causal track
therefore follows this filter, unless the model predicted the last fixes better (the
median of the last three paired differences of their squared misses: a vehicle
accelerating from rest outruns a constant-velocity prediction from 8-s fixes), and the
model from the fix at which they are first released. The smoother itself, and every
estimate, are untouched.

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

import numpy as np

_H = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]])


def transition(dt: float, q: float) -> tuple[np.ndarray, np.ndarray]:
    """State transition ``F`` (4x4) and process noise ``Q`` (4x4) over ``dt`` s of the
    constant-velocity model with white acceleration of PSD ``q`` (m^2/s^3) per axis
    (exact for the double integrator)."""
    F = np.eye(4)
    F[0, 2] = F[1, 3] = dt
    b = q * np.array([[dt ** 3 / 3.0, dt ** 2 / 2.0], [dt ** 2 / 2.0, dt]])
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
        S = _H @ self.P @ _H.T + var * np.eye(2)
        nu = pos - self.x[:2]
        if float(nu @ np.linalg.solve(S, nu)) > self.gate and self.rejects < self.max_rejects:
            self.rejects += 1
            return False
        self.rejects = 0
        K = self.P @ _H.T @ np.linalg.inv(S)
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


@dataclass
class CausalFloor:
    """The kinematic floor of an online causal track (see the module docstring): the
    filter's state recorded after each fix while the parameters are held, whether the track
    follows it there, and the fix time from which it follows the model (``until``; inf
    while held, the first fix where there is no hold)."""
    filt: KinematicFilter
    until: float = math.inf
    t: list[float] = field(default_factory=list)          # fix times while held
    x: list[np.ndarray] = field(default_factory=list)     # the filter's state right after
    use: list[bool] = field(default_factory=list)         # the track follows the filter
    diff: list[float] = field(default_factory=list)       # model's minus filter's miss (m^2)
    next_row: int = 0                                     # next row of the fix table

    def step(self, t_fix: float, fixes: tuple, model_pred: np.ndarray | None,
             held: bool) -> bool:
        """The update at the fix ``t_fix``: the filter takes the fixes of the table
        ``fixes`` (times, horizontal positions, per-axis variances, ...; time order) up to
        it, after scoring both predictors on its first fix there (``model_pred``: the
        model's state predicted there before the update; None at the first knot). ``held``:
        the parameters are still held after this update; if not, the track follows the
        model from here, and True is returned (once)."""
        if t_fix >= self.until:
            return False
        t, pos, var = fixes[0], fixes[1], fixes[2]
        i = self.next_row
        if (model_pred is not None and self.filt.started and i < len(t)
                and abs(float(t[i]) - t_fix) <= 1e-6):
            e_kin = float(np.sum((pos[i, :2] - self.filt.at(t_fix)[:2]) ** 2))
            e_mod = float(np.sum((pos[i, :2] - np.asarray(model_pred)[:2]) ** 2))
            self.diff.append(e_mod - e_kin)
        while i < len(t) and t[i] <= t_fix + 1e-9:
            self.filt.update(float(t[i]), pos[i], float(var[i]))
            i += 1
        self.next_row = i
        if held:
            self.t.append(float(t_fix))
            self.x.append(self.filt.at(t_fix))
            # the filter's unless the model predicted the last fixes better (the median of
            # the last three paired differences: one outlying fix does not decide)
            recent = self.diff[-3:]
            self.use.append(not recent or float(np.median(recent)) >= 0.0)
            return False
        self.until = float(t_fix)
        return bool(self.t)

    def apply(self, knots: np.ndarray, X: np.ndarray) -> None:
        """Knot states ``X`` (n, 6: NED position, velocity) of the causal track at ``knots``
        (n,) s, in place: before ``until``, horizontally the filter's after the fixes at
        which the track follows it (each knot from the last fix at or before it)."""
        held = np.asarray(knots) < self.until - 1e-9
        if not self.t or not held.any():
            return
        kt = np.array(self.t)
        j = np.clip(np.searchsorted(kt, np.asarray(knots) + 1e-9) - 1, 0, len(kt) - 1)
        use = held & np.array(self.use)[j]
        K = track_from(kt, np.array(self.x), np.asarray(knots)[use])
        X[use, 0:2], X[use, 3:5] = K[:, :2], K[:, 2:]
