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

import dataclasses
import logging
import math
from collections.abc import Sequence

import numpy as np

from aqfg.data.mission import Mission
from aqfg.fg import dead_reckoning, gnss_noise, jackknife
from aqfg.fg.batch import MISFIT_INFLATION, BatchSmoother
from aqfg.fg.common import check_missions, mission_model
from aqfg.fg.effect_guard import (
    base_record,
    bic_cost,
    dynamics_effect,
    guard_estimates,
    label,
    moves,
    variable_estimates,
    widen_by_other_minimum,
)
from aqfg.fg.fixed_lag import FixedLagSmoother, UpdateInfo
from aqfg.fg.settings import FGSettings
from aqfg.fg.structural_sigma import cover_refit, structural_sigma
from aqfg.fg.structure import structural_shift
from aqfg.model.effects import resolve
from aqfg.model.retrace import inertial_track
from aqfg.result import EffectStep, Estimate, Result

__all__ = ["BatchSmoother", "FixedLagSmoother", "FGSettings", "UpdateInfo", "fit_fg"]

log = logging.getLogger(__name__)
# The effect step's batch solves, for the cost estimate: the model as given, the refit with
# the effect tried and the structural refit (measured 3 where it tried one; 1 where the
# model explained the fixes); and the most parameters an effect it adopts adds.
EFFECT_STEP_SOLVES = 3
EFFECT_STEP_PARAMS = 2


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

    The steps: the fixes weighted by the GNSS noise (``FGSettings.graph.gnss_noise``), the
    batch (:func:`fit_batch`) or online (:func:`fit_online`) fit of the weighted
    missions, and the noise's record (:func:`with_gnss_noise`).
    """
    missions = check_missions(missions)
    if mode not in ("batch", "online"):
        raise ValueError(f"mode must be 'batch' or 'online', got {mode!r}")
    st = settings or FGSettings()
    weighted, noise = gnss_noise.apply(list(missions), st.graph.gnss_noise, st.online.kinematic_q,
                                       st.graph.sensors.gnss_sigma, track=mode == "online")
    if mode == "batch":
        res = fit_batch(weighted, model, effects, estimate, init, settings, progress)
    else:
        res = fit_online(weighted, model, effects, estimate, init, window, settings, progress)
    return with_gnss_noise(res, noise)


def with_gnss_noise(res: Result, noise: gnss_noise.GnssNoise | None) -> Result:
    """``res`` with the GNSS noise its fixes were weighted by (its ``gnss_noise``)."""
    return res if noise is None else dataclasses.replace(res, gnss_noise=noise)


def fit_batch(missions: list[Mission], model, effects: Sequence, estimate, init,
              settings: FGSettings | None, progress) -> Result:
    """The batch fit of :func:`fit_fg`: the solve with the model as given (and its
    structural sigma, :func:`_solve`), then the effect step (:func:`adopt_effect`, where
    :func:`auto_effect_applies`) or the tracks (:func:`_finish`), then the block jackknife
    of a one-mission fit too short for the sandwich (:func:`_block_jackknife`); the
    warnings not logged by the steps are logged last."""
    st = settings or FGSettings()
    auto = auto_effect_applies(st, estimate)
    res, bs = _solve(missions, model, effects, estimate, init, settings, progress,
                     log_warnings=not auto, test_always=auto, refit=not auto)
    if auto:
        res = adopt_effect(res, bs, list(missions), model, effects, init, settings, progress)
    else:
        res = _finish(res, bs, missions, model, effects)
    logged = 0 if auto else len(res.warnings)
    if st.batch.block_jackknife and len(missions) == 1 and res.too_short_for_sandwich:
        res = _block_jackknife(res, missions[0], model, effects, init, st)
    for w in res.warnings[logged:]:
        log.warning("fg: %s", w)
    return res


def fit_online(missions: list[Mission], model, effects: Sequence, estimate, init,
               window: float | None, settings: FGSettings | None, progress) -> Result:
    """The online fit of :func:`fit_fg`: a fixed-lag smoother per mission, each from
    ``init``; several missions' results merged by :func:`merge_online`."""
    results = [FixedLagSmoother(model, effects=effects, estimate=estimate, init=init,
                                window=window or 24.0, settings=settings,
                                progress=progress).run(m) for m in missions]
    return results[0] if len(results) == 1 else merge_online(results)


