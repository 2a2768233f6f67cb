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
from aqfg.fg import dead_reckoning, gnss_noise, jackknife
from aqfg.fg.batch import MISFIT_INFLATION, BatchSmoother
from aqfg.fg.common import FGSettings, check_missions, mission_model
from aqfg.fg.fastlm import FastSystem
from aqfg.fg.fixed_lag import FixedLagSmoother, UpdateInfo
from aqfg.fg.structure import structural_shift
from aqfg.model.effects import CurrentTerm, HeadingTerm, resolve
from aqfg.model.params import difference
from aqfg.model.retrace import inertial_track
from aqfg.result import Result

__all__ = ["BatchSmoother", "FixedLagSmoother", "FGSettings", "UpdateInfo", "fit_fg"]

log = logging.getLogger(__name__)

# the structural sigma looks for a missing effect where the block sandwich raised any sigma
# of the fit above the model's (significantly: aqfg.fg.covariance), not only where it
# raised one 3x (the warning's level, batch.MISFIT_INFLATION): docs/independent-vehicle.md
STRUCTURAL_MISFIT = 1.0 + 1e-9


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
    res = _fit(missions, mode, estimate, init, effects, window, progress, settings, model)
    return res


def _fit(missions, mode, estimate, init, effects, window, progress, settings, model) -> Result:
    """:func:`fit_fg` with the fixes weighted by the GNSS noise (``FGSettings.gnss_noise``)."""
    st0 = settings or FGSettings()
    missions, noise = gnss_noise.apply(list(missions), st0.gnss_noise, st0.online_kinematic_q,
                                       st0.sensors.gnss_sigma, track=mode == "online")
    res = _fit_weighted(missions, mode, estimate, init, effects, window, progress, settings, model)
    if noise is not None:
        res.info["gnss_noise"] = noise.document()
    return res


def _fit_weighted(missions, mode, estimate, init, effects, window, progress, settings, model
                  ) -> Result:
    if mode == "batch":
        st = settings or FGSettings()
        auto = auto_effect_applies(st, estimate)
        res, bs = _solve(missions, model, effects, estimate, init, settings, progress,
                         log_warnings=not auto, test_always=auto, refit=not auto)
        if auto:
            res = adopt_effect(res, bs, list(missions), model, effects, init, settings,
                               progress)
        else:
            res = _finish(res, bs, missions, model, effects)
        n_warn = len(res.info.get("warnings", []))
        if st.block_jackknife and len(missions) == 1 and res.info.get("too_short_for_sandwich"):
            _block_jackknife(res, missions[0], model, effects, init, st)
        for w in res.info.get("warnings", [])[0 if auto else n_warn:]:
            log.warning("fg: %s", w)
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


def _block_jackknife(res: Result, mission: Mission, model, effects: Sequence, init,
                     settings: FGSettings) -> None:
    """:attr:`FGSettings.block_jackknife` on the batch fit ``res`` of ``mission``, in place:
    its refits keep ``res``'s model (its effects, the effect step's among them) and its
    estimated parameters, without the effect step, the heading profile or the track's
    noise, and log nothing (their warnings are theirs, not the fit's)."""
    have = {getattr(e, "name", e) for e in effects}
    eff = (*effects, *(n for n in res.effects if n not in have))
    quick = settings.with_(auto_effect=False, heading_profile=False, adapt_track=False)
    est = tuple(res.estimated)

    def refit(m: Mission) -> Result:
        r, b = _solve([m], model, eff, est, init, quick, progress=False, log_warnings=False)
        return _finish(r, b, [m], model, eff)
    jackknife.widen(res, mission, refit)


def auto_effect_applies(settings: FGSettings, estimate: Sequence[str] | None) -> bool:
    """Whether a batch fit (``aqfg fit``'s or the fleet's) takes the effect step
    (:attr:`FGSettings.auto_effect`): on, the default parameters (no ``estimate``: with it
    the user has chosen the model) and the structural test that names the effect."""
    return settings.auto_effect and estimate is None and settings.structural_sigma


