"""Other starts to solve a batch graph from, and the plausibility of a solution.

The closed-form starts (:mod:`aqfg.fg.init`) lead LM into one heading basin; the
generators here yield the other values worth solving from (other basins of the closed
form, turned headings, a high sway-drag start, a given start), each as
``(label, gtsam.Values)``; :func:`plausibility_verdicts` checks a solution physically
(:mod:`aqfg.fg.plausibility`).
"""
from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np

from aqfg.fg import factors as fc
from aqfg.fg import plausibility
from aqfg.fg.common import initial_states
from aqfg.fg.graph import BuiltGraph, MissionPart
from aqfg.fg.init import Start, distinct_headings, start_states
from aqfg.fg.plausibility import Plausibility


def high_sway(starts: list[Start]) -> list[Start]:
    """The starts whose sway drag is at least ten times their surge drag: a hull there
    does not slide on a held course whatever the exact value (the non-sliding starts)."""
    return [s for s in starts if s.fixed["k_yz"] >= 10.0 * s.fixed["k_x"]]


def set_variable(vals: gtsam.Values, bg: BuiltGraph, part: MissionPart,
                  values: dict[str, float]) -> None:
    """Write ``values`` (those of the layout's variable group among them) into every
    variable-parameter segment node of mission ``part`` in ``vals``, projected into the
    bounds."""
    names = bg.layout.names["variable"]
    for seg in range(len(part.seg_starts)):
        key = fc.node_key("variable", part.index, seg)
        v = vals.atVector(key).copy()
        for n, val in values.items():
            if n in names:
                v[names.index(n)] = val
        vals.update(key, bg.layout.project("variable", v))


def plausibility_verdicts(bg: BuiltGraph, values: gtsam.Values) -> list[Plausibility]:
    """Physical plausibility of every mission's part of a solution."""
    out = []
    for part in bg.parts:
        X = np.array([values.atVector(k) for k in part.keys])
        nd = {}
        for g in bg.layout.groups:
            nd[g] = values.atVector(fc.node_key(g) if g == "fixed" else fc.node_key(g, part.index, 0))
        p = bg.layout.full(nd)
        out.append(plausibility.check(part.model, part.mission, part.knots, X, p,
                                      bg.layout.estimated))
    return out


def given_start(bg: BuiltGraph, also_start: dict[str, float] | None):
    """The ``also_start`` parameters with knot states from the fixes."""
    if not also_start:
        return
    yield "given start", fix_state_values(bg, also_start)


def fix_state_values(bg: BuiltGraph, params: dict[str, float]) -> gtsam.Values:
    """The graph's start values with knot states from the fixes and the (finite)
    ``params`` set by name in every parameter node, projected into the bounds."""
    vals = gtsam.Values(bg.values)
    for part in bg.parts:
        for k, x in zip(part.keys, initial_states(part.mission, part.knots)):
            vals.update(k, x)
    for g, key, _ in bg.nodes:
        names = bg.layout.names[g]
        v = vals.atVector(key).copy()
        for i, n in enumerate(names):
            if n in params and np.isfinite(params[n]):
                v[i] = float(params[n])
        vals.update(key, bg.layout.project(g, v))
    return vals