def merge_online(results: list[Result]) -> Result:
    """Several missions' online results as one: the first mission's history and values
    (as :mod:`aqfg.ekf.estimator` does), every mission's track and timings, and every
    mission's history (``histories``) and its estimates (``per_mission``)."""
    r0 = results[0]
    timings: dict = {}
    for r in results:
        for k, v in r.timings.items():
            timings.setdefault(k, []).extend(v)
    per = {r.missions[0].name: {n: Estimate(r.values[n], r.sigma.get(n, np.nan))
                                for n in r.estimated} for r in results}
    return dataclasses.replace(r0, missions=[r.missions[0] for r in results], timings=timings,
                               info=dict(r0.info), per_mission=per,
                               histories=[h for r in results for h in r.histories])


def _block_jackknife(res: Result, mission: Mission, model, effects: Sequence, init,
                     settings: FGSettings) -> Result:
    """:attr:`FGSettings.batch.block_jackknife` on the batch fit ``res`` of ``mission``
    (:func:`aqfg.fg.jackknife.widen`): its refits keep ``res``'s model (its effects, the
    effect step's among them) and its estimated parameters, without the effect step, the
    heading profile or the track's noise, and log nothing (their warnings are theirs, not
    the fit's)."""
    have = {getattr(e, "name", e) for e in effects}
    eff = (*effects, *(n for n in res.effects if n not in have))
    quick = settings.with_(batch={"auto_effect": False, "heading_profile": False,
                                   "adapt_track": False})
    est = tuple(res.estimated)

    def refit(m: Mission) -> Result:
        r, b = _solve([m], model, eff, est, init, quick, progress=False, log_warnings=False)
        return _finish(r, b, [m], model, eff)
    return jackknife.widen(res, mission, refit)


def auto_effect_applies(settings: FGSettings, estimate: Sequence[str] | None) -> bool:
    """Whether a batch fit (``aqfg fit``'s or the fleet's) takes the effect step
    (:attr:`FGSettings.batch.auto_effect`): on, the default parameters (no ``estimate``: with it
    the user has chosen the model) and the structural test that names the effect."""
    return settings.batch.auto_effect and estimate is None and settings.batch.structural_sigma


def _solve(missions: Sequence[Mission], model, effects: Sequence, estimate, init, settings,
           progress, log_warnings: bool = True, test_always: bool = False,
           refit: bool = False) -> tuple[Result, BatchSmoother]:
    """The batch solve of :func:`fit_fg` with the model as given, and its structural sigma
    (checked by a refit with the effect where ``refit``: :func:`refit_structure`);
    :func:`_finish` completes it."""
    bs = BatchSmoother(model, effects=effects, estimate=estimate, init=init,
                       settings=settings, progress=progress)
    bs.log_warnings = log_warnings
    bs.inertial = bs.settings.batch.dr_horizon <= 0   # re-traced once, with the final constants
    bs.defer_track = True
    res = bs.run(missions)
    sol = bs.fast_solution or bs.short_solution
    if sol is not None:
        fs, ev = sol
        # (the effect step's test only at the nominal noise: an evidence-chosen one on short
        # data widens the sigma, it does not add effects)
        res = structural_sigma(res, list(missions), fs, ev, bs.settings,
                               log_warnings=log_warnings and not refit,
                               test_always=test_always and bs.fast_solution is not None)
        if refit:
            res = refit_structure(res, list(missions), model, effects, estimate, init,
                                  bs.settings, progress)
            if log_warnings and res.sigma_structure is not None:
                log.warning("fg: %s", res.sigma_structure.warning)
    return res, bs


