"""The fixed-lag smoother's window in numpy: the online engine without a Python callback per
factor (:class:`aqfg.fg.fixed_lag.FixedLagSmoother` with ``FGSettings.online_engine =
"numpy"``).

The GTSAM engine (ISAM2 with ``CustomFactor`` s) calls Python for every new and every
relinearised dynamics factor (docs/speed.md). This engine holds the same problem as arrays:

* knots only at fix times, one dynamics factor per fix interval (``ProcessNoise.cov(dt)`` is
  the exact covariance of the model error over any ``dt``, so the statistics are those of
  the 1-s knots; the causal track's intermediate states are the model's prediction, as
  they are with 1-s knots);
* variables ``z = [theta (P), x_0 .. x_{n-1} (6 each)]``: the estimated parameters (the
  layout's groups concatenated) and the window's knots (NED position, velocity);
* factors: the first-knot prior, dynamics (``Model.propagate``, whitened by
  ``W^T W = (q Q(dt))^-1``), the surface constraint of planar vehicles, GNSS position and
  USBL range/bearing fixes with GTSAM's Huber reweighting, parameter priors, removable
  "hold" priors on the parameters, and the marginal of the knots that left the window (a
  dense Gaussian on ``[theta, oldest knot]``, a Schur complement, linearised where the
  knot left, as GTSAM's linear container factor), whose current moves by a Gauss-Markov
  step and whose heading offset by a random-walk step as knots leave (every
  ``WALK_EVERY`` s of them; ``FGSettings.online_current_walk``, ``online_heading_walk``,
  :meth:`LagWindow._walk`);
* per update one Gauss-Newton step (as one ISAM2 iteration): each dynamics factor keeps
  its linearisation (prediction and Jacobians at ``(x0_lin, theta_lin)``) until its first
  knot or the parameters moved past ``FGSettings.relin_*`` from it; the fixes (cheap) are
  relinearised at every step. The system is a few knots x 6 + P: one dense Cholesky; the
  parameters' marginal covariance is the inverse's parameter block. The parameters are
  projected into the layout's bounds after each step (as the batch LM).
* with the compiled kernel, a dynamics factor's linearisation and swap into the quadratic
  (``linearise_into``), the step (``window_step``) and the marginalisation
  (``schur_drop``) are one C++ call each; the numpy code here is their reference
  (``FGSettings.fast_cpp_block=False``; docs/speed.md).

:meth:`LagWindow.unsupported` says why a configuration needs the GTSAM engine
(measurement effects such as a lever arm or USBL distortions, a Cauchy loss, random-walk
parameters, a thrust lag). Depth readings of a non-planar vehicle: the reading nearest to
each knot, as the batch's (:meth:`LagWindow._depth`).
"""
from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy.linalg.lapack import dposv as _posv

from aqfg.fg import factors as fc
from aqfg.fg.robust import huber_cost, huber_scalar, huber_weight, row_norms
from aqfg.model.measurements import range_bearing
from aqfg.model.vehicle import compiled_kernel


def _kernel():
    """The compiled kernel module (the caller checked that it is built; looked up per use,
    not held, so that a window stays deep-copyable)."""
    cpp = compiled_kernel()
    assert cpp is not None
    return cpp


_EMPTY = np.zeros(0)
# s: the current's walk is applied to the marginal in steps of at least this (one step
# costs ~90-170 us; its correlation time is minutes, FGSettings.online_current_walk)
WALK_EVERY = 30.0


def _kernel_factory(geometry, cols):
    """A function ``steps -> f`` building :meth:`LagWindow._propagator`'s kernel calls with
    the geometry's arrays converted once (a plain function: the window stays
    deep-copyable; the compiled functions are looked up per call of the factory)."""
    from aqfg.model.params import N_DYN
    dirs = np.ascontiguousarray(geometry.dirs, float)
    side = np.ascontiguousarray(geometry.side, float)
    planar = bool(geometry.planar)
    nd = N_DYN

    def make(steps):
        cpp = _kernel()
        kernel = cpp.propagate
        args = (np.ascontiguousarray(steps.h, float), np.ascontiguousarray(steps.warm, np.uint8),
                np.ascontiguousarray(steps.R, float), np.ascontiguousarray(steps.dem, float),
                np.ascontiguousarray(steps.tm, float), dirs, side, planar)

        def f(x0, p):
            return kernel(x0, p[:nd], *args)
        if cols is not None:
            into = cpp.linearise_into

            def block_into(x0, p, th, W, o, H, b, Hb, bb):
                return into(x0, p[:nd], th, cols, W, o, H, b, Hb, bb, *args)
            f.into = block_into  # type: ignore[attr-defined]
        return f
    return make


