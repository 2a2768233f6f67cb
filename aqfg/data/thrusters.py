"""Thruster sign check: does each thruster's command push the vehicle the way its axis says?

A thruster mounted or wired reversed (or a ``reversed`` flag missing from an import map)
makes the motion model push the vehicle backwards; the fits then absorb it into wrong
parameters. The check needs no fit. The GNSS fixes are thinned to one per correlation time
of the thrust demands (:func:`correlation_time`); over each interval between them the mean
velocity, rotated into the body frame with the logged heading, and the mean thrust demand
``d_i = u_i|u_i|`` of each thruster are formed, and between consecutive intervals the
acceleration. The logged heading may be off by an unknown angle (an IMU's yaw is not
referenced to north: theta_e), so the body frame is then turned to put the mission's mean
velocity while driven forward (each interval weighted by its time and the size of its summed
demand, whatever its sign: a slow boat drifts astern in the wind between legs, and a frame
set by time alone turned such a log 180 deg): the vehicle is taken to travel forward on the
whole when its thrusters push it (where that turns it more than 90 deg from the logged
heading, a finding must hold in both frames: :func:`thruster_findings`). For each thruster
``i`` with a horizontal axis ``a_i`` two partial correlations are taken, the other
thrusters' demands held (linear least squares):

- ``d_i`` with the speed along ``a_i`` (the speed follows the thrust);
- ``d_i`` with the acceleration along ``a_i``, the drag ``v|v|`` along ``a_i`` held too
  (the thrust causes the acceleration; a speed controller raising the thrust when the
  vehicle is slow makes the speed alone correlate negatively, not the acceleration);

and for all thrusters together the summed demand along body x with the surge speed and
acceleration. Each correlation gives a one-sided probability of so negative a value by
chance (Student's t on the effective number of samples of two autocorrelated series,
Bretherton et al. 1999, J. Climate 12, eq. 31: ``1/n_eff = 1/n + (2/n) sum_k (1 - k/n)
rho_x(k) rho_y(k)``, lags up to n/5); the two are combined by Stouffer's method (their
normal scores summed over sqrt 2). A combined probability below :data:`ALPHA`, shared
(Bonferroni) among the tests of one mission, is a finding where each of the two is also
below :data:`AGREE` on its own: a reversed thruster pushes against both the speed and the
acceleration, while a controller holding the vehicle against the wind, raising the thrust
as the vehicle is pushed back, can make the acceleration alone correlate negatively. Pure
functions of a :class:`~aqfg.data.mission.Mission`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aqfg import distributions as dist
from aqfg.data.mission import Mission

ALPHA = 1e-3               # false-alarm probability of one mission's check (all tests)
AGREE = 0.05               # each of the two correlations must be this negative on its own


@dataclass(frozen=True)
class ThrusterFinding:
    """A command correlating negatively with the motion it should cause.

    ``thruster``: 0-based index, or None for all thrusters together (surge); ``r``: the
    partial correlation of the demand with the speed, ``r_acc`` with the acceleration;
    ``n``: intervals between fixes used; ``n_eff``: their effective number (speed);
    ``p``: one-sided combined probability of correlations this negative by chance."""
    thruster: int | None
    axis: tuple[float, float, float]
    r: float
    r_acc: float
    n: int
    n_eff: float
    p: float

    def message(self) -> str:
        stat = (f"r = {self.r:.2f} with the speed, {self.r_acc:.2f} with the acceleration, over "
                f"{self.n} intervals between fixes, {self.n_eff:.0f} effective; p = {self.p:.1g}")
        if self.thruster is None:
            return ("the summed thrust demand (u|u| along each thruster's axis) correlates "
                    "negatively with the forward motion from the fixes and the heading "
                    f"({stat}): are the thrusters reversed (all of them, or one whose own "
                    "tests lack the contrast to show it)? See [motors] reversed in the "
                    "import map")
        i = self.thruster + 1
        ax = ", ".join(f"{x:g}" for x in self.axis)
        return (f"thruster {i} (u{i}, axis [{ax}]) pushes against the motion it should cause: "
                f"its demand u{i}|u{i}| correlates negatively with the motion along its axis "
                f"from the fixes and the heading ({stat}). Mounted or wired reversed? Set "
                f"[motors] reversed for thruster {i} in the import map (or negate u{i})")


def effective_n(x: np.ndarray, y: np.ndarray) -> float:
    """Effective number of independent pairs of two autocorrelated series (module doc)."""
    n = len(x)
    xc, yc = x - x.mean(), y - y.mean()
    vx, vy = float(np.dot(xc, xc)), float(np.dot(yc, yc))
    if n < 3 or vx <= 0 or vy <= 0:
        return float(n)
    k = np.arange(1, max(n // 5, 1) + 1)
    s = float(np.sum((1.0 - k / n) * _acf(xc)[k] * _acf(yc)[k]))
    inv = 1.0 / n + 2.0 * s / n
    return float(min(n, 1.0 / inv)) if inv > 0 else float(n)


def _acf(xc: np.ndarray) -> np.ndarray:
    """Autocorrelation of a centred series at lags 0 .. n - 1 (biased estimate)."""
    f = np.fft.rfft(xc, 2 * len(xc))
    a = np.fft.irfft(f * np.conj(f))[:len(xc)]
    return a / a[0]


def negative_correlation(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float]:
    """``(r, n_eff, p)``: Pearson r of x and y and the one-sided probability of an r this
    negative by chance (Student's t with ``n_eff - 2`` degrees of freedom); p = 1 when the
    series are too short or constant."""
    if len(x) < 4 or np.ptp(x) == 0 or np.ptp(y) == 0:
        return 0.0, float(len(x)), 1.0
    r = float(np.corrcoef(x, y)[0, 1])
    n_eff = effective_n(x, y)
    if n_eff <= 3 or not np.isfinite(r):
        return r, n_eff, 1.0
    t = r * np.sqrt((n_eff - 2.0) / max(1.0 - r * r, 1e-12))
    return r, n_eff, float(dist.t_cdf(t, n_eff - 2.0))


def _yaw(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q.T
    return np.unwrap(np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)))


def _mean_demand(m: Mission, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n, N) mean of u|u| over [a, b] with each command held until the next row."""
    ts, u = m.motors.t, m.motors.u
    d = u * np.abs(u)
    cum = np.vstack([np.zeros((1, d.shape[1])), np.cumsum(d[:-1] * np.diff(ts)[:, None], 0)])

    def integral(t: np.ndarray) -> np.ndarray:
        k = np.clip(np.searchsorted(ts, t, side="right") - 1, 0, len(ts) - 1)
        return cum[k] + d[k] * (t - ts[k])[:, None]
    return (integral(b) - integral(a)) / (b - a)[:, None]


def correlation_time(m: Mission) -> float:
    """Seconds over which the thrust demands change: the shortest lag at which one
    thruster's demand autocorrelation falls below 1/e (the logged command interval when
    the demands are constant)."""
    t, u = m.motors.t, m.motors.u
    step = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    best = np.inf
    for d in (u * np.abs(u)).T:
        dc = d - d.mean()
        if len(dc) < 4 or not np.any(dc):
            continue
        below = np.flatnonzero(_acf(dc)[:len(dc) // 2] < np.exp(-1.0))
        if len(below):
            best = min(best, float(below[0]) * step)
    return float(best) if np.isfinite(best) else step


def body_motion(m: Mission, window: float = 0.0) -> tuple[np.ndarray, ...]:
    """``(a, b, v, acc)``: consecutive intervals [a, b] between GNSS fixes inside the inputs,
    each at least ``window`` s long (a fix ends an interval once that long), the mean
    horizontal velocity over each (n, 2) and the acceleration from each interval's middle
    to the next one's (n - 1, 2), body x (forward), y (starboard), rotated with the logged
    heading at the interval's middle (the acceleration: at the middle between them)."""
    g = m.gnss
    empty = np.zeros((0, 2))
    if g is None or len(g.t) < 2:
        return np.zeros(0), np.zeros(0), empty, empty
    inside = (g.t >= m.t0) & (g.t <= m.t1)
    t, ne = g.t[inside], g.ne[inside]
    keep, last = [], -np.inf
    for i, ti in enumerate(t):
        if ti > last and ti >= last + window:
            keep.append(i)
            last = ti
    t, ne = t[keep], ne[keep]
    a, b = t[:-1], t[1:]
    mid = 0.5 * (a + b)
    v = np.diff(ne, axis=0) / (b - a)[:, None]
    acc = np.diff(v, axis=0) / np.diff(mid)[:, None] if len(v) > 1 else empty
    yaw = _yaw(m.imu.q)
    return a, b, _to_body(v, np.interp(mid, m.imu.t, yaw)), \
        _to_body(acc, np.interp(0.5 * (mid[1:] + mid[:-1]), m.imu.t, yaw))


def _to_body(v: np.ndarray, psi: np.ndarray) -> np.ndarray:
    c, s = np.cos(psi), np.sin(psi)
    return np.column_stack([c * v[:, 0] + s * v[:, 1], -s * v[:, 0] + c * v[:, 1]])


def _turn(v: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """Body vectors (n, 2) in the frame whose x axis is the direction ``forward``."""
    n = float(np.hypot(*forward))
    c, s = (forward / n) if n > 0 else (1.0, 0.0)
    return np.column_stack([c * v[:, 0] + s * v[:, 1], -s * v[:, 0] + c * v[:, 1]])


def _residual(y: np.ndarray, others: np.ndarray) -> np.ndarray:
    """``y`` less its least-squares fit on ``others`` (columns) and a constant."""
    A = np.column_stack([np.ones(len(y)), others])
    return y - A @ np.linalg.lstsq(A, y, rcond=None)[0]


def thruster_findings(m: Mission, alpha: float = ALPHA) -> list[ThrusterFinding]:
    """The thrusters (and the summed thrust) whose demand correlates negatively with the
    motion it should cause, beyond chance at level ``alpha`` for the mission (module doc).
    Thrusters pointing more up or down than sideways are not tested (the fixes are
    horizontal); a mission without two fixes inside its inputs gives none.

    The frame is turned so the mean motion while the thrusters push points forward (the
    logged heading's offset is unknown: theta_e). Where that turns it more than 90 deg from
    the logged heading, the data contradict either the heading or the vehicle's going
    forward when pushed (a log of one manoeuvre astern); a finding is then reported only
    where both frames show it."""
    a, b, v, acc = body_motion(m, correlation_time(m))
    if len(a) < 5:
        return []
    dem = _mean_demand(m, a, b)
    dirs = np.asarray(m.thruster_dir, dtype=float)
    # each interval weighted by its time and its summed demand's size, whatever its sign:
    # a slow vehicle drifts astern in the wind between legs
    push = np.abs(dem @ dirs[:, 0]) * (b - a)
    mean = (v * (push if push.sum() > 0 else b - a)[:, None]).sum(axis=0)
    mid = 0.5 * (a + b)
    dem_acc = _mean_demand(m, mid[:-1], mid[1:])          # between the velocities' middles
    found = _findings(_turn(v, mean), _turn(acc, mean), dem, dem_acc, dirs, alpha)
    if mean[0] < 0:
        logged = {f.thruster for f in _findings(v, acc, dem, dem_acc, dirs, alpha)}
        found = [f for f in found if f.thruster in logged]
    return found


def _findings(v: np.ndarray, acc: np.ndarray, dem: np.ndarray, dem_acc: np.ndarray,
              dirs: np.ndarray, alpha: float) -> list[ThrusterFinding]:
    """The findings with body velocities ``v`` and accelerations ``acc`` in one frame
    (``dem``, ``dem_acc``: the mean demands over the velocities' and the accelerations'
    intervals)."""
    v_acc = 0.5 * (v[1:] + v[:-1])
    axes: list[tuple[int | None, np.ndarray, np.ndarray, np.ndarray]] = []
    for i, ax in enumerate(dirs):
        h = ax[:2]
        if np.linalg.norm(h) > abs(ax[2]):
            axes.append((i, h / np.linalg.norm(h), np.delete(dem, i, axis=1),
                         np.delete(dem_acc, i, axis=1)))
    if len(axes) > 1 and np.any(dirs[:, 0] != 0):
        axes.append((None, np.array([1.0, 0.0]), np.zeros((len(dem), 0)),
                     np.zeros((len(dem_acc), 0))))
    level = alpha / max(len(axes), 1)
    out = []
    for k, h, others, others_acc in axes:
        d = dem @ dirs[:, 0] if k is None else dem[:, k]
        d_acc = dem_acc @ dirs[:, 0] if k is None else dem_acc[:, k]
        r, n_eff, p1 = negative_correlation(_residual(d, others), _residual(v @ h, others))
        va = v_acc @ h
        held = np.column_stack([others_acc, va * np.abs(va)])
        r_acc, _, p2 = negative_correlation(_residual(d_acc, held), _residual(acc @ h, held))
        z = (dist.norm_ppf(np.clip(p1, 1e-300, 1.0)) + dist.norm_ppf(np.clip(p2, 1e-300, 1.0)))
        p = float(dist.norm_cdf(z / np.sqrt(2.0)))
        if p < level and max(p1, p2) < AGREE:
            axis = (1.0, 0.0, 0.0) if k is None else tuple(float(c) for c in dirs[k])
            out.append(ThrusterFinding(k, axis, r, r_acc, len(d), n_eff, p))  # type: ignore[arg-type]
    return out
