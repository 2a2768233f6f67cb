"""A mission's side of the joint fit (:mod:`aqfg.fg.schur`) on its numpy system
(:class:`aqfg.fg.fastlm.FastSystem`) instead of its GTSAM graph: the same residuals,
Jacobians, damping and bounds, the locals (states, variable and sensor nodes) eliminated
by the banded Cholesky of the states and a dense Schur complement of the mission's own
parameters. :class:`FastSession` serves :class:`aqfg.fg.schur_mission.MissionSession`'s
requests where the mission's graph has that form; the final result (marginals, tracks)
stays with the GTSAM graph, once per fit."""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import scipy.linalg as sla

from aqfg.fg.fastlm import (
    FastSystem,
    damping_scales,
    levenberg_marquardt_fast,
    steps_to_bounds,
)
from aqfg.fg.fastlm_ops import tri
from aqfg.fg.schur_system import FIXED, ReducedSystem

if TYPE_CHECKING:
    from aqfg.fg.schur_mission import MissionProblem


class FastSession:
    """The session's state on the numpy system: the point ``(X, th, evaluation)``, its
    normal equations, the prepared trial's factorisation and held components, and the
    pending candidate. ``fcols``: the fixed node's columns in ``th``."""

    def __init__(self, problem: MissionProblem, fs: FastSystem):
        self.p, self.fs = problem, fs
        X, th = fs.from_values(problem.bg.values)
        self.x = (X, th, fs.evaluate(X, th))
        o, d = fs.node_off.get(FIXED, (0, 0))
        self.fcols = np.arange(o, o + d)
        self.lcols = np.setdiff1d(np.arange(fs.P), self.fcols)
        self.lin: tuple | None = None       # (D, E, Hsp, Hpp, gs, gp, hs, hp) at self.x
        self.trial: int | None = None
        self.fac: tuple | None = None       # (factorisation, damped lam, held {col: step})
        self.cand: tuple | None = None      # (trial, (X, th, ev))

    # ------------------------------------------------------------------ requests
    def sys(self, f: np.ndarray, lam: float, trial: int, commit: int | None = None,
            start: bool = False, sandwich: tuple[float, float] | None = None) -> dict:
        if commit is not None and self.cand is not None and self.cand[0] == commit:
            self.x, self.lin = self.cand[1], None
        self.cand = None
        f = np.asarray(f, float)
        recovered = False
        if len(self.fcols) and not np.array_equal(self.x[1][self.fcols], f):
            if start:
                th = self.x[1].copy()
                th[self.fcols] = f
                self.x = (self.x[0], th, self.fs.evaluate(self.x[0], th))
            else:
                self.x = self._solve_at(f)
                recovered = True
            self.lin = None
        system = self._reduce(lam, {})
        self.trial = trial
        out = {"system": system, "recovered": recovered}
        if sandwich is not None:                # (t0, block): the final, undamped system
            values = self.values()
            out["sandwich"] = self.p.sandwich_part(self.p.bg.linearize(values), *sandwich)
        return out

    def step(self, trial: int, delta_f: np.ndarray, f_new: np.ndarray, mode: str) -> dict:
        """As :meth:`MissionSession._step`: "try", "probe" or "final"."""
        if self.trial != trial or self.fac is None:
            return {"lost": True}
        fs = self.fs
        X, th, _ = self.x
        dX, dth = self._back_substitute(delta_f)
        if mode != "final":
            new = th + dth
            hit = (new < fs.lo) | (new > fs.hi)
            hit[self.fcols] = False
            if np.any(hit):
                return {"clamped": self._reduce(self.fac[1], steps_to_bounds(fs, th, new, hit))}
            if mode == "probe":
                return {"ok": True}
        thc = fs.project(th + dth)
        thc[self.fcols] = np.asarray(f_new, float)
        Xc = X + dX
        ev = fs.evaluate(Xc, thc)
        self.cand = (trial, (Xc, thc, ev))
        return {"cost": float(ev["cost"])}

    def result(self, f: np.ndarray, others: np.ndarray | None,
               sandwich: dict | None = None) -> dict:
        f = np.asarray(f, float)
        if len(self.fcols) and not np.array_equal(self.x[1][self.fcols], f):
            self.x = self._solve_at(f)                  # a fresh session
            sandwich = None
        res = self.p.result(self.values(), others, sandwich)
        res.model = None
        out: dict = {"result": res}
        if self.p.settings.batch.adapt_track:
            out["track"] = self.adapted_track()
        return out

    def adapted_track(self) -> tuple:
        """The mission's track and residuals smoothed again with its parameters held at
        the current point under the process noise its evidence chooses, and that noise's
        factor (:attr:`aqfg.fg.settings.BatchSettings.adapt_track`, as the batch's
        :meth:`~aqfg.fg.batch.BatchSmoother.smooth_tracks`; the fleet's
        :func:`~aqfg.fleet.worker.track_op` without a second graph)."""
        from aqfg.fg import noise
        from aqfg.fg.batch_result import batch_result
        fs, s, bg = self.fs, self.p.settings, self.p.bg
        X0, th, ev = self.x
        q, Xq, _ = noise.track_noise_search(fs, X0, th, ev, s)
        X = X0
        if np.any(q != 1.0):
            fs.set_process_scale(1.0, per_part=q)
            try:
                X, *_ = levenberg_marquardt_fast(fs, None, s, start=(Xq, th), hold_params=True)
            finally:
                fs.set_process_scale(1.0)
        cov = {n.key: np.zeros((bg.layout.dim(n.group),) * 2) for n in bg.nodes}
        mr = batch_result(bg.layout, fs.to_values(X, th, bg.values), bg.parts, bg.nodes, cov,
                          s, inertial_track=False).missions[0]
        return mr.track, mr.residuals, float(q[0])

    # ------------------------------------------------------------------ linear algebra
    def values(self):
        """The current point as the graph's values."""
        return self.fs.to_values(self.x[0], self.x[1], self.p.bg.values)

    def _linearize(self) -> tuple:
        if self.lin is None:
            D, E, Hsp, Hpp, gs, gp = self.fs.normal(self.x[2])
            self.lin = (D, E, Hsp, Hpp, gs, gp, *damping_scales(self.fs, D, Hpp),
                        np.diag(Hpp).copy())
        return self.lin

    def _reduce(self, lam: float, held: dict[int, float]) -> ReducedSystem:
        """Damp the locals by ``lam`` x their floored diagonal (the fixed node is damped
        by the caller, on the sum), hold the local components ``held`` at their steps,
        eliminate the rest: the Schur complement on the fixed node."""
        D, E, Hsp, Hpp, gs, gp, hs, hp, raw_p = self._linearize()
        fs = self.fs
        idx6 = np.arange(6)
        Dd = D.copy()
        Dd[:, idx6, idx6] += lam * hs
        Hppd = Hpp.copy()
        lc = self.lcols
        Hppd[lc, lc] += lam * hp[lc]
        try:
            fac = fs.factor(Dd, E, Hsp, Hppd)
        except ValueError as e:             # a non-finite or not positive definite system
            raise np.linalg.LinAlgError(str(e)) from e
        self.fac = (fac, lam, held)
        _, _, Z, S = fac
        u = tri(fac[0], -gs.reshape(-1, 1))
        rhs = -gp - Z.T @ u[:, 0]
        F = self.fcols
        hcols = np.array(sorted(held), int)
        free = np.setdiff1d(lc, hcols)
        if len(hcols):
            rhs = rhs - S[:, hcols] @ np.array([held[j] for j in hcols])
        H, eta = S[np.ix_(F, F)], rhs[F]
        if len(free):
            c = sla.cho_factor(S[np.ix_(free, free)], check_finite=False)
            K = sla.cho_solve(c, np.column_stack([S[np.ix_(free, F)], rhs[free]]),
                              check_finite=False)
            H = H - S[np.ix_(F, free)] @ K[:, :len(F)]
            eta = eta - S[np.ix_(F, free)] @ K[:, len(F)]
        return ReducedSystem(np.array(H), np.array(eta), float(self.x[2]["cost"]), raw_p[F])

    def _back_substitute(self, delta_f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The locals' step given the fixed node's (and the held components')."""
        assert self.fac is not None and self.lin is not None
        fac, _, held = self.fac
        fix = {**held, **{int(j): float(v) for j, v in zip(self.fcols, delta_f)}}
        return self.fs.solve(fac, self.lin[4], self.lin[5], fix or None)

    def _solve_at(self, f: np.ndarray) -> tuple:
        """The mission's locals solved with the fixed node held at ``f`` (its own LM, from
        the current point), as :meth:`MissionProblem.solve`."""
        X, th, _ = self.x
        th = self.fs.project(th.copy())
        th[self.fcols] = f
        X, th, _, ev, *_ = levenberg_marquardt_fast(
            self.fs, None, self.p.settings, start=(X, th),
            hold_params=[int(j) for j in self.fcols] if len(self.fcols) else False)
        return X, th, ev