def _finish(res: Result, bs: BatchSmoother, missions: Sequence[Mission], model,
            effects: Sequence) -> Result:
    """The dead-reckoning constants, smoothed tracks and model-only re-traces of a solve."""
    # the constants to dead-reckon with: multi-step prediction error where it differs
    # significantly from the smoother's one-interval fit (aqfg.fg.dead_reckoning), from
    # the nominal fit's states (as the fleet's)
    res = dead_reckoning.refine(res, list(missions), bs.settings.batch.dr_horizon)
    res = bs.smooth_tracks(res)
    return with_inertial_tracks(res, missions, model, effects)


def with_inertial_tracks(res: Result, missions: Sequence[Mission], model,
                         effects: Sequence) -> Result:
    """``res`` with each mission's model-only re-trace (:func:`aqfg.model.retrace.
    inertial_track`) where its result has none."""
    out = list(res.missions)
    for i, (m, mr) in enumerate(zip(missions, res.missions)):
        if not len(mr.inertial.t):
            out[i] = dataclasses.replace(
                mr, inertial=inertial_track(mission_model(model, m, effects), m, mr.p))
    return dataclasses.replace(res, missions=out)


@dataclasses.dataclass(frozen=True)
class EffectTry:
    """A refit with a candidate effect (:func:`_try_effect`): its record (the fields of
    :class:`aqfg.result.EffectStep` it gives), the refit and its solver (None where it failed), why it may
    not be adopted (empty: it may), and how far it moved each variable estimate,
    ``{(mission or "", name): refit - base}``."""
    rec: dict
    new: Result | None
    bs: BatchSmoother | None
    why: str
    moved: dict[tuple[str, str], float]


def adopt_effect(res: Result, bs: BatchSmoother, missions: list[Mission], model,
                 effects: Sequence, init, settings: FGSettings | None, progress=False) -> Result:
    """:attr:`FGSettings.batch.auto_effect`: where the structural test of the batch fit ``res``
    names missing effects (its ``structural_test``), the fit again with the
    best-supported one of the vehicle's dynamics (not a drift of the heading offset or the
    current) added, and with the one of largest score statistic if that is another
    (:func:`effect_candidates`); the lower-cost result of those that explain the fixes
    better (lower cost), are plausible, and keep the heading offset and the current within
    3 sigma of ``res``'s honest sigma (which includes the effect's predicted shift);
    otherwise ``res``, saying why. Its ``effect_step`` records the step and the base fit's
    estimates. Returns the finished fit (:func:`_finish`)."""
    called, picks = effect_candidates(res, bs, missions, effects)
    if not picks:
        return _finish(res, bs, missions, model, effects)
    cost0 = res.cost
    tried = [_try_effect(pick, guard_estimates(res, pick["effect"]), cost0, missions, model,
                         effects, init, settings, progress, untested=called is None)
             for pick in picks]
    # the model-as-given fit's structural sigma checked by the refit with its effect, as
    # `--no-auto-effect` checks it (refit_structure): its record and a refused step's fit
    ss_effect = res.sigma_structure.effect if res.sigma_structure is not None else None
    res = refit_structure(res, missions, model, effects, None, init, settings, progress,
                          tried=next((t for t in tried if t.rec["effect"] == ss_effect), None))
    ok = [t for t in tried if not t.why]
    best = min(ok, key=lambda t: t.rec["cost_after"]) if ok else tried[0]
    step = _effect_record(res, tried, best, called, cost0)
    name = step.effect
    if best.why:
        refused = dataclasses.replace(res, effect_step=step, info=dict(res.info), warnings=[
            *res.warnings,
            f"the effect {name} was not added ({best.why}): the model is fitted as given"])
        return _finish(refused, bs, missions, model, effects)
    assert best.new is not None and best.bs is not None
    new = refit_structure(best.new, missions, model, (*effects, name), None, init,
                          best.bs.settings, progress)
    new = _finish(new, best.bs, missions, model, (*effects, name))
    # the batch time is both solves'
    base_s = float(res.timings.get("batch", [0.0])[0])
    step = dataclasses.replace(step, seconds_base=base_s)
    timings = {**new.timings, "batch": [base_s + float(new.timings.get("batch", [0.0])[0])]}
    warnings = [_added_warning(res, step, best.moved, called), *new.warnings]
    return dataclasses.replace(new, timings=timings, info=dict(new.info), effect_step=step,
                               warnings=warnings)