def alternative_starts(bg: BuiltGraph, verdicts: list[Plausibility], init: dict,
                       short: bool = False):
    """Other starts worth solving from: other heading basins of the closed form, when
    the first solution is implausible or another basin explained the fixes almost as
    well (robust misfit within 25 %); on data too ``short`` for the sandwich with the
    constants given (one closed-form start), also that start turned by 90, 180 and
    270 deg (a global search in the heading: over the first 20 s of a slow leg the
    closed form is poor, and the heading basin it led to was 134 deg off while one
    7 deg off had the lower cost, docs/independent-vehicle.md; with the constants
    searched, the grid's starts cover the heading, and a turned start found a sliding
    basin 0.2 % lower in cost on a mission whose model lacks an effect); and, when it
    is implausible and the constants were searched, the best start with a sway drag
    at least ten times the surge drag (an implausible solution slides sideways with k_yz near zero; on a
    7.5-min crop of an Otter mission every heading start slid into it)."""
    if not bg.starts or "variable" not in bg.layout.names \
            or "theta_e" not in bg.layout.names["variable"]:
        return
    if not all(bg.starts):
        # a mission with too few fixes for the closed form started at the null heading
        # offset; the other quarters of the circle are started too (4 fixes in the first
        # 8 s of an Otter mission ended 146 deg off from the null start, sigma 18 deg)
        if "theta_e" not in init:
            for turn in (90.0, 180.0, 270.0):
                yield (f"turned heading start {turn:.0f} deg (no closed form)",
                       turned_values(bg, np.radians(turn)))
        return
    heads = [distinct_headings(st) for st in bg.starts]
    implausible = not all(v.plausible for v in verdicts)
    n_alt = max(len(h) for h in heads)
    user = "theta_e" in init
    tried = [heads[0][0].theta_e]
    for j in range(0 if user else 1, min(n_alt, 3)):
        if user and not implausible:
            break
        close = any(len(h) > j and h[j].misfit <= 1.25 * h[0].misfit for h in heads)
        if not (implausible or close):
            continue
        sts = [h[j] if len(h) > j else h[0] for h in heads]
        tried.append(sts[0].theta_e)
        yield (f"alternative heading start {np.degrees(sts[0].theta_e):.0f} deg",
               start_values(bg, sts, implausible, init))
    if short and not user and all(len(st) == 1 for st in bg.starts):
        for turn in np.radians([90.0, 180.0, 270.0]):
            th = heads[0][0].theta_e + turn
            if any(abs(np.angle(np.exp(1j * (th - t)))) < np.radians(30.0) for t in tried):
                continue
            sts = [replace(h[0], theta_e=float(h[0].theta_e + turn), current=np.zeros(2))
                   for h in heads]
            yield (f"turned heading start {np.degrees(th):.0f} deg",
                   start_values(bg, sts, implausible, init))
    searched = len(bg.starts[0]) > 1
    if implausible and searched and not user:
        sway = [high_sway(st) for st in bg.starts]
        if all(sway):
            sts = [w[0] for w in sway]
            yield (f"high sway-drag start {np.degrees(sts[0].theta_e):.0f} deg",
                   start_values(bg, sts, True, init))


def evaluable_values(bg: BuiltGraph, cost, init: dict) -> gtsam.Values:
    """The graph's start values, or, where ``cost(values)`` is not finite there, the values
    of the first of the other closed-form starts, in misfit order, where it is; the nominal
    constants with the knot states from the fixes last. (A grid point's constants can
    make the dynamics from the start's states diverge: a drag so stiff that the explicit
    integration is unstable at the speeds of those states.)"""
    if np.isfinite(cost(bg.values)):
        return bg.values
    if bg.starts and all(bg.starts):
        for j in range(1, max(len(st) for st in bg.starts)):
            vals = start_values(bg, [st[min(j, len(st) - 1)] for st in bg.starts], True, init)
            if np.isfinite(cost(vals)):
                return vals
    nominal = dict(zip(bg.layout.names["fixed"], bg.layout.initial("fixed"))) \
        if "fixed" in bg.layout.names else {}
    vals = fix_state_values(bg, {n: v for n, v in nominal.items() if n not in init})
    return vals if np.isfinite(cost(vals)) else bg.values


def turned_values(bg: BuiltGraph, turn: float) -> gtsam.Values:
    """The graph's start values with the heading offset of each mission that has no
    closed-form start turned by ``turn`` rad and its current at zero (the knot states
    stay those interpolated from the fixes)."""
    vals = gtsam.Values(bg.values)
    names = bg.layout.names["variable"]
    for part, st in zip(bg.parts, bg.starts):
        if not st:
            key = fc.node_key("variable", part.index, 0)
            th = float(vals.atVector(key)[names.index("theta_e")]) + turn
            set_variable(vals, bg, part, {"theta_e": th, "s_x": 0.0, "s_y": 0.0})
    return vals


def start_values(bg: BuiltGraph, sts: list[Start], constants: bool, init: dict
                 ) -> gtsam.Values:
    """Values of the graph at the starts ``sts`` (one per mission): knot states, heading
    offset and current; the constants of the first mission's start where they are
    estimated and ``constants`` (or not given by the user)."""
    vals = gtsam.Values(bg.values)
    for part, st in zip(bg.parts, sts):
        for k, x in zip(part.keys, start_states(st, part.mission, part.knots)):
            vals.update(k, x)
        set_variable(vals, bg, part, {"theta_e": st.theta_e, "s_x": st.current[0],
                                       "s_y": st.current[1]})
    if "fixed" in bg.layout.names:
        key = fc.node_key("fixed")
        fnames = bg.layout.names["fixed"]
        f = vals.atVector(key).copy()
        for n in ("k", "k_x", "k_yz"):
            if n in fnames and (constants or n not in init):
                f[fnames.index(n)] = sts[0].fixed[n]
        vals.update(key, bg.layout.project("fixed", f))
    return vals
