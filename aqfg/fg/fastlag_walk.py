"""The random walk of the current and the heading offset in
:class:`aqfg.fg.fastlag.LagWindow`: a Gauss-Markov step applied to the marginal of the knots
that left the window (``FGSettings.online.current_walk``, ``heading_walk``)."""
from __future__ import annotations

import math
from typing import Any

import numpy as np

# s: the current's walk is applied to the marginal in steps of at least this (one step
# costs ~90-170 us; its correlation time is minutes, FGSettings.online.current_walk)
WALK_EVERY = 30.0


class WindowWalk:
    """Mixin of :class:`aqfg.fg.fastlag.LagWindow`: the walk of its marginal."""

    P: int
    s: Any
    layout: Any
    H: np.ndarray
    b: np.ndarray
    mu0: np.ndarray
    dyn: list[list]
    _walk_idx: np.ndarray
    _walk_var: np.ndarray
    _walk_stat: np.ndarray
    _walk_cache: dict

    def _init_walk(self) -> None:
        """The walking parameters' indices, variances per second and stationary variances."""
        s, layout = self.s, self.layout
        # random walk of the current and the heading offset (FGSettings.online.current_walk,
        # heading_walk): variance per second of each estimated parameter that walks
        cw = float(s.online.current_walk)
        hw = float(s.online.heading_walk)
        rate = {"s_x": cw, "s_y": cw, "theta_e": hw}
        wv = [j for j, n in enumerate(layout.estimated)
              if rate.get(n, 0.0) > 0 and n in layout.names.get("variable", ())]
        self._walk_idx = np.array(wv, int)
        self._walk_var = np.array([rate[layout.estimated[j]] ** 2 for j in wv])
        # its stationary variance: the current's prior (s.graph.prior_sigma), inf: a plain walk
        self._walk_stat = np.array([float(s.graph.prior_sigma.get(layout.estimated[j], math.inf))
                                    ** 2 for j in wv])
        self._walk_cache: dict = {}
        self._walk_due = 0.0           # s of the marginal's time not walked yet

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
        ``online.heading_walk`` rad per sqrt(s)) of the information that has left the window
        moves before it meets the window's data: a first-order Gauss-Markov process (the
        INS bias model) around the
        prior's centre ``mu0``, ``s' - mu0 = a (s - mu0) + w``, diffusing as a random walk of
        ``online.current_walk`` m/s per sqrt(s) over short times and with the current's
        prior (``FGSettings.graph.prior_sigma``) as its stationary sigma, so that the prior does
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
        # kept symmetric: each step rescales the walking columns by 1/a and subtracts a
        # product that is symmetric only to rounding; left to accumulate over ~80 steps
        # (40 min) the asymmetry ran the current to its bound and the window diverged
        H[:L, :L] = 0.5 * (H[:L, :L] + H[:L, :L].T)
        b[:L] -= CM @ (sd * bw)



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