def _solve(missions: Sequence[Mission], model, effects: Sequence, estimate, init, settings,
           progress, log_warnings: bool = True, test_always: bool = False,
           refit: bool = False) -> tuple[Result, BatchSmoother]:
    """The batch solve of :func:`fit_fg` with the model as given, and its structural sigma
    (checked by a refit with the effect where ``refit``: :func:`refit_structure`);
    :func:`_finish` completes it."""
    bs = BatchSmoother(model, effects=effects, estimate=estimate, init=init,
                       settings=settings, progress=progress)
    bs.log_warnings = log_warnings
    bs.inertial = bs.settings.dr_horizon <= 0   # re-traced once, with the final constants
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
            if log_warnings and "sigma_structure" in res.info:
                log.warning("fg: %s", res.info["sigma_structure"]["warning"])
    return res, bs


def _finish(res: Result, bs: BatchSmoother, missions: Sequence[Mission], model,
            effects: Sequence) -> Result:
    """The dead-reckoning constants, smoothed tracks and model-only re-traces of a solve."""
    # the constants to dead-reckon with: multi-step prediction error where it differs
    # significantly from the smoother's one-interval fit (aqfg.fg.dead_reckoning), from
    # the nominal fit's states (as the fleet's)
    res = dead_reckoning.refine(res, list(missions), bs.settings.dr_horizon)
    res = bs.smooth_tracks(res)
    for m, mr in zip(missions, res.missions):
        if not len(mr.inertial.t):
            mr.inertial = inertial_track(mission_model(model, m, effects), m, mr.p)
    return res


def _widen_by_other_minimum(res: Result, others: list[Result]) -> None:
    """Where another local minimum of the same model (another start) explains the fixes as
    well as ``res`` (cost within :func:`aqfg.fg.batch.ambiguity_margin`), the data do not
    decide between them: each estimated parameter's sigma (and each mission's) widened by
    its difference between the two, in place; ``info["other_minimum"]`` records it. (On
    `heldout-103` at 8-s fixes the lower of two minima 4.4 apart in cost put the current
    0.019 m/s off with sigma 0.005, the other 0.008 off: docs/independent-vehicle.md.)"""
    from aqfg.fg.batch import ambiguity_margin
    cost = float(res.info.get("cost", np.nan))
    near = [o for o in others
            if float(o.info.get("cost", np.inf)) - cost < ambiguity_margin(cost)]
    if not near:
        return
    # the largest difference over the near minima, top-level and per mission
    d_top: dict[str, float] = {}
    d_per: dict[tuple[str, str], float] = {}
    for o in near:
        for n in res.estimated:
            if n in res.sigma and n in o.values:
                d_top[n] = max(d_top.get(n, 0.0), abs(difference(n, o.values[n], res.values[n])))
        for m, est in (res.info.get("per_mission") or {}).items():
            oe = (o.info.get("per_mission") or {}).get(m, {})
            for n, e in est.items():
                if n in oe and isinstance(e, dict) and e.get("sigma") is not None:
                    d = abs(difference(n, float(oe[n]["value"]), float(e["value"])))
                    d_per[m, n] = max(d_per.get((m, n), 0.0), d)
    for (m, n), d in d_per.items():
        e = res.info["per_mission"][m][n]
        e["sigma"] = float(np.hypot(float(e["sigma"]), d))
    before = {n: float(res.sigma[n]) for n in d_top}
    for n, d in d_top.items():
        res.sigma[n] = float(np.hypot(res.sigma[n], d))
    res.info["other_minimum"] = {"cost": [float(o.info.get("cost", np.nan)) for o in near],
                                 "difference": d_top, "sigma_before": before}


def base_record(res: Result) -> dict:
    """``info["auto_effect"]["base"]``: the model-as-given fit's effects, values and sigmas
    (and each mission's, for a joint fit), kept beside a fit that added an effect."""
    return {"effects": list(res.effects),
            "values": {n: float(res.values[n]) for n in
                       (res.model.active_names if res.model is not None else res.values)},
            "sigma": {n: float(v) for n, v in res.sigma.items()},
            **({"per_mission": res.info["per_mission"]}
               if len(res.missions) > 1 and res.info.get("per_mission") else {})}


