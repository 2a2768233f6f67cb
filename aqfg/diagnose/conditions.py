"""Where does the model fail? Relate residual size to what the vehicle was doing.

Conditions (sampled on a regular grid, then averaged over the ``memory`` seconds before
each residual, because a missing force shows in the position only after it has acted):

==================  =====================================================  =========
name                meaning                                                unit
==================  =====================================================  =========
turn_rate           |yaw rate| of the IMU attitude                         rad/s
speed               horizontal speed of the fitted track                   m/s
thrust              mean |u| over the thrusters                            -
thrust_difference   |mean u starboard - mean u port| (differential thrust)  -
reverse             fraction of thrusters commanded backwards              -
station_distance    horizontal distance to the USBL station                m
elapsed             time since the mission start                           s
heading             corrected heading (circular)                           rad
==================  =====================================================  =========

Statistic: Spearman's rank correlation between the squared normalised residual (NIS per
measurement) and each linear condition; for the heading, Mardia's circular-linear
correlation of the NIS ranks with (cos, sin) of the heading. Residuals and conditions are
both autocorrelated in time, so the p-values use the effective sample size
``n_eff = n / (1 + 2 sum_k rho_x(k) rho_y(k))`` (Bartlett; Pyper & Peterman 1998, lags up
to n/5). Holm's correction is applied over all (series, condition) pairs.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from aqfg.data.mission import Mission
from aqfg.distributions import holm
from aqfg.model.vehicle import attitude_at, yaw_of
from aqfg.result import Track

LINEAR = ("turn_rate", "speed", "thrust", "thrust_difference", "reverse", "station_distance",
          "elapsed")
CIRCULAR = ("heading",)
UNITS = {"turn_rate": "rad/s", "speed": "m/s", "thrust": "-", "thrust_difference": "-",
         "reverse": "-", "station_distance": "m", "elapsed": "s", "heading": "rad"}
# (phrase when errors grow with the condition, phrase when they grow as it falls)
PHRASES = {
    "turn_rate": ("in turns", "on straight legs"),
    "speed": ("at high speed", "at low speed"),
    "thrust": ("at high thrust", "at low thrust"),
    "thrust_difference": ("with differential thrust (one propeller pushing harder)",
                          "when the propellers push equally"),
    "reverse": ("during reverse commands", "when no propeller reverses"),
    "station_distance": ("far from the USBL station", "close to the USBL station"),
    "elapsed": ("later in the mission", "early in the mission"),
}


@dataclass
class ConditionSignals:
    """Conditions on a regular time grid ``t`` (s): ``{name: (n,) values}``."""
    t: np.ndarray
    values: dict

    def mean_before(self, name: str, t: np.ndarray, memory: float) -> np.ndarray:
        """Mean of a condition over ``[t - memory, t]`` (circular mean for the heading)."""
        t = np.asarray(t, float)
        if name in CIRCULAR:
            c = self._window_mean(np.cos(self.values[name]), t, memory)
            s = self._window_mean(np.sin(self.values[name]), t, memory)
            return np.arctan2(s, c)
        return self._window_mean(self.values[name], t, memory)

    def _window_mean(self, y: np.ndarray, t: np.ndarray, memory: float) -> np.ndarray:
        dt = self.t[1] - self.t[0] if len(self.t) > 1 else 1.0
        cs = np.concatenate([[0.0], np.cumsum(y) * dt])
        tt = np.concatenate([self.t, [self.t[-1] + dt]])
        a = np.interp(t - memory, tt, cs)
        b = np.interp(t, tt, cs)
        span = np.clip(t, tt[0], tt[-1]) - np.clip(t - memory, tt[0], tt[-1])
        with np.errstate(invalid="ignore", divide="ignore"):
            out = np.where(span > 1e-9, (b - a) / np.where(span > 1e-9, span, 1.0),
                           np.interp(t, self.t, y))
        return out


def condition_signals(mission: Mission, track: Track, theta_e: float = 0.0,
                      rate: float = 10.0) -> ConditionSignals:
    """Sample every condition at ``rate`` Hz over the mission (track gives speed/position)."""
    t = np.arange(mission.t0, mission.t1 + 1e-9, 1.0 / rate)
    R = attitude_at(mission, t)
    yaw = np.unwrap(yaw_of(R))
    # yaw rate: central differences of the IMU yaw, smoothed over ~1 s
    rate_raw = np.gradient(yaw, t) if len(t) > 1 else np.zeros_like(t)
    k = max(1, int(round(rate)))
    turn = np.convolve(np.abs(rate_raw), np.ones(k) / k, mode="same")
    v = np.column_stack([np.interp(t, track.t, track.vel[:, j]) for j in range(2)])
    pos = np.column_stack([np.interp(t, track.t, track.pos[:, j]) for j in range(2)])
    jm = np.clip(np.searchsorted(mission.motors.t, t, side="right") - 1, 0, len(mission.motors.t) - 1)
    u = mission.motors.u[jm]
    side = mission.thruster_side()
    stb, port = side > 0, side < 0
    if stb.any() and port.any():
        diff = np.abs(u[:, stb].mean(axis=1) - u[:, port].mean(axis=1))
    else:
        diff = np.zeros(len(t))
    vals = {
        "turn_rate": turn,
        "speed": np.linalg.norm(v, axis=1),
        "thrust": np.abs(u).mean(axis=1),
        "thrust_difference": diff,
        "reverse": (u < -0.05).mean(axis=1),
        "elapsed": t - mission.t0,
        "heading": np.mod(yaw + theta_e, 2 * np.pi),
    }
    if mission.usbl_station is not None:
        st = np.asarray(mission.usbl_station, float)
        vals["station_distance"] = np.linalg.norm(pos - st[:2], axis=1)
    return ConditionSignals(t, vals)


# ---------------------------------------------------------------- statistics
def _acf(x: np.ndarray, nlag: int) -> np.ndarray:
    x = x - x.mean()
    d = float(np.dot(x, x))
    if d <= 0:
        return np.zeros(nlag + 1)
    n = len(x)
    f = np.fft.rfft(x, 2 * n)
    ac = np.fft.irfft(f * np.conj(f))[: nlag + 1] / d
    return ac


def effective_n(x: np.ndarray, y: np.ndarray) -> float:
    """Effective number of independent pairs for the correlation of two autocorrelated
    series: ``n / (1 + 2 sum_k (n-k)/n rho_x(k) rho_y(k))`` over lags up to n/5 (Bartlett;
    Pyper & Peterman 1998)."""
    n = len(x)
    nlag = max(1, n // 5)
    k = np.arange(1, nlag + 1)
    s = float(np.sum((n - k) / n * _acf(x, nlag)[1:] * _acf(y, nlag)[1:]))
    return float(np.clip(n / (1.0 + 2.0 * s), 3.0, n))


def spearman_autocorr(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float]:
    """Spearman's rho, its two-sided p-value with the effective sample size, and n_eff.

    The autocorrelation of ``y`` is taken from its ranks with the part explained by ``x``
    removed, so that a real dependence on an autocorrelated condition does not count as
    autocorrelation of the residuals (under the null hypothesis nothing is removed).
    """
    rx, ry = stats.rankdata(x), stats.rankdata(y)
    if np.std(rx) == 0 or np.std(ry) == 0:
        return 0.0, 1.0, float(len(x))
    rho = float(np.corrcoef(rx, ry)[0, 1])
    ry_res = ry - rho * (np.std(ry) / np.std(rx)) * (rx - rx.mean())
    ne = effective_n(rx, ry_res)
    tt = rho * np.sqrt(max(ne - 2, 1.0) / max(1 - rho ** 2, 1e-12))
    p = float(2 * stats.t.sf(abs(tt), max(ne - 2, 1.0)))
    return rho, p, ne


def circular_linear(theta: np.ndarray, y: np.ndarray) -> tuple[float, float, float, float]:
    """Mardia's circular-linear rank correlation R (0..1) of ``y`` with angle ``theta``,
    its p-value (``n_eff R^2 ~ chi2(2)``), n_eff, and the angle where ``y`` peaks."""
    ry = stats.rankdata(y)
    c, s = np.cos(theta), np.sin(theta)
    if np.std(ry) == 0 or np.std(c) == 0 or np.std(s) == 0:
        return 0.0, 1.0, float(len(y)), float("nan")
    rc = np.corrcoef(ry, c)[0, 1]
    rs = np.corrcoef(ry, s)[0, 1]
    rcs = np.corrcoef(c, s)[0, 1]
    R2 = max((rc ** 2 + rs ** 2 - 2 * rc * rs * rcs) / max(1 - rcs ** 2, 1e-12), 0.0)
    # direction of the peak: regress ranks on (cos, sin); residual ranks for the autocorrelation
    A = np.column_stack([np.ones_like(c), c, s])
    coef = np.linalg.lstsq(A, ry, rcond=None)[0]
    ry_res = ry - A @ coef
    ne = min(effective_n(ry_res, c), effective_n(ry_res, s))
    p = float(stats.chi2.sf(ne * R2, 2))
    return float(np.sqrt(R2)), p, ne, float(np.mod(np.arctan2(coef[2], coef[1]), 2 * np.pi))


@dataclass
class ConditionEffect:
    """How the residuals of one series relate to one condition.

    ``rho``: Spearman rank correlation (for the heading: circular-linear R, >= 0, with the
    worst heading in ``peak``); ``p_value`` / ``p_adjusted`` (Holm); ``ratio``: mean NIS
    per dof in the top quartile of the condition over that in the bottom quartile (for the
    heading: the quarter of headings around ``peak`` over the opposite quarter).
    ``quartiles`` (4,) condition bin edges' centres and ``binned`` (4,) mean NIS per dof.
    """
    series: str
    condition: str
    rho: float
    p_value: float
    n: int
    n_eff: float
    ratio: float
    bin_centres: np.ndarray
    binned: np.ndarray
    peak: float = float("nan")
    p_adjusted: float = float("nan")

    @property
    def phrase(self) -> str:
        if self.condition == "heading":
            return f"on headings near {np.degrees(self.peak):.0f} deg"
        hi, lo = PHRASES[self.condition]
        return hi if self.rho > 0 else lo

    def to_json(self) -> dict:
        return {"series": self.series, "condition": self.condition, "rho": self.rho,
                "p_value": self.p_value, "p_adjusted": self.p_adjusted, "n": self.n,
                "n_eff": self.n_eff, "ratio": self.ratio, "phrase": self.phrase}


def _binned(x: np.ndarray, y: np.ndarray, nb: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Mean of ``y`` per quantile bin of ``x`` (bin centres = mean ``x``); a condition that
    is mostly at one value (e.g. no reverse command) gets a bin for that value and bins for
    the rest."""
    lo = float(np.min(x))
    at_lo = x <= lo + 1e-12
    if at_lo.mean() > 1.0 / nb and (~at_lo).any():
        rest = x[~at_lo]
        k = max(1, min(nb - 1, len(np.unique(rest))))
        q = np.quantile(rest, np.linspace(0, 1, k + 1))
        j = np.where(at_lo, 0, 1 + np.clip(np.searchsorted(q, x, side="right") - 1, 0, k - 1))
        nbins = k + 1
    else:
        q = np.quantile(x, np.linspace(0, 1, nb + 1))
        j = np.clip(np.searchsorted(q, x, side="right") - 1, 0, nb - 1)
        nbins = nb
    cnt = np.bincount(j, minlength=nbins)
    ok = cnt > 0
    m = np.bincount(j, y, minlength=nbins)[ok] / cnt[ok]
    c = np.bincount(j, x, minlength=nbins)[ok] / cnt[ok]
    return c, m


