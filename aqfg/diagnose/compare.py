"""Compare the model with the measurements.

* per sensor: the measured value beside the model's prediction and the normalised residual
  over time (read from a fit's :class:`~aqfg.result.Residuals`, or computed for any track
  with :func:`predict_measurements`);
* the model-only track between fixes: from each fix, dead-reckon to the next with the model
  alone (:func:`aqfg.model.retrace.rollout` from the fitted state), beside the fixes on a map;
* the growth of the position error with the time since the last fix, and the held-out
  dead-reckoning error: from each fix used by the fit, dead-reckon and compare with the
  fixes the fit never saw (:func:`heldout_dr`).

Positions are NED metres; errors are horizontal (north, east) because depth is measured
directly by the depth sensor and an ASV does not move vertically.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from aqfg.data.mission import Gnss, Mission, Usbl
from aqfg.model.retrace import rollout, usbl_positions
from aqfg.model.vehicle import Model, attitude_at
from aqfg.result import MissionResult, Residuals, Track

DEFAULT_GNSS_SIGMA = 1.0        # m, when gnss.csv has no sigma column and no fit says otherwise


# ---------------------------------------------------------------- per-sensor comparison
@dataclass
class SensorSeries:
    """One sensor: measured and predicted values and normalised residuals over time.

    ``measured``/``predicted``/``normalised`` are (n, d) with component names ``labels``
    and units ``units``; ``nis`` (n,) is the sum of squared normalised components and
    ``dof`` (n,) the number of components per measurement.
    """
    sensor: str
    t: np.ndarray
    measured: np.ndarray | None
    predicted: np.ndarray | None
    raw: np.ndarray
    normalised: np.ndarray
    labels: tuple[str, ...]
    units: tuple[str, ...]

    @property
    def nis(self) -> np.ndarray:
        return np.nansum(self.normalised ** 2, axis=1)

    @property
    def dof(self) -> np.ndarray:
        return np.sum(np.isfinite(self.normalised), axis=1).astype(float)

    def sigma(self) -> np.ndarray:
        """Per-component 1-sigma (median of raw / normalised), in the sensor's units."""
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.abs(self.raw / self.normalised)
        s[~np.isfinite(s)] = np.nan
        return np.nanmedian(s, axis=0) if len(s) else np.full(self.raw.shape[1], np.nan)


_LABELS = {"gnss": (("north", "east"), ("m", "m")),
           "usbl": (("range", "bearing"), ("m", "rad")),
           "depth": (("depth",), ("m",)),
           "dynamics": (("north", "east", "down", "vn", "ve", "vd"),
                        ("m", "m", "m", "m/s", "m/s", "m/s"))}


def sensor_series(mres: MissionResult) -> list[SensorSeries]:
    """The per-sensor comparison held by a fit's residuals (all streams it reports)."""
    out = []
    for name, r in mres.residuals.items():
        raw = np.atleast_2d(np.asarray(r.raw, float).reshape(len(r.t), -1))
        nrm = np.atleast_2d(np.asarray(r.normalised, float).reshape(len(r.t), -1))
        d = raw.shape[1]
        labels, units = _LABELS.get(name, (tuple(f"{name}[{i}]" for i in range(d)), ("-",) * d))
        if len(labels) != d:
            labels, units = tuple(f"{name}[{i}]" for i in range(d)), ("-",) * d
        meas = None if r.measured is None else np.asarray(r.measured, float).reshape(len(r.t), -1)
        pred = None if r.predicted is None else np.asarray(r.predicted, float).reshape(len(r.t), -1)
        # components the model pins (e.g. the vertical of a surface vehicle) carry nothing
        keep = np.array([np.nanmax(np.abs(nrm[:, j])) > 1e-9 if len(nrm) else True
                         for j in range(d)])
        if not keep.any():
            continue
        def sel(a: np.ndarray | None, keep: np.ndarray = keep) -> np.ndarray | None:
            return None if a is None else a[:, keep]
        out.append(SensorSeries(name, np.asarray(r.t, float), sel(meas), sel(pred), raw[:, keep],
                                nrm[:, keep], tuple(np.array(labels)[keep]),
                                tuple(np.array(units)[keep])))
    return out


def interp_track(track: Track, t: np.ndarray) -> np.ndarray:
    """State [pos, vel] (n, 6) of a track at times ``t`` (linear between its samples)."""
    t = np.atleast_1d(np.asarray(t, float))
    X = np.column_stack([track.pos, track.vel])
    return np.column_stack([np.interp(t, track.t, X[:, j]) for j in range(6)])


