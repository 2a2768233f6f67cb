"""What the batch and fixed-lag smoothers share: knots, initial values, measurement
factors of a mission, residuals and the inertial re-trace.

Times are seconds on the mission clock; states are ``[north, east, down, vn, ve, vd]``.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import gtsam
import numpy as np

from aqfg.data.mission import Mission
from aqfg.fg import factors as fc
from aqfg.fg.settings import FGSettings
from aqfg.model import retrace as retrace
from aqfg.model.params import BASE_NAMES
from aqfg.model.vehicle import Model, attitude_at
from aqfg.result import Residuals, Track

ProgressFn = Callable[[float, str], None]


def progress_fn(progress) -> ProgressFn:
    """A ``(fraction, message)`` callback from ``None`` / ``False`` (silent), ``True``
    (a line on stderr) or a callable."""
    if callable(progress):
        return progress
    if progress:
        import sys

        def show(frac: float, msg: str) -> None:
            print(f"\r[{100 * frac:5.1f}%] {msg:<60s}", end="" if frac < 1 else "\n",
                  file=sys.stderr, flush=True)
        return show
    return lambda frac, msg: None


def default_estimate(model: Model, mode: str) -> tuple[str, ...]:
    """Batch: the six base parameters and those of the active effects; online: the
    variable group only (the paper's online mode, fixed parameters held)."""
    if mode == "online":
        return tuple(n for n in model.active_names if model.spec(n).group == "variable")
    return tuple(model.active_names)


def mission_model(model: Model | None, mission: Mission, effects=()) -> Model:
    """The model for one mission: the given model (effects, geometry) on its clock, or one
    built from the mission."""
    if model is None:
        return Model.for_mission(mission, effects)
    m = replace(model, t0=mission.t0)
    return m.with_effects(*effects) if effects else m


# ---------------------------------------------------------------- knots and initial values
def knot_times(mission: Mission, spacing: float, t_start: float | None = None,
               t_end: float | None = None) -> np.ndarray:
    """Regular grid of ``spacing`` s merged with the fix times (so each fix is a knot).

    Starts at the first fix (the paper's initial position); grid points closer than
    ``spacing / 4`` to a fix are dropped.
    """
    if spacing <= 0:
        raise ValueError(f"knot spacing must be positive, got {spacing}")
    tf = mission.fix_times()
    if not len(tf):
        raise ValueError(f"mission {mission.name!r} has no GNSS or USBL fix: nothing anchors "
                         "the trajectory")
    if not np.any((tf >= mission.t0) & (tf <= mission.t1)):
        raise ValueError(f"mission {mission.name!r}: no GNSS or USBL fix inside the inputs "
                         f"(t {mission.t0:.6g} .. {mission.t1:.6g} s): nothing anchors the "
                         "trajectory")
    t0 = tf[0] if t_start is None else t_start
    t1 = mission.t1 if t_end is None else t_end
    tf = np.unique(tf[(tf >= t0) & (tf <= t1)])
    grid = np.arange(t0, t1 + 1e-9, spacing)
    if len(grid) == 0 or grid[-1] < t1 - 1e-6:
        grid = np.append(grid, t1)
    if len(tf):
        j = np.searchsorted(tf, grid)
        d = np.minimum(np.abs(tf[np.clip(j, 0, len(tf) - 1)] - grid),
                       np.abs(grid - tf[np.clip(j - 1, 0, len(tf) - 1)]))
        grid = grid[d > spacing / 4]
    k = np.unique(np.concatenate([grid, tf]))
    keep = np.concatenate([[True], np.diff(k) > 1e-6])
    return k[keep]


def robust_fixes(mission: Mission) -> tuple[np.ndarray, np.ndarray]:
    """Fix times and NED positions with gross outliers removed (for initial values only:
    the factors keep every fix under the robust loss)."""
    t, p = retrace.fixes(mission)
    if len(t) < 5:
        return t, p
    n = len(t)
    keep = np.ones(n, bool)

    def judge(i: np.ndarray, nb: np.ndarray) -> np.ndarray:
        # fixes i (m,) against their neighbours nb (m, j): within 6 median spreads (+1 m)
        # of the neighbours' median, plus 1.5 m per second of the neighbourhood
        q = p[nb, :2]                                        # (m, j, 2)
        med = np.median(q, axis=1)
        spread = np.median(np.abs(q - med[:, None, :]).reshape(len(i), -1), axis=1) + 1.0
        dt = np.max(np.abs(t[nb] - t[i][:, None]), axis=1)
        return np.linalg.norm(p[i, :2] - med, axis=1) < 6 * spread + 1.5 * dt

    inner = np.arange(3, n - 3)               # six neighbours each: vectorised
    if len(inner):
        off = np.array([-3, -2, -1, 1, 2, 3])
        keep[inner] = judge(inner, inner[:, None] + off)
    for i in sorted(set(range(min(3, n))) | set(range(max(n - 3, 0), n))):
        lo, hi = max(0, i - 3), min(n, i + 4)
        nb = np.delete(np.arange(lo, hi), i - lo)
        keep[i] = judge(np.array([i]), nb[None, :])[0]
    return t[keep], p[keep]


def robust_fix_table(mission: Mission, settings: FGSettings
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Fix times, horizontal NED positions (n, 2), their per-axis variance (m^2) (GNSS
    sigma, or the USBL tangential sigma at the fix's range) and whether each is a USBL fix,
    for innovation statistics."""
    t, p = retrace.fixes(mission)
    g, u, sn = mission.gnss, mission.usbl, settings.graph.sensors
    # retrace.fixes' order: GNSS then USBL, stably sorted by time
    gt = g.t if g is not None else np.zeros(0)
    ut = u.t if u is not None else np.zeros(0)
    order = np.argsort(np.concatenate([gt, ut]), kind="stable")
    is_u = np.concatenate([np.zeros(len(gt), bool), np.ones(len(ut), bool)])[order]
    var = np.full(len(t), sn.gnss_sigma ** 2)
    if u is not None and len(ut):
        rng = np.interp(t, ut, u.range)
        var[is_u] = np.hypot(sn.usbl_range_sigma, rng[is_u] * sn.usbl_bearing_sigma) ** 2
    if g is not None and len(gt) and g.sigma is not None:
        sg = np.interp(t, gt, np.nan_to_num(g.sigma, nan=sn.gnss_sigma))
        var[~is_u] = sg[~is_u] ** 2
    return t, p[:, :2], var, is_u


def initial_states(mission: Mission, knots: np.ndarray) -> np.ndarray:
    """Initial knot states: positions interpolated between fixes, velocities from their
    central differences over one typical fix interval, depth from the depth sensor."""
    tf, pf = robust_fixes(mission)
    X = np.zeros((len(knots), 6))
    for a in range(2):
        X[:, a] = np.interp(knots, tf, pf[:, a])
    w = max(float(np.median(np.diff(tf))) if len(tf) > 1 else 1.0, 1.0)
    for a in range(2):
        X[:, 3 + a] = (np.interp(knots + w, tf, pf[:, a]) - np.interp(knots - w, tf, pf[:, a])) / (2 * w)
    if not mission.planar and mission.depth is not None and len(mission.depth.t):
        X[:, 2] = np.interp(knots, mission.depth.t, mission.depth.depth)
        X[:, 5] = (np.interp(knots + 1, mission.depth.t, mission.depth.depth)
                   - np.interp(knots - 1, mission.depth.t, mission.depth.depth)) / 2
    return X


def first_knot_term(mission: Mission, key: int, x0: np.ndarray, settings: FGSettings
                    ) -> fc.LinearTerm:
    """Prior at the first knot: around the first fix, velocity zero (paper §II-E5)."""
    g = settings.graph
    vert = g.surface_sigma if mission.planar else (max(g.init_pos_sigma, 1.0), g.init_vel_sigma)
    sig = np.array([g.init_pos_sigma, g.init_pos_sigma, vert[0],
                    g.init_vel_sigma, g.init_vel_sigma, vert[1]])
    mean = np.array(x0, float).copy()
    mean[3:] = 0.0
    if mission.planar:
        mean[2] = 0.0
    return fc.prior_term(key, mean, sig)


def first_knot_prior(mission: Mission, key: int, x0: np.ndarray, settings: FGSettings):
    """:func:`first_knot_term` as a factor."""
    return first_knot_term(mission, key, x0, settings).factor()


# ---------------------------------------------------------------- measurements of a mission
@dataclass
class Measurements:
    """The fixes and depth readings of a mission in [t_start, t_end], with what their
    factors need (attitude at the measurement time, noise sigmas)."""
    gnss_t: np.ndarray
    gnss_z: np.ndarray          # (n, 2)
    gnss_sigma: np.ndarray      # (n,)
    gnss_R: np.ndarray          # (n, 3, 3)
    usbl_t: np.ndarray
    usbl_z: np.ndarray          # (n, 2) range, bearing
    usbl_sigma: np.ndarray      # (n, 2)
    usbl_R: np.ndarray
    station: np.ndarray | None
    depth_t: np.ndarray
    depth_z: np.ndarray

    @classmethod
    def of(cls, mission: Mission, settings: FGSettings, t_start: float = -np.inf,
           t_end: float = np.inf, attitudes: bool = True) -> Measurements:
        sn = settings.graph.sensors
        z2 = np.zeros((0, 2))
        g = mission.gnss
        if g is not None and len(g.t):
            sel = (g.t >= t_start - 1e-9) & (g.t <= t_end + 1e-9)
            gt, gz = g.t[sel], g.ne[sel]
            gs = (np.where(np.isfinite(g.sigma[sel]) & (g.sigma[sel] > 0), g.sigma[sel],
                           sn.gnss_sigma)          # the column is optional per row (NaN)
                  if g.sigma is not None else np.full(len(gt), sn.gnss_sigma))
        else:
            gt, gz, gs = np.zeros(0), z2, np.zeros(0)
        u = mission.usbl
        if u is not None and len(u.t):
            sel = (u.t >= t_start - 1e-9) & (u.t <= t_end + 1e-9)
            ut, uz = u.t[sel], np.column_stack([u.range[sel], u.bearing[sel]])
            us = np.array([sn.usbl_sigmas(r) for r in uz[:, 0]]).reshape(-1, 2)
            station = np.asarray(mission.usbl_station, float)
        else:
            ut, uz, us, station = np.zeros(0), z2, z2, None
        d = mission.depth
        if d is not None and len(d.t) and not mission.planar:
            sel = (d.t >= t_start - 1e-9) & (d.t <= t_end + 1e-9)
            dt_, dz = d.t[sel], d.depth[sel]
        else:
            dt_, dz = np.zeros(0), np.zeros(0)

        def att(t):
            return attitude_at(mission, t) if len(t) and attitudes else np.zeros((0, 3, 3))
        return cls(gt, gz, gs, att(gt), ut, uz, us, att(ut), station, dt_, dz)


def knot_index(knots: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Index of the knot nearest to each time."""
    if len(knots) == 1:
        return np.zeros(len(np.atleast_1d(t)), int)
    j = np.clip(np.searchsorted(knots, t), 1, len(knots) - 1)
    return np.where(np.abs(knots[j - 1] - t) <= np.abs(knots[j] - t), j - 1, j)


def depth_assignment(knots: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each knot with a depth reading nearby: (reading index, knot index); the reading
    nearest to the knot is kept (one depth factor per knot)."""
    if not len(t):
        return np.zeros(0, int), np.zeros(0, int)
    k = knot_index(knots, t)
    d = np.abs(knots[k] - t)
    best: dict[int, int] = {}
    for i in np.argsort(d, kind="stable"):
        best.setdefault(int(k[i]), int(i))
    ki = np.array(sorted(best), dtype=np.int64)
    return np.array([best[j] for j in ki], dtype=int), ki


def measurement_factors(model: Model, layout: fc.ParamLayout, meas: Measurements,
                        knots: np.ndarray, kx: Callable[[int], int],
                        node_keys: Callable[[str, float], tuple], settings: FGSettings,
                        base: np.ndarray | None = None) -> list:
    """GNSS, USBL and depth factors (fix times must be knots). ``kx(i)`` = key of knot i;
    ``node_keys(stream, t)`` = ((group, key), ...) of the nodes a measurement reads."""
    sn = settings.graph.sensors
    out = []
    kg = knot_index(knots, meas.gnss_t)
    ku = knot_index(knots, meas.usbl_t)
    for i in range(len(meas.gnss_t)):
        t = float(meas.gnss_t[i])
        k = int(kg[i])
        noise = sn.wrap(gtsam.noiseModel.Isotropic.Sigma(2, float(meas.gnss_sigma[i])), "gnss")
        out.append(fc.gnss_factor(model, layout, kx(k), node_keys("gnss", t), meas.gnss_z[i],
                                  meas.gnss_R[i], t, noise, base))
    for i in range(len(meas.usbl_t)):
        assert meas.station is not None, "USBL fixes come with the station position"
        t = float(meas.usbl_t[i])
        k = int(ku[i])
        noise = sn.wrap(gtsam.noiseModel.Diagonal.Sigmas(meas.usbl_sigma[i]), "usbl")
        out.append(fc.usbl_factor(model, layout, kx(k), node_keys("usbl", t), meas.usbl_z[i],
                                  meas.usbl_R[i], t, meas.station, noise, base))
    ri, ki = depth_assignment(knots, meas.depth_t)
    noise = sn.wrap(gtsam.noiseModel.Isotropic.Sigma(1, sn.depth_sigma), "depth")
    for r, k in zip(ri, ki):
        out.append(fc.depth_factor(kx(int(k)), float(meas.depth_z[r]),
                                   float(meas.depth_t[r] - knots[k]), noise))
    return out


# ---------------------------------------------------------------- results
def interp_states(track: Track, t: np.ndarray) -> np.ndarray:
    """States (n, 6) at times ``t``: linear interpolation of the track (exact at knots)."""
    X = np.column_stack([track.pos, track.vel])
    return np.column_stack([np.interp(t, track.t, X[:, a]) for a in range(6)]).reshape(-1, 6)


def residuals(model: Model, mission: Mission, track: Track, p_at: Callable[[float], np.ndarray],
              settings: FGSettings) -> dict:
    """Residuals (measured - predicted) of every GNSS, USBL and depth measurement against
    ``track``, raw and divided by the sensor sigma. ``p_at(t)``: full parameters at time t."""
    meas = Measurements.of(mission, settings, track.t[0], track.t[-1])
    out = {}
    if len(meas.gnss_t):
        X = interp_states(track, meas.gnss_t)
        ps = [p_at(t) for t in (meas.gnss_t[0], meas.gnss_t[-1])]
        moving = np.array([0.0, 0.0, 0.0, 1.0, 1.0, 0.0])       # shows a time offset
        if all(np.array_equal(model.h_gnss(moving, np.eye(3), 0.0, q)[0], np.zeros(2))
               for q in ps) and np.array_equal(ps[0], ps[-1]):
            pred = X[:, :2].copy()            # no sensor offset: the fix is the position
        else:
            pred = np.array([model.h_gnss(X[i], meas.gnss_R[i], t, p_at(t))[0]
                             for i, t in enumerate(meas.gnss_t)])
        raw = meas.gnss_z - pred
        out["gnss"] = Residuals(meas.gnss_t, raw, raw / meas.gnss_sigma[:, None], meas.gnss_z, pred)
    if len(meas.usbl_t):
        X = interp_states(track, meas.usbl_t)
        pred = np.array([model.h_usbl(X[i], meas.usbl_R[i], t, p_at(t), meas.station)[0]
                         for i, t in enumerate(meas.usbl_t)])
        raw = meas.usbl_z - pred
        raw[:, 1] = fc.wrap_angle(raw[:, 1])
        out["usbl"] = Residuals(meas.usbl_t, raw, raw / meas.usbl_sigma, meas.usbl_z, pred)
    if len(meas.depth_t):
        X = interp_states(track, meas.depth_t)
        pred = X[:, 2:3]
        raw = meas.depth_z[:, None] - pred
        out["depth"] = Residuals(meas.depth_t, raw, raw / settings.graph.sensors.depth_sigma,
                                 meas.depth_z[:, None], pred)
    return out


def piecewise_inertial(model: Model, mission: Mission, p_segments: list[np.ndarray],
                       seg_starts: np.ndarray, rate: float = 10.0) -> Track:
    """The paper's inertial trajectory (from the first fix, model only); with parameters
    that change over time segments the rollout switches parameters at ``seg_starts``."""
    if len(p_segments) == 1:
        return retrace.inertial_track(model, mission, p_segments[0], rate)
    tf, pf = retrace.fixes(mission)
    t_out = np.arange(tf[0], mission.t1 + 1e-9, 1.0 / rate)
    x = np.concatenate([pf[0], np.zeros(3)])
    ts, P, V = [np.array([tf[0]])], [pf[0][None]], [np.zeros((1, 3))]
    t_cur = tf[0]
    for j, p in enumerate(p_segments):
        t_next = seg_starts[j + 1] if j + 1 < len(seg_starts) else np.inf
        sel = t_out[(t_out > t_cur + 1e-9) & (t_out <= t_next + 1e-9)]
        if not len(sel):
            continue
        tr = retrace.rollout(model, mission, p, x, t_cur, sel)
        ts.append(tr.t[1:]); P.append(tr.pos[1:]); V.append(tr.vel[1:])
        x = np.concatenate([tr.pos[-1], tr.vel[-1]])
        t_cur = tr.t[-1]
    return Track(np.concatenate(ts), np.vstack(P), np.vstack(V))


def check_missions(missions) -> list[Mission]:
    if isinstance(missions, Mission):
        missions = [missions]
    missions = list(missions)
    if not missions:
        raise ValueError("no mission given")
    for m in missions:
        if not isinstance(m, Mission):
            raise ValueError(f"expected aqfg.data.mission.Mission objects, got {type(m).__name__}")
        if m.usbl is not None and len(m.usbl.t) and m.usbl_station is None:
            raise ValueError(f"mission {m.name!r}: usbl data without a [usbl] station")
    veh = {m.vehicle for m in missions}
    if len(veh) > 1:
        raise ValueError(f"missions of one fit must share the vehicle type, got {sorted(veh)}")
    return missions


__all__ = ["default_estimate", "knot_times", "initial_states", "Measurements",
           "measurement_factors", "residuals", "piecewise_inertial", "BASE_NAMES"]


def outliers(res: dict, threshold: float = 5.0) -> dict[str, list[dict]]:
    """Fixes whose whitened residual exceeds ``threshold`` sigma (the robust loss has
    down-weighted them): ``{stream: [{"t", "sigmas"}, ...]}`` for GNSS and USBL."""
    out: dict[str, list[dict]] = {}
    for stream in ("gnss", "usbl"):
        r = res.get(stream)
        if r is None or not len(r.t):
            continue
        z = np.linalg.norm(np.nan_to_num(r.normalised, nan=0.0), axis=1)
        idx = np.flatnonzero(z > threshold)
        if len(idx):
            out[stream] = [{"t": float(r.t[i]), "sigmas": round(float(z[i]), 1)} for i in idx]
    return out
