"""The heading basins of a batch fit: their summaries, the ambiguity between them and
what the fit must say in words.

Each LM solve from another start is summarised by :func:`basin_summary` into
``Result.basins``; basins within :func:`ambiguity_margin` of the best and more than
``AMBIGUOUS_GAP`` from it in heading make the fit ambiguous, and their spread widens the
sigmas (:func:`ambiguity_variance`); on data too short for the sandwich the heading profile
widens them (:func:`widen_by_profile`). :func:`batch_warnings` words it all for the user.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from aqfg.fg import observability
from aqfg.fg.fastlm import FastSystem
from aqfg.fg.graph import BuiltGraph
from aqfg.fg.graph_lm import LMOutcome
from aqfg.fg.profile import heading_profile, worth_walking
from aqfg.fg.settings import FGSettings
from aqfg.result import HeadingEvidence, Result


def basin_summary(bg: BuiltGraph, out: LMOutcome, verdicts, label: str) -> dict:
    """Summary of one solve for ``Result.basins``."""
    th: dict[str, float] = {}
    if "variable" in bg.layout.names and "theta_e" in bg.layout.names["variable"]:
        i = bg.layout.names["variable"].index("theta_e")
        for n in bg.nodes:
            if n.group == "variable" and n.mission is not None:
                th.setdefault(bg.parts[n.mission].mission.name, float(out.values.atVector(n.key)[i]))
    # the parameter values of the first mission (and the shared ones), by name
    vals: dict[str, float] = {}
    for n in bg.nodes:
        if n.mission in (None, 0):
            vals.update(zip(bg.layout.names[n.group], map(float, out.values.atVector(n.key))))
    return {"start": label, "cost": out.cost, "theta_e": th, "values": vals,
            "converged": out.converged,
            "iterations": out.iterations,
            "plausible": all(v.plausible for v in verdicts),
            "checks": {bg.parts[i].mission.name: v.as_dict() for i, v in enumerate(verdicts)}}


def sigma_by_name(layout, node_list, cov) -> dict:
    """1-sigma of the first mission's nodes by parameter name (as Result.sigma)."""
    out: dict[str, float] = {}
    for g, k, mi in node_list:
        if mi not in (None, 0) or k not in cov:
            continue
        for n, c in zip(layout.names[g], np.sqrt(np.maximum(np.diag(cov[k]), 0.0))):
            out.setdefault(n, c)
    return out


# rad: solutions this far apart in heading are different basins
AMBIGUOUS_GAP = np.radians(10.0)


# the honest sigma this many times the model's: the fixes are not explained as the noise
# model says (warned; the structural sigma is looked for, aqfg.fg.structure)
MISFIT_INFLATION = 3.0


def ambiguity_margin(best_cost: float) -> float:
    """Cost (1/2 chi-square) within which another basin explains the fixes as well as the
    best one: 2 (a likelihood ratio of e^2), or 1 % of the cost when the model misses
    physics and the cost is large."""
    return max(2.0, 0.01 * float(best_cost))


def as_good_a_basin(b: dict, best_cost: float, other: dict) -> bool:
    """Basin ``b`` (a ``Result.basins`` entry) explains the fixes as well as the best cost
    (:func:`ambiguity_margin`) and is another heading basin than ``other`` (more than
    ``AMBIGUOUS_GAP`` apart)."""
    return (basin_rank(b) - best_cost < ambiguity_margin(best_cost)
            and _heading_gap(b, other) > AMBIGUOUS_GAP)


def ambiguity_variance(chosen: dict[str, float], ambiguous: list[dict], cost: float
                       ) -> dict[str, float]:
    """Variance to add to each parameter's sigma when other basins (``Result.ambiguous``
    entries) explain the fixes as well as the chosen solution (``chosen`` values, cost
    ``cost``): the second moment about the chosen value of the mixture of the solutions,
    weighted by their likelihood ratios ``exp(cost - cost_b)`` (the chosen one weight 1);
    angles (theta_e) wrapped. Names: those of the basins' ``values`` (the first mission's
    and the shared parameters)."""
    return basin_spread(chosen, [(b["values"], basin_rank(b)) for b in ambiguous], cost)


