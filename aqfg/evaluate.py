"""Accuracy metrics against ground truth (simulated missions): what the experiments report.

Every function is pure numpy on :class:`aqfg.result.Track` / :class:`aqfg.data.mission.Truth`
arrays. Positions are NED metres, times seconds on the mission clock. Position errors are
horizontal by default (the paper's ground truth is GNSS, §V), ``horizontal=False`` gives
the 3-D distance.

* :func:`position_error` -- distance between an estimated track and the truth over time
  (the paper's "error in estimated position", Fig. 10);
* :func:`rmse`, :func:`inertial_rmse` -- RMS of that distance; the latter on the paper's
  inertial trajectory (model only from the first fix, Table II);
* :func:`dead_reckoning_error` -- the model alone over a horizon from the true state: what
  a vehicle dead-reckons through between fixes;
* :func:`time_since_fix`, :func:`error_between_fixes` -- how the error grows between
  absolute fixes;
* :func:`percentile` -- e.g. the 95th-percentile error of Fig. 10;
* :func:`param_errors`, :func:`consistency` -- estimate minus truth, divided by the
  reported 1-sigma: are the covariances honest?
* :func:`heading_truth` -- the true heading offset over time (with heading drift);
* :func:`summary` -- mean, spread and quantiles of a Monte Carlo sample.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from aqfg.data.mission import Mission, Truth
from aqfg.model.frames import heading, wrap_angle
from aqfg.model.params import vector
from aqfg.result import Track


def _interp_rows(t_src: np.ndarray, X: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Linear interpolation of the columns of ``X`` (n, d) at times ``t`` (held at the ends)."""
    return np.column_stack([np.interp(t, t_src, X[:, j]) for j in range(X.shape[1])])


def _check_track(track: Track, what: str = "track") -> None:
    t = np.asarray(track.t)
    if t.ndim != 1 or len(t) < 1:
        raise ValueError(f"{what} has no samples")
    if np.asarray(track.pos).shape != (len(t), 3):
        raise ValueError(f"{what}.pos must be ({len(t)}, 3), got {np.asarray(track.pos).shape}")
    if len(t) > 1 and np.any(np.diff(t) < 0):
        raise ValueError(f"{what}.t must be non-decreasing")