def variable_estimates(res: Result) -> dict[tuple[str, str], tuple[float, float]]:
    """``{(mission or "", name): (value, sigma)}`` of the heading offset and the current:
    per mission where a joint fit has them per mission, else the fit's."""
    names = [n for n in ("theta_e", "s_x", "s_y") if n in res.estimated]
    per = res.per_mission
    out: dict[tuple[str, str], tuple[float, float]] = {}
    for n in names:
        rows = [(m, e[n]) for m, e in per.items() if n in e] if len(res.missions) > 1 else []
        if rows:
            out.update({(m, n): (e.value, e.sigma) for m, e in rows})
        else:
            out[("", n)] = (float(res.values[n]), float(res.sigma.get(n, np.nan)))
    return out


def guard_estimates(res: Result, effect: str) -> dict[tuple[str, str], tuple[float, float]]:
    """The effect step's guard for a refit of ``res`` with ``effect``: ``res``'s
    :func:`variable_estimates` with each sigma widened (in quadrature) by the move the
    structural test predicts for that effect (its ``shift``), unless the sigma already
    holds it (``sigma_structure``). A refit that moves the estimates as predicted is the
    effect at work; one that moves them far beyond went elsewhere. Without the prediction
    a REMUS 100 whose current the effect corrects by 0.015 m/s (7 of the fit's sigmas, the
    fixes explained) was refused (docs/independent-vehicle.md)."""
    est = variable_estimates(res)
    st = res.info.get("structural_test") or {}
    if (res.info.get("sigma_structure") or {}).get("effect") == effect \
            or not st.get("suggested", True):
        # (a test that suggests nothing predicts no move the guard should allow)
        return est
    ranked = st.get("ranked", [])
    shift: dict[str, float] = next((c.get("shift", {}) for c in ranked if c["effect"] == effect), {})
    return {(m, n): (v, float(math.hypot(s, shift.get(n, 0.0)))) for (m, n), (v, s) in est.items()}


def _label(mission: str, name: str) -> str:
    """``name``, or ``mission:name`` for a joint fit's per-mission value."""
    return f"{mission}:{name}" if mission else name


def moves(base: dict, after: dict) -> tuple[dict[tuple[str, str], float], list[str]]:
    """From the :func:`variable_estimates` ``base`` (the model as given) to ``after`` (a
    refit): each estimate's move, ``{(mission or "", name): after - base}``, and the labels
    of those beyond 3 of ``base``'s sigmas (a NaN sigma counts as beyond: nothing says the
    move is within it), the effect step's guard."""
    moved = {(m, n): difference(n, after[m, n][0], v)
             for (m, n), (v, _) in base.items() if (m, n) in after}
    far = [_label(m, n) for (m, n), d in moved.items() if not abs(d) <= 3.0 * base[m, n][1]]
    return moved, far


def dynamics_effect(name: str) -> bool:
    """An effect the effect step may add: one of the vehicle's dynamics, not a drift of the
    heading offset or the current, which would make the reported values those at the start
    (and the two drifts stand in for each other: docs/independent-vehicle.md)."""
    return not isinstance(resolve(name), (HeadingTerm, CurrentTerm))


