"""The online smoother's numpy engine: the window of :mod:`aqfg.fg.fastlag` (knots at the
fixes only, one Gauss-Newton step per update, no Python callback per factor)."""
from __future__ import annotations

import numpy as np

from aqfg.fg import factors as fc
from aqfg.fg.common import first_knot_prior
from aqfg.fg.fastlag import LagWindow
from aqfg.fg.online.engine import BROAD_STATE_SIGMA, WindowEngine
from aqfg.fg.online.records import OnlineEvent


class NumpyEngine(WindowEngine):
    """:class:`aqfg.fg.fastlag.LagWindow` behind :class:`WindowEngine`. The knots between
    fixes join the causal track as the model's prediction from the last fix, computed when
    the track is read (:meth:`materialise`)."""
    name = "numpy"

    def __init__(self, host, x0: np.ndarray, t0: float, hold: bool):
        super().__init__(host)
        h = host
        s = h.settings
        pf = first_knot_prior(h.mission, fc.state_key(0, 0), x0, s)
        prior, hold_sig = h.priors.sigmas(), h.priors.hold_sigmas()
        mean = (np.concatenate([h.priors.mean(g) for g in h.layout.groups])
                if h.layout.groups else np.zeros(0))
        self.win = LagWindow(h.model, h.layout, s, h.mission, h.window, prior,
                             hold_sig if hold else None, x0, np.asarray(pf.prior()),
                             np.asarray(pf.noiseModel().sigmas()), t0, 0, prior_mean=mean)
        self.hold_placed = hold
        self.deferred: list[tuple] = []          # causal states between fixes, deferred
        self.under_review: list[float] = []      # USBL fixes left out, still in the window
        h.knots.append(t0)
        h.filtered.append(x0.copy())

    def params(self) -> np.ndarray:
        return self.win.full_params()

    def predict(self, t_fix, t_last, new_t, all_t) -> np.ndarray:
        """One knot at the fix (its dynamics factor over every input since the last one);
        the knots between are deferred (:meth:`materialise`)."""
        h, eng = self.host, self.win
        i0 = len(h.knots)
        n_new = len(new_t)
        if n_new > 1:
            # the parameters of now (params_view: a new array per estimate, never written)
            self.deferred.append((i0, all_t, eng.z[-6:].copy(), eng.params_view()))
            h.filtered.extend([None] * (n_new - 1))      # type: ignore[list-item]
        x_fix = eng.add(float(t_fix), i0 + n_new - 1, h.steps.interval(all_t),
                        h.noise.q_scale)
        if not eng.last_ok:
            h.note_diverged_prediction(float(t_fix))
        h.filtered.append(x_fix)
        h.knots.extend(new_t.tolist())
        return x_fix

    def measure(self, t_fix, t_last, all_t, drop_usbl, usbl_scale) -> None:
        self.win.take_fixes(usbl=not drop_usbl, usbl_scale=usbl_scale)
        if drop_usbl:
            self.under_review.append(float(t_fix))

    def solve(self, t_fix: float) -> tuple[np.ndarray, np.ndarray]:
        eng = self.win
        self._step(t_fix)
        th, sg = eng.z[:eng.P].copy(), eng.sigma()      # th: inside the bounds
        for g, sl in eng.slices.items():
            self.host.last_params[g] = th[sl]
        return th, sg

    def _step(self, t_fix: float) -> None:
        """The Gauss-Newton step(s), surviving a system that is not positive definite: the
        marginal is replaced by broad priors around the current estimate and the step
        retried; if that fails too, the step is skipped (recorded in the host's events)."""
        eng, s = self.win, self.host.settings
        for _ in range(max(s.online.iterations_per_update, 1)):
            try:
                eng.step()
            except np.linalg.LinAlgError as exc:
                err = str(exc) or type(exc).__name__
                eng.broaden(BROAD_STATE_SIGMA, s.graph.prior_scale)
                try:
                    eng.step()
                    self.host.events.append(OnlineEvent(float(t_fix), "restarted (broad priors)",
                                                        {"error": err}))
                except np.linalg.LinAlgError:
                    self.host.events.append(OnlineEvent(float(t_fix), "fix skipped",
                                                        {"error": err}))
                return

    def read_states(self, t_fix: float, i_fix: int) -> None:
        h, eng = self.host, self.win
        h.filtered[i_fix] = eng.z[-6:].copy()
        for i in reversed(h.anchor_idx):
            if h.knots[i] < t_fix - h.window + 1e-6:
                break
            x = eng.state(i)
            if x is None:
                break
            h.latest[i] = x

    def review(self, t_fix: float) -> None:
        """USBL fixes the gate left out, seen again against their knot's smoothed estimate
        once later fixes are in: a fix that agrees now (the same gate, without the
        prediction's process noise) was good and the track was off -- it joins the window;
        one whose knot has left the window stays out. The gate alone cannot tell a 8-m
        range outlier from a track 8 m off; a smoother can, a few fixes later."""
        if not self.under_review:
            return
        eng, gate = self.win, self.host.gate
        keep = []
        for t in self.under_review:
            if t >= t_fix - 1e-9:
                keep.append(t)
                continue
            i = eng.index_at(t)
            if i is None:
                continue                           # left the window: stays out
            x = eng.z[eng.P + 6 * i:eng.P + 6 * i + 6]
            if gate.readmits(t, x) and eng.readmit_usbl(t):
                gate.rejected[t] = False
                continue
            keep.append(t)
        self.under_review = keep

    def release(self, t_fix: float) -> None:
        self.win.release()
        for _ in range(2):
            self._step(t_fix)
        self.host.events.append(OnlineEvent(float(t_fix), "parameters released"))

    def set_lag(self, lag: float) -> None:
        self.win.lag = lag

    def set_mission(self, mission) -> None:
        self.win.set_mission(mission)

    def materialise(self) -> None:
        """The deferred causal states between fixes: the model's prediction from the fix
        before them with the parameters of then (one kernel roll-out each)."""
        h = self.host
        pending, self.deferred = self.deferred, []
        for i0, all_t, x, p in pending:
            steps, off = h.steps.steps(all_t)
            with np.errstate(all="ignore"):
                Xi = h.model.rollout_segments(x, p, steps, off)[1:-1]
            if not np.all(np.isfinite(Xi)):
                Xi = np.where(np.isfinite(Xi), Xi, np.where(np.isfinite(x), x, 0.0))
            h.filtered[i0:i0 + len(Xi)] = list(Xi)

    def keep_deferred_from(self, n: int) -> None:
        self.deferred = [q for q in self.deferred if q[0] >= n]
