"""Held-out dead reckoning: predict the fixes the fit never saw, with their uncertainty.

From the fitted state at each fix *used by the fit* (an anchor), the model alone integrates
the inputs (no fix) up to the next anchor, and predicts every held-out fix in between with
the model's measurement function (GNSS: north/east of the antenna; USBL: range and bearing).
The innovation ``nu = z - h(f(x_a, p))`` has covariance (first order, EKF prediction)

    S = G Sigma_a G^T + H Q(dt) H^T + R,       G = d h(f(x_a, p)) / d (x_a, p)

with ``Sigma_a`` the joint covariance of the anchor state and the estimated parameters from
the fit's own information matrix, ``Q(dt)`` the smoother's process noise over the
prediction interval and ``R`` the sensor noise. Under a consistent model the normalised
innovation squared ``nu^T S^-1 nu`` is ``chi2(2)`` for each fix, independently of the fit
(the fixes are held out), which is what the consistency test uses
(:func:`aqfg.diagnose.consistency.nis_test`).

Acoustic outliers: a held-out USBL fix further than ``outlier_m`` from the fitted track
(range or across-track) is an outlier; it is counted and left out of the scores, as the
smoother's robust loss leaves it out of the fit.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aqfg.data.mission import Mission
from aqfg.diagnose.consistency import ConsistencyTest, nis_test
from aqfg.diagnose.marginals import anchor_covariances
from aqfg.fg.common import interp_states
from aqfg.fg.score import LinearSystem
from aqfg.fg.settings import FGSettings
from aqfg.model.reference import wrap_angle
from aqfg.model.vehicle import Model, attitude_at
from aqfg.result import MissionResult, Track


@dataclass
class HeldOut:
    """Innovations of the held-out fixes (n,) and the model-only legs between anchors.

    ``sensor`` "gnss"/"usbl"; ``t`` fix time, ``dt`` s since its anchor, ``anchor`` its
    anchor's index; ``nu`` (n, 2) innovation (GNSS north/east m; USBL range m, bearing
    rad); ``S`` (n, 2, 2) its covariance; ``nis`` (n,); ``err`` (n,) the innovation as a
    horizontal distance (m; USBL: ``sqrt(dr^2 + (r_h db)^2)``); ``noise`` (n,) the fix's
    own noise as a mean squared distance (m^2); ``outlier`` (n,) excluded USBL outliers.
    ``legs``: one model-only :class:`Track` per anchor (for maps).
    """
    sensor: np.ndarray
    t: np.ndarray
    dt: np.ndarray
    anchor: np.ndarray
    anchor_t: np.ndarray
    nu: np.ndarray
    S: np.ndarray
    nis: np.ndarray
    err: np.ndarray
    noise: np.ndarray
    outlier: np.ndarray
    legs: list
    fix_ne: np.ndarray          # (n, 2) the held-out fixes as positions (m), for maps

    @property
    def used(self) -> np.ndarray:
        return ~self.outlier

    @property
    def rmse(self) -> float:
        """RMS distance (m) between the dead-reckoned predictions and the held-out fixes."""
        u = self.used
        return float(np.sqrt(np.mean(self.err[u] ** 2))) if u.any() else float("nan")

    @property
    def rmse_excess(self) -> float:
        """The same with the fixes' own noise removed: ``sqrt(max(mean e^2 - mean noise, 0))``."""
        u = self.used
        if not u.any():
            return float("nan")
        return float(np.sqrt(max(np.mean(self.err[u] ** 2) - np.mean(self.noise[u]), 0.0)))

    @property
    def loglik(self) -> np.ndarray:
        """Gaussian predictive log-likelihood of each held-out fix (n,):
        ``-(nis + log det S + 2 log 2 pi) / 2``."""
        return -0.5 * (self.nis + np.log(np.linalg.det(self.S)) + 2 * np.log(2 * np.pi))

    def consistency(self, window: float = 60.0, alpha: float = 0.05,
                    level: float = 0.01) -> ConsistencyTest:
        u = self.used
        return nis_test(self.t[u], self.nis[u], np.full(u.sum(), 2.0), window, alpha=alpha,
                        level=level)

    def growth(self, nbins: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """RMS innovation distance vs time since the anchor: bin centres (s), RMS (m), counts."""
        u = self.used
        dt, e = self.dt[u], self.err[u]
        if not len(dt):
            return np.zeros(0), np.zeros(0), np.zeros(0, int)
        bins = np.linspace(0.0, dt.max() + 1e-9, nbins + 1)
        j = np.clip(np.digitize(dt, bins) - 1, 0, nbins - 1)
        n = np.bincount(j, minlength=nbins)
        with np.errstate(invalid="ignore", divide="ignore"):
            rms = np.sqrt(np.bincount(j, e ** 2, minlength=nbins) / n)
        return 0.5 * (bins[:-1] + bins[1:]), rms, n


def _fix_rows(mission: Mission, settings: FGSettings):
    """Held-out fixes: (sensor, t, z (2,), R (2x2)) sorted by time."""
    rows = []
    sn = settings.graph.sensors
    g = mission.gnss
    if g is not None and len(g.t):
        sig = g.sigma if g.sigma is not None else np.full(len(g.t), sn.gnss_sigma)
        for i in range(len(g.t)):
            s = sig[i] if np.isfinite(sig[i]) else sn.gnss_sigma
            rows.append(("gnss", float(g.t[i]), g.ne[i].astype(float), np.eye(2) * s ** 2))
    u = mission.usbl
    if u is not None and len(u.t):
        for i in range(len(u.t)):
            s = sn.usbl_sigmas(float(u.range[i]))
            rows.append(("usbl", float(u.t[i]), np.array([u.range[i], u.bearing[i]], float),
                         np.diag(s ** 2)))
    rows.sort(key=lambda r: r[1])
    return rows


def _propagate_legs(model: Model, fit: Mission, p: np.ndarray, chains: dict, x0: dict,
                    n_dyn: int) -> dict:
    """Integrate every leg (``chains[a]``: its times, the first being its anchor's) from
    ``x0[a]``, all legs in lockstep (one batched kernel call per sub-interval index).
    Returns ``{a: (states (n, 6), transition matrices (n, 6, 6), d state / d p (n, 6,
    n_dyn))}`` at the leg's times after the first."""
    if not chains:
        return {}
    knots = np.unique(np.concatenate(list(chains.values())))
    steps, off = model.steps(fit, knots)
    seg0 = {a: int(np.searchsorted(knots, c[0] - 1e-9)) for a, c in chains.items()}
    out = {a: (np.zeros((len(c) - 1, 6)), np.zeros((len(c) - 1, 6, 6)),
               np.zeros((len(c) - 1, 6, n_dyn))) for a, c in chains.items()}
    x = {a: np.asarray(x0[a], float).copy() for a in chains}
    Phi = {a: np.eye(6) for a in chains}
    Jp = {a: np.zeros((6, n_dyn)) for a in chains}
    r = 0
    while True:
        act = [a for a, c in chains.items() if r < len(c) - 1]
        if not act:
            break
        segs = [seg0[a] + r for a in act]
        idx = np.concatenate([np.arange(off[k], off[k + 1]) for k in segs])
        sub = type(steps)(steps.h[idx], steps.warm[idx], steps.R[idx], steps.dem[idx],
                          steps.tm[idx])
        offs = np.concatenate([[0], np.cumsum([off[k + 1] - off[k] for k in segs])])
        X1, JX, JP = model.propagate_many(np.array([x[a] for a in act]), p, sub, offs)
        for i, a in enumerate(act):
            x[a] = X1[i]
            Phi[a] = JX[i] @ Phi[a]
            Jp[a] = JX[i] @ Jp[a] + JP[i]
            out[a][0][r], out[a][1][r], out[a][2][r] = x[a], Phi[a], Jp[a]
        r += 1
    return out


def _thin_anchors(anchors: np.ndarray, horizon: float | None) -> np.ndarray:
    """The anchor times (s) thinned to one per ``horizon`` seconds (None: all of them)."""
    if horizon is None:
        return anchors
    keep, last = [], -np.inf
    for ta in anchors:
        if ta >= last + horizon - 1e-6:
            keep.append(ta); last = ta
    return np.asarray(keep)


def _anchor_knots(knots: np.ndarray, anchors: np.ndarray) -> np.ndarray:
    """The index of each anchor time among the graph's knot times (both s)."""
    ka = np.searchsorted(knots, anchors - 1e-6)
    ka = np.clip(ka, 0, len(knots) - 1)
    if np.max(np.abs(knots[ka] - anchors)) > 1e-6:
        raise ValueError("held-out evaluation: the fit's fixes are not all knots of its graph")
    return ka


def _leg_chains(anchors: np.ndarray, t_rows: np.ndarray, a_of: np.ndarray, gap: float,
                t1: float, leg_sample: float) -> dict[int, tuple[np.ndarray, list[int]]]:
    """``{anchor index: (its leg's times after the anchor (s), its held-out rows)}``: each
    leg runs to the next anchor (the last one ``gap`` s, at most to ``t1``), sampled every
    ``leg_sample`` s and at its held-out fixes."""
    chains = {}
    for a in range(len(anchors)):
        ta = anchors[a]
        tb = anchors[a + 1] if a + 1 < len(anchors) else min(ta + gap, t1)
        sel = [j for j in range(len(t_rows)) if a_of[j] == a and t_rows[j] <= tb + 1e-9]
        if tb <= ta + 1e-6:
            continue
        grid = np.arange(ta + leg_sample, tb, leg_sample)
        tk = np.unique(np.concatenate([grid, t_rows[sel], [tb]]))
        tk = tk[tk > ta + 1e-9]
        if len(tk):
            chains[a] = (tk, sel)
    return chains


@dataclass(frozen=True)
class _Predictor:
    """What predicting one held-out fix needs besides its own leg: the model at the fitted
    parameters ``p``, the USBL station ``st``, the fitted track (for USBL outliers) and,
    per estimated parameter, its index in the full vector and among the dynamics columns
    (-1: not a dynamics parameter)."""
    model: Model
    p: np.ndarray
    settings: FGSettings
    planar: bool
    st: np.ndarray | None
    track: Track
    full_idx: list[int]
    dyn_pos: np.ndarray
    outlier_m: float


def _measure(pr: _Predictor, sensor: str, x: np.ndarray, R_att: np.ndarray, t: float,
             z: np.ndarray):
    """The innovation ``z - h(x)`` (USBL bearing wrapped), the measurement Jacobians
    ``(Hp, Hth)`` and the fix as a north/east position (m)."""
    if sensor == "gnss":
        h, Hp, Hth = pr.model.h_gnss(x, R_att, t, pr.p)
        return z - h, Hp, Hth, z
    st = pr.st
    assert st is not None, "USBL fixes need the station position"
    h, Hp, Hth = pr.model.h_usbl(x, R_att, t, pr.p, st)
    nu = z - h
    nu[1] = float(wrap_angle(nu[1]))
    fix_ne = np.asarray(st[:2], float) + z[0] * np.array([np.cos(z[1]), np.sin(z[1])])
    return nu, Hp, Hth, fix_ne


def _sensitivity(pr: _Predictor, Hp: np.ndarray, Hth: np.ndarray, Phi: np.ndarray,
                 Jp: np.ndarray) -> np.ndarray:
    """``G`` (2, 6 + n_th): the prediction's derivative by the anchor state and the
    estimated parameters, through the leg's transition ``Phi`` and parameter Jacobian ``Jp``."""
    n_th = len(pr.full_idx)
    G = np.zeros((2, 6 + n_th))
    G[:, :6] = Hp @ Phi            # Hp: d/d[pos, vel] (time offsets read vel)
    for c in range(n_th):
        col = Hth[:, pr.full_idx[c]].copy() if pr.full_idx[c] < Hth.shape[1] else np.zeros(2)
        if pr.dyn_pos[c] >= 0:
            col += Hp @ Jp[:, pr.dyn_pos[c]]
        G[:, 6 + c] = col
    return G


def _usbl_distance(pr: _Predictor, x: np.ndarray, R_att: np.ndarray, t: float,
                   z: np.ndarray, nu: np.ndarray, R: np.ndarray) -> tuple[float, float, bool]:
    """A USBL innovation as a horizontal distance (m), the fix's noise as a mean squared
    distance (m^2), and whether the fix is an outlier: further than ``outlier_m`` off the
    *fitted* track (not the dead-reckoned one), in range or across it."""
    st = pr.st
    assert st is not None
    rh = float(np.hypot(*(x[:2] - np.asarray(st[:2], float))))
    err = float(np.hypot(nu[0], rh * nu[1]))
    noise = float(R[0, 0] + rh ** 2 * R[1, 1])
    xs = interp_states(pr.track, np.array([t]))[0]
    hs = pr.model.h_usbl(xs, R_att, t, pr.p, st)[0]
    ds = z - hs
    ds[1] = float(wrap_angle(ds[1]))
    outlier = bool(abs(ds[0]) > pr.outlier_m or rh * abs(ds[1]) > pr.outlier_m)
    return err, noise, outlier


def _predict_fix(pr: _Predictor, row: tuple, leg_state: tuple, R_att: np.ndarray,
                 Sa: np.ndarray, dt: float) -> tuple:
    """One held-out fix ``row`` (sensor, t, z, R) predicted from the leg's state at its
    time ``leg_state`` (x, Phi, Jp), ``dt`` s after the anchor whose state + parameter
    covariance is ``Sa``: (nu, S, nis, err, noise, outlier, fix_ne) as in :class:`HeldOut`."""
    sensor, tj, z, R = row
    xj, Phj, Jpj = leg_state
    nu, Hp, Hth, fix_ne = _measure(pr, sensor, xj, R_att, tj, z)
    G = _sensitivity(pr, Hp, Hth, Phj, Jpj)
    Q = pr.settings.graph.process.cov(dt, pr.planar)
    S = G @ Sa @ G.T + Hp @ Q @ Hp.T + R
    S = 0.5 * (S + S.T)
    nis = float(nu @ np.linalg.solve(S, nu))
    if sensor == "gnss":
        err, noise, outlier = float(np.linalg.norm(nu)), float(np.trace(R)), False
    else:
        err, noise, outlier = _usbl_distance(pr, xj, R_att, tj, z, nu, R)
    return nu, S, nis, err, noise, outlier, fix_ne


_FIELDS = ("sensor", "t", "dt", "anchor", "nu", "S", "nis", "err", "noise", "outlier",
           "fix_ne")


def heldout_innovations(model: Model, fit: Mission, heldout: Mission, mres: MissionResult,
                        lin: LinearSystem, mission_index: int, estimated: tuple[str, ...],
                        settings: FGSettings, horizon: float | None = None,
                        outlier_m: float = 5.0, leg_sample: float = 0.5) -> HeldOut:
    """Predict every held-out fix of ``heldout`` by dead reckoning from the previous fix of
    ``fit`` (the anchor), with the innovation covariance from the fit's linear system
    ``lin`` (:func:`aqfg.diagnose.linearise.linear_system` of the same fit).

    With ``horizon`` (s), the anchors are thinned to one per ``horizon`` seconds and each
    dead-reckons over its whole window, passing fit fixes without using them (longer
    prediction gaps; every held-out fix is still predicted exactly once).
    """
    anchors = _thin_anchors(np.unique(fit.fix_times()), horizon)
    rows = _fix_rows(heldout, settings)
    if len(anchors) < 1 or not rows:
        raise ValueError(f"mission {fit.name!r}: not enough fixes to hold some out "
                         f"({len(anchors)} fit fixes, {len(rows)} held out)")
    assert lin.knots is not None and lin.param_cols is not None, \
        "a LinearSystem from aqfg.diagnose.linearise"
    dyn_cols = list(model.dyn_columns())
    est = [n for n in estimated if (mission_index, n) in lin.param_cols]
    pcol = np.array([lin.param_cols[(mission_index, n)] for n in est], int)
    full_idx = [model.index(n) for n in est]
    dyn_pos = np.array([dyn_cols.index(i) if i in dyn_cols else -1 for i in full_idx])
    ka = _anchor_knots(lin.knots[mission_index], anchors)
    # the last anchor's window: the anchors' usual gap (one anchor: the rest of the mission,
    # e.g. a run shorter than two horizons)
    gap = float(np.median(np.diff(anchors))) if len(anchors) > 1 else float(fit.t1 - anchors[0])
    t_rows = np.array([r[1] for r in rows])
    # the anchors that have targets, and the joint covariance of each one's state + params
    a_of = np.searchsorted(anchors, t_rows - 1e-9) - 1       # last anchor strictly before
    use = sorted({int(a) for a in a_of if a >= 0})
    Sig = anchor_covariances(lin, mission_index, ka[use], pcol)
    pos_of = {a: i for i, a in enumerate(use)}
    X_fit = interp_states(mres.track, anchors)
    st = heldout.usbl_station if heldout.usbl_station is not None else fit.usbl_station
    pr = _Predictor(model, mres.p, settings, fit.planar, st, mres.track, full_idx, dyn_pos,
                    outlier_m)
    chains = _leg_chains(anchors, t_rows, a_of, gap, fit.t1, leg_sample)
    run = _propagate_legs(model, fit, mres.p, {a: np.concatenate([[anchors[a]], tk])
                                               for a, (tk, _) in chains.items()},
                          {a: X_fit[a] for a in chains}, len(dyn_cols))
    out: dict[str, list] = {k: [] for k in _FIELDS}
    legs = []
    for a, (tk, sel) in chains.items():
        ta = anchors[a]
        X, Phis, Jps = run[a]
        legs.append(Track(np.concatenate([[anchors[a]], tk]),
                          np.vstack([X_fit[a, :3], X[:, :3]]),
                          np.vstack([X_fit[a, 3:], X[:, 3:]])))
        if not sel:
            continue
        states = {float(tk[i]): (X[i], Phis[i], Jps[i]) for i in range(len(tk))}
        Rt = attitude_at(fit, t_rows[sel])
        for q, j in enumerate(sel):
            tj = rows[j][1]
            leg_state = states[float(tj)] if float(tj) in states else states[min(
                states, key=lambda s: abs(s - tj))]
            pred = _predict_fix(pr, rows[j], leg_state, Rt[q], Sig[pos_of[a]], tj - ta)
            for k, v in zip(_FIELDS, (rows[j][0], tj, tj - ta, a, *pred)):
                out[k].append(v)
    if not out["t"]:
        raise ValueError(f"mission {fit.name!r}: no held-out fix lies between two fit fixes")
    arr = {k: np.array(v) for k, v in out.items()}
    return HeldOut(arr["sensor"], arr["t"], arr["dt"], arr["anchor"].astype(int), anchors,
                   arr["nu"], arr["S"], arr["nis"], arr["err"], arr["noise"],
                   arr["outlier"].astype(bool), legs, arr["fix_ne"])