def effect_candidates(res: Result, bs: BatchSmoother, missions: list[Mission],
                      effects: Sequence) -> tuple[dict | None, list[dict]]:
    """The effect step's candidates for the batch fit ``res`` (structural-test entries),
    at most two, and the best-supported one the test calls for (None: none is)."""
    st = res.structural_test
    have = {getattr(e, "name", e) for e in effects}

    def dynamics(c: dict) -> bool:
        return c["effect"] not in have and dynamics_effect(c["effect"])
    # the candidates: the best-supported one the test calls for, and the one of largest
    # score statistic whether or not it passes the test's level alone (the test says the
    # model misses something; which effect explains it best, the refit's cost decides: on a
    # weak-propeller Otter at 1-s fixes the test called for the wind drag alone, whose
    # refit left the current 0.07 m/s off at cost 3015, where the linear drag, ranked first
    # by its statistic, fits at cost 1681 with the current 0.003 off;
    # docs/independent-vehicle.md)
    called = next((c for c in (st.called_for if st is not None else []) if dynamics(c)), None)
    if called is not None:
        assert st is not None
        top = next((c for c in st.ranked if dynamics(c)), called)
        return called, [called] + ([top] if top["effect"] != called["effect"] else [])
    # the fixes not explained (the sandwich's sigma MISFIT_INFLATION times the model's)
    # and no effect reaching the test's level: the one of largest score statistic is
    # tried, adopted only where it also lowers the cost by what its parameters cost (BIC;
    # a second candidate doubled the extra time). Under such a misfit the robust test
    # loses its power: a wide-condition Otter at 8-s fixes (0.17 m/s current) was 14x
    # inflated and its linear drag's p 0.52, and the refit with it lowered the cost
    # 1162 -> 376 and put the current 0.087 -> 0.007 m/s off (docs/independent-vehicle.md)
    return None, [c for c in _ranked_if_unexplained(res, bs, missions) if dynamics(c)][:1]


def _effect_record(res: Result, tried: list[EffectTry], best: EffectTry, called: dict | None,
                   cost0: float) -> EffectStep:
    """The effect step's record: the chosen try's, whether the fixes were explained, the
    model-as-given fit's cost and estimates (:func:`base_record`), every try where there
    were two, and whether the effect was adopted (else why not)."""
    r = best.rec
    two = len(tried) > 1
    assert called is not None or not two    # two are tried only where the test calls for one
    return EffectStep(
        effect=r["effect"], adopted=not best.why, p_value_robust=r["p_value_robust"],
        cost_before=cost0, base=base_record(res), cost_after=r["cost_after"],
        fixes_explained=res.sigma_structure is None,
        predicted_move=r["predicted_move"], moved=r.get("moved"), reason=best.why,
        untested=called is None,
        tried=[{**{k: v for k, v in t.rec.items() if k != "moved"},
                **({"reason": t.why} if t.why else {})} for t in tried] if two else None,
        called_for=called["effect"] if two and called is not None else None)


