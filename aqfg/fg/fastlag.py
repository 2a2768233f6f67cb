"""The fixed-lag smoother's window in numpy: the online engine without a Python callback per
factor (:class:`aqfg.fg.fixed_lag.FixedLagSmoother` with ``FGSettings.online.engine =
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
  ``WALK_EVERY`` s of them; ``FGSettings.online.current_walk``, ``heading_walk``,
  :meth:`LagWindow._walk`);
* per update one Gauss-Newton step (as one ISAM2 iteration): each dynamics factor keeps
  its linearisation (prediction and Jacobians at ``(x0_lin, theta_lin)``) until its first
  knot or the parameters moved past ``FGSettings.relin_*`` from it; the fixes (cheap) are
  relinearised at every step. The system is a few knots x 6 + P: one dense Cholesky; the
  parameters' marginal covariance is the inverse's parameter block. The parameters are
  projected into the layout's bounds after each step (as the batch LM).
* with the compiled kernel, a dynamics factor's linearisation and swap into the quadratic
  (``linearise_into``), the step (``window_step``) and the marginalisation
  (``schur_drop``) are one C++ call each; the numpy code here and in
  :mod:`aqfg.fg.fastlag_dyn` is their reference
  (``FGSettings.online.cpp_block=False``; docs/speed.md).

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
from aqfg.fg.fastlag_dyn import WindowDynamics, _kernel, _kernel_factory
from aqfg.fg.fastlag_fixes import WindowFixes
from aqfg.fg.fastlag_walk import WALK_EVERY, WindowWalk, _small_inv
from aqfg.model.vehicle import compiled_kernel

__all__ = ["LagWindow", "WALK_EVERY", "_kernel", "_kernel_factory", "_small_inv"]



_EMPTY = np.zeros(0)


class LagWindow(WindowFixes, WindowDynamics, WindowWalk):
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
        self.model, self.layout, self.s = model, layout, settings
        self.planar = bool(mission.planar)
        self.lag = float(lag)
        self._init_layout(prior_mean)
        self._init_weights(hold_sigma)
        self.set_mission(mission)
        self._init_caches()
        self._init_estimate(x0, prior_sigma, first_mean, first_sigma, t0, kid0)
        self._init_walk()
        self._take_fixes(float(t0) - 1e-6, float(t0))

    def _init_layout(self, prior_mean: np.ndarray | None) -> None:
        """The estimated parameters' layout: start values, prior centre, bounds, slices per
        group and the kernel's Jacobian columns of each."""
        model, layout = self.model, self.layout
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

    def _init_weights(self, hold_sigma: np.ndarray | None) -> None:
        """The hold priors' and the robust losses' weights, and the relinearisation thresholds
        of the parameters."""
        s, model, layout = self.s, self.model, self.layout
        self.hold_w = None if hold_sigma is None else 1.0 / np.asarray(hold_sigma, float) ** 2
        sn = s.graph.sensors
        self.k_gnss = (None if sn.robust == "none" or "gnss" not in sn.robust_on
                       else sn.robust_k_gnss)
        self.k_usbl = (None if sn.robust == "none" or "usbl" not in sn.robust_on
                       else sn.robust_k)
        self.surf_w = 1.0 / np.asarray(s.graph.surface_sigma, float) ** 2
        self.relin_th = s.online.relin_param_fraction * np.array([model.spec(n).scale
                                                       for n in layout.estimated])
        self._relin_th_l = self.relin_th.tolist()

    def _init_caches(self) -> None:
        """The caches of the window's index arrays and whether the C++ blocks are used."""
        P = self.P
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
                      and self.s.online.cpp_block)
        self._lcols = (np.ascontiguousarray(self.jcols, np.int64)
                       if self.jcols is not None and P and cpp is not None
                       and hasattr(cpp, "linearise_into") and self.s.online.cpp_block else None)
        self.last_ok = True

    def _init_estimate(self, x0: np.ndarray, prior_sigma: np.ndarray, first_mean: np.ndarray,
                       first_sigma: np.ndarray, t0: float, kid0: int) -> None:
        """The estimate of the first knot and the held quadratic with the parameters' prior and
        the first knot's prior; no dynamics factors and fixes yet."""
        P, th0 = self.P, self.th0
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

    # ------------------------------------------------------------------ configuration
    @staticmethod
    def unsupported(model, layout: fc.ParamLayout, mission, settings) -> str:
        """Why this engine cannot run the configuration ("" when it can)."""
        from aqfg.fg.fastlm import _plain_sensors
        from aqfg.model.effects import FixDelayTerm, SensorOffsetTerm, UsblTerm
        if settings.graph.sensors.robust not in ("huber", "none"):
            return f"{settings.graph.sensors.robust} loss"
        if settings.graph.walk_sigma:
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
        # the tables only: no attitude at every fix (gnss_R, usbl_R left empty), which
        # would make each update of a growing live mission slower than the last
        m = Measurements.of(mission, self.s, attitudes=False)
        self.tab_g = (m.gnss_t, m.gnss_z, m.gnss_sigma)
        self.tab_u = (m.usbl_t, m.usbl_z, m.usbl_sigma)
        self.tab_d = (m.depth_t, m.depth_z)
        self.station = None if m.station is None else np.asarray(m.station, float)

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

    def release(self) -> None:
        """Remove the hold priors on the parameters."""
        self.hold_w = None

    def broaden(self, state_sigma: np.ndarray, prior_scale: float) -> None:
        """Recovery from a failed step: broad priors around the current estimate on every
        knot (``state_sigma``) and the parameters (``graph.prior_scale`` x their scales), and the
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
        ``online.relin_pos``."""
        # in Python floats: a few knots, and numpy calls cost microseconds each
        P = self.P
        th = self.z[:P]
        X = self.z[P:].reshape(-1, 6)
        Xl = X.tolist()
        rp = self.s.online.relin_pos
        for i, (x, f) in enumerate(zip(Xl, self.FXL)):
            # NaN (no fix): False
            if abs(x[0] - f[0]) > rp or abs(x[1] - f[1]) > rp or abs(x[2] - f[2]) > rp:
                self._set_fix(i)
        if not self.dyn:
            return
        # a dynamics factor is exactly invariant to a move of its first knot's position
        # (the model never reads it: x1 and the block shift with it), so only the velocity
        # and the parameters are compared
        rv, rt, thl = self.s.online.relin_vel, self._relin_th_l, th.tolist()
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

    # ------------------------------------------------------------------ tests
    def cost(self, z: np.ndarray) -> float:
        """The window's linearised cost (1/2 chi-square up to a constant) at ``z``: held
        quadratic and hold priors; its gradient is :meth:`system`'s ``g``."""
        P = self.P
        c = float(0.5 * z @ self.H @ z + self.b @ z)
        if self.hold_w is not None:
            c += 0.5 * float(np.sum(self.hold_w * (z[:P] - self.th0) ** 2))
        return c



_ZERO6 = np.zeros(6)