def position_error(track: Track, truth: Truth, t: np.ndarray | None = None,
                   horizontal: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Distance (m) between ``track`` and the truth at times ``t`` (default: the track's own
    times inside the truth's span). Both are interpolated linearly in time.

    Returns ``(t, err)``; times outside the truth's or the track's span are dropped.
    """
    _check_track(track)
    tt = np.asarray(truth.t, float)
    ts = np.asarray(track.t, float)
    t = ts if t is None else np.asarray(t, float)
    keep = (t >= max(tt[0], ts[0]) - 1e-9) & (t <= min(tt[-1], ts[-1]) + 1e-9)
    t = t[keep]
    if not len(t):
        return t, np.zeros(0)
    est = _interp_rows(ts, np.asarray(track.pos, float), t)
    tru = _interp_rows(tt, np.asarray(truth.pos, float), t)
    d = est - tru
    if horizontal:
        d = d[:, :2]
    return t, np.linalg.norm(d, axis=1)


def rmse(track: Track, truth: Truth, t: np.ndarray | None = None, t_from: float | None = None,
         t_to: float | None = None, horizontal: bool = True) -> float:
    """RMS position error (m) of ``track`` vs truth, at ``t`` (default the track's times),
    restricted to ``[t_from, t_to]``."""
    tt, e = position_error(track, truth, t, horizontal)
    sel = np.ones(len(tt), bool)
    if t_from is not None:
        sel &= tt >= t_from - 1e-9
    if t_to is not None:
        sel &= tt <= t_to + 1e-9
    if not sel.any():
        return float("nan")
    return float(np.sqrt(np.mean(e[sel] ** 2)))


def inertial_rmse(model, mission: Mission, p: np.ndarray, truth: Truth, rate: float = 1.0,
                  horizontal: bool = True) -> float:
    """RMSE (m) of the paper's inertial trajectory (Table II): the model alone integrates
    the mission's inputs with parameters ``p`` (full vector) from the first fix, sampled at
    ``rate`` Hz, compared with the truth."""
    from aqfg.model.retrace import inertial_track
    tr = inertial_track(model, mission, np.asarray(p, float), rate=rate)
    return rmse(tr, truth, horizontal=horizontal)


def dead_reckoning_error(model, mission: Mission, p: np.ndarray, truth: Truth,
                         horizon: float = 60.0, every: float = 30.0) -> float:
    """Median horizontal error (m) of the model alone (parameters ``p``) ``horizon`` s after
    starting from the true state, started every ``every`` s (NaN for a mission shorter than
    the horizon). Unlike :func:`inertial_rmse` (the whole mission from the first fix) it
    measures the gap between fixes, not the accumulated drift of a whole mission."""
    from aqfg.model.retrace import rollout
    if truth.vel is None:
        raise ValueError("dead_reckoning_error needs the true velocity (truth.csv vn, ve, vd)")
    errs = []
    for t0 in np.arange(truth.t[0] + 10.0, truth.t[-1] - horizon, every):
        i = int(np.searchsorted(truth.t, t0))
        x0 = np.concatenate([truth.pos[i], truth.vel[i]])
        tr = rollout(model, mission, p, x0, truth.t[i], np.array([truth.t[i] + horizon]))
        j = int(np.searchsorted(truth.t, truth.t[i] + horizon))
        errs.append(float(np.hypot(*(tr.pos[-1, :2] - truth.pos[j, :2]))))
    return float(np.median(errs)) if errs else float("nan")


def time_since_fix(t: np.ndarray, fix_t: np.ndarray) -> np.ndarray:
    """Seconds since the latest fix at or before each time (NaN before the first fix)."""
    t = np.asarray(t, float)
    f = np.sort(np.asarray(fix_t, float))
    j = np.searchsorted(f, t + 1e-9, side="right") - 1
    out = np.full(len(t), np.nan)
    ok = j >= 0
    out[ok] = t[ok] - f[j[ok]]
    return out


@dataclass
class BetweenFixes:
    """Error statistics per interval between consecutive fixes.

    ``t0`` (m,) start of each interval (a fix time), ``peak`` (m,) largest error in it,
    ``mean`` (m,) mean error in it; ``bins`` (b+1,) edges in seconds since the fix and
    ``growth`` (b,) mean error in each bin (how the error grows during dead reckoning).
    """
    t0: np.ndarray
    peak: np.ndarray
    mean: np.ndarray
    bins: np.ndarray
    growth: np.ndarray


def error_between_fixes(t: np.ndarray, err: np.ndarray, fix_t: np.ndarray,
                        bin_width: float = 1.0) -> BetweenFixes:
    """Per-interval peak/mean error and mean error vs time since the last fix."""
    t = np.asarray(t, float)
    err = np.asarray(err, float)
    if t.shape != err.shape:
        raise ValueError(f"t {t.shape} and err {err.shape} must have the same shape")
    f = np.unique(np.asarray(fix_t, float))
    j = np.searchsorted(f, t + 1e-9, side="right") - 1
    ok = j >= 0
    t0, peak, mean = [], [], []
    for i in np.unique(j[ok]):
        e = err[j == i]
        t0.append(f[i]); peak.append(e.max()); mean.append(e.mean())
    since = time_since_fix(t, f)
    top = np.nanmax(since) if ok.any() else 0.0
    bins = np.arange(0.0, top + bin_width + 1e-9, bin_width)
    k = np.clip(np.floor(since[ok] / bin_width).astype(int), 0, len(bins) - 2)
    s = np.bincount(k, weights=err[ok], minlength=len(bins) - 1)
    c = np.bincount(k, minlength=len(bins) - 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        growth = np.where(c > 0, s / np.maximum(c, 1), np.nan)
    return BetweenFixes(np.array(t0), np.array(peak), np.array(mean), bins, growth)


def percentile(err: np.ndarray, q: float = 95.0) -> float:
    """The ``q``-th percentile of the error samples (NaN when empty)."""
    err = np.asarray(err, float)
    err = err[np.isfinite(err)]
    return float(np.percentile(err, q)) if len(err) else float("nan")


def heading_truth(truth_params: Mapping[str, float], t: np.ndarray, t0: float = 0.0
                  ) -> np.ndarray:
    """True heading offset theta_e (rad) at times ``t``: the constant plus the hidden
    heading drift ``heading_drift.rate`` (rad/s) from the mission start ``t0``."""
    p = vector({"theta_e": float(truth_params["theta_e"]),
                "heading_drift.rate": float(truth_params.get("heading_drift.rate", 0.0) or 0.0)})
    return heading(p, np.asarray(t, float) - t0)


@dataclass
class ParamErrors:
    """Estimate minus truth per parameter, the reported 1-sigma, and their ratio ``z``."""
    names: tuple[str, ...]
    error: np.ndarray
    sigma: np.ndarray
    z: np.ndarray

    def as_dict(self) -> dict[str, dict[str, float]]:
        return {n: {"error": float(e), "sigma": float(s), "z": float(z)}
                for n, e, s, z in zip(self.names, self.error, self.sigma, self.z)}


def param_errors(values: Mapping[str, float], sigma: Mapping[str, float],
                 truth_params: Mapping[str, float], names: Sequence[str]) -> ParamErrors:
    """Errors (estimate - truth), reported sigma and ``z = error / sigma`` for ``names``.

    Heading errors (``theta_e``) are wrapped into [-pi, pi). A missing or non-positive
    sigma gives ``z = NaN``. Raises KeyError naming a parameter absent from the estimate
    or the truth.
    """
    names = tuple(names)
    errs: list[float] = []
    sigs: list[float] = []
    for n in names:
        if n not in values:
            raise KeyError(f"parameter {n!r} is not in the estimate (has: {', '.join(values)})")
        if n not in truth_params:
            raise KeyError(f"parameter {n!r} is not in the truth")
        e = float(values[n]) - float(truth_params[n])
        if n == "theta_e":
            e = float(wrap_angle(e))
        errs.append(e)
        sigs.append(float(sigma.get(n, np.nan)))
    err, sig = np.array(errs), np.array(sigs)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = np.where(sig > 0, err / np.where(sig > 0, sig, 1.0), np.nan)
    return ParamErrors(names, err, sig, z)


def consistency(z: np.ndarray) -> dict[str, float]:
    """Honesty of reported sigmas from normalised errors ``z`` (any shape; NaN ignored).

    ``rms``: RMS of z (1 for honest Gaussian sigmas, > 1 over-confident); ``within2``:
    fraction with |z| <= 2 (0.954 for honest sigmas); ``n``: number of finite z.
    """
    z = np.asarray(z, float).ravel()
    z = z[np.isfinite(z)]
    if not len(z):
        return {"rms": float("nan"), "within2": float("nan"), "n": 0}
    return {"rms": float(np.sqrt(np.mean(z ** 2))), "within2": float(np.mean(np.abs(z) <= 2.0)),
            "n": int(len(z))}


def summary(x: Sequence[float]) -> dict[str, float]:
    """Mean, standard deviation, median, 10th and 90th percentiles and count of a Monte
    Carlo sample (NaN entries are counted in ``n_nan`` and left out)."""
    a = np.asarray(x, float).ravel()
    fin = a[np.isfinite(a)]
    if not len(fin):
        nan = float("nan")
        return {"mean": nan, "std": nan, "median": nan, "p10": nan, "p90": nan, "n": 0,
                "n_nan": int(len(a))}
    return {"mean": float(fin.mean()), "std": float(fin.std(ddof=1)) if len(fin) > 1 else 0.0,
            "median": float(np.median(fin)), "p10": float(np.percentile(fin, 10)),
            "p90": float(np.percentile(fin, 90)), "n": int(len(fin)),
            "n_nan": int(len(a) - len(fin))}
