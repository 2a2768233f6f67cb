"""GNSS noise that is not white: its size and correlation time, and the weight of each fix.

A receiver's position error is coloured: consecutive fixes of a 5-Hz receiver share most of
it (its own filter, multipath and the atmosphere change over seconds), so 5 fixes a second
hold far less than 5 independent fixes' information, while fixes seconds apart are nearly
independent. Treated as white with one sigma, dense fixes drag the smoothed states and the
model's constants towards their common error, and the sigma that suits them is wrong for
sparse fixes.

The error is described as a first-order Gauss-Markov (AR(1)) process per horizontal axis,
``e(t+dt) = rho e(t) + w``, ``rho = exp(-dt / tau)``, stationary 1-sigma ``sigma``:

* :func:`measure` estimates ``sigma`` and ``tau`` from dense fixes (median spacing <= 1 s):
  the residuals of a constant-velocity Rauch-Tung-Striebel smoother on the fixes (white
  acceleration of PSD ``q`` per axis, the accelerations a vehicle has; the fixes at their
  stated sigma), their RMS and their lag-one autocorrelation at the median spacing
  (residuals beyond 5 RMS left out as outliers, the RMS recomputed until none is). What is
  measured is the wander of the fixes about a track of the vehicle's accelerations; an
  error common to all fixes over minutes moves that track with it and is not seen. (The
  measurement variance by maximum likelihood is no use here: a receiver's own filter makes
  its fixes smooth, and the likelihood then puts all of their error into the motion.)
* :func:`judged_sigma` is the sigma of the fixes as a reference that predictions are
  judged against (the diagnosis's held-out fixes): the stated sigma unless the fixes'
  wander about the smoother, plus what the smoother absorbs of white noise, shows it too
  large.
* :func:`fix_sigma` gives each fix the variance of an independent fix carrying the same
  information on a slowly varying quantity: ``sigma^2 (1 + rho) / (1 - rho)`` with ``rho``
  from its spacing to the neighbouring fixes (the variance of the mean of an AR(1)
  sequence is ``(1 + rho) / (1 - rho)`` times the white one). Fixes further apart than
  ``tau`` keep about ``sigma``; 0.2-s fixes with ``tau`` = 5 s count about 1/50 each.

The online smoother, whose output is the track, weights each fix by its own error,
``sigma`` (``track=True``): the correlation takes nothing from what a fix says about the
position at its time. On four BlueBoat runs with 4-s fixes this brought the causal and
the corrected track 1.6-6x closer to the 5-Hz fixes than the stated 1.5 m, and closer
than the (1 + rho) / (1 - rho) weights. The batch fit estimates the vehicle's constants:
it takes :func:`fix_sigma` and never a sigma below the fix's stated one (``track=False``):
fixes tighter than the model's error between them moved the constants to predict worse
(the 60-s prediction 2.3-2.9x worse on three of those runs); there the measurement only
down-weights dense fixes. The online estimates of the heading offset and the current
are then not widened for the correlation of dense fixes.
"""
from __future__ import annotations

import copy
import math
from dataclasses import asdict, dataclass

import numpy as np

from aqfg.data.mission import Gnss, Mission
from aqfg.fg.kinematic import transition

DENSE_SPACING = 1.0     # s: fixes this dense (median) are measured
MIN_FIXES = 30
MAX_RHO = 0.999         # inflation bounded at (1 + MAX_RHO) / (1 - MAX_RHO), about 2000
CLIP_K = 5.0            # residuals beyond this many RMS are outliers, left out


@dataclass(frozen=True)
class GnssNoise:
    """The GNSS error as an AR(1) process: ``sigma`` (m per horizontal axis), ``tau`` (s),
    measured on ``n_fixes`` fixes of median spacing ``spacing`` (s)."""
    sigma: float
    tau: float
    n_fixes: int = 0
    spacing: float = float("nan")

    def document(self) -> dict:
        """The ``gnss_noise`` entry of parameters.json (format doc, "Outputs")."""
        return {k: (float(v) if isinstance(v, float) else v) for k, v in asdict(self).items()}

    @staticmethod
    def from_document(doc: dict, where: str) -> GnssNoise:
        try:
            s, t = float(doc["sigma"]), float(doc["tau"])
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"{where}: gnss_noise needs numbers sigma (m) and tau (s)") from e
        if not (s > 0 and t > 0 and math.isfinite(s) and math.isfinite(t)):
            raise ValueError(f"{where}: gnss_noise sigma and tau must be positive, got {s}, {t}")
        return GnssNoise(s, t, int(doc.get("n_fixes", 0) or 0), float(doc.get("spacing", np.nan)))