def relate(series: str, t: np.ndarray, nis_per_dof: np.ndarray, signals: ConditionSignals,
           memory: float = 5.0, min_n: int = 12) -> list[ConditionEffect]:
    """Correlate one residual series (``nis_per_dof`` (n,) at times ``t``) with every
    condition averaged over the ``memory`` s before each residual."""
    t = np.asarray(t, float)
    y = np.asarray(nis_per_dof, float)
    ok = np.isfinite(y)
    t, y = t[ok], y[ok]
    out: list[ConditionEffect] = []
    if len(t) < min_n:
        return out
    for name in signals.values:
        x = signals.mean_before(name, t, memory)
        good = np.isfinite(x)
        if good.sum() < min_n:
            continue
        xg, yg = x[good], y[good]
        if name in CIRCULAR:
            R, p, ne, peak = circular_linear(xg, yg)
            d = np.abs(np.angle(np.exp(1j * (xg - peak))))
            near, far = d < np.pi / 4, d > 3 * np.pi / 4
            ratio = (float(yg[near].mean() / yg[far].mean())
                     if near.any() and far.any() and yg[far].mean() > 0 else float("nan"))
            centres = np.linspace(0, 2 * np.pi, 9)[:-1] + np.pi / 8
            jb = np.clip((xg // (np.pi / 4)).astype(int), 0, 7)
            cnt = np.bincount(jb, minlength=8)
            with np.errstate(invalid="ignore", divide="ignore"):
                binned = np.bincount(jb, yg, minlength=8) / cnt
            out.append(ConditionEffect(series, name, R, p, int(len(yg)), ne, ratio, centres,
                                       binned, peak))
            continue
        if np.ptp(xg) <= 1e-12:
            continue
        rho, p, ne = spearman_autocorr(xg, yg)
        centres, binned = _binned(xg, yg)
        lo, hi = binned[0], binned[-1]
        if rho < 0:
            lo, hi = hi, lo
        ratio = float(hi / lo) if np.isfinite(lo) and lo > 0 else float("nan")
        out.append(ConditionEffect(series, name, rho, p, int(len(yg)), ne, ratio, centres, binned))
    return out


def adjust(effects: list[ConditionEffect]) -> list[ConditionEffect]:
    """Fill in Holm-adjusted p-values over all effects given (in place) and return them."""
    adj = holm(np.array([e.p_value for e in effects]))
    for e, a in zip(effects, adj):
        e.p_adjusted = float(a)
    return effects


def in_words(effects: list[ConditionEffect], alpha: float = 0.05, max_items: int = 3) -> str:
    """A sentence such as "Errors grow in turns and at high thrust." from the significant
    conditions (Holm-adjusted p < ``alpha``) with errors growing (ratio > 1.2), strongest
    first; one phrase per condition."""
    sig = [e for e in effects if e.p_adjusted < alpha and (not np.isfinite(e.ratio) or e.ratio > 1.2)]
    sig.sort(key=lambda e: (-abs(e.rho), e.p_adjusted))
    seen, phrases = set(), []
    for e in sig:
        if e.condition in seen:
            continue
        seen.add(e.condition)
        phrases.append(e.phrase)
        if len(phrases) == max_items:
            break
    if not phrases:
        return "Errors show no significant dependence on turns, speed, heading, thrust, " \
               "reverse commands, distance to the station or elapsed time."
    txt = phrases[0] if len(phrases) == 1 else ", ".join(phrases[:-1]) + " and " + phrases[-1]
    return f"Errors grow {txt}."