def predict_measurements(model: Model, mission: Mission, track: Track, p: np.ndarray,
                         gnss_sigma: float = DEFAULT_GNSS_SIGMA,
                         usbl_sigma: tuple[float, float] = (0.15, np.radians(1.5))
                         ) -> dict[str, Residuals]:
    """Residuals (measured - predicted) of the fixes for any track (e.g. the truth or an
    inertial track), with the model's measurement functions and the given noise sigmas
    (GNSS sigma column when present; USBL (range m, bearing rad))."""
    from aqfg.model.reference import wrap_angle
    out: dict[str, Residuals] = {}
    if mission.gnss is not None and len(mission.gnss.t):
        g = mission.gnss
        X = interp_track(track, g.t)
        R = attitude_at(mission, g.t)
        pred = np.array([model.h_gnss(X[i], R[i], g.t[i], p)[0] for i in range(len(g.t))])
        sig = np.full(len(g.t), gnss_sigma) if g.sigma is None else np.where(
            np.isfinite(g.sigma), g.sigma, gnss_sigma)
        raw = g.ne - pred
        out["gnss"] = Residuals(g.t, raw, raw / sig[:, None], g.ne.copy(), pred)
    if mission.usbl is not None and len(mission.usbl.t):
        u = mission.usbl
        X = interp_track(track, u.t)
        R = attitude_at(mission, u.t)
        pred = np.array([model.h_usbl(X[i], R[i], u.t[i], p, mission.usbl_station)[0]
                         for i in range(len(u.t))])
        meas = np.column_stack([u.range, u.bearing])
        raw = meas - pred
        raw[:, 1] = wrap_angle(raw[:, 1])
        out["usbl"] = Residuals(u.t, raw, raw / np.asarray(usbl_sigma)[None, :], meas, pred)
    return out


# ---------------------------------------------------------------- fixes as positions
@dataclass
class Fixes:
    """Absolute fixes as horizontal positions: ``t`` (n,), ``ne`` (n, 2) m, ``cov`` (n, 2, 2)
    their noise covariance (m^2), ``source`` (n,) "gnss" or "usbl"."""
    t: np.ndarray
    ne: np.ndarray
    cov: np.ndarray
    source: np.ndarray

    def __len__(self) -> int:
        return len(self.t)

    def select(self, mask: np.ndarray) -> Fixes:
        return Fixes(self.t[mask], self.ne[mask], self.cov[mask], self.source[mask])


def fixes_of(mission: Mission, gnss_sigma: float = DEFAULT_GNSS_SIGMA,
             usbl_sigma: tuple[float, float] = (0.15, np.radians(1.5))) -> Fixes:
    """All GNSS and USBL fixes of a mission as horizontal positions with covariances.

    A USBL fix's covariance follows from its range and bearing sigmas (paper Fig. 5):
    radial ``sigma_r``, tangential ``r_h * sigma_b``.
    """
    ts, ne, cov, src = [], [], [], []
    if mission.gnss is not None and len(mission.gnss.t):
        g = mission.gnss
        s = np.full(len(g.t), gnss_sigma) if g.sigma is None else np.where(
            np.isfinite(g.sigma), g.sigma, gnss_sigma)
        ts.append(g.t); ne.append(g.ne)
        cov.append(s[:, None, None] ** 2 * np.eye(2)[None])
        src.append(np.full(len(g.t), "gnss"))
    if mission.usbl is not None and len(mission.usbl.t):
        u = mission.usbl
        P = usbl_positions(mission)
        st = np.asarray(mission.usbl_station, float)
        d = P[:, :2] - st[:2]
        rh = np.maximum(np.linalg.norm(d, axis=1), 1e-6)
        er = d / rh[:, None]
        et = np.column_stack([-er[:, 1], er[:, 0]])
        sr, sb = usbl_sigma
        C = (sr ** 2 * er[:, :, None] * er[:, None, :]
             + (rh * sb)[:, None, None] ** 2 * et[:, :, None] * et[:, None, :])
        ts.append(u.t); ne.append(P[:, :2]); cov.append(C)
        src.append(np.full(len(u.t), "usbl"))
    if not ts:
        return Fixes(np.zeros(0), np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros(0, dtype="<U4"))
    t = np.concatenate(ts)
    o = np.argsort(t, kind="stable")
    return Fixes(t[o], np.vstack(ne)[o], np.concatenate(cov)[o], np.concatenate(src)[o])


