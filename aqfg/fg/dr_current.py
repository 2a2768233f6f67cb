"""The drift a dead reckoning needs: each mission's current by multi-step prediction error,
used for the model-only predictions where it predicts left-out time blocks better than the
smoother's.

The smoother learns the current ``s`` (NED, m/s) from one-interval velocity changes, where
it enters through the drag of the water-relative velocity: with quadratic drag its pull is
``2 k_x |v - s|``, nothing while the vehicle is slow. A boat that idles between legs drifts
with the wind and the water at exactly those times, and a model-only re-trace through them
integrates the current's error for minutes (a real ASV's 166-s run: 5.4 m with the
smoother's current, 1.9 m with this one).

:func:`refine_current` re-estimates ``(s_x, s_y)`` of each mission, the vehicle's
constants as they are, by the predictions of :mod:`aqfg.fg.predictions` (from the smoothed
state at a fix to every fix within ``horizon`` s, errors divided by their lead, Huber
loss). It replaces the smoother's where it predicts better out of sample: the mission's
predictions grouped into blocks of ``horizon`` s by start time, each block's Huber cost (at
the smoother's robust scale) under the current fitted without that block (one Gauss-Newton
step from the full fit, residuals linearised: the current enters nearly linearly over a
horizon) against under the smoother's. Its 1-sigma is the larger of the smoother's and the
leave-one-block-out jackknife's. A mission with a piecewise current
(``FGSettings.graph.walk_sigma``) or fewer than two blocks keeps the smoother's.

It is the drift of the model's own predictions (the mission's parameter vector, its
re-trace ``inertial.csv``), reported in ``parameters.json`` under
``dead_reckoning.current``. The reported current stays the smoother's estimate of the
water: on a simulated Otter whose linear drag the model lacks, the prediction-error
current took up the missing drag's drift, about 0.1 m/s off the water's, and with it the
60-s dead reckoning from the true states came 10-25 % and the whole-mission re-trace
30-65 % closer to the truth (otter-dev-current-weakprop, otter-heldout-111 and -146 of
tests/data). On aqfg's simulator, where the model is the vehicle, the two tie out of
sample and either may be kept: a 15-min re-trace then moves by 1-2 m either way, with no
loss over several missions.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from aqfg.data.mission import Mission
from aqfg.fg.dr_records import CURRENT, CurrentRefit
from aqfg.fg.predictions import (
    HUBER_C,
    Predictions,
    Segment,
    forward_jacobian,
    robust_scale,
    segments,
)
from aqfg.fg.robust import huber_cost, huber_weight
from aqfg.model.retrace import inertial_track
from aqfg.result import Result

MIN_BLOCKS = 2         # fewer time blocks: the smoother's current stays
MAX_STEPS = 4          # Gauss-Newton steps of the fit at most
STEP_TOL = 1e-4        # m/s, a step this small ends the fit


def refine_current(result: Result, missions: list[Mission], horizon: float,
                   segs: list[Segment] | None = None) -> Result:
    """``result`` with each mission's current by ``horizon``-s prediction error where it
    predicts left-out blocks better (module docstring), the records in
    ``dead_reckoning.current`` (``result`` itself is not changed). ``segs``: ``result``'s
    prediction segments (:func:`aqfg.fg.predictions.segments`), built where None."""
    model = result.model
    dr = result.dead_reckoning
    if (horizon <= 0 or model is None or dr is None
            or not all(n in result.estimated for n in CURRENT)):
        return result
    result = dataclasses.replace(result, missions=list(result.missions))
    idx = np.array([model.index(n) for n in CURRENT])
    records = []
    segs_all = segs if segs is not None else segments(model, missions, result, horizon)
    piecewise = result.history is not None       # a walk: every mission's is piecewise
    per = result.per_mission                     # the other missions' reported sigma
    for i, (m, mr) in enumerate(zip(missions, result.missions)):
        before = (float(mr.p[idx[0]]), float(mr.p[idx[1]]))
        own = [dataclasses.replace(s, mission=0) for s in segs_all if s.mission == i]
        keys = np.array([int(s.t0 // horizon) for s in own])
        blocks = np.unique(keys)
        if piecewise or len(blocks) < MIN_BLOCKS:
            records.append(CurrentRefit(m.name, len(blocks), before, reason=(
                "piecewise current" if piecewise else
                f"too little data: {len(blocks)} block(s) of {horizon:.0f} s")))
            continue
        pred = Predictions(model, own, [mr.p.copy()], idx, np.zeros(2, bool))
        x_sm = np.array(before)
        r0 = pred.residuals(x_sm)
        c_h = HUBER_C * robust_scale(r0)         # at the smoother's current
        rows = np.repeat(np.concatenate([np.full(len(s.rows), k) for s, k in zip(own, keys)]), 2)

        x_all, r, J = _irls(pred, x_sm, r0, c_h)
        # leave-one-block-out: one Gauss-Newton step from the full fit without the block,
        # its residuals linearised (the current enters nearly linearly over a horizon)
        w = huber_weight(np.abs(r), c_h)
        cost_sm = cost_cv = 0.0
        x_loo = []
        for b in blocks:
            out = rows == b
            keep = ~out
            A = (J[keep] * w[keep, None]).T @ J[keep]
            try:
                d = -np.linalg.solve(A, J[keep].T @ (w[keep] * r[keep]))
            except np.linalg.LinAlgError:
                d = np.zeros(2)
            x_loo.append(x_all + d)
            cost_sm += float(np.sum(huber_cost(np.abs(r0[out]), c_h)))
            cost_cv += float(np.sum(huber_cost(np.abs(r[out] + J[out] @ d), c_h)))
        X = np.array(x_loo)
        n = len(X)
        sig_jk = np.sqrt((n - 1) / n * np.sum((X - X.mean(axis=0)) ** 2, axis=0))
        own_est = per.get(m.name, {})
        sig_sm = np.array([result.sigma.get(c, np.nan) if i == 0 else
                           own_est[c].sigma if c in own_est else np.nan for c in CURRENT])
        sig = np.fmax(sig_jk, sig_sm)
        applied = cost_cv < cost_sm
        records.append(CurrentRefit(
            m.name, n, before, (float(x_all[0]), float(x_all[1])),
            (float(sig[0]), float(sig[1])), cost_sm,
            cost_cv, applied, "" if applied else "the smoother's current predicts the "
            "left-out blocks as well"))
        if applied:
            _apply(result, m, i, idx, x_all)
    return dataclasses.replace(result, dead_reckoning=dataclasses.replace(
        dr, current=tuple(records)))


def _irls(pred: Predictions, x: np.ndarray, r: np.ndarray, c_h: float
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The current minimising the Huber cost (threshold ``c_h``) of ``pred``'s residuals
    from ``x`` (residuals ``r``) by reweighted Gauss-Newton (the residuals are nearly linear
    in the current: two or three steps); the current, its residuals and the Jacobian of
    the last step."""
    for _ in range(MAX_STEPS):
        J = pred.jacobian(x) if pred.analytic else forward_jacobian(pred.residuals, x, r)
        w = huber_weight(np.abs(r), c_h)
        try:
            d = -np.linalg.solve((J * w[:, None]).T @ J, J.T @ (w * r))
        except np.linalg.LinAlgError:
            break
        x = x + d
        r = pred.residuals(x)
        if np.max(np.abs(d)) < STEP_TOL:
            break
    return x, r, J


def _apply(result: Result, mission: Mission, i: int, idx: np.ndarray, x: np.ndarray) -> None:
    """Mission ``i``'s dead-reckoning current ``x`` into a copy of its record (parameter
    vector, re-trace redone) in ``result.missions`` (the reported current stays the
    smoother's)."""
    mr = result.missions[i]
    p = mr.p.copy()
    p[idx] = x
    inertial = mr.inertial if result.model is None else inertial_track(result.model, mission, p)
    result.missions[i] = dataclasses.replace(mr, p=p, inertial=inertial)


def smoother_vector(result: Result, i: int, constants: bool = True) -> np.ndarray:
    """Mission ``i``'s parameter vector as the smoother estimated it: its constants (not
    with ``constants`` False) and current where those refined for dead reckoning replaced
    them (:mod:`aqfg.fg.dead_reckoning`, :func:`refine_current`)."""
    p = result.missions[i].p.copy()
    dr = result.dead_reckoning
    if result.model is None or dr is None:
        return p
    for n, v in (dr.before if constants and dr.applied else {}).items():
        p[result.model.index(n)] = v
    for c in dr.current:
        if c.applied and c.mission == result.missions[i].name:
            p[[result.model.index(n) for n in CURRENT]] = c.before
    return p