def _added_warning(res: Result, step: EffectStep, moved: dict[tuple[str, str], float],
                   called: dict | None) -> str:
    """The warning of a fit that added the effect ``step.effect`` to the model as given
    (``res``): why that effect, the costs, and how far the heading offset and the current
    moved (the largest move over the missions)."""
    name = step.effect
    th = [abs(d) for (_, n), d in moved.items() if n == "theta_e"]
    cur = [math.hypot(d, moved.get((m, "s_y"), 0.0)) for (m, n), d in moved.items()
           if n == "s_x"]
    parts = []
    if th:
        parts.append(f"theta_e moved by {np.degrees(max(th)):.2g} deg")
    if cur:
        parts.append(f"the current by {max(cur):.2g} m/s")
    infl = max(res.sigma_inflation.values(), default=float("nan"))
    why_this = (f"which explains the fixes best of those tried (the model as given does not "
                f"explain them, sigma inflated {infl:.1f}x, and no effect reached the "
                f"structural test's level: {name}'s robust p = {step.p_value_robust:.2g}"
                if called is None else
                f"which the data call for (robust score test p = {step.p_value_robust:.2g}"
                if name == called["effect"] else
                f"which explains the fixes best of those tried (the data call for "
                f"{called['effect']}, robust score test p = {called['p_value_robust']:.2g}; "
                f"{name}'s p = {step.p_value_robust:.2g}")
    return (f"added the effect {name}, {why_this}; cost {step.cost_before:.1f} -> "
            f"{step.cost_after:.1f}){': ' + ' and '.join(parts) if parts else ''}; "
            f"--no-auto-effect fits the model as given")


def _ranked_if_unexplained(res: Result, bs: BatchSmoother, missions: list[Mission]
                           ) -> list[dict]:
    """The structural test's candidates of the batch fit ``res`` (solver ``bs``) ranked by
    their score statistic whatever their p-values, where the fit does not explain its
    fixes (a sigma inflated more than ``MISFIT_INFLATION`` times by the sandwich) on its
    nominal-noise solution; else none. The ranking :func:`structural_sigma` recorded
    (``structural_test``), or the test's where it recorded none."""
    infl = max(res.sigma_inflation.values(), default=0.0)
    if infl <= MISFIT_INFLATION or bs.fast_solution is None or res.model is None:
        return []
    ranked = res.structural_test.ranked if res.structural_test is not None else None
    if ranked is None:
        fs, ev = bs.fast_solution
        sh = structural_shift(missions, fs, ev, res.model, tuple(res.estimated))
        ranked = sh.ranked if sh is not None else []
    return [c for c in ranked if c["statistic"] > 0.0]