def sensor_sigmas(series: list[SensorSeries]) -> dict:
    """Noise sigmas a fit used, read back from its residuals: ``{"gnss": m,
    "usbl": (range m, bearing rad)}`` (entries only for sensors present)."""
    out: dict[str, float | tuple[float, float]] = {}
    for s in series:
        sig = s.sigma()
        if s.sensor == "gnss" and np.all(np.isfinite(sig)):
            out["gnss"] = float(np.mean(sig))
        if s.sensor == "usbl" and np.all(np.isfinite(sig)):
            out["usbl"] = (float(sig[0]), float(sig[1]))
    return out


# ---------------------------------------------------------------- fit / held-out split
@dataclass
class Split:
    """A mission thinned for fitting, and the fixes held out from it."""
    fit: Mission
    heldout: Mission          # the same mission holding only the held-out fixes
    gnss_period: float


def split_fixes(mission: Mission, gnss_period: float = 8.0,
                heldout_sigma: float | None = None) -> Split:
    """Keep one GNSS fix every ``gnss_period`` s and every other USBL fix for the fit; the
    remaining fixes are held out for evaluating dead reckoning.

    GNSS already sparser than ``gnss_period`` is split alternately like the USBL.
    ``heldout_sigma`` (m): the 1-sigma of each held-out GNSS fix (their noise floor and
    their consistency test; :func:`aqfg.fg.gnss_noise.judged_sigma`); None: their stated
    sigma.
    """
    fit, held = copy.copy(mission), copy.copy(mission)
    if mission.gnss is not None and len(mission.gnss.t):
        g = mission.gnss
        keep = np.zeros(len(g.t), bool)
        last = -np.inf
        for i, ti in enumerate(g.t):
            if ti >= last + gnss_period - 1e-6:
                keep[i] = True
                last = ti
        if keep.sum() > 0.5 * len(keep) + 1:     # GNSS already sparse: alternate
            keep = np.arange(len(g.t)) % 2 == 0
        def sel_gnss(m: np.ndarray) -> Gnss:
            return Gnss(g.t[m], g.ne[m], None if g.sigma is None else g.sigma[m])
        fit.gnss, held.gnss = sel_gnss(keep), sel_gnss(~keep)
        if heldout_sigma is not None:
            held.gnss = Gnss(held.gnss.t, held.gnss.ne, np.full(len(held.gnss.t), heldout_sigma))
    if mission.usbl is not None and len(mission.usbl.t):
        u = mission.usbl
        keep = np.arange(len(u.t)) % 2 == 0
        def sel_usbl(m: np.ndarray) -> Usbl:
            return Usbl(u.t[m], u.range[m], u.bearing[m],
                        None if u.elevation is None else u.elevation[m])
        fit.usbl, held.usbl = sel_usbl(keep), sel_usbl(~keep)
    return Split(fit, held, gnss_period)