def _smoother_residuals(t: np.ndarray, z: np.ndarray, q: float, r2: float
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Residuals ``z - x_s`` (n, 2) of the constant-velocity RTS smoother and the smoothed
    position variance (n,) (one per axis: the axes share the model)."""
    n = len(t)
    xf = np.zeros((n, 4)); Pf = np.zeros((n, 4, 4)); xp = np.zeros((n, 4)); Pp = np.zeros((n, 4, 4))
    H = np.zeros((2, 4)); H[0, 0] = H[1, 1] = 1.0
    x = np.array([z[0, 0], z[0, 1], 0.0, 0.0]); P = np.diag([r2, r2, 100.0, 100.0])
    Fs = [np.eye(4)]
    R, I4, Ht = r2 * np.eye(2), np.eye(4), H.T
    steps: dict[float, tuple[np.ndarray, np.ndarray]] = {}   # by interval: fixes are regular
    for i in range(n):
        if i:
            dt = float(t[i] - t[i - 1])
            if dt not in steps:
                steps[dt] = transition(dt, q)
            F, Q = steps[dt]
            Fs.append(F)
            x = F @ x; P = F @ P @ F.T + Q
        xp[i], Pp[i] = x, P
        S = H @ P @ Ht + R
        K = P @ Ht @ np.linalg.inv(S)
        x = x + K @ (z[i] - H @ x); P = (I4 - K @ H) @ P
        xf[i], Pf[i] = x, P
    xs, Ps = xf.copy(), Pf.copy()
    for i in range(n - 2, -1, -1):
        G = Pf[i] @ Fs[i + 1].T @ np.linalg.inv(Pp[i + 1])
        xs[i] = xf[i] + G @ (xs[i + 1] - xp[i + 1])
        Ps[i] = Pf[i] + G @ (Ps[i + 1] - Pp[i + 1]) @ G.T
    return z - xs[:, :2], 0.5 * (Ps[:, 0, 0] + Ps[:, 1, 1])


def _inlier_residuals(t: np.ndarray, ne: np.ndarray, q: float, sigma: float
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
    """The constant-velocity smoother's residuals (n, 2), smoothed position variances (n,),
    inlier mask (n,) and the median spacing (s) of one mission's fixes (stated 1-sigma
    ``sigma``, m); None where they are too few or too sparse (module docstring)."""
    t = np.asarray(t, float); ne = np.asarray(ne, float)[:, :2]
    if len(t) < MIN_FIXES:
        return None
    dt = float(np.median(np.diff(t)))
    if not (0.0 < dt <= DENSE_SPACING):
        return None
    res, ps = _smoother_residuals(t, ne, q, float(sigma) ** 2)
    # an outlying fix (a jump) must not set the noise of all the others: residuals beyond
    # CLIP_K RMS left out, the RMS of the rest recomputed, until none is
    ok = np.ones(len(t), bool)
    for _ in range(10):
        rms = math.sqrt(float(np.mean(res[ok] ** 2)))
        keep = np.all(np.abs(res) <= CLIP_K * rms, axis=1)
        if not rms > 0 or np.array_equal(keep, ok):
            break
        ok = keep
    return res, ps, ok, dt


def measure_fixes(t: np.ndarray, ne: np.ndarray, q: float, sigma: float
                  ) -> tuple[float, float, int, float] | None:
    """(sigma, lag-one autocorrelation, n, median spacing) of one mission's fixes (stated
    1-sigma ``sigma``, m), or None where they are too few or too sparse (module docstring)."""
    got = _inlier_residuals(t, ne, q, sigma)
    if got is None:
        return None
    res, _, ok, dt = got
    pair = ok[1:] & ok[:-1]
    num = float(np.sum(res[1:][pair] * res[:-1][pair]))
    den = float(np.sum(res[ok] ** 2)) * pair.sum() / max(int(ok.sum()), 1)
    rho = num / den if den > 0 else 0.0
    return math.sqrt(float(np.mean(res[ok] ** 2))), rho, len(t), dt


def judged_sigma(missions: list[Mission], q: float, default_sigma: float) -> float | None:
    """The 1-sigma (m per axis) of the fixes as the reference a prediction is judged
    against: None (their stated sigma stands) unless their wander shows it too large.

    Under white noise of the stated sigma ``s``, the constant-velocity smoother's residuals
    have variance ``s^2 - P_s`` (``P_s`` its smoothed position variance): their mean square
    plus ``P_s`` estimates ``s^2``, its standard error about ``s^2 sqrt(2 / n)`` for ``n``
    fixes. Where that estimate lies more than three standard errors below ``s^2`` the fixes
    are steadier than stated and its root is returned (a receiver logged at 1 m whose fixes
    wander 0.1 m: about 0.25 m, the smoother's variance at 1 m included, so never below what
    it can tell); otherwise None. On a simulated receiver with the stated noise the estimate
    is within 3 % of it."""
    ms = vs = n = 0.0
    for m in missions:
        if m.gnss is None:
            continue
        s = stated_sigma(m, default_sigma)
        got = _inlier_residuals(m.gnss.t, m.gnss.ne, q, s)
        if got is None:
            continue
        res, ps, ok, _ = got
        k = float(ok.sum())
        ms += k * float(np.mean(res[ok] ** 2) + np.mean(ps[ok]))
        vs += k * s ** 2
        n += k
    if not n:
        return None
    est, stated = ms / n, vs / n
    return math.sqrt(est) if est < stated * (1.0 - 3.0 * math.sqrt(2.0 / n)) else None


def stated_sigma(mission: Mission, default: float) -> float:
    """The median of the mission's gnss.csv sigma column (``default`` where it has none)."""
    g = mission.gnss
    if g is None or g.sigma is None or not np.any(np.isfinite(g.sigma) & (g.sigma > 0)):
        return float(default)
    s = np.asarray(g.sigma, float)
    return float(np.median(s[np.isfinite(s) & (s > 0)]))


