"""The fixes of :class:`aqfg.fg.fastlag.LagWindow` (GNSS positions and USBL range/bearing
with GTSAM's Huber reweighting, and the depth readings of a non-planar vehicle): their table
per window knot, their Gauss-Newton terms, and their (re)linearisation into the window's held
quadratic."""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from aqfg.fg import factors as fc
from aqfg.fg.robust import huber_cost, huber_scalar, huber_weight, row_norms
from aqfg.model.measurements import range_bearing


class WindowFixes:
    """Mixin of :class:`aqfg.fg.fastlag.LagWindow`: its fixes (times in s, NED positions
    in m)."""

    P: int
    n: int
    s: Any
    planar: bool
    z: np.ndarray
    H: np.ndarray
    b: np.ndarray
    kt: list[float]
    fx: list[list | None]
    FXL: list[list[float]]
    k_gnss: float | None
    k_usbl: float | None
    tab_g: tuple
    tab_u: tuple
    tab_d: tuple
    station: np.ndarray | None

    def index_at(self, t: float) -> int | None:
        """Window index of the knot at time ``t`` (None: not in the window)."""
        return next((j for j, tk in enumerate(self.kt) if abs(tk - t) < 1e-9), None)

    def _depth(self, t_lo: float, t_hi: float) -> None:
        """The depth reading nearest to the newest knot among those in (t_lo, t_hi] (one
        per knot, as the batch's): ``down + vd * dt`` of the knot, the reading ``dt`` s
        from it, its variance widened by the process noise's position variance over
        ``dt``; linear, so added to the held quadratic once."""
        dt_, dz = self.tab_d
        if self.planar or not len(dt_):
            return
        a, b = int(dt_.searchsorted(t_lo + 1e-9)), int(dt_.searchsorted(t_hi + 1e-9))
        if b <= a:
            return
        tk = self.kt[-1]
        j = a + int(np.argmin(np.abs(dt_[a:b] - tk)))
        e = float(dt_[j] - tk)
        var = self.s.graph.sensors.depth_sigma ** 2 + float(self.s.graph.process.cov(abs(e))[2, 2])
        o = self.P + 6 * (self.n - 1)
        J = np.zeros(6)
        J[2], J[5] = 1.0, e
        self.H[o:o + 6, o:o + 6] += np.outer(J, J) / var
        self.b[o:o + 6] -= (float(dz[j]) / var) * J

    def _take_fixes(self, t_lo: float, t_hi: float, usbl: bool = True,
                    usbl_scale: float = 1.0) -> None:
        """The fixes in (t_lo, t_hi] onto the newest knot, linearised at its estimate
        (``usbl`` False: its GNSS fixes only; ``usbl_scale`` multiplies its USBL sigmas)."""
        self._depth(t_lo, t_hi)
        gt, gz, gs = self.tab_g
        lo, hi = t_lo + 1e-9, t_hi + 1e-9
        a, b = int(gt.searchsorted(lo)), int(gt.searchsorted(hi))
        ut, uz, us = self.tab_u
        c, d = int(ut.searchsorted(lo)), int(ut.searchsorted(hi))
        if not usbl:
            d = c
        if b <= a and d <= c:
            self.fx.append(None)
            self.FXL.append([math.nan] * 3)
            return
        self.fx.append([gz[a:b], gs[a:b], uz[c:d],
                        us[c:d] if usbl_scale == 1.0 else us[c:d] * usbl_scale, None, None])
        self.FXL.append([0.0] * 3)
        self._set_fix(self.n - 1)

    def fix_terms(self, i: int, x: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """Cost (Huber), gradient (3,) and Gauss-Newton block (3, 3) of the fixes of window
        knot ``i`` at position ``x`` (NED, m), Huber weights at ``x``."""
        f = self.fx[i]
        assert f is not None
        gz, gs, uz, us = f[:4]
        if len(gz) == 1 and not len(uz):
            return self._gnss1(x, gz[0], float(gs[0]))
        if len(uz) == 1 and not len(gz):
            return self._usbl1(x, uz[0], us[0])
        Hk = np.zeros((3, 3))
        gk = np.zeros(3)
        cost = 0.0
        if len(gz):
            r = (x[:2] - gz) / gs[:, None]
            d = row_norms(r)
            w = huber_weight(d, self.k_gnss)
            cost += float(np.sum(huber_cost(d, self.k_gnss)))
            Hk[0, 0] = Hk[1, 1] = float(np.sum(w / gs ** 2))
            gk[:2] = np.sum((w / gs)[:, None] * r, axis=0)
        if len(uz):
            h, Hd = range_bearing(np.broadcast_to(x[:3] - self.station, (len(uz), 3)))
            raw = h - uz
            raw[:, 1] = fc.wrap_angle(raw[:, 1])
            r = raw / us
            J = Hd / us[:, :, None]
            d = row_norms(r)
            w = huber_weight(d, self.k_usbl)
            cost += float(np.sum(huber_cost(d, self.k_usbl)))
            Jt = J.transpose(0, 2, 1)
            Hk += np.einsum("k,kij->ij", w, np.matmul(Jt, J))
            gk += np.einsum("k,kij,kj->i", w, Jt, r)
        return cost, gk, Hk

    def _gnss1(self, x: np.ndarray, z: np.ndarray, s: float):
        """:meth:`fix_terms` of one GNSS fix, in scalars (numpy calls cost microseconds)."""
        r0, r1 = (float(x[0]) - float(z[0])) / s, (float(x[1]) - float(z[1])) / s
        d = math.hypot(r0, r1)
        w, cost = huber_scalar(d, self.k_gnss)
        Hk = np.zeros((3, 3))
        Hk[0, 0] = Hk[1, 1] = w / (s * s)
        return cost, np.array([w * r0 / s, w * r1 / s, 0.0]), Hk

    def _usbl1(self, x: np.ndarray, z: np.ndarray, sig: np.ndarray):
        """:meth:`fix_terms` of one USBL fix (range, bearing; :func:`range_bearing`)."""
        assert self.station is not None
        dn, de, dd = (float(x[0] - self.station[0]), float(x[1] - self.station[1]),
                      float(x[2] - self.station[2]))
        rng = math.sqrt(dn * dn + de * de + dd * dd)
        rh2 = dn * dn + de * de
        sr, sb = float(sig[0]), float(sig[1])
        r0 = (rng - float(z[0])) / sr
        r1 = float(fc.wrap_angle(math.atan2(de, dn) - float(z[1]))) / sb
        d = math.hypot(r0, r1)
        w, cost = huber_scalar(d, self.k_usbl)
        rr, hh = max(rng, 1e-9), max(rh2, 1e-12)
        J = np.array([[dn / rr / sr, de / rr / sr, dd / rr / sr],
                      [-de / hh / sb, dn / hh / sb, 0.0]])
        return cost, w * (J[0] * r0 + J[1] * r1), w * (J.T @ J)

    def _set_fix(self, i: int) -> None:
        """(Re)linearise the fixes of window knot ``i`` at its estimate."""
        f = self.fx[i]
        assert f is not None
        o = self.P + 6 * i
        if len(f[0]) == 1 and not len(f[2]):
            return self._set_gnss1(i, f, o)
        x = self.z[o:o + 3].copy()
        _, gk, Hk = self.fix_terms(i, x)
        bk = gk - Hk @ x
        if f[4] is not None:
            self.H[o:o + 3, o:o + 3] += Hk - f[4]
            self.b[o:o + 3] += bk - f[5]
        else:
            self.H[o:o + 3, o:o + 3] += Hk
            self.b[o:o + 3] += bk
        f[4], f[5] = Hk, bk
        self.FXL[i] = x.tolist()

    def _set_gnss1(self, i: int, f: list, o: int) -> None:
        """:meth:`_set_fix` of a knot with one GNSS fix, relinearised, in Python floats: the
        same numbers as the matrix form (``Hk = diag(h, h, 0)``, ``gk = (g0, g1, 0)``: the
        zero entries change nothing)."""
        x0, x1, x2 = self.z[o:o + 3].tolist()
        gz, s = f[0][0], float(f[1][0])
        r0, r1 = (x0 - float(gz[0])) / s, (x1 - float(gz[1])) / s
        d = math.hypot(r0, r1)
        k = self.k_gnss
        w = 1.0 if k is None or d <= k else k / d
        h = w / (s * s)
        g0, g1 = w * r0 / s, w * r1 / s
        z0 = 0.0 * x0 + 0.0 * x1 + 0.0 * x2          # (Hk x)'s zero terms (NaN with x)
        b0, b1, b2 = g0 - (h * x0 + z0), g1 - (h * x1 + z0), 0.0 - z0
        Hp, bp = f[4], f[5]
        H, b = self.H, self.b
        if Hp is None:
            H[o, o] += h
            H[o + 1, o + 1] += h
            b[o] += b0
            b[o + 1] += b1
            b[o + 2] += b2
        else:
            H[o, o] += h - Hp[0, 0]
            H[o + 1, o + 1] += h - Hp[1, 1]
            b[o] += b0 - bp[0]
            b[o + 1] += b1 - bp[1]
            b[o + 2] += b2 - bp[2]
        Hk = np.zeros((3, 3))
        Hk[0, 0] = Hk[1, 1] = h
        f[4], f[5] = Hk, np.array([b0, b1, b2])
        self.FXL[i] = [x0, x1, x2]


    def readmit_usbl(self, t: float) -> bool:
        """Add the USBL fixes at time ``t`` to their knot (one left out by the caller's gate,
        still in the window); False when the knot has left the window."""
        i = self.index_at(t)
        if i is None:
            return False
        ut, uz, us = self.tab_u
        c, d = int(ut.searchsorted(t - 1e-9)), int(ut.searchsorted(t + 1e-9))
        if d <= c:
            return False
        f = self.fx[i]
        if f is None:
            gz, gs = self.tab_g[1], self.tab_g[2]
            self.fx[i] = [gz[0:0], gs[0:0], uz[c:d], us[c:d], None, None]
        else:
            f[2], f[3] = uz[c:d], us[c:d]
        self._set_fix(i)
        return True

    def take_fixes(self, usbl: bool = True, usbl_scale: float = 1.0) -> None:
        """The fixes since the knot before the newest onto the newest (after
        ``add(..., take_fixes=False)``); ``usbl`` False leaves its USBL fixes out,
        ``usbl_scale`` multiplies their sigmas."""
        self._take_fixes(self.kt[-2], self.kt[-1], usbl, usbl_scale)