def adopt_effect(res: Result, bs: BatchSmoother, missions: list[Mission], model,
                 effects: Sequence, init, settings: FGSettings | None, progress=False) -> Result:
    """:attr:`FGSettings.auto_effect`: where the structural test of the batch fit ``res``
    names missing effects (``info["structural_test"]``), the fit again with the
    best-supported one of the vehicle's dynamics (not a drift of the heading offset or the
    current) added, and with the one of largest score statistic if that is another; the
    lower-cost result of those that explain the fixes better (lower cost), are plausible,
    and keep the heading offset and the current within 3 sigma of ``res``'s honest sigma
    (which includes the effect's predicted shift); otherwise ``res``, saying why.
    ``info["auto_effect"]`` records the step and the base fit's estimates."""
    st = res.info.get("structural_test")
    have = {getattr(e, "name", e) for e in effects}

    def dynamics(c: dict) -> bool:
        return c["effect"] not in have and dynamics_effect(c["effect"])
    # the candidates, at most two: the best-supported one the test calls for, and the one
    # of largest score statistic whether or not it passes the test's level alone (the test
    # says the model misses something; which effect explains it best, the refit's cost
    # decides: on a weak-propeller Otter at 1-s fixes the test called for the wind drag
    # alone, whose refit left the current 0.07 m/s off at cost 3015, where the linear drag,
    # ranked first by its statistic, fits at cost 1681 with the current 0.003 off;
    # docs/independent-vehicle.md)
    called = next((c for c in (st or {}).get("called_for", []) if dynamics(c)), None)
    if called is not None:
        top = next((c for c in (st or {}).get("ranked", []) if dynamics(c)), called)
        picks = [called] + ([top] if top["effect"] != called["effect"] else [])
    else:
        # the fixes not explained (the sandwich's sigma MISFIT_INFLATION times the
        # model's) and no effect reaching the test's level: the one of largest score
        # statistic is tried, adopted only where it also lowers the cost by what its
        # parameters cost (BIC; a second candidate doubled the extra time). Under such a
        # misfit the robust test loses its power: a wide-condition Otter at 8-s fixes
        # (0.17 m/s current) was 14x inflated and its linear drag's p 0.52, and the refit
        # with it lowered the cost 1162 -> 376 and put the current 0.087 -> 0.007 m/s off
        # (docs/independent-vehicle.md)
        picks = [c for c in _ranked_if_unexplained(res, bs, missions) if dynamics(c)][:1]
        if not picks:
            return _finish(res, bs, missions, model, effects)
    cost0 = float(res.info.get("cost", np.nan))
    tried = []
    for pick in picks:
        tried.append(_try_effect(pick, guard_estimates(res, pick["effect"]), cost0, missions,
                                 model, effects, init, settings, progress,
                                 untested=called is None))
    # the model-as-given fit's structural sigma checked by the refit with its effect, as
    # `--no-auto-effect` checks it (refit_structure): its record and a refused step's fit
    ss_effect = (res.info.get("sigma_structure") or {}).get("effect")
    res = refit_structure(res, missions, model, effects, None, init, settings, progress,
                          tried=next((t for t in tried if t["rec"]["effect"] == ss_effect),
                                     None))
    ok = [t for t in tried if not t["why"]]
    best = min(ok, key=lambda t: t["rec"]["cost_after"]) if ok else tried[0]
    name, new, bs_new, why, moved = (best["rec"]["effect"], best["new"], best["bs"],
                                     best["why"], best["moved"])
    rec: dict = {**best["rec"], "fixes_explained": "sigma_structure" not in res.info,
                 "cost_before": cost0, "base": base_record(res)}
    if len(tried) > 1:
        assert called is not None           # two are tried only where the test calls for one
        rec["tried"] = [{**{k: v for k, v in t["rec"].items() if k != "moved"},
                         **({"reason": t["why"]} if t["why"] else {})} for t in tried]
        rec["called_for"] = called["effect"]
    if called is None:
        rec["untested"] = True
    rec["adopted"] = not why
    if why:
        rec["reason"] = why
        res.info["auto_effect"] = rec
        res.info.setdefault("warnings", []).append(
            f"the effect {name} was not added ({why}): the model is fitted as given")
        return _finish(res, bs, missions, model, effects)
    assert new is not None
    new = refit_structure(new, missions, model, (*effects, name), None, init,
                          bs_new.settings, progress)
    new = _finish(new, bs_new, missions, model, (*effects, name))
    # the batch time is both solves'
    rec["seconds_base"] = float(res.timings.get("batch", [0.0])[0])
    new.timings["batch"] = [rec["seconds_base"] + float(new.timings.get("batch", [0.0])[0])]
    new.info["auto_effect"] = rec
    # the largest move over the missions
    th = [abs(d) for (_, n), d in moved.items() if n == "theta_e"]
    cur = [math.hypot(d, moved.get((m, "s_y"), 0.0)) for (m, n), d in moved.items()
           if n == "s_x"]
    parts = []
    if th:
        parts.append(f"theta_e moved by {np.degrees(max(th)):.2g} deg")
    if cur:
        parts.append(f"the current by {max(cur):.2g} m/s")
    infl = max(res.info.get("sigma_inflation", {}).values(), default=float("nan"))
    why_this = (f"which explains the fixes best of those tried (the model as given does not "
                f"explain them, sigma inflated {infl:.1f}x, and no effect reached the "
                f"structural test's level: {name}'s robust p = {rec['p_value_robust']:.2g}"
                if called is None else
                f"which the data call for (robust score test p = {rec['p_value_robust']:.2g}"
                if name == called["effect"] else
                f"which explains the fixes best of those tried (the data call for "
                f"{called['effect']}, robust score test p = {called['p_value_robust']:.2g}; "
                f"{name}'s p = {rec['p_value_robust']:.2g}")
    new.info.setdefault("warnings", []).insert(
        0, f"added the effect {name}, {why_this}; cost {rec['cost_before']:.1f} -> "
           f"{rec['cost_after']:.1f}){': ' + ' and '.join(parts) if parts else ''}; "
           f"--no-auto-effect fits the model as given")
    return new


