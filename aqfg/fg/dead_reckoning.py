"""The vehicle's thrust/drag constants for dead reckoning: multi-step prediction error.

The batch smoother fits every parameter to one-knot-interval dynamics residuals under white
process noise (an equation-error criterion). Where the model is the vehicle that is the
efficient estimate; where it is not (every real robot), the constants that best explain
1-s velocity changes are not those that best predict the track over the minutes between
fixes. On the Otter USV missions the smoother's constants were sluggish (k, k_x 10-30x
below what predicts well) and its dead reckoning 2-5x worse than the update-error method's,
whose criterion is a multi-step prediction (docs/independent-vehicle.md).

:func:`refine_constants` keeps the smoother's heading offset, current and trajectory and
re-estimates the estimated *fixed* parameters (k, k_x, k_yz and the fixed effects'
parameters) by the error of the model's own prediction, started from the smoothed state at
a fix and run without corrections to every fix within ``horizon`` s (the gap a user
dead-reckons through; :mod:`aqfg.fg.predictions`). The residuals are the horizontal
position errors divided by their lead time (the mean velocity error since the start, m/s),
under a Huber loss: a prediction's error grows with its lead, and raw position errors let the
longest leads alone choose constants that damp every prediction (on a real ASV, constants
that predicted the seconds between online fixes worse than the smoother's). Their
1-sigma is a time-block sandwich (blocks of ``horizon`` s, one Bartlett lag: overlapping
horizons share model error), reported wider by the Student-t factor of its dof
(:func:`aqfg.fg.covariance.honest_covariance`). The refined constants replace the
smoother's only where the two differ significantly (Wald test at 1 % with the refined
covariance): on a vehicle that is the model the smoother's own, more efficient, estimate
stays. :func:`refine` then re-estimates each mission's current the same way
(:mod:`aqfg.fg.dr_current`).
"""
from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import numpy as np
from scipy.optimize import least_squares

from aqfg import distributions as dist
from aqfg.data.mission import Mission
from aqfg.fg.covariance import honest_covariance
from aqfg.fg.dr_current import refine_current
from aqfg.fg.dr_records import DeadReckoning
from aqfg.fg.predictions import (
    HUBER_C,
    Predictions,
    Segment,
    forward_jacobian,
    robust_scale,
    segments,
    to_v,
    to_x,
)
from aqfg.fg.robust import huber_cost, huber_weight
from aqfg.model.params import FIXED_BASE
from aqfg.model.retrace import inertial_track
from aqfg.model.vehicle import Model
from aqfg.result import Result

WALD_ALPHA = 0.01      # the refined constants replace the smoother's beyond this test level
MIN_BLOCKS = 3         # fewer time blocks than parameters + this: not refined


def _huber(r: np.ndarray, c: float) -> float:
    return float(np.sum(huber_cost(np.abs(r), c)))


def _rms(q: np.ndarray) -> float:
    return float(np.sqrt(np.mean(q ** 2)))


def _huber_fit(residuals: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, r0: np.ndarray,
               lo: np.ndarray, hi: np.ndarray, both: np.ndarray, scale: float,
               jac: Callable[[np.ndarray], np.ndarray] | None = None
               ) -> tuple[np.ndarray, np.ndarray, float]:
    """The constants ``x`` minimising the Huber cost of the prediction errors from ``x0``
    (residuals ``r0``, robust scale ``scale``; Jacobian ``jac``, forward differences
    without), refitted once where the scale at the fit differs by more than 20 %:
    ``(x, residuals, scale)``."""
    # start: the smoother's constants with thrust and surge drag (``both``) scaled together
    # (the same top speed, a faster response), the best of a coarse grid by the Huber cost;
    # the smoother's are sluggish where the model is not the vehicle (10-30x on the Otter)
    if both.sum() == 2:
        best = (_huber(r0, HUBER_C * scale), x0)
        for f in (3.0, 10.0, 30.0):
            xs = np.clip(x0 + np.where(both, np.log(f), 0.0), lo + 1e-9, hi - 1e-9)
            cost = _huber(residuals(xs), HUBER_C * scale)
            if cost < best[0]:
                best = (cost, xs)
        x0 = best[1]

    def huber_fit(x_start, scale):
        return least_squares(residuals, x_start, jac="2-point" if jac is None else jac,
                             bounds=(lo, hi), loss="huber", f_scale=HUBER_C * scale,
                             diff_step=1e-4, xtol=1e-6, ftol=1e-8, max_nfev=100)
    sol = huber_fit(x0, scale)
    r1 = residuals(sol.x)
    s1 = robust_scale(r1)                                     # the scale at the fit
    if abs(s1 / scale - 1.0) > 0.2:
        scale = s1
        sol = huber_fit(sol.x, scale)
        r1 = residuals(sol.x)
    return sol.x, r1, scale


