"""The fleet's effect step (:attr:`FGSettings.batch.auto_effect`, as ``aqfg fit``'s
:func:`aqfg.fg.fit.adopt_effect`): which effect the vehicles' structural tests call for,
whether the fleet's refit with it is kept, and the record of the step. One model serves
the whole fleet, so that its vehicles' constants compare (``fleet.json``'s test)."""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

from aqfg.fg.effect_guard import base_record, dynamics_effect, guard_estimates, moves, variable_estimates
from aqfg.fg.structural_sigma import cover_refit
from aqfg.result import EffectStep, FleetEffect, Result


def choose(results: dict[str, Result], effects: Sequence) -> dict | None:
    """The effect of the vehicle's dynamics (not a drift) that the most vehicles' structural
    tests call for (``structural_test.called_for``), ties broken by the summed
    score statistic: ``{"effect", "vehicles", "statistic", "p_value_robust": {vehicle: p}}``;
    None where no vehicle's test calls for one not already in ``effects``."""
    have = {getattr(e, "name", e) for e in effects}
    votes: dict[str, dict] = {}
    for v, r in results.items():
        st = r.structural_test
        if st is None:
            continue
        stat = {c["effect"]: float(c.get("statistic", 0.0)) for c in st.ranked}
        for c in st.called_for:
            e = c["effect"]
            if e in have or not dynamics_effect(e):
                continue
            x = votes.setdefault(e, {"effect": e, "vehicles": [], "statistic": 0.0,
                                     "p_value_robust": {}})
            x["vehicles"].append(v)
            x["statistic"] += stat.get(e, 0.0)
            x["p_value_robust"][v] = float(c["p_value_robust"])
    if not votes:
        return None
    return max(votes.values(), key=lambda x: (len(x["vehicles"]), x["statistic"]))


def _cost(results: dict[str, Result]) -> float:
    return sum(r.cost for r in results.values())


def judge(before: dict[str, Result], after: dict[str, Result], effect: str) -> str:
    """Why the fleet's refit ``after`` with ``effect`` may not replace ``before`` ("" where
    it may): it must lower the fleet's cost, every vehicle's fit must be plausible, and
    every mission's heading offset and current must stay within 3 of ``before``'s honest
    sigmas widened by the effect's predicted shift (:func:`aqfg.fg.effect_guard.guard_estimates`)."""
    c0, c1 = _cost(before), _cost(after)
    why = []
    for v, r in before.items():
        n = after[v]
        if n.plausible is False:
            why.append(f"vehicle {v}'s fit is not plausible")
            continue
        _, far = moves(guard_estimates(r, effect), variable_estimates(n))
        if far:
            why.append(f"it moves vehicle {v}'s {', '.join(far)} by more than 3 sigma of the "
                       "fit without it")
    if not c1 < c0:
        why.insert(0, f"it does not lower the fleet's cost ({c0:.1f} -> {c1:.1f})")
    return "; ".join(why)


def record(before: dict[str, Result], pick: dict, after: dict[str, Result] | None,
           why: str) -> None:
    """Each vehicle's ``effect_step`` (as :func:`aqfg.fg.fit.adopt_effect`'s, plus
    ``fleet``: the vehicles whose tests called for it, the fleet's cost and the step's
    message) and that message among its warnings, on ``after``'s results (the refit, None
    where it failed) where the effect was added (``why`` empty), else on ``before``'s:
    the results in those dicts are replaced by the recorded ones."""
    cost_before = _cost(before)
    cost_after = _cost(after) if after is not None else math.nan
    name, p = pick["effect"], min(pick["p_value_robust"].values())
    # one message for the fleet, the same in every vehicle's warnings
    message = (
        f"the effect {name} was not added to the fleet's model ({why}): the model is fitted "
        "as given" if why else
        f"added the effect {name} to the fleet's model, which the fits of "
        f"{len(pick['vehicles'])} of {len(before)} vehicles call for (robust score test "
        f"p = {p:.2g}; fleet cost {cost_before:.1f} -> {cost_after:.1f}); "
        "aqfg fleet --no-auto-effect (FGSettings.batch.auto_effect = False) fits the model as given")
    fleet = FleetEffect(list(pick["vehicles"]), cost_before, cost_after, message)
    for v, r in before.items():
        st = r.sigma_structure
        if after is not None and st is not None and st.effect == name and st.proven:
            # the model-as-given fit's structural sigma checked by the refit with its
            # effect, as aqfg fit's effect step does (aqfg.fg.fit.refit_structure)
            r = before[v] = cover_refit(r, after[v])
        step = EffectStep(effect=name, adopted=not why,
                          p_value_robust=pick["p_value_robust"].get(v, p),
                          cost_before=r.cost, base=base_record(r),
                          cost_after=(after[v].cost
                                      if after is not None else math.nan),
                          fixes_explained=r.sigma_structure is None, reason=why,
                          fleet=fleet)
        if why:
            before[v] = dataclasses.replace(r, effect_step=step, info=dict(r.info),
                                            warnings=[*r.warnings, message])
            continue
        assert after is not None
        a = after[v]
        after[v] = dataclasses.replace(a, effect_step=step, info=dict(a.info),
                                       warnings=[message, *a.warnings])