def _ranked_if_unexplained(res: Result, bs: BatchSmoother, missions: list[Mission]
                           ) -> list[dict]:
    """The structural test's candidates of the batch fit ``res`` (solver ``bs``) ranked by
    their score statistic whatever their p-values, where the fit does not explain its
    fixes (a sigma inflated more than ``MISFIT_INFLATION`` times by the sandwich) on its
    nominal-noise solution; else none. The ranking :func:`structural_sigma` recorded
    (``info["structural_test"]``), or the test's where it recorded none."""
    infl = max(res.info.get("sigma_inflation", {}).values(), default=0.0)
    if infl <= MISFIT_INFLATION or bs.fast_solution is None or res.model is None:
        return []
    ranked = (res.info.get("structural_test") or {}).get("ranked")
    if ranked is None:
        fs, ev = bs.fast_solution
        sh = structural_shift(missions, fs, ev, res.model, tuple(res.estimated))
        ranked = sh.ranked if sh is not None else []
    return [c for c in ranked if c["statistic"] > 0.0]


def n_fix_residuals(missions: Sequence[Mission]) -> int:
    """How many scalar fix residuals ``missions`` have (GNSS and USBL two each, depth one):
    the n of an information criterion."""
    n = 0
    for m in missions:
        n += 2 * (len(m.gnss.t) if m.gnss is not None else 0)
        n += 2 * (len(m.usbl.t) if m.usbl is not None else 0)
        n += len(m.depth.t) if m.depth is not None else 0
    return n


def bic_cost(effect: str, missions: Sequence[Mission]) -> float:
    """What ``effect``'s parameters cost in the batch's cost (1/2 chi-square) by the
    Bayesian information criterion: half their count times log n, n the fix residuals
    (:func:`n_fix_residuals`)."""
    return 0.5 * len(resolve(effect).params) * math.log(max(n_fix_residuals(missions), 2))


def _try_effect(pick: dict, base: dict, cost0: float, missions: list[Mission], model,
                effects: Sequence, init, settings: FGSettings | None, progress,
                estimate: Sequence[str] | None = None, untested: bool = False) -> dict:
    """The fit again with the candidate effect ``pick`` (a structural-test entry) added,
    judged against the model-as-given fit (``base``: its variable estimates and the guard's
    sigmas, :func:`guard_estimates`; ``cost0``: its cost). Returns ``{"rec", "new",
    "bs", "why", "moved"}``; ``why`` is empty where the refit may be adopted: it lowers the
    cost, is plausible, and keeps the heading offset and the current within 3 of ``base``'s
    sigmas; ``untested``: the effect did not reach the structural test's level, and must
    also lower the cost by half its parameter count times log n (BIC, n the fix residuals,
    :func:`n_fix_residuals`)."""
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
        if new is None or float(o.info.get("cost", np.inf)) < float(new.info.get("cost", np.inf)):
            new, bs_new = o, bs_o
    if new is not None:
        why = ""
        _widen_by_other_minimum(new, [o for o in solved if o is not new])
        rec["cost_after"] = float(new.info.get("cost", np.nan))
        moved, far = moves(base, variable_estimates(new))
        rec["moved"] = {_label(m, n): d for (m, n), d in moved.items()}
        if not new.info.get("plausible", True):
            why = "its fit is not plausible"
        elif not rec["cost_after"] < cost0:
            why = f"it does not lower the cost ({cost0:.1f} -> {rec['cost_after']:.1f})"
        elif untested and not cost0 - rec["cost_after"] > (bic := bic_cost(name, missions)):
            why = (f"untested, it lowers the cost by {cost0 - rec['cost_after']:.1f}, not "
                   f"the {bic:.1f} its parameters cost (BIC)")
        elif far:
            why = f"it moves {', '.join(far)} by more than 3 sigma of the fit without it"
    else:
        rec["cost_after"] = float("nan")
    return {"rec": rec, "new": new, "bs": bs_new, "why": why, "moved": moved}


