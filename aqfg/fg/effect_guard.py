"""The judgements of the batch fit's effect step (:func:`aqfg.fg.fit.adopt_effect`) and of
the fleet's (:mod:`aqfg.fleet.effect`), as functions of results that return values: the
estimates the step guards (the heading offset and the current), how far a refit moves
them, what an effect's parameters cost, and the widening where another minimum explains
the fixes as well."""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from aqfg.data.mission import Mission
from aqfg.fg.batch import ambiguity_margin
from aqfg.model.effects import CurrentTerm, HeadingTerm, resolve
from aqfg.model.params import difference
from aqfg.result import BaseFit, OtherMinimum, Result


def widen_by_other_minimum(res: Result, others: list[Result]) -> Result:
    """Where another local minimum of the same model (another start) explains the fixes as
    well as ``res`` (cost within :func:`aqfg.fg.batch.ambiguity_margin`), the data do not
    decide between them: ``res`` with each estimated parameter's sigma (and each
    mission's) widened by its difference between the two; its ``other_minimum``
    records it. (On `heldout-103` at 8-s fixes the lower of two minima 4.4 apart in cost
    put the current 0.019 m/s off with sigma 0.005, the other 0.008 off:
    docs/independent-vehicle.md.)"""
    cost = res.cost
    near = [o for o in others
            if o.cost - cost < ambiguity_margin(cost)]
    if not near:
        return res
    # the largest difference over the near minima, top-level and per mission
    d_top: dict[str, float] = {}
    d_per: dict[tuple[str, str], float] = {}
    for o in near:
        for n in res.estimated:
            if n in res.sigma and n in o.values:
                d_top[n] = max(d_top.get(n, 0.0), abs(difference(n, o.values[n], res.values[n])))
        for m, est in res.per_mission.items():
            oe = o.per_mission.get(m, {})
            for n, e in est.items():
                if n in oe and e.sigma_computed:
                    d = abs(difference(n, oe[n].value, e.value))
                    d_per[m, n] = max(d_per.get((m, n), 0.0), d)
    per = {m: dict(est) for m, est in res.per_mission.items()}
    for (m, n), d in d_per.items():
        e = per[m][n]
        per[m][n] = dataclasses.replace(e, sigma=float(np.hypot(e.sigma, d)))
    before = {n: float(res.sigma[n]) for n in d_top}
    sigma = dict(res.sigma)
    for n, d in d_top.items():
        sigma[n] = float(np.hypot(sigma[n], d))
    other = OtherMinimum([o.cost for o in near], d_top, before)
    return dataclasses.replace(res, sigma=sigma, info=dict(res.info), per_mission=per,
                               other_minimum=other)


def base_record(res: Result) -> BaseFit:
    """The effect step's ``base``: the model-as-given fit's effects, values and sigmas (and
    each mission's, for a joint fit), kept beside a fit that added an effect."""
    return BaseFit(list(res.effects),
                   {n: float(res.values[n]) for n in
                    (res.model.active_names if res.model is not None else res.values)},
                   {n: float(v) for n, v in res.sigma.items()},
                   res.per_mission if len(res.missions) > 1 and res.per_mission else None)


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
    st = res.structural_test
    if (res.sigma_structure is not None and res.sigma_structure.effect == effect) \
            or (st is not None and not st.suggested):
        # (a test that suggests nothing predicts no move the guard should allow)
        return est
    ranked = st.ranked if st is not None else []
    shift: dict[str, float] = next((c.get("shift", {}) for c in ranked if c["effect"] == effect), {})
    return {(m, n): (v, float(math.hypot(s, shift.get(n, 0.0)))) for (m, n), (v, s) in est.items()}


def label(mission: str, name: str) -> str:
    """``name``, or ``mission:name`` for a joint fit's per-mission value."""
    return f"{mission}:{name}" if mission else name


def moves(base: dict, after: dict) -> tuple[dict[tuple[str, str], float], list[str]]:
    """From the :func:`variable_estimates` ``base`` (the model as given) to ``after`` (a
    refit): each estimate's move, ``{(mission or "", name): after - base}``, and the labels
    of those beyond 3 of ``base``'s sigmas (a NaN sigma counts as beyond: nothing says the
    move is within it), the effect step's guard."""
    moved = {(m, n): difference(n, after[m, n][0], v)
             for (m, n), (v, _) in base.items() if (m, n) in after}
    far = [label(m, n) for (m, n), d in moved.items() if not abs(d) <= 3.0 * base[m, n][1]]
    return moved, far


def dynamics_effect(name: str) -> bool:
    """An effect the effect step may add: one of the vehicle's dynamics, not a drift of the
    heading offset or the current, which would make the reported values those at the start
    (and the two drifts stand in for each other: docs/independent-vehicle.md)."""
    return not isinstance(resolve(name), (HeadingTerm, CurrentTerm))


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
