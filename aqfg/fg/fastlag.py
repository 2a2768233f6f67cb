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
  knot left, as GTSAM's linear container factor);
* per update one Gauss-Newton step (as one ISAM2 iteration): each dynamics factor keeps
  its linearisation (prediction and Jacobians at ``(x0_lin, theta_lin)``) until its first
  knot or the parameters moved past ``FGSettings.relin_*`` from it; the fixes (cheap) are
  relinearised at every step. The system is a few knots x 6 + P: one dense Cholesky; the
  parameters' marginal covariance is the inverse's parameter block. The parameters are
  projected into the layout's bounds after each step (as the batch LM).

:meth:`LagWindow.unsupported` says why a configuration needs the GTSAM engine
(measurement effects such as a lever arm or USBL distortions, a Cauchy loss, random-walk
parameters, a thrust lag, depth readings of a non-planar vehicle).
"""
from __future__ import annotations

import numpy as np

from aqfg.fg import factors as fc
from aqfg.model.measurements import range_bearing


class LagWindow:
    """The window's factors and estimate (see the module docstring). Times in s, states
    ``[n, e, d, vn, ve, vd]``."""

    def __init__(self, model, layout: fc.ParamLayout, settings, mission, lag: float,
                 prior_sigma: np.ndarray, hold_sigma: np.ndarray | None,
                 x0: np.ndarray, first_mean: np.ndarray, first_sigma: np.ndarray,
                 t0: float, kid0: int):
        s = settings
        self.model, self.layout, self.s = model, layout, s
        self.planar = bool(mission.planar)
        self.lag = float(lag)
        groups = layout.groups
        self.th = np.concatenate([layout.initial(g) for g in groups]) if groups else np.zeros(0)
        P = self.P = len(self.th)
        self.th0 = self.th.copy()
        self.lo = np.concatenate([layout.bounds(g)[0] for g in groups]) if groups else np.zeros(0)
        self.hi = np.concatenate([layout.bounds(g)[1] for g in groups]) if groups else np.zeros(0)
        self.slices = {}
        c = 0
        for g in groups:
            self.slices[g] = slice(c, c + layout.dim(g))
            c += layout.dim(g)
        # kernel J_p columns -> theta columns
        ncol = len(model.dyn_columns())
        self.Jsel = np.zeros((ncol, P))
        for g in layout.dyn_groups():
            for j, pos in enumerate(layout.dyn_pos[g]):
                if pos >= 0:
                    self.Jsel[pos, self.slices[g].start + j] = 1.0
        self.pidx = np.arange(P)
        self.prior_w = 1.0 / np.asarray(prior_sigma, float) ** 2
        self.hold_w = None if hold_sigma is None else 1.0 / np.asarray(hold_sigma, float) ** 2
        sn = s.sensors
        self.k_gnss = (None if sn.robust == "none" or "gnss" not in sn.robust_on
                       else sn.robust_k_gnss)
        self.k_usbl = (None if sn.robust == "none" or "usbl" not in sn.robust_on
                       else sn.robust_k)
        self.surf_w = 1.0 / np.asarray(s.surface_sigma, float) ** 2
        self.relin = np.array([s.relin_pos] * 3 + [s.relin_vel] * 3)
        self.set_mission(mission)
        # window
        self.kt = [float(t0)]
        self.kid = [int(kid0)]
        self.X = np.asarray(x0, float).reshape(1, 6).copy()
        self.first: tuple[np.ndarray, np.ndarray] | None = (
            np.asarray(first_mean, float).copy(), 1.0 / np.asarray(first_sigma, float) ** 2)
        self.marg: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None   # H, g, z_lin
        z6 = np.zeros((0, 6))
        self.W = np.zeros((0, 6, 6))
        self.X0L, self.PRED = z6, z6
        self.THL = np.zeros((0, P))
        self.A0 = np.zeros((0, 6, 6))          # -W J_x (at the linearisation point)
        self.AT = np.zeros((0, 6, P))          # -W J_theta
        self.steps: list = []                  # kernel steps per interval
        # fixes on the window's knots: (knot time, z, sigma) per stream
        self.g_t, self.g_z, self.g_s = np.zeros(0), np.zeros((0, 2)), np.zeros(0)
        self.u_t, self.u_z, self.u_s = np.zeros(0), np.zeros((0, 2)), np.zeros((0, 2))
        self._wcache: dict = {}
        self.cov = np.full((P, P), np.nan)
        self._take_fixes(float(t0) - 1e-6, float(t0))

    # ------------------------------------------------------------------ configuration
    @staticmethod
    def unsupported(model, layout: fc.ParamLayout, mission, settings) -> str:
        """Why this engine cannot run the configuration ("" when it can)."""
        from aqfg.fg.fastlm import _plain_sensors
        from aqfg.model.effects import SensorOffsetTerm, UsblTerm
        if settings.sensors.robust not in ("huber", "none"):
            return f"{settings.sensors.robust} loss"
        if settings.walk_sigma:
            return "random-walk parameters"
        if any(isinstance(e, (SensorOffsetTerm, UsblTerm)) for e in model.effects) \
                or layout.meas_groups("gnss") or layout.meas_groups("usbl") \
                or not _plain_sensors(layout.base):
            return "measurement effects"
        if model.lookback > 0:
            return "thrust lag (warm-up steps between knots)"
        if not mission.planar and mission.depth is not None and len(mission.depth.t):
            return "depth readings"
        if not model.uses_cpp:
            return "no compiled kernel for this model"
        return ""

    def set_mission(self, mission) -> None:
        """The fix table of ``mission`` (again when a live mission grows)."""
        from aqfg.fg.common import Measurements
        m = Measurements.of(mission, self.s)
        self.tab_g = (m.gnss_t, m.gnss_z, m.gnss_sigma)
        self.tab_u = (m.usbl_t, m.usbl_z, m.usbl_sigma)
        self.station = None if m.station is None else np.asarray(m.station, float)

    def _take_fixes(self, t_lo: float, t_hi: float) -> None:
        """Fixes in (t_lo, t_hi] onto the newest knot."""
        t = self.kt[-1]
        gt, gz, gs = self.tab_g
        a, b = np.searchsorted(gt, [t_lo + 1e-9, t_hi + 1e-9])
        if b > a:
            self.g_t = np.concatenate([self.g_t, np.full(b - a, t)])
            self.g_z = np.concatenate([self.g_z, gz[a:b]])
            self.g_s = np.concatenate([self.g_s, gs[a:b]])
        ut, uz, us = self.tab_u
        a, b = np.searchsorted(ut, [t_lo + 1e-9, t_hi + 1e-9])
        if b > a:
            self.u_t = np.concatenate([self.u_t, np.full(b - a, t)])
            self.u_z = np.concatenate([self.u_z, uz[a:b]])
            self.u_s = np.concatenate([self.u_s, us[a:b]])

    # ------------------------------------------------------------------ building
    def full_params(self) -> np.ndarray:
        th = np.clip(self.th, self.lo, self.hi)
        return self.layout.full({g: th[sl] for g, sl in self.slices.items()})

    def _whitening(self, dt: float, q: float) -> np.ndarray:
        key = (round(dt, 9), q)
        W = self._wcache.get(key)
        if W is None:
            L = np.linalg.cholesky(q * self.s.process.cov(dt, self.planar))
            W = self._wcache[key] = np.linalg.inv(L)
        return W

    def add(self, t: float, kid: int, steps, q_scale: float) -> np.ndarray:
        """A new knot at fix time ``t`` after the newest one, with the dynamics factor over
        ``steps`` linearised at the current estimate and the fixes in between; returns the
        model's prediction there (the knot's initial value)."""
        t_last = self.kt[-1]
        x0 = self.X[-1]
        th = self.th
        pred, Jx, Jp = self.model.propagate(x0, self.full_params(), steps)
        W = self._whitening(t - t_last, q_scale)
        self.W = np.concatenate([self.W, W[None]])
        self.X0L = np.concatenate([self.X0L, x0[None]])
        self.THL = np.concatenate([self.THL, th[None]])
        self.PRED = np.concatenate([self.PRED, pred[None]])
        self.A0 = np.concatenate([self.A0, -(W @ Jx)[None]])
        self.AT = np.concatenate([self.AT, -(W @ (Jp @ self.Jsel))[None]])
        self.steps.append(steps)
        x1 = pred if np.all(np.isfinite(pred)) else np.where(np.isfinite(x0), x0, 0.0) * \
            np.array([1, 1, 1, 0, 0, 0.0])
        self.X = np.concatenate([self.X, x1[None]])
        self.kt.append(float(t))
        self.kid.append(int(kid))
        self._take_fixes(t_last, float(t))
        return np.array(x1)

    def broaden(self, state_sigma: np.ndarray, prior_scale: float) -> None:
        """Recovery from a failed step: the marginal is replaced by broad priors around the
        current estimate (``state_sigma`` on the oldest knot, ``prior_scale`` x the
        parameters' scales), and every dynamics factor is relinearised at the estimate."""
        P = self.P
        sc = np.array([prior_scale * self.layout.model.spec(n).scale
                       for n in self.layout.estimated])
        w = np.concatenate([1.0 / sc ** 2, 1.0 / np.asarray(state_sigma, float) ** 2])
        X0 = np.where(np.isfinite(self.X), self.X, 0.0)
        self.X = X0
        self.th = np.clip(np.where(np.isfinite(self.th), self.th, self.th0), self.lo, self.hi)
        self.marg = (np.diag(w), np.zeros(P + 6), np.concatenate([self.th, self.X[0]]))
        self.first = None
        self.X0L = self.X0L + np.inf               # forces the relinearisation

    def release(self) -> None:
        """Remove the hold priors on the parameters."""
        self.hold_w = None

    # ------------------------------------------------------------------ the system
    def _relinearise(self) -> None:
        """Relinearise the dynamics factors whose first knot or parameters moved past the
        thresholds since their linearisation."""
        m = len(self.steps)
        if not m:
            return
        dx = np.abs(self.X[:-1] - self.X0L) > self.relin
        dth = np.abs(self.th - self.THL) > self.s.relin_param
        redo = np.flatnonzero(dx.any(axis=1) | dth.any(axis=1))
        if not len(redo):
            return
        p = self.full_params()
        th = self.th
        for i in redo:
            x0 = self.X[i]
            pred, Jx, Jp = self.model.propagate(x0, p, self.steps[i])
            W = self.W[i]
            self.X0L[i], self.THL[i], self.PRED[i] = x0, th, pred
            self.A0[i] = -(W @ Jx)
            self.AT[i] = -(W @ (Jp @ self.Jsel))

    def _system(self, X: np.ndarray, th: np.ndarray, lo: int, hi: int, unary: tuple[int, ...],
                params: bool, marginal: bool):
        """Gauss-Newton normal equations ``(H, g)`` over ``[theta, x_lo .. x_hi-1]`` at
        ``(X, th)`` of the dynamics factors between those knots, the unary factors of the
        knots ``unary`` (window indices), the parameter priors (``params``) and the
        marginal (``marginal``; on knot 0)."""
        P = self.P
        n = hi - lo
        m = n - 1
        N = P + 6 * n
        Xw = X[lo:hi]
        if m > 0:
            sl = slice(lo, hi - 1)
            W = self.W[sl]
            A0, AT = self.A0[sl], self.AT[sl]
            e = (np.matmul(W, (Xw[1:] - self.PRED[sl])[:, :, None])
                 + np.matmul(A0, (Xw[:-1] - self.X0L[sl])[:, :, None])
                 + np.matmul(AT, (th - self.THL[sl])[:, :, None]))
            J = np.zeros((m, 6, N))
            J[:, :, :P] = AT
            S = J[:, :, P:].reshape(m, 6, n, 6)
            ar = np.arange(m)
            S[ar, :, ar, :] = A0
            S[ar, :, ar + 1, :] = W
            J2 = J.reshape(6 * m, N)
            H = J2.T @ J2
            g = J2.T @ e.reshape(-1)
        else:
            H = np.zeros((N, N))
            g = np.zeros(N)
        D = np.zeros((n, 6, 6))
        gs = np.zeros((n, 6))
        cost_u = 0.0
        kt = np.asarray(self.kt[lo:hi])
        sel = np.asarray(unary, int) - lo
        if self.planar:
            w = self.surf_w
            D[sel, 2, 2] += w[0]
            D[sel, 5, 5] += w[1]
            gs[sel, 2] += w[0] * Xw[sel, 2]
            gs[sel, 5] += w[1] * Xw[sel, 5]
        if self.first is not None and lo == 0 and 0 in unary:
            mean, wf = self.first
            D[0] += np.diag(wf)
            gs[0] += wf * (Xw[0] - mean)
        ut = set(float(kt[i]) for i in sel)
        if len(self.g_t):
            keep = np.array([t in ut for t in self.g_t])
            if keep.any():
                gi = np.searchsorted(kt, self.g_t[keep] - 1e-9)
                sig = self.g_s[keep]
                r = (Xw[gi, :2] - self.g_z[keep]) / sig[:, None]
                w = _huber(r, self.k_gnss) / sig ** 2
                for a in range(2):
                    np.add.at(D[:, a, a], gi, w)
                    np.add.at(gs[:, a], gi, w * r[:, a] * sig)
                cost_u += 0.0
        if len(self.u_t):
            keep = np.array([t in ut for t in self.u_t])
            if keep.any():
                ui = np.searchsorted(kt, self.u_t[keep] - 1e-9)
                sig = self.u_s[keep]
                h, Hd = range_bearing(Xw[ui, :3] - self.station)
                raw = h - self.u_z[keep]
                raw[:, 1] = fc.wrap_angle(raw[:, 1])
                r = raw / sig
                Jm = Hd / sig[:, :, None]
                w = _huber(r, self.k_usbl)
                Jt = Jm.transpose(0, 2, 1)
                np.add.at(D[:, :3, :3], ui, w[:, None, None] * np.matmul(Jt, Jm))
                np.add.at(gs[:, :3], ui, w[:, None] * np.matmul(Jt, r[:, :, None])[:, :, 0])
        Hs = H[P:, P:].reshape(n, 6, n, 6)
        ar = np.arange(n)
        Hs[ar, :, ar, :] += D
        g[P:] += gs.reshape(-1)
        if params and P:
            wp = self.prior_w
            gp = wp * (th - self.th0)
            if self.hold_w is not None:
                wp = wp + self.hold_w
                gp = gp + self.hold_w * (th - self.th0)
            H[self.pidx, self.pidx] += wp
            g[:P] += gp
        if marginal and self.marg is not None and lo == 0:
            Hm, gm, zl = self.marg
            k = P + 6
            z = np.concatenate([th, Xw[0]])
            H[:k, :k] += Hm
            g[:k] += gm + Hm @ (z - zl)
        return H, g

    def step(self) -> None:
        """One Gauss-Newton step of the window (relinearising what moved), then the knots
        older than the lag are marginalised. Raises ``np.linalg.LinAlgError`` when the
        system is not positive definite (the estimate is left as it was)."""
        self._relinearise()
        n = len(self.kt)
        H, g = self._system(self.X, self.th, 0, n, tuple(range(n)), True, True)
        with np.errstate(all="ignore"):
            np.linalg.cholesky(H)             # raises when not positive definite
            Hi = np.linalg.inv(H)
            d = -(Hi @ g)
        if not np.all(np.isfinite(d)):
            raise np.linalg.LinAlgError("non-finite step")
        P = self.P
        self.th = np.clip(self.th + d[:P], self.lo, self.hi)
        self.X = self.X + d[P:].reshape(n, 6)
        self.cov = Hi[:P, :P]
        self._marginalise()

    def _marginalise(self) -> None:
        """Fold the knots older than ``lag`` before the newest into the marginal prior on
        ``[theta, new oldest knot]`` (a Schur complement at the current estimate)."""
        P = self.P
        while len(self.kt) > 2 and self.kt[0] < self.kt[-1] - self.lag - 1e-6:
            H, g = self._system(self.X, self.th, 0, 2, (0,), False, True)
            a = np.arange(P, P + 6)
            b = np.concatenate([np.arange(P), np.arange(P + 6, P + 12)])
            Haa = H[np.ix_(a, a)]
            Hba = H[np.ix_(b, a)]
            K = np.linalg.solve(Haa, Hba.T).T            # H_ba H_aa^-1
            Hm = H[np.ix_(b, b)] - K @ Hba.T
            gm = g[b] - K @ g[a]
            self.marg = (0.5 * (Hm + Hm.T), gm, np.concatenate([self.th, self.X[1]]))
            self.first = None
            t0 = self.kt.pop(0)
            self.kid.pop(0)
            self.X = self.X[1:]
            for name in ("W", "X0L", "THL", "PRED", "A0", "AT"):
                setattr(self, name, getattr(self, name)[1:])
            self.steps.pop(0)
            for pre in ("g", "u"):
                tt = getattr(self, pre + "_t")
                if len(tt) and tt[0] <= t0 + 1e-9:
                    k = tt > t0 + 1e-9
                    for f in ("_t", "_z", "_s"):
                        setattr(self, pre + f, getattr(self, pre + f)[k])

    # ------------------------------------------------------------------ reading
    def sigma(self) -> np.ndarray:
        """1-sigma of the parameters (marginal of the last step's linearisation)."""
        return np.sqrt(np.maximum(np.diag(self.cov), 0.0))

    def group_values(self) -> dict[str, np.ndarray]:
        return {g: self.th[sl].copy() for g, sl in self.slices.items()}

    def state(self, kid: int) -> np.ndarray | None:
        """Estimate of the knot with orchestration index ``kid`` (None: not in the window)."""
        try:
            return self.X[self.kid.index(kid)].copy()
        except ValueError:
            return None

    # ------------------------------------------------------------------ tests
    def cost(self, X: np.ndarray, th: np.ndarray) -> float:
        """The window's linearised cost (0.5 chi-square up to a constant) at ``(X, th)``,
        dynamics at their cached linearisation, fixes exact (Huber), for derivative
        checks: its gradient at ``(X, th)`` is ``g`` of the system there."""
        P = self.P
        n = len(X)
        c = 0.0
        if n > 1:
            e = (np.matmul(self.W, (X[1:] - self.PRED)[:, :, None])
                 + np.matmul(self.A0, (X[:-1] - self.X0L)[:, :, None])
                 + np.matmul(self.AT, (th - self.THL)[:, :, None]))
            c += 0.5 * float(np.sum(e ** 2))
        if self.planar:
            c += 0.5 * float(np.sum(self.surf_w[0] * X[:, 2] ** 2 + self.surf_w[1] * X[:, 5] ** 2))
        if self.first is not None:
            mean, wf = self.first
            c += 0.5 * float(np.sum(wf * (X[0] - mean) ** 2))
        kt = np.asarray(self.kt)
        if len(self.g_t):
            gi = np.searchsorted(kt, self.g_t - 1e-9)
            r = (X[gi, :2] - self.g_z) / self.g_s[:, None]
            c += _huber_cost(r, self.k_gnss)
        if len(self.u_t):
            ui = np.searchsorted(kt, self.u_t - 1e-9)
            h, _ = range_bearing(X[ui, :3] - self.station)
            raw = h - self.u_z
            raw[:, 1] = fc.wrap_angle(raw[:, 1])
            c += _huber_cost(raw / self.u_s, self.k_usbl)
        if P:
            w = self.prior_w + (0.0 if self.hold_w is None else self.hold_w)
            c += 0.5 * float(np.sum(w * (th - self.th0) ** 2))
        if self.marg is not None:
            Hm, gm, zl = self.marg
            dz = np.concatenate([th, X[0]]) - zl
            c += float(gm @ dz + 0.5 * dz @ Hm @ dz)
        return c


def _huber(r: np.ndarray, k: float | None) -> np.ndarray:
    """GTSAM's Huber weight of whitened residual rows ``r`` (n, m): 1 within ``k`` of the
    row's norm, ``k / |r|`` beyond."""
    if k is None:
        return np.ones(len(r))
    d = np.sqrt(np.sum(r * r, axis=1))
    return np.where(d > k, k / np.maximum(d, 1e-300), 1.0)


def _huber_cost(r: np.ndarray, k: float | None) -> float:
    d = np.sqrt(np.sum(r * r, axis=1))
    if k is None:
        return 0.5 * float(np.sum(d * d))
    return float(np.sum(np.where(d > k, k * (d - 0.5 * k), 0.5 * d * d)))