def measure(missions: list[Mission], q: float, default_sigma: float) -> GnssNoise | None:
    """The GNSS noise of the missions' dense fixes, pooled (RMS sigma, the autocorrelation
    weighted by fixes); None where no mission has dense fixes. ``default_sigma``: the
    fixes' sigma where gnss.csv states none."""
    got = [g for m in missions if m.gnss is not None
           for g in [measure_fixes(m.gnss.t, m.gnss.ne, q, stated_sigma(m, default_sigma))]
           if g is not None]
    if not got:
        return None
    n = np.array([g[2] for g in got], float)
    sigma = math.sqrt(float(np.sum(n * np.array([g[0] for g in got]) ** 2) / n.sum()))
    rho = float(np.clip(np.sum(n * np.array([g[1] for g in got])) / n.sum(), 1e-6, MAX_RHO))
    dt = float(np.median([g[3] for g in got]))
    return GnssNoise(sigma, -dt / math.log(rho), int(n.sum()), dt)


def fix_sigma(t: np.ndarray, noise: GnssNoise) -> np.ndarray:
    """Per-fix 1-sigma (m): ``sigma sqrt((1 + rho) / (1 - rho))``, ``rho`` from the mean
    spacing to the neighbouring fixes (module docstring)."""
    t = np.asarray(t, float)
    if len(t) < 2:
        return np.full(len(t), noise.sigma)
    d = np.diff(t)
    gap = np.empty(len(t))
    gap[0], gap[-1] = d[0], d[-1]
    gap[1:-1] = 0.5 * (d[:-1] + d[1:])
    rho = np.minimum(np.exp(-np.maximum(gap, 0.0) / noise.tau), MAX_RHO)
    return noise.sigma * np.sqrt((1.0 + rho) / (1.0 - rho))


def weighted(mission: Mission, noise: GnssNoise | None, default_sigma: float,
             track: bool = True) -> Mission:
    """A copy of ``mission`` whose gnss.csv sigma is ``noise.sigma`` (``track``: the error
    of each fix, for an estimate of the track) or :func:`fix_sigma` never below the fix's
    stated sigma (``default_sigma`` where it states none; for the vehicle's constants).
    ``noise`` None or no fixes: the mission as it is."""
    g = mission.gnss
    if noise is None or g is None or not len(g.t):
        return mission
    s = np.full(len(g.t), noise.sigma) if track else fix_sigma(g.t, noise)
    if not track:
        stated = (np.full(len(g.t), float(default_sigma)) if g.sigma is None else
                  np.where(np.isfinite(g.sigma) & (g.sigma > 0), g.sigma, default_sigma))
        s = np.maximum(s, stated)
    out = copy.copy(mission)
    out.gnss = Gnss(g.t, g.ne, s)
    return out


def resolve(missions: list[Mission], noise, q: float, default_sigma: float
            ) -> GnssNoise | None:
    """The GNSS noise ``noise`` names (:attr:`FGSettings.graph.gnss_noise`): a :class:`GnssNoise`
    as it is, ``"measure"``: :func:`measure` on these missions' fixes (constant-velocity
    PSD ``q``), None: none (the fixes' stated sigma)."""
    if isinstance(noise, str):
        if noise != "measure":
            raise ValueError(f"gnss_noise must be a GnssNoise, 'measure' or None, got {noise!r}")
        return measure(missions, q, default_sigma)
    return noise


def apply(missions: list[Mission], noise, q: float, default_sigma: float, track: bool = True
          ) -> tuple[list[Mission], GnssNoise | None]:
    """The missions with their fixes weighted by ``noise`` (:attr:`FGSettings.graph.gnss_noise`):
    a :class:`GnssNoise`, ``"measure"`` (:func:`measure` on these missions' fixes, with
    the constant-velocity PSD ``q``) or None (the fixes' stated sigma, as they are);
    ``track`` as :func:`weighted`."""
    noise = resolve(missions, noise, q, default_sigma)
    if noise is None:
        return list(missions), None
    return [weighted(m, noise, default_sigma, track) for m in missions], noise