# ---------------------------------------------------------------- dead reckoning from fixes
@dataclass
class DeadReckoning:
    """Dead reckoning from anchor fixes, compared with target fixes.

    ``anchor_t`` (k,) anchor times; ``tracks`` one model-only :class:`Track` per anchor
    (sampled for plotting); per target comparison (n,): ``t``, ``dt`` (s since the anchor),
    ``err`` (n, 2) fix - dead-reckoned position (north, east, m), ``cov`` (n, 2, 2) the
    fix noise, ``anchor`` (n,) index of the anchor.
    """
    anchor_t: np.ndarray
    tracks: list[Track]
    t: np.ndarray
    dt: np.ndarray
    err: np.ndarray
    cov: np.ndarray
    anchor: np.ndarray
    horizon: float | None

    @property
    def dist(self) -> np.ndarray:
        return np.linalg.norm(self.err, axis=1)

    @property
    def rmse(self) -> float:
        """Horizontal RMS distance between dead-reckoned positions and fixes (m)."""
        return float(np.sqrt(np.mean(np.sum(self.err ** 2, axis=1)))) if len(self.t) else float("nan")

    @property
    def rmse_excess(self) -> float:
        """RMS dead-reckoning error with the fixes' own noise removed:
        ``sqrt(max(mean|e|^2 - mean tr(cov), 0))`` (m)."""
        if not len(self.t):
            return float("nan")
        ms = np.mean(np.sum(self.err ** 2, axis=1)) - np.mean(np.trace(self.cov, axis1=1, axis2=2))
        return float(np.sqrt(max(ms, 0.0)))

    def growth(self, bins: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """RMS error vs time since the anchor: bin centres (s), RMS (m), counts."""
        if bins is None:
            top = float(self.dt.max()) if len(self.dt) else 1.0
            bins = np.linspace(0.0, top + 1e-9, min(16, max(2, len(self.dt) // 8)) + 1)
        j = np.clip(np.digitize(self.dt, bins) - 1, 0, len(bins) - 2)
        sq = np.sum(self.err ** 2, axis=1)
        n = np.bincount(j, minlength=len(bins) - 1)
        s = np.bincount(j, sq, minlength=len(bins) - 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            rms = np.sqrt(s / n)
        return 0.5 * (bins[:-1] + bins[1:]), rms, n


def dead_reckon(model: Model, mission: Mission, track: Track, p: np.ndarray,
                anchor_t: np.ndarray, targets: Fixes, horizon: float | None = None,
                sample: float = 0.5) -> DeadReckoning:
    """From the fitted state at each anchor time, integrate the model alone (no fix) and
    compare with the target fixes after it: up to the next anchor when ``horizon`` is None,
    else up to ``horizon`` seconds. ``sample``: spacing (s) of the returned tracks."""
    anchor_t = np.asarray(anchor_t, float)
    X0 = interp_track(track, anchor_t)
    tracks, rows = [], []
    for i, ta in enumerate(anchor_t):
        if horizon is None:
            if i + 1 >= len(anchor_t):
                break
            tb = anchor_t[i + 1]
        else:
            tb = min(ta + horizon, mission.t1)
        if tb <= ta + 1e-6:
            continue
        sel = np.nonzero((targets.t > ta + 1e-9) & (targets.t <= tb + 1e-9))[0]
        grid = np.arange(ta + sample, tb, sample)
        t_out = np.unique(np.concatenate([grid, targets.t[sel], [tb]]))
        tr = rollout(model, mission, p, X0[i], ta, t_out)
        tracks.append(Track(tr.t, tr.pos, tr.vel))
        if len(sel):
            P = np.column_stack([np.interp(targets.t[sel], tr.t, tr.pos[:, j]) for j in range(2)])
            for k, s in enumerate(sel):
                rows.append((targets.t[s], targets.t[s] - ta, targets.ne[s] - P[k], targets.cov[s], i))
    if rows:
        t, dt, err, cov, anc = (np.array([r[j] for r in rows]) for j in range(5))
    else:
        t, dt, err, cov, anc = (np.zeros(0), np.zeros(0), np.zeros((0, 2)), np.zeros((0, 2, 2)),
                                np.zeros(0, int))
    return DeadReckoning(anchor_t, tracks, t, dt, err, cov, anc.astype(int), horizon)


def between_fixes(model: Model, mission: Mission, mres: MissionResult,
                  fixes: Fixes | None = None, min_gap: float = 0.0) -> DeadReckoning:
    """The model-only track between consecutive fixes: from the fitted state at each fix,
    dead-reckon to the next one. With dense fixes, ``min_gap`` (s) thins the anchors so
    that each leg spans at least that long (each leg still ends at a fix)."""
    fx = fixes_of(mission) if fixes is None else fixes
    if len(fx) < 2:
        raise ValueError(f"mission {mission.name!r}: need at least two fixes to dead-reckon between them")
    t = np.unique(fx.t)
    if min_gap > 0:
        keep, last = [], -np.inf
        for ti in t:
            if ti >= last + min_gap - 1e-6:
                keep.append(ti); last = ti
        t = np.asarray(keep)
    return dead_reckon(model, mission, mres.track, mres.p, t, fx, horizon=None)


def heldout_dr(model: Model, split: Split, mres: MissionResult, horizon: float | None = None,
               sigmas: dict | None = None) -> DeadReckoning:
    """Held-out dead-reckoning error: from the fitted state at each fix *used by the fit*,
    integrate the model alone and compare with the held-out fixes up to the next fit fix
    (``horizon`` None) or up to ``horizon`` seconds."""
    sig = dict(sigmas or {})
    kw = {}
    if "gnss" in sig:
        kw["gnss_sigma"] = sig["gnss"]
    if "usbl" in sig:
        kw["usbl_sigma"] = sig["usbl"]
    anchors = fixes_of(split.fit, **kw)
    targets = fixes_of(split.heldout, **kw)
    if not len(anchors) or not len(targets):
        raise ValueError(f"mission {split.fit.name!r}: no fixes to hold out for evaluating dead reckoning")
    return dead_reckon(model, split.fit, mres.track, mres.p, np.unique(anchors.t), targets, horizon)