def _information(residuals: Callable[[np.ndarray], np.ndarray], x: np.ndarray, r: np.ndarray,
                 c_h: float, segs: list, blocks: set, horizon: float,
                 jac: Callable[[np.ndarray], np.ndarray] | None = None):
    """At the fit ``x`` (residuals ``r``, Huber threshold ``c_h``): the weighted
    Gauss-Newton information ``A`` (Jacobian ``jac``, by forward differences without), the per-block score
    outer products ``B`` (segments grouped by mission and start time, Bartlett lag 1
    within a mission), the Huber weights and the sorted block keys."""
    J = jac(x) if jac is not None else forward_jacobian(residuals, x, r)
    w = huber_weight(np.abs(r), c_h)
    A = (J * w[:, None]).T @ J
    seg_rows = np.repeat(np.arange(len(segs)), [2 * len(s.rows) for s in segs])
    g_seg = np.zeros((len(segs), len(x)))
    np.add.at(g_seg, seg_rows, J * (w * r)[:, None])
    keys = sorted(blocks)
    kpos = {k: j for j, k in enumerate(keys)}
    G = np.zeros((len(keys), len(x)))
    for s, g in zip(segs, g_seg):
        G[kpos[(s.mission, int(s.t0 // horizon))]] += g
    B = G.T @ G
    for j in range(len(keys) - 1):          # Bartlett lag 1 within a mission
        if keys[j][0] == keys[j + 1][0] and keys[j + 1][1] == keys[j][1] + 1:
            C = np.outer(G[j], G[j + 1])
            B += 0.5 * (C + C.T)
    return A, B, w, keys


def refine(result: Result, missions: list[Mission], horizon: float) -> Result:
    """The constants (:func:`refine_constants`), then each mission's current
    (:func:`aqfg.fg.dr_current.refine_current`) a dead reckoning of ``horizon`` s drifts
    with, by prediction error: a new result (``result`` is not changed). Both predict from
    the same segments: the constants change no parameter the fixes' positions read."""
    segs = (segments(result.model, missions, result, horizon)
            if horizon > 0 and result.model is not None else None)
    return refine_current(refine_constants(result, missions, horizon, segs), missions,
                          horizon, segs)


def refine_constants(result: Result, missions: list[Mission], horizon: float,
                     segs: list[Segment] | None = None) -> Result:
    """``result`` (a batch fit) with its estimated fixed parameters re-estimated by
    ``horizon``-s prediction error (module docstring) where they predict significantly
    better, and a :class:`~aqfg.fg.dr_records.DeadReckoning` record saying what was done
    and why (``horizon`` <= 0: ``result`` itself, with none). ``result`` is not changed.
    ``segs``: ``result``'s prediction segments (:func:`aqfg.fg.predictions.segments`),
    built where None."""
    if horizon <= 0:
        return result
    t_start = time.perf_counter()
    model = result.model
    names = [n for n in result.estimated if model is not None and model.spec(n).group == "fixed"]
    rec = DeadReckoning(float(horizon), tuple(names))

    def done(rec: DeadReckoning, timed: bool = False) -> Result:
        timings = ({**result.timings, "dead_reckoning": [time.perf_counter() - t_start]}
                   if timed else result.timings)
        return dataclasses.replace(result, dead_reckoning=rec, timings=timings)
    if model is None or not names:
        return done(dataclasses.replace(rec, reason="no thrust/drag constant estimated"))
    if segs is None:
        segs = segments(model, missions, result, horizon)
    blocks = {(s.mission, int(s.t0 // horizon)) for s in segs}
    if len(blocks) < len(names) + MIN_BLOCKS:
        return done(dataclasses.replace(
            rec, reason=f"too little data: {len(blocks)} blocks of {horizon:.0f} s"))
    idx = np.array([model.index(n) for n in names])
    logs = np.array([n in FIXED_BASE for n in names])
    specs = [model.spec(n) for n in names]
    p_missions = [mr.p.copy() for mr in result.missions]

    pred = Predictions(model, segs, p_missions, idx, logs)
    residuals = pred.residuals
    jac = pred.jacobian if pred.analytic else None

    lo = np.array([np.log(max(sp.lower, 1e-12)) if lg else sp.lower for sp, lg in zip(specs, logs)])
    hi = np.array([np.log(sp.upper) if lg and np.isfinite(sp.upper) else
                   (np.inf if lg else sp.upper) for sp, lg in zip(specs, logs)])
    x_fg = to_x(np.array([result.values[n] for n in names]), logs)
    x0 = np.clip(x_fg, lo + 1e-9, hi - 1e-9)
    r0 = residuals(x0)
    e0 = pred.errors(x0)             # in m, for the report (the states of x0 are cached)
    scale = robust_scale(r0)
    both = np.array([n in ("k", "k_x") for n in names]) & logs
    x, r, scale = _huber_fit(residuals, x0, r0, lo, hi, both, scale, jac)
    A, B, w, keys = _information(residuals, x, r, HUBER_C * scale, segs, blocks, horizon, jac)
    try:
        Ai = np.linalg.inv(A)
    except np.linalg.LinAlgError:
        return done(dataclasses.replace(
            rec, reason="prediction error does not determine the constants"))
    cov, cov_model, dof, wald = _wald(Ai, B, w, r, x - x_fg, len(keys))
    thr = float(dist.chi2_ppf(1.0 - WALD_ALPHA, len(x)))
    v_new = to_v(x, logs)
    D = np.where(logs, v_new, 1.0)
    sig_new = np.sqrt(np.maximum(np.diag(cov), 0.0)) * D
    sig_mod = np.sqrt(np.maximum(np.diag(cov_model), 0.0)) * D
    rec = dataclasses.replace(
        rec, segments=len(segs), blocks=len(keys), dof=int(dof), wald=wald,
        wald_threshold=thr, before={n: float(result.values[n]) for n in names},
        sigma_before={n: float(result.sigma.get(n, np.nan)) for n in names},
        after={n: float(v) for n, v in zip(names, v_new)},
        sigma_after={n: float(s) for n, s in zip(names, sig_new)})
    rec = _with_errors(rec, e0, pred.errors(x))
    if not (wald > thr and np.all(np.isfinite(sig_new))):
        return done(dataclasses.replace(rec, reason=(
            f"the smoother's constants predict as well (Wald {wald:.1f} <= {thr:.1f})"
            if wald <= thr else "refined sigma not finite")), timed=True)
    out = done(dataclasses.replace(rec, applied=True), timed=True)
    return _apply(out, missions, model, names, idx, p_missions, v_new, sig_new, sig_mod)


def _with_errors(rec: DeadReckoning, before: np.ndarray, after: np.ndarray) -> DeadReckoning:
    """``rec`` with the RMS and median absolute horizontal prediction errors (m) before
    and after."""
    return dataclasses.replace(rec, rms_before_m=_rms(before), rms_after_m=_rms(after),
                               median_abs_before_m=float(np.median(np.abs(before))),
                               median_abs_after_m=float(np.median(np.abs(after))))


def _apply(result: Result, missions: list[Mission], model: Model, names: list[str], idx: np.ndarray,
           p_missions: list[np.ndarray], v_new: np.ndarray, sig_new: np.ndarray,
           sig_mod: np.ndarray) -> Result:
    """``result`` with the refined constants ``names`` (at ``idx`` of each mission's
    parameter vector ``p_missions``) and their sigmas, the inertial re-traces redone."""
    values, sigma = dict(result.values), dict(result.sigma)
    sigma_model, sigma_inflation = dict(result.sigma_model), dict(result.sigma_inflation)
    for n, v, sg, sm in zip(names, v_new, sig_new, sig_mod):
        values[n] = float(v)
        sigma[n] = float(sg)
        sigma_model[n] = float(sm)
        sigma_inflation[n] = float(sg / max(sm, 1e-300))
    recs = []
    for i, mr in enumerate(result.missions):
        p = p_missions[i].copy()
        p[idx] = v_new
        recs.append(dataclasses.replace(mr, p=p, inertial=inertial_track(model, missions[i], p)))
    return dataclasses.replace(result, values=values, sigma=sigma, sigma_model=sigma_model,
                               sigma_inflation=sigma_inflation, missions=recs)


def _wald(Ai: np.ndarray, B: np.ndarray, w: np.ndarray, r: np.ndarray, d: np.ndarray,
          n_blocks: int) -> tuple[np.ndarray, np.ndarray, int, float]:
    """The refined constants' covariance (sandwich-inflated, :func:`honest_covariance`),
    the model's ``s^2 A^-1``, the blocks' degrees of freedom and the Wald statistic of
    their move ``d`` from the smoother's, from ``A^-1`` (``Ai``), the block scores' ``B``,
    the Huber weights ``w`` and the residuals ``r``."""
    n_eff = float(np.sum(w))
    s2 = float(np.sum(w * r ** 2) / max(n_eff - len(d), 1.0))
    dof = n_blocks - len(d)
    cov = honest_covariance({0: s2 * Ai}, {0: Ai @ B @ Ai}, dof)[0]
    # the refined covariance alone (Hausman's would subtract the smoother's, smaller
    # where it is efficient): a false replacement on a vehicle that is the model costs
    # little (aqfg's simulator: within 2 sigma of the truth), a missed one on a vehicle
    # that is not costs half its dead-reckoning accuracy (docs/independent-vehicle.md)
    try:
        wald = float(d @ np.linalg.solve(cov, d))
    except np.linalg.LinAlgError:
        wald = np.inf
    return cov, s2 * Ai, dof, wald