def widen_by_profile(res: Result, fs: FastSystem, bg: BuiltGraph, node_list, values,
                      s: FGSettings) -> None:
    """:attr:`FGSettings.batch.heading_profile`: the heading offset's profile over the circle
    (:func:`aqfg.fg.profile.heading_profile`, one mission's theta_e) into
    ``res.heading_profile``; each sigma of the first mission's parameters widened to
    the profile's spread about the fit where that is larger (the former sigmas in
    ``res.sigma_before_profile``)."""
    lay = bg.layout
    if "theta_e" not in lay.estimated:
        return
    js = [fs.node_off[n.key][0] + lay.names["variable"].index("theta_e")
          for n in node_list if n.group == "variable"]
    if len(js) != 1 or not worth_walking(float(res.sigma.get("theta_e", np.inf))):
        return
    held = [fs.node_off[n.key][0] + i for n in node_list if n.group == "fixed"
            for i in range(lay.dim("fixed"))]
    X0, th0 = fs.from_values(values)
    prof = heading_profile(fs, X0, th0, js[0], s, held)
    before = {}
    for g, k, mi in node_list:
        if mi not in (None, 0):
            continue
        o, _ = fs.node_off[k]
        for i, n in enumerate(lay.names[g]):
            v = prof.heading_spread() if o + i == js[0] else prof.spread(o + i)
            sd = float(np.sqrt(v))
            if n in res.sigma and sd > res.sigma[n]:
                before[n] = res.sigma[n]
                res.sigma[n] = sd
    res.sigma_before_profile = before
    res.heading_profile = HeadingEvidence(tuple(float(t) for t in prof.theta),
                                          tuple(float(v) for v in prof.log_evidence),
                                          float(res.sigma["theta_e"]))
    # one basin's sigma stays the unimodal one (the online smoother's priors and its
    # restart tolerance; the spread is added to what it reports until its next batch)
    res.sigma_unimodal = {**before, **res.sigma_unimodal}
    for e in res.per_mission.values():
        for n in before:
            if n in e and e[n].sigma_computed:
                e[n] = dataclasses.replace(e[n], sigma=max(e[n].sigma, res.sigma[n]))


def basin_rank(b: dict) -> float:
    """A basin's (a ``Result.basins`` entry) cost for comparing it with the chosen one: its
    ``rank`` where the basins were ranked by evidence, else its cost."""
    return float(b.get("rank", b["cost"]))


def basin_spread(chosen: dict[str, float], others: list[tuple[dict[str, float], float]],
            cost: float) -> dict[str, float]:
    w = np.array([1.0] + [np.exp(min(cost - c, 50.0)) for _, c in others])
    w /= w.sum()
    out = {}
    for n, v in chosen.items():
        if not all(n in o for o, _ in others):
            continue
        d = np.array([float(o[n]) - float(v) for o, _ in others])
        if n == "theta_e":
            d = np.angle(np.exp(1j * d))
        out[n] = float(np.sum(w[1:] * d ** 2))
    return out


def _heading_gap(a: dict, b: dict) -> float:
    """Largest heading difference (rad) between two basins' missions."""
    gaps = [abs(np.angle(np.exp(1j * (a["theta_e"][n] - b["theta_e"].get(n, a["theta_e"][n])))))
            for n in a["theta_e"]]
    return max(gaps, default=0.0)


def batch_warnings(res: Result) -> list[str]:
    """What a user must be told about the batch fit ``res``, in words."""
    out = []
    if res.solve is not None and res.solve.hit_iteration_limit:
        out.append(f"the optimiser stopped at its iteration limit ({res.iterations}) before "
                   "converging: the estimate may not be a minimum (raise max_iterations or "
                   "check the data)")
    if res.plausible is False:
        for name, chk in res.plausibility.items():
            for r in chk.get("reasons", []):
                out.append(f"{name}: implausible solution: {r}; no start gave a plausible one "
                           "(the model may lack the vehicle's physics: run `aqfg diagnose`)")
    for b in res.ambiguous:
        th = ", ".join(f"{n} {np.degrees(v):.1f} deg" for n, v in b["theta_e"].items())
        ev = (f", {b['rank']:.1f} with its evidence's noise"
              if abs(basin_rank(b) - float(b["cost"])) > 0.05 else "")
        out.append(f"another heading basin fits almost as well (theta_e {th}, cost "
                   f"{b['cost']:.1f}{ev}): the heading offset is ambiguous")
    if res.ambiguous and "theta_e" in res.sigma_unimodal:
        out.append("the sigmas cover the basins that fit as well (theta_e's "
                   f"{np.degrees(res.sigma_unimodal['theta_e']):.1f} deg within the "
                   "chosen basin)")
    before = res.sigma_before_profile.get("theta_e")
    prof = res.heading_profile
    if before is not None and prof is not None and prof.sigma_theta_e > 2.0 * before:
        out.append(f"these fixes hardly determine the heading offset: its evidence over the "
                   f"whole circle gives sigma {np.degrees(prof.sigma_theta_e):.0f} deg "
                   f"({np.degrees(before):.1f} deg within the chosen basin)")
    for n, v in (res.observability or {}).items():
        if v["verdict"] == observability.NOT:
            out.append(f"{n} is not determined by this data: {v['reason']}")
    infl = res.sigma_inflation
    big = {n: f for n, f in infl.items() if f > MISFIT_INFLATION}
    if big:
        worst = max(big, key=lambda n: big[n])
        out.append(f"the model does not explain the fixes as its noise model says: sigma "
                   f"inflated up to {big[worst]:.1f}x ({worst}) to stay honest; run "
                   "`aqfg diagnose` to find the missing physics")
    return out
