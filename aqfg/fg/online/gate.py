"""The online smoother's USBL gate: a USBL fix whose range and bearing innovation against the
model's prediction is beyond ``FGSettings.online.gate_usbl`` (chi-square(2)) is left out,
as the EKF's gate does (:mod:`aqfg.ekf.window`); the fixes' statistics also tell whether a
held model fails (:mod:`aqfg.fg.online.policy`)."""
from __future__ import annotations

import math

import numpy as np

from aqfg.data.mission import Mission
from aqfg.fg import noise
from aqfg.fg.common import robust_fix_table
from aqfg.fg.online.adapt import NoiseAdapter


class UsblGate:
    """The fix tables of one mission and the gate's state.

    ``fixes`` (:func:`aqfg.fg.common.robust_fix_table`), the USBL table and ``rejected``
    (USBL fix time -> left out) outlive a replay; ``taken_m2`` (the statistic of the fixes
    taken), ``rejects`` (consecutive USBL fixes left out) and ``forced_scale`` (the sigma
    factor of a fix taken by the count) start again at each (re)start (:meth:`restart`)."""

    def __init__(self, mission: Mission, settings):
        self.settings = settings
        self.rejected: dict[float, bool] = {}
        self.set_mission(mission)
        self.restart()

    def restart(self) -> None:
        self.taken_m2: list[float] = []
        self.rejects = 0
        self.forced_scale = 1.0

    def set_mission(self, mission: Mission) -> None:
        """The tables of ``mission`` (a newer copy in live use)."""
        self.fixes = robust_fix_table(mission, self.settings)
        self.usbl_tab = self._table(mission)

    def _table(self, mission: Mission) -> dict:
        """Per USBL fix time (rounded to the microsecond): range, bearing, range variance,
        bearing sigma, the previous fix's per-axis variance and the station, for
        :meth:`check` (in Python floats: it runs at every USBL update). Empty without
        USBL or with the gate off."""
        u, s = mission.usbl, self.settings
        if u is None or not len(u.t) or not math.isfinite(s.online.gate_usbl):
            return {}
        t, _, var, _ = self.fixes
        st = tuple(float(c) for c in np.asarray(mission.usbl_station, float)[:3])
        out = {}
        for k in range(len(u.t)):
            i = int(t.searchsorted(u.t[k] - 1e-6))
            sr, sb = s.graph.sensors.usbl_sigmas(float(u.range[k]))
            out[round(float(u.t[k]), 6)] = (float(u.range[k]), float(u.bearing[k]),
                                            float(sr) ** 2, float(sb),
                                            float(var[i - 1]) if i > 0
                                            else s.graph.sensors.gnss_sigma ** 2, st)
        return out

    def is_usbl(self, t_fix: float) -> bool:
        """Whether a gated USBL fix is at ``t_fix``."""
        return round(float(t_fix), 6) in self.usbl_tab

    def innovation(self, t_fix: float, x_pred: np.ndarray) -> tuple[float, float] | None:
        """Squared horizontal innovation (m^2) of the fix at ``t_fix`` (the first, GNSS
        before USBL) against ``x_pred``, and its per-axis variance; None: no fix there. In
        scalars: this runs at every update (numpy calls cost microseconds each)."""
        t, pos, var, _ = self.fixes
        i = int(t.searchsorted(t_fix - 1e-6))
        if i >= len(t) or abs(float(t[i]) - t_fix) > 1e-6:
            return None
        p0, p1 = pos[i, :2].tolist()
        x0, x1 = x_pred[:2].tolist()
        return (p0 - x0) ** 2 + (p1 - x1) ** 2, float(var[i])

    def left_out(self, t_fix: float) -> bool:
        """The fix :meth:`innovation` reads at ``t_fix`` is a USBL fix the gate left out."""
        t, _, _, is_u = self.fixes
        i = int(t.searchsorted(t_fix - 1e-6))
        return (i < len(t) and bool(is_u[i])
                and bool(self.rejected.get(float(t_fix), False)))

    def check(self, t_fix: float, dt: float, x_pred: np.ndarray, noise_q: NoiseAdapter,
              held: bool) -> bool:
        """True when the USBL fix at ``t_fix`` is to be left out: its range and bearing
        innovation against the model's prediction ``x_pred`` is beyond
        ``settings.online.gate_usbl`` (chi-square(2)), and fewer than
        ``settings.online.max_rejects`` USBL fixes in a row were left out before it (the EKF's rule,
        :mod:`aqfg.ekf.window`). Recorded in ``rejected``.

        The prediction's per-axis variance is that of the process noise in use over the
        interval (``noise_q``), plus the previous fix's (GNSS sigma^2, or a USBL fix's
        tangential one: an upper bound along its range); the range and the tangential
        innovation each add it to their own sensor variance. In range and bearing, not as
        a position: the USBL outliers are mostly in range (7-16 m on a 0.15-m range
        sigma), which a position's isotropic tangential variance (2.6 m at 100 m) hides.

        No gate while the parameters are ``held`` at their start values (before the first
        batch): the prediction of a model whose heading is not known yet is 7-22 m off on
        a crop of `otter-dev-calm-b`, and good fixes were left out. A track can be off
        after that too (a turn the model gets wrong): the fixes left out are seen again by
        the engine's review once later fixes are in. And only where the model has shown
        what it is: the process noise adapted up (the model fails, the dynamics are loose,
        and the Huber loss no longer bounds an outlier's pull), or the last fixes taken
        all within the 99 % quantile (the model holds; a burst of outliers would drag it).
        With the noise still nominal while a model starts to fail (the adaptation lags),
        good fixes 5-22 m from the prediction were left out on Otter crops and the causal
        track suffered (`otter-dev-current-weakprop` from 150 s: 2.22 -> 3.45 m;
        `otter-dev-calm-a` from 300 s, whose released constants ran off: 3.39 -> 11.3 m)."""
        s = self.settings
        self.forced_scale = 1.0
        if dt <= 0:
            return False
        m2 = self._statistic(t_fix, dt, x_pred, noise_q)
        if m2 is None:
            return False
        usbl = self.is_usbl(t_fix)
        # the model has shown it fails (the process noise adapted up) or that it does not
        # (the last fixes taken were all within the 99 % quantile)
        recent = self.taken_m2[-s.online.adapt_window:]
        known = noise_q.q_scale > 1.0 or (len(recent) >= 3 and max(recent) <= noise.CHI2_2_99)
        gating = usbl and known and not held
        forced = gating and self.rejects >= s.online.max_rejects
        out = gating and not forced and m2 > s.online.gate_usbl
        # a fix taken by the count enters at the robust loss's edge: its sigmas scaled so
        # that its whitened residual at the prediction is the Huber threshold, a pull
        # falling with the residual (k^2 / |r|). The Huber loss bounds a fix's pull
        # (k / sigma), not how far it moves a track loosened by the fixes left out before
        # it: a 12-m range outlier forced after three moved the numpy engine's track 9 m
        # and its current 0.5 m/s, and the good fixes after it were left out
        # (docs/independent-vehicle.md). A track that is off gets to the fixes too: by the
        # adaptation (the forced fixes' innovations) and the review of those left out.
        if forced and m2 > s.online.gate_usbl:
            k = s.graph.sensors.robust_k if s.graph.sensors.robust != "none" else 1.0
            self.forced_scale = max(1.0, math.sqrt(self.m2(t_fix, x_pred, None)) / k)
        if not out and not forced:          # (a fix taken by the count says nothing)
            self.taken_m2.append(m2)
            if len(self.taken_m2) > 4 * s.online.adapt_window:
                del self.taken_m2[:-s.online.adapt_window]
        if usbl:
            self.rejects = self.rejects + 1 if out else 0
            self.rejected[float(t_fix)] = out
        return out

    def _statistic(self, t_fix: float, dt: float, x_pred: np.ndarray,
                   noise_q: NoiseAdapter) -> float | None:
        """The fix's chi-square(2) statistic against the prediction: a USBL fix's in range
        and bearing (:meth:`m2`); a GNSS fix's (never left out) as a position, as the
        adaptation has it (:func:`aqfg.fg.noise.innovation_u`: the previous state as
        uncertain as this fix). GNSS fixes are scored without USBL too: a GNSS-only
        mission's held model is judged by them. None: no fix at ``t_fix``."""
        q = noise_q.q_pos(dt)
        if self.is_usbl(t_fix):
            return self.m2(t_fix, x_pred, noise_q.q_scale * q)
        inn = self.innovation(t_fix, x_pred)
        if inn is None:
            return None
        return noise.innovation_u(inn[0], inn[1], noise_q.q_scale * q)

    def m2(self, t_fix: float, x: np.ndarray, q_pos: float | None) -> float:
        """The gate's statistic (chi-square(2)) of the USBL fix at ``t_fix`` against the
        state ``x``, whose per-axis variance is ``q_pos`` plus the previous fix's
        (:meth:`check`); ``q_pos`` None: the state exact, the sensor's sigmas alone (the
        fix's squared whitened residual at ``x``)."""
        z_r, z_b, sr2, sb, v_prev, (n0, e0, d0) = self.usbl_tab[round(float(t_fix), 6)]
        pv = 0.0 if q_pos is None else q_pos + v_prev
        dn, de, dd = float(x[0]) - n0, float(x[1]) - e0, float(x[2]) - d0
        rh = math.hypot(dn, de)
        er = z_r - math.sqrt(rh * rh + dd * dd)
        et = math.remainder(z_b - math.atan2(de, dn), 2.0 * math.pi) * rh
        return er * er / (sr2 + pv) + et * et / max((rh * sb) ** 2 + pv, 1e-300)

    def readmits(self, t: float, x: np.ndarray) -> bool:
        """A USBL fix left out at ``t`` agrees with its knot's smoothed estimate ``x`` now
        (the same gate, without the prediction's process noise)."""
        return self.m2(t, x, 0.0) <= self.settings.online.gate_usbl