def _try_effect(pick: dict, base: dict, cost0: float, missions: list[Mission], model,
                effects: Sequence, init, settings: FGSettings | None, progress,
                estimate: Sequence[str] | None = None, untested: bool = False) -> EffectTry:
    """The fit again with the candidate effect ``pick`` (a structural-test entry) added,
    judged against the model-as-given fit (``base``: its variable estimates and the guard's
    sigmas, :func:`guard_estimates`; ``cost0``: its cost). Its ``why`` is empty where the
    refit may be adopted: it lowers the cost, is plausible, and keeps the heading offset
    and the current within 3 of ``base``'s sigmas; ``untested``: the effect did not reach
    the structural test's level, and must also lower the cost by half its parameter count
    times log n (BIC, n the fix residuals, :func:`aqfg.fg.effect_guard.n_fix_residuals`)."""
    name = pick["effect"]
    # solved from the effect's one-step values and from its null, the lower cost kept: with
    # the linear drag the sway drag has two local minima (linear, c_yz > 0 and k_yz small;
    # or quadratic, c_yz at its bound 0), not a stop too early (a 1000x tighter stop ends
    # where the default does); the two starts ended 3-31 apart in cost on five of seven
    # Otter runs, each lower on some, and the higher one's sigma(theta_e) was 0.16 deg with
    # theta_e 1.0 deg off on one (docs/independent-vehicle.md)
    one_step = {n: v for n, v in pick.get("estimate", {}).items()
                if math.isfinite(v) and n not in (init or {})}
    starts = [{**(init or {}), **one_step}] + ([dict(init or {})] if one_step else [])
    # (the parameters the user chose, where any, and the effect's)
    est = None if estimate is None else (*estimate, *resolve(name).params)
    rec: dict = {"effect": name, "p_value_robust": float(pick["p_value_robust"]),
                 "predicted_move": dict(pick.get("shift", {}))}
    why = ""
    new = bs_new = None
    moved: dict[tuple[str, str], float] = {}     # (mission or "", name) -> refit - base
    solved = []
    for start in starts:
        try:
            o, bs_o = _solve(missions, model, (*effects, name), est, start, settings,
                             progress, log_warnings=False)
        except Exception as e:  # noqa: BLE001 -- an optional refit; the model as given stands
            why = why or f"its fit failed ({type(e).__name__}: {e})"
            continue
        solved.append(o)
        # (a start whose solve ends at a non-finite cost loses to any other: on
        # otter-dev-calm-a the one-step start, sway drag 101/s, ends at NaN after one
        # iteration, the null start at 1427, against 3189 without the effect)
        if new is None or _finite_cost(o) < _finite_cost(new):
            new, bs_new = o, bs_o
    if new is None:
        rec["cost_after"] = float("nan")
        return EffectTry(rec, None, None, why, moved)
    new = widen_by_other_minimum(new, [o for o in solved if o is not new])
    rec["cost_after"] = new.cost
    moved, far = moves(base, variable_estimates(new))
    rec["moved"] = {label(m, n): d for (m, n), d in moved.items()}
    if new.plausible is False:
        why = "its fit is not plausible"
    elif not rec["cost_after"] < cost0:
        why = f"it does not lower the cost ({cost0:.1f} -> {rec['cost_after']:.1f})"
    elif untested and not cost0 - rec["cost_after"] > (bic := bic_cost(name, missions)):
        why = (f"untested, it lowers the cost by {cost0 - rec['cost_after']:.1f}, not "
               f"the {bic:.1f} its parameters cost (BIC)")
    elif far:
        why = f"it moves {', '.join(far)} by more than 3 sigma of the fit without it"
    else:
        why = ""
    return EffectTry(rec, new, bs_new, why, moved)


def refit_structure(res: Result, missions: list[Mission], model, effects: Sequence,
                    estimate, init, settings: FGSettings | None, progress=False,
                    tried: EffectTry | None = None) -> Result:
    """Where the structural sigma of the batch fit ``res`` (:func:`structural_sigma`) rests
    on an effect the data prove (a dynamics effect), the fit again with that effect added
    (as the effect step tries it, :func:`_try_effect`; ``tried``: that try where the effect
    step made it), and ``res`` with sigmas that hold its exact move
    (:func:`aqfg.fg.structural_sigma.cover_refit`). The first-order shift assumes the
    estimates move linearly with the effect; on a GNSS-only Otter the sway drag changed
    basin when `reverse_thrust` joined, and the current moved 0.009 m/s where 0.0007 was
    predicted (docs/independent-vehicle.md)."""
    ss = res.sigma_structure
    have = {getattr(e, "name", e) for e in effects}
    if ss is None or not ss.proven or ss.effect in have or not dynamics_effect(ss.effect):
        return res
    name = ss.effect
    if tried is None:
        pick = next((c for c in ss.ranked if c["effect"] == name),
                    {"effect": name, "p_value_robust": ss.p_value_robust})
        tried = _try_effect(pick, variable_estimates(res), res.cost,
                            missions, model, effects, init, settings, progress, estimate)
    return cover_refit(res, tried.new, tried.why)


def _finite_cost(res: Result) -> float:
    """The batch cost of ``res``, infinite where it is missing or not finite."""
    c = res.cost
    return c if math.isfinite(c) else math.inf