class LagWindow:
    """The window's factors and estimate (see the module docstring). Times in s, states
    ``[n, e, d, vn, ve, vd]``.

    The factors whose linearisation is held (dynamics at their linearisation point, the
    surface constraint, the priors and the marginal) sum to one quadratic
    ``1/2 z^T H z + b^T z`` in the window's variables ``z`` (absolute values), kept up to
    date incrementally: a new knot extends it, a relinearised dynamics factor swaps its
    contribution, a knot leaving the window is eliminated from it (Schur complement, with
    the fixes on that knot linearised there). The fixes (Huber-weighted) and the hold
    priors are added at each step.
    """

    def __init__(self, model, layout: fc.ParamLayout, settings, mission, lag: float,
                 prior_sigma: np.ndarray, hold_sigma: np.ndarray | None,
                 x0: np.ndarray, first_mean: np.ndarray, first_sigma: np.ndarray,
                 t0: float, kid0: int, prior_mean: np.ndarray | None = None):
        s = settings
        self.model, self.layout, self.s = model, layout, s
        self.planar = bool(mission.planar)
        self.lag = float(lag)
        groups = layout.groups
        th0 = np.concatenate([layout.initial(g) for g in groups]) if groups else np.zeros(0)
        P = self.P = len(th0)
        self.th0 = th0.copy()
        # the parameters' prior centre (default: the start values th0, where they are held)
        self.mu0 = th0.copy() if prior_mean is None else np.asarray(prior_mean, float).copy()
        self.lo = np.concatenate([layout.bounds(g)[0] for g in groups]) if groups else np.zeros(0)
        self.hi = np.concatenate([layout.bounds(g)[1] for g in groups]) if groups else np.zeros(0)
        self.slices = {}
        c = 0
        for g in groups:
            self.slices[g] = slice(c, c + layout.dim(g))
            c += layout.dim(g)
        ncol = len(model.dyn_columns())
        self.Jsel = np.zeros((ncol, P))          # kernel J_p columns -> theta
        for g in layout.dyn_groups():
            for j, pos in enumerate(layout.dyn_pos[g]):
                if pos >= 0:
                    self.Jsel[pos, self.slices[g].start + j] = 1.0
        self.pidx = np.arange(P)
        self.names = layout.estimated
        jc = [int(np.flatnonzero(self.Jsel[:, j])[0]) if self.Jsel[:, j].any() else -1
              for j in range(P)]
        self.jcols = np.array(jc, int) if all(c >= 0 for c in jc) else None
        # the same columns as a slice (a view) when they are consecutive
        self._jsl = (slice(jc[0], jc[0] + P) if P and self.jcols is not None
                     and jc == list(range(jc[0], jc[0] + P)) else None)
        self.hold_w = None if hold_sigma is None else 1.0 / np.asarray(hold_sigma, float) ** 2
        sn = s.sensors
        self.k_gnss = (None if sn.robust == "none" or "gnss" not in sn.robust_on
                       else sn.robust_k_gnss)
        self.k_usbl = (None if sn.robust == "none" or "usbl" not in sn.robust_on
                       else sn.robust_k)
        self.surf_w = 1.0 / np.asarray(s.surface_sigma, float) ** 2
        self.relin_th = s.fast_relin_param * np.array([model.spec(n).scale
                                                       for n in layout.estimated])
        self._relin_th_l = self.relin_th.tolist()
        self.set_mission(mission)
        self._wcache: dict = {}
        self._dyn_idx: dict = {}       # (N, knot) -> flat indices of a dynamics block in H
        self._fp: tuple | None = None  # (theta bytes, full_params) of the last call
        self._rhs_cols = (self.pidx, self.pidx + 1)
        self._keep: dict = {}          # N -> the variables left when the oldest knot goes
        self._rhs: dict = {}           # N -> [0, I_P; 0, 0]: the step's right-hand sides
        self._kern: Callable | None = None     # steps -> kernel calls (_kernel_factory)
        # kernel columns of theta for the C++ block (kernel.hpp ``linearise``); None: numpy
        cpp = compiled_kernel()
        # the window's solve and Schur complement in C++ (kernel window_step, schur_drop;
        # the numpy code below is their reference)
        self._cwin = (cpp is not None and hasattr(cpp, "window_step")
                      and self.s.fast_cpp_block)
        self._lcols = (np.ascontiguousarray(self.jcols, np.int64)
                       if self.jcols is not None and P and cpp is not None
                       and hasattr(cpp, "linearise_into") and self.s.fast_cpp_block else None)
        self.last_ok = True
        # the estimate and the held quadratic
        self.z = np.concatenate([th0, np.asarray(x0, float)])
        self.n = 1
        self.kt = [float(t0)]
        self.kid = [int(kid0)]
        N = P + 6
        self.H = np.zeros((N, N))
        self.b = np.zeros(N)
        wp = 1.0 / np.asarray(prior_sigma, float) ** 2
        self.H[self.pidx, self.pidx] += wp
        self.b[:P] -= wp * self.mu0
        wf = 1.0 / np.asarray(first_sigma, float) ** 2
        ii = P + np.arange(6)
        self.H[ii, ii] += wf
        self.b[ii] -= wf * np.asarray(first_mean, float)
        self._surface(0)
        # dynamics factors, one per interval: [steps, W, H_i, b_i, kernel]; their
        # linearisation points
        self.dyn: list[list] = []
        # (Python lists of float lists: a few knots, read and written at every update)
        self.X0L: list[list[float]] = []
        self.THL: list[list[float]] = []
        self.last_pred = np.asarray(x0, float)
        # fixes per window knot: [gnss z, sigma, usbl z, sigma, H_k, b_k] or None, and the
        # position each knot's fixes are linearised at (NaN: no fix)
        self.fx: list[list | None] = []
        self.FXL: list[list[float]] = []
        self.cov = np.full((P, P), np.nan)
        # random walk of the current and the heading offset (FGSettings.online_current_walk,
        # online_heading_walk): variance per second of each estimated parameter that walks
        cw = float(s.online_current_walk)
        hw = float(s.online_heading_walk)
        rate = {"s_x": cw, "s_y": cw, "theta_e": hw}
        wv = [j for j, n in enumerate(layout.estimated)
              if rate.get(n, 0.0) > 0 and n in layout.names.get("variable", ())]
        self._walk_idx = np.array(wv, int)
        self._walk_var = np.array([rate[layout.estimated[j]] ** 2 for j in wv])
        # its stationary variance: the current's prior (s.prior_sigma), inf: a plain walk
        self._walk_stat = np.array([float(s.prior_sigma.get(layout.estimated[j], math.inf))
                                    ** 2 for j in wv])
        self._walk_cache: dict = {}
        self._walk_due = 0.0           # s of the marginal's time not walked yet
        self._take_fixes(float(t0) - 1e-6, float(t0))

    # ------------------------------------------------------------------ configuration
    @staticmethod
    def unsupported(model, layout: fc.ParamLayout, mission, settings) -> str:
        """Why this engine cannot run the configuration ("" when it can)."""
        from aqfg.fg.fastlm import _plain_sensors
        from aqfg.model.effects import FixDelayTerm, SensorOffsetTerm, UsblTerm
        if settings.sensors.robust not in ("huber", "none"):
            return f"{settings.sensors.robust} loss"
        if settings.walk_sigma:
            return "random-walk parameters"
        if any(isinstance(e, (SensorOffsetTerm, UsblTerm, FixDelayTerm)) for e in model.effects) \
                or layout.meas_groups("gnss") or layout.meas_groups("usbl") \
                or not _plain_sensors(layout.base):
            return "measurement effects"
        if model.lookback > 0:
            return "thrust lag (warm-up steps between knots)"
        if not model.uses_cpp:
            return "no compiled kernel for this model"
        return ""

    def set_mission(self, mission) -> None:
        """The fix table of ``mission`` (again when a live mission grows)."""
        from aqfg.fg.common import Measurements
        m = Measurements.of(mission, self.s)
        self.tab_g = (m.gnss_t, m.gnss_z, m.gnss_sigma)
        self.tab_u = (m.usbl_t, m.usbl_z, m.usbl_sigma)
        self.tab_d = (m.depth_t, m.depth_z)
        self.station = None if m.station is None else np.asarray(m.station, float)

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
        var = self.s.sensors.depth_sigma ** 2 + float(self.s.process.cov(abs(e))[2, 2])
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

    # ------------------------------------------------------------------ reading
    @property
    def X(self) -> np.ndarray:
        """The window's knot estimates (n, 6) (a view)."""
        return self.z[self.P:].reshape(-1, 6)

    @property
    def th(self) -> np.ndarray:
        return self.z[:self.P]

    def full_params(self) -> np.ndarray:
        """The full parameter vector at the estimate (inside the bounds; a new array)."""
        return self.params_view().copy()

    def params_view(self) -> np.ndarray:
        """:meth:`full_params` without the copy: computed once per parameter estimate, a new
        array each time the estimate changes, never written (callers may keep it)."""
        th = self.z[:self.P]
        key = th.tobytes()
        if self._fp is None or self._fp[0] != key:
            th = np.minimum(np.maximum(th, self.lo), self.hi)
            self._fp = (key, self.layout.full({g: th[sl] for g, sl in self.slices.items()}))
        return self._fp[1]

    def sigma(self) -> np.ndarray:
        """1-sigma of the parameters (marginal of the last step's linearisation)."""
        return np.sqrt(np.maximum(self.cov.diagonal(), 0.0))

    def group_values(self) -> dict[str, np.ndarray]:
        return {g: self.z[sl].copy() for g, sl in self.slices.items()}

    def state(self, kid: int) -> np.ndarray | None:
        """Estimate of the knot with orchestration index ``kid`` (None: not in the window)."""
        try:
            i = self.kid.index(kid)
        except ValueError:
            return None
        o = self.P + 6 * i
        return self.z[o:o + 6].copy()

    # ------------------------------------------------------------------ building
    def _surface(self, k: int) -> None:
        if self.planar:
            o = self.P + 6 * k
            self.H[o + 2, o + 2] += self.surf_w[0]
            self.H[o + 5, o + 5] += self.surf_w[1]

    def _propagator(self, steps):
        """The dynamics factor's kernel over ``steps``: ``f(x0, p) -> (x1, Jx, Jp)``
        (:func:`fc.propagator`), with the vehicle's geometry converted once; with the C++
        block (``FGSettings.fast_cpp_block``) also ``f.into``, the factor linearised and
        swapped into the held quadratic in one call (kernel ``linearise_into``)."""
        if self._kern is None:
            if compiled_kernel() is None or not self.model.uses_cpp:
                return fc.propagator(self.model, steps)
            self._kern = _kernel_factory(self.model.geometry, self._lcols)
        return self._kern(steps)

    def _whitening(self, dt: float, q: float) -> np.ndarray:
        """``W`` with ``W^T W = (q Q(dt))^-1``: ``L^-1 / sqrt(q)`` for ``Q(dt) = L L^T``."""
        key = round(dt, 9)
        W = self._wcache.get(key)
        if W is None:
            W = self._wcache[key] = np.linalg.inv(np.linalg.cholesky(
                self.s.process.cov(dt, self.planar)))
        return W if q == 1.0 else W * (1.0 / math.sqrt(q))

    def dyn_linear(self, i: int, x0: np.ndarray, th: np.ndarray, pred, Jx, Jp, W):
        """Whitened linear model ``J [theta, x_i, x_i+1] + c`` of dynamics factor ``i``
        linearised at ``(x0, th)`` (kernel results ``pred, Jx, Jp``): the negated residual
        ``f(x0, p) - x1`` (the sign leaves the normal equations as they are)."""
        P = self.P
        M = np.empty((6, P + 12))
        M[:, :P] = (Jp[:, self._jsl] if self._jsl is not None else
                    Jp[:, self.jcols] if self.jcols is not None else Jp @ self.Jsel)
        M[:, P:P + 6] = Jx
        M[:, P + 6:] = _MINUS_I6
        c = W @ (pred - M[:, :P + 6] @ np.concatenate([th, x0]))
        return W @ M, c

    def _set_dyn(self, i: int, x0: np.ndarray, th: np.ndarray, pred, Jx, Jp) -> None:
        J, c = self.dyn_linear(i, x0, th, pred, Jx, Jp, self.dyn[i][1])
        Jt = J.T
        self._set_block(i, x0, th, Jt @ J, Jt @ c)

    def _linearise(self, i: int, x0: np.ndarray, th: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Linearise dynamics factor ``i`` at ``(x0, th)`` (full parameters ``p``) into the
        held quadratic, unless the model's prediction is not finite; returns the
        prediction."""
        d = self.dyn[i]
        into = getattr(d[4], "into", None)
        if into is not None:                 # one C++ call (kernel ``linearise_into``)
            H = self.H
            if not H.flags.c_contiguous:
                H = self.H = np.ascontiguousarray(H)
            pred = into(x0, p, th, d[1], self.P + 6 * i, H, self.b, d[2], d[3])
            if all(map(math.isfinite, pred.tolist())):
                self.X0L[i] = x0.tolist()
                self.THL[i] = th.tolist()
            return pred
        pred, Jx, Jp = d[4](x0, p)
        if all(map(math.isfinite, pred.tolist())):
            self._set_dyn(i, x0, th, pred, Jx, Jp)
        return pred

    def _set_block(self, i: int, x0: np.ndarray, th: np.ndarray, Hi: np.ndarray,
                   bi: np.ndarray) -> None:
        """Swap dynamics factor ``i``'s block ``(Hi, bi)`` (over ``[theta, x_i, x_i+1]``)
        into the held quadratic."""
        d = self.dyn[i]
        dH, db = Hi - d[2], bi - d[3]
        H = self.H
        if not H.flags.c_contiguous:
            H = self.H = np.ascontiguousarray(H)
        N = len(H)
        key = (N, i)
        ix = self._dyn_idx.get(key)
        if ix is None:          # rows/columns [theta, x_i, x_i+1] of H, flat and plain
            P, o = self.P, self.P + 6 * i
            r = np.concatenate([np.arange(P), np.arange(o, o + 12)])
            ix = self._dyn_idx[key] = ((r[:, None] * N + r[None, :]).ravel(), r)
        Hf = H.reshape(-1)      # a view (C-contiguous)
        Hf[ix[0]] += dH.ravel()
        self.b[ix[1]] += db
        d[2], d[3] = Hi, bi
        self.X0L[i] = x0.tolist()
        self.THL[i] = th.tolist()

    def add(self, t: float, kid: int, steps, q_scale: float) -> np.ndarray:
        """A new knot at fix time ``t`` after the newest one, with the dynamics factor over
        ``steps`` linearised at the current estimate; returns the model's prediction there
        (the knot's initial value). The caller then adds the fixes in between with
        :meth:`take_fixes`, once (after gating them against the prediction)."""
        P, n = self.P, self.n
        t_last = self.kt[-1]
        x0 = self.z[-6:].copy()
        th = self.z[:P].copy()
        prop = self._propagator(steps)                # the kernel's arguments prepared once
        N = P + 6 * n
        H = np.zeros((N + 6, N + 6))
        H[:N, :N] = self.H
        self.H = H
        self.b = np.concatenate([self.b, _ZERO6])
        self.n = n + 1
        self.kt.append(float(t))
        self.kid.append(int(kid))
        self._surface(n)
        self.dyn.append([steps, self._whitening(t - t_last, q_scale),
                         np.zeros((P + 12, P + 12)), np.zeros(P + 12), prop])
        self.X0L.append(x0.tolist())
        self.THL.append(th.tolist())
        pred = self.last_pred = self._linearise(n - 1, x0, th, self.params_view())
        ok = self.last_ok = all(map(math.isfinite, pred.tolist()))
        x1 = pred if ok else np.where(np.isfinite(x0), x0, 0.0) * np.array([1, 1, 1, 0, 0, 0.0])
        self.z = np.concatenate([self.z, x1])
        if not ok:              # a diverged model: relinearised at the next step
            self.X0L[-1] = [math.inf] * 6
        return np.array(x1)

    def index_at(self, t: float) -> int | None:
        """Window index of the knot at time ``t`` (None: not in the window)."""
        return next((j for j, tk in enumerate(self.kt) if abs(tk - t) < 1e-9), None)

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

    def release(self) -> None:
        """Remove the hold priors on the parameters."""
        self.hold_w = None

    def broaden(self, state_sigma: np.ndarray, prior_scale: float) -> None:
        """Recovery from a failed step: broad priors around the current estimate on every
        knot (``state_sigma``) and the parameters (``prior_scale`` x their scales), and the
        dynamics factors relinearised at the estimate."""
        P = self.P
        sc = np.array([prior_scale * self.layout.model.spec(n).scale
                       for n in self.layout.estimated])
        w = np.concatenate([1.0 / sc ** 2, np.tile(1.0 / np.asarray(state_sigma) ** 2, self.n)])
        z = np.where(np.isfinite(self.z), self.z, 0.0)
        z[:P] = np.clip(np.where(np.isfinite(self.z[:P]), z[:P], self.th0), self.lo, self.hi)
        self.z = z
        self.H = np.where(np.isfinite(self.H), self.H, 0.0)
        self.b = np.where(np.isfinite(self.b), self.b, 0.0)
        k = np.arange(len(z))
        self.H[k, k] += w
        self.b -= w * z
        self.X0L = [[math.inf] * 6 for _ in self.X0L]     # forces the relinearisation

    # ------------------------------------------------------------------ the system
    def _relinearise(self) -> None:
        """Relinearise the dynamics factors whose first knot or parameters moved past the
        thresholds since their linearisation, and the fixes whose knot moved past
        ``relin_pos``."""
        # in Python floats: a few knots, and numpy calls cost microseconds each
        P = self.P
        th = self.z[:P]
        X = self.z[P:].reshape(-1, 6)
        Xl = X.tolist()
        rp = self.s.relin_pos
        for i, (x, f) in enumerate(zip(Xl, self.FXL)):
            # NaN (no fix): False
            if abs(x[0] - f[0]) > rp or abs(x[1] - f[1]) > rp or abs(x[2] - f[2]) > rp:
                self._set_fix(i)
        if not self.dyn:
            return
        # a dynamics factor is exactly invariant to a move of its first knot's position
        # (the model never reads it: x1 and the block shift with it), so only the velocity
        # and the parameters are compared
        rv, rt, thl = self.s.relin_vel, self._relin_th_l, th.tolist()
        move = []
        for i, (x, x0, t0) in enumerate(zip(Xl, self.X0L, self.THL)):
            if abs(x[3] - x0[3]) > rv or abs(x[4] - x0[4]) > rv or abs(x[5] - x0[5]) > rv:
                move.append(i)
                continue
            for a, b, r in zip(thl, t0, rt):
                if abs(a - b) > r:
                    move.append(i)
                    break
        if not move:
            return
        p = self.params_view()
        th = th.copy()
        for i in move:
            self._linearise(i, X[i].copy(), th, p)

    def system(self, z: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Gauss-Newton normal equations ``(H, g)`` of the window at ``z`` (default: the
        estimate): held quadratic, fixes and hold priors."""
        z = self.z if z is None else z
        H = self.H.copy()
        g = self.H @ z + self.b
        if self.hold_w is not None and self.P:
            H[self.pidx, self.pidx] += self.hold_w
            g[:self.P] += self.hold_w * (z[:self.P] - self.th0)
        return H, g

    def step(self) -> None:
        """One Gauss-Newton step of the window (relinearising what moved), then the knots
        older than the lag are marginalised. Raises ``np.linalg.LinAlgError`` when the
        system is not positive definite (the estimate is left as it was)."""
        self._relinearise()
        P = self.P
        if self._cwin:                # kernel window_step: the same solve in one C++ call
            ok, step, cov = _kernel().window_step(
                self.H, self.b, self.z, _EMPTY if self.hold_w is None else self.hold_w,
                self.th0, P)
        else:
            H, g = self.system()
            N = len(g)
            rhs = self._rhs.get(N)
            if rhs is None:
                rhs = self._rhs[N] = np.zeros((N, P + 1))
                rhs[self._rhs_cols] = 1.0
            rhs = rhs.copy()
            rhs[:, 0] = g
            # Cholesky solve (LAPACK posv: fails when H is not positive definite): the step,
            # and the parameters' columns of H^-1
            _, sol, info = _posv(H, rhs, lower=1, overwrite_a=1, overwrite_b=1)
            ok = info == 0 and bool(np.isfinite(sol).all())
            step, cov = sol[:, 0], sol[:P, 1:]
        if not ok:
            raise np.linalg.LinAlgError("the window's system is not positive definite")
        z = self.z - step
        z[:P] = np.minimum(np.maximum(z[:P], self.lo), self.hi)
        self.z = z
        self.cov = cov
        self._marginalise()

    def _marginalise(self) -> None:
        """Eliminate the knots older than ``lag`` before the newest from the held quadratic
        (Schur complement at the factors' linearisation points)."""
        P = self.P
        while self.n > 2 and self.kt[0] < self.kt[-1] - self.lag - 1e-6:
            z = self.z
            N = len(z)
            H, b = self.H, self.b
            t_gone = self.kt[0]
            # [theta, x0, rest] -> [theta, rest]: x0 eliminated (flat indices: one take)
            keep = self._keep.get(N)
            if keep is None:
                k = np.concatenate([np.arange(P), np.arange(P + 6, N)])
                keep = self._keep[N] = (k, (k[:, None] * N + k[None, :]).ravel())
            if self._cwin:                       # kernel schur_drop: one C++ call
                ok, Hn, bn = _kernel().schur_drop(H, b, P, 6)
                if not ok:
                    raise np.linalg.LinAlgError("a marginalised knot's information is singular")
                self.H, self.b = Hn, bn
            else:
                Har = H[P:P + 6].take(keep[0], axis=1)                        # (6, N-6)
                rhs = np.concatenate([Har, b[P:P + 6, None]], axis=1)
                _, sol, info = _posv(H[P:P + 6, P:P + 6], rhs, lower=1)      # H_aa^-1 [H_ar, b_a]
                if info != 0:
                    raise np.linalg.LinAlgError("a marginalised knot's information is singular")
                Hn = H.take(keep[1]).reshape(N - 6, N - 6)
                Hn -= Har.T @ sol[:, :-1]
                self.H = Hn
                self.b = b.take(keep[0]) - Har.T @ sol[:, -1]
            self.z = z.take(keep[0])
            self.n -= 1
            self.kt.pop(0)
            self.kid.pop(0)
            self.dyn.pop(0)
            del self.X0L[0], self.THL[0]
            self.fx.pop(0)
            del self.FXL[0]
            self._walk_due += self.kt[0] - t_gone
        if len(self._walk_idx) and self._walk_due >= WALK_EVERY:
            self._walk(self._walk_due)
            self._walk_due = 0.0

    def _walk_step(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """The Gauss-Markov step over ``dt`` s of each walking parameter: its factor ``a``
        and the variance ``var(w)`` (:meth:`_walk`; a plain walk where the stationary
        variance is infinite), cached per interval."""
        key = round(dt, 9)
        out = self._walk_cache.get(key)
        if out is None:
            stat = self._walk_stat
            gm = np.isfinite(stat)
            tau = 2.0 * np.where(gm, stat, 1.0) / self._walk_var
            a = np.where(gm, np.exp(-dt / tau), 1.0)
            q = np.where(gm, np.where(gm, stat, 0.0) * (1.0 - a * a), self._walk_var * dt)
            out = self._walk_cache[key] = (a, q)
        return out

    def _walk(self, dt: float) -> None:
        """The current (and the heading offset: a plain random walk of
        ``online_heading_walk`` rad per sqrt(s)) of the information that has left the window
        moves before it meets the window's data: a first-order Gauss-Markov process (the
        INS bias model) around the
        prior's centre ``mu0``, ``s' - mu0 = a (s - mu0) + w``, diffusing as a random walk of
        ``online_current_walk`` m/s per sqrt(s) over short times and with the current's
        prior (``FGSettings.prior_sigma``) as its stationary sigma, so that the prior does
        not wash out over a long mission (``a = exp(-dt / tau)``, ``tau = 2 S / sigma^2``,
        ``var(w) = S (1 - a^2)``).

        Applied to the marginal ``H_m`` only -- the held quadratic less the window's own
        dynamics factors (the only other terms on the parameters): the affine map, then the
        covariance grown by ``var(w)`` (Woodbury: ``H_m' = H_m - C M^-1 C^T``,
        ``C = H_m E S``, ``M = I + S E^T H_m E S``, the mean kept). Within the window the
        parameters stay one value: the walk acts between the past and the window."""
        if not dt > 0:
            return
        P = self.P
        w = self._walk_idx
        a, q = self._walk_step(dt)
        # the marginal lives on [theta, oldest knot] (each Schur complement links the
        # eliminated knot's neighbours only): everything below acts on that leading block
        L = P + 6
        H, b = self.H, self.b
        Cm = H[:L, w].copy()                         # (L, k): the marginal's columns
        bw = b[w].copy()
        if self.dyn:                                 # less the window's dynamics factors
            # (stacked, one numpy call each: this runs at every knot that leaves)
            S = np.array([d[2] for d in self.dyn])[:, :L, w]    # (n - 1, L, k)
            Cm[:P] -= S[:, :P].sum(axis=0)
            Cm[P:] -= S[0, P:]                       # factor 0 is the one on the oldest knot
            bw -= np.array([d[3] for d in self.dyn])[:, w].sum(axis=0)
        if np.any(a < 1.0):          # the mean reversion: z_w = (z_w' - c) / a on H_m, b_m
            f = 1.0 / a
            c = (1.0 - a) * self.mu0[w]
            Ct = Cm * f[None, :]
            Ct[w] *= f[:, None]
            D = Ct - Cm
            H[:L, w] += D
            H[w, :L] += D.T
            H[np.ix_(w, w)] -= D[w]
            bt = bw * f
            b[w] += bt - bw
            b[:L] -= Ct @ c
            bw = bt - Ct[w] @ c
            Cm = Ct
        sd = np.sqrt(q)
        C = Cm * sd[None, :]
        M = np.eye(len(w)) + sd[:, None] * Cm[w] * sd[None, :]      # >= I
        Mi = _small_inv(M)
        CM = C @ Mi
        H[:L, :L] -= CM @ C.T
        b[:L] -= CM @ (sd * bw)

    # ------------------------------------------------------------------ tests
    def cost(self, z: np.ndarray) -> float:
        """The window's linearised cost (1/2 chi-square up to a constant) at ``z``: held
        quadratic and hold priors; its gradient is :meth:`system`'s ``g``."""
        P = self.P
        c = float(0.5 * z @ self.H @ z + self.b @ z)
        if self.hold_w is not None:
            c += 0.5 * float(np.sum(self.hold_w * (z[:P] - self.th0) ** 2))
        return c


_MINUS_I6 = -np.eye(6)
_ZERO6 = np.zeros(6)


def _small_inv(M: np.ndarray) -> np.ndarray:
    """Inverse of a small symmetric positive-definite matrix (closed form for 1x1 and 2x2:
    LAPACK's call overhead is ~10 us, the walk of the current runs at every knot that
    leaves the window)."""
    if M.shape == (1, 1):
        return 1.0 / M
    if M.shape == (2, 2):
        a, c, d = float(M[0, 0]), float(M[0, 1]), float(M[1, 1])
        det = a * d - c * c
        return np.array([[d, -c], [-c, a]]) / det
    return np.linalg.inv(M)