def structural_sigma(res: Result, missions: list[Mission], fs: FastSystem, ev: dict,
                     settings: FGSettings, log_warnings: bool = True,
                     test_always: bool = False) -> Result:
    """:attr:`FGSettings.structural_sigma`: where the batch fit ``res`` (nominal noise) does
    not explain the fixes (the block sandwich raised a sigma above the model's,
    ``STRUCTURAL_MISFIT``, or the data are too short for the sandwich)
    and the data call for a missing effect, the sigma of the heading offset and the
    current widened by the shift that effect would cause
    (:func:`aqfg.fg.structure.structural_shift`, on the batch's numpy system ``fs``
    at its nominal-noise solution, or the evidence's on short data, evaluation ``ev``),
    in place; ``info["sigma_structure"]``
    and a warning say which effect and how much. ``test_always``: the test also where the
    fixes are explained (for :attr:`FGSettings.auto_effect`), its result in
    ``info["structural_test"]`` (the sigma is widened only where they are not); the test's
    ranking is recorded there whether or not it suggests an effect (``suggested``)."""
    infl = res.info.get("sigma_inflation", {})
    # data too short for the sandwich cannot show a misfit by it: the test decides alone
    # there (a 170-s crop of an Otter mission put the current 0.46 m/s off with sigma 0.03,
    # where the effects the test suggested would move it 0.3: docs/independent-vehicle.md)
    misfit = max(infl.values(), default=0.0) > STRUCTURAL_MISFIT or \
        bool(res.info.get("too_short_for_sandwich"))
    if (not settings.structural_sigma or settings.walk_sigma or res.model is None
            or not (misfit or test_always)):
        return res
    sh = structural_shift(missions, fs, ev, res.model, tuple(res.estimated))
    if sh is None:
        return res
    res.info["structural_test"] = sh.to_json()
    if not misfit or not sh.suggested:
        return res
    before = {n: float(res.sigma[n]) for n in sh.shift if n in res.sigma}
    for n, d in sh.shift.items():
        if n in res.sigma:
            res.sigma[n] = float(np.hypot(res.sigma[n], d))
        for e in (res.info.get("per_mission") or {}).values():
            # a joint fit's per-mission values: the same shift (the largest over them)
            if isinstance(e.get(n), dict) and "sigma" in e[n]:
                e[n]["sigma"] = float(np.hypot(e[n]["sigma"], d))
    w = _structure_warning(sh.effect, sh.proven, sh.p_robust, sh.shift)
    res.info["sigma_structure"] = {**sh.to_json(), "sigma_before": before, "warning": w}
    res.info.setdefault("warnings", []).append(w)
    if log_warnings:
        log.warning("fg: %s", w)
    return res


def _structure_warning(effect: str, proven: bool, p_robust: float, shift: dict[str, float],
                       moved: dict[str, float] | None = None) -> str:
    """The structural sigma's warning: which effect and how far it moves the heading offset
    and the current (its first-order ``shift``; with ``moved``, the refit's move beside it),
    which the sigma includes (the larger of the two)."""
    def words(d: dict[str, float]) -> str:
        parts = []
        if "theta_e" in d:
            parts.append(f"theta_e by {np.degrees(d['theta_e']):.2g} deg")
        cur = [d[n] for n in ("s_x", "s_y") if n in d]
        if cur:
            parts.append(f"the current by {math.sqrt(sum(c * c for c in cur)):.2g} m/s")
        return " and ".join(parts) or "the estimates"
    verb = "call for" if proven else "suggest (do not prove)"
    how = (f"refitted with it, {words(moved)} move (to first order {words(shift)}); sigma "
           "includes the larger" if moved is not None else
           f"with it {words(shift)} would move; sigma includes that shift")
    return (f"the data {verb} the effect {effect} (robust score test p = {p_robust:.2g}): "
            f"{how} (try --effect {effect}, or `aqfg diagnose`)")


