"""Factor-graph smoothing of vehicle missions: the public entry points.

* :class:`BatchSmoother` (:mod:`aqfg.fg.batch`): whole missions, several missions of
  one vehicle sharing the fixed-parameter node; ``run(missions) -> Result``.
* :class:`FixedLagSmoother` (:mod:`aqfg.fg.fixed_lag`): online, window of ``window``
  seconds updated after each fix; ``run(mission) -> Result`` or a step-by-step API.
* :func:`fit_fg`: the same call shape as :func:`aqfg.ekf.estimator.fit_update_error`, so the CLI and
  the experiments switch method with one flag.

The graph (:mod:`aqfg.fg.factors`): state knots ``[pos, vel]`` (NED) on a regular grid merged
with the fix times, dynamics factors integrating every input sample between knots with the
shared model, GNSS/USBL/depth factors, and parameter nodes (fixed / variable / sensor).
"""
from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import numpy as np

from aqfg.data.mission import Mission
from aqfg.fg import dead_reckoning
from aqfg.fg.batch import MISFIT_INFLATION, BatchSmoother
from aqfg.fg.common import FGSettings, check_missions, mission_model
from aqfg.fg.fastlm import FastSystem
from aqfg.fg.fixed_lag import FixedLagSmoother, UpdateInfo
from aqfg.model.retrace import inertial_track
from aqfg.result import Result

__all__ = ["BatchSmoother", "FixedLagSmoother", "FGSettings", "UpdateInfo", "fit_fg"]

log = logging.getLogger(__name__)


def fit_fg(missions: Sequence[Mission] | Mission, *, mode: str = "batch",
           estimate: Sequence[str] | None = None, init: dict[str, float] | None = None,
           effects: Sequence = (), window: float | None = None, progress=False,
           settings: FGSettings | None = None, model=None) -> Result:
    """Fit with the factor graph; the entry point of ``aqfg fit --method fg``.

    ``mode``: "batch" (all missions jointly, one shared fixed-parameter node) or "online"
    (fixed-lag smoother per mission, window ``window`` s, default 24). ``estimate``:
    parameter names (default batch: the six base parameters and those of the effects;
    online: the variable ones). ``init``: initial values, and the values of the parameters
    not estimated. ``effects``: model effects (names or UserEffect objects).
    """
    missions = check_missions(missions)
    if mode not in ("batch", "online"):
        raise ValueError(f"mode must be 'batch' or 'online', got {mode!r}")
    if mode == "batch":
        horizon = (settings or FGSettings()).dr_horizon
        bs = BatchSmoother(model, effects=effects, estimate=estimate, init=init,
                           settings=settings, progress=progress)
        bs.inertial = horizon <= 0         # re-traced once, with the final constants (below)
        bs.defer_track = True
        res = bs.run(missions)
        if bs.fast_solution is not None:
            fs, ev = bs.fast_solution
            res = structural_sigma(res, list(missions), fs, ev, bs.settings,
                                   log_warnings=bs.log_warnings)
        # the constants to dead-reckon with: multi-step prediction error where it differs
        # significantly from the smoother's one-interval fit (aqfg.fg.dead_reckoning), from
        # the nominal fit's states (as the fleet's)
        res = dead_reckoning.refine(res, list(missions), horizon)
        res = bs.smooth_tracks(res)
        for m, mr in zip(missions, res.missions):
            if not len(mr.inertial.t):
                mr.inertial = inertial_track(mission_model(model, m, effects), m, mr.p)
        return res
    results = [FixedLagSmoother(model, effects=effects, estimate=estimate, init=init,
                                window=window or 24.0, settings=settings,
                                progress=progress).run(m) for m in missions]
    if len(results) == 1:
        return results[0]
    # several missions online: each from ``init``; the first mission's history and values
    # (as aqfg.ekf.estimator does), all of them in info
    r0 = results[0]
    timings: dict = {}
    for r in results:
        for k, v in r.timings.items():
            timings.setdefault(k, []).extend(v)
    r0.missions = [r.missions[0] for r in results]
    r0.timings = timings
    r0.info["histories"] = [r.history for r in results]
    r0.info["per_mission"] = {r.missions[0].name: {n: {"value": r.values[n], "sigma": r.sigma.get(n, np.nan)}
                                                   for n in r.estimated} for r in results}
    return r0


def structural_sigma(res: Result, missions: list[Mission], fs: FastSystem, ev: dict,
                     settings: FGSettings, log_warnings: bool = True) -> Result:
    """:attr:`FGSettings.structural_sigma`: where the batch fit ``res`` (nominal noise) does
    not explain the fixes (its honest sigma more than ``MISFIT_INFLATION`` x the model's)
    and the data call for a missing effect, the sigma of the heading offset and the
    current widened by the shift that effect would cause
    (:func:`aqfg.diagnose.structure.structural_shift`, on the batch's numpy system ``fs``
    at its nominal-noise solution, evaluation ``ev``), in place; ``info["sigma_structure"]``
    and a warning say which effect and how much."""
    infl = res.info.get("sigma_inflation", {})
    if (not settings.structural_sigma or settings.walk_sigma
            or res.model is None or max(infl.values(), default=0.0) <= MISFIT_INFLATION):
        return res
    from aqfg.diagnose.structure import structural_shift
    sh = structural_shift(missions, fs, ev, res.model, tuple(res.estimated))
    if sh is None:
        return res
    before = {n: float(res.sigma[n]) for n in sh.shift if n in res.sigma}
    for n, d in sh.shift.items():
        if n in res.sigma:
            res.sigma[n] = float(np.hypot(res.sigma[n], d))
    res.info["sigma_structure"] = {**sh.to_json(), "sigma_before": before}
    parts = []
    if "theta_e" in sh.shift:
        parts.append(f"theta_e by {np.degrees(sh.shift['theta_e']):.2g} deg")
    cur = [sh.shift[n] for n in ("s_x", "s_y") if n in sh.shift]
    if cur:
        parts.append(f"the current by {math.sqrt(sum(c * c for c in cur)):.2g} m/s")
    w = (f"the data call for the effect {sh.effect} (robust score test p = {sh.p_robust:.2g}): "
         f"with it {' and '.join(parts) or 'the estimates'} would move; sigma includes that "
         f"shift (try --effect {sh.effect}, or `aqfg diagnose`)")
    res.info.setdefault("warnings", []).append(w)
    if log_warnings:
        log.warning("fg: %s", w)
    return res