def refit_structure(res: Result, missions: list[Mission], model, effects: Sequence,
                    estimate, init, settings: FGSettings | None, progress=False,
                    tried: dict | None = None) -> Result:
    """Where the structural sigma of the batch fit ``res`` (:func:`structural_sigma`) rests
    on an effect the data prove (a dynamics effect), the fit again with that effect added
    (as the effect step tries it, :func:`_try_effect`; ``tried``: that try where the effect
    step made it), and ``res``'s sigmas hold its exact move (:func:`cover_refit`), in
    place. The first-order shift assumes the estimates move linearly with the effect; on a
    GNSS-only Otter the sway drag changed basin when `reverse_thrust` joined, and the
    current moved 0.009 m/s where 0.0007 was predicted (docs/independent-vehicle.md)."""
    ss = res.info.get("sigma_structure")
    have = {getattr(e, "name", e) for e in effects}
    if not ss or not ss.get("proven") or ss["effect"] in have \
            or not dynamics_effect(ss["effect"]):
        return res
    name = ss["effect"]
    if tried is None:
        pick = next((c for c in ss.get("ranked", []) if c["effect"] == name),
                    {"effect": name, "p_value_robust": ss["p_value_robust"]})
        tried = _try_effect(pick, variable_estimates(res), float(res.info.get("cost", np.nan)),
                            missions, model, effects, init, settings, progress, estimate)
    return cover_refit(res, tried["new"], tried["why"])


def cover_refit(res: Result, new: Result | None, why: str = "") -> Result:
    """``res``'s variable parameters' sigmas (top level and each mission's) widened to hold
    their exact move to ``new``, the fit again with the effect of its structural sigma
    (``info["sigma_structure"]``), where that move exceeds the first-order shift they
    hold, in place; used where ``new`` is plausible and lowers the cost. The record:
    ``info["sigma_structure"]["refit"]``; the structural warning says the move."""
    ss = res.info["sigma_structure"]
    rec: dict = {"effect": ss["effect"]}
    ss["refit"] = rec
    if new is None:
        rec["failed"] = why or "no solution"
        return res
    rec["cost"] = float(new.info.get("cost", np.nan))
    if not new.info.get("plausible", True):
        rec["not_used"] = "implausible"
        return res
    if not rec["cost"] < float(res.info.get("cost", np.nan)):
        rec["not_used"] = "it does not lower the cost"
        return res
    first = ss.get("shift", {})
    names: list[str] = [n for n in ("theta_e", "s_x", "s_y")
                        if n in res.sigma and n in new.values]
    move: dict[str, float] = {n: abs(difference(n, new.values[n], res.values[n])) for n in names}
    before = {n: float(res.sigma[n]) for n in names}
    for n in names:
        res.sigma[n] = _cover(res.sigma[n], move[n], first.get(n, 0.0))
    per, per_new = res.info.get("per_mission") or {}, new.info.get("per_mission") or {}
    for m, est_m in per.items():
        for n in names:
            em, en = est_m.get(n), per_new.get(m, {}).get(n)
            if isinstance(em, dict) and isinstance(en, dict) and em.get("sigma") is not None:
                d = abs(difference(n, float(en["value"]), float(em["value"])))
                em["sigma"] = _cover(float(em["sigma"]), d, first.get(n, 0.0))
                move[f"{m}:{n}"] = d
    rec.update(move=move, sigma_before=before)
    w = _structure_warning(ss["effect"], True, float(ss["p_value_robust"]), first,
                           moved={n: move[n] for n in names})
    warns = res.info.setdefault("warnings", [])
    warns[:] = [w if x == ss.get("warning") else x for x in warns]
    ss["warning"] = w
    return res


def _cover(sigma: float, move: float, first: float) -> float:
    """``sigma`` (which holds the first-order shift ``first`` in quadrature) widened to
    hold the exact ``move`` instead, where that is larger."""
    if not move > first:
        return float(sigma)
    return float(math.sqrt(sigma * sigma + move * move - first * first))
