"""The batch factor graph of missions of one vehicle: its parts, nodes and factors.

:func:`build_graph` lays out each mission's state knots (one every
``FGSettings.graph.knot_spacing``), its parameter segments (the random walk of the variable
parameters), the parameter nodes with their priors, the dynamics factors reading one
:class:`aqfg.fg.factors.DynamicsCache` and the measurement factors; :class:`BuiltGraph`
evaluates and linearises the result (see :mod:`aqfg.fg.batch`).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import gtsam
import numpy as np

from aqfg.data.mission import Mission
from aqfg.fg import factors as fc
from aqfg.fg.common import (
    Measurements,
    default_estimate,
    first_knot_term,
    initial_states,
    knot_times,
    measurement_factors,
    mission_model,
)
from aqfg.fg.init import Start, candidate_starts, current_prior, start_states
from aqfg.fg.settings import FGSettings
from aqfg.fg.user_factors import FactorSource, GraphKeys
from aqfg.memo import remember
from aqfg.model.params import N_DYN
from aqfg.model.vehicle import Model
from aqfg.result import Result


@dataclass
class MissionPart:
    """One mission's share of the graph."""
    index: int
    mission: Mission
    model: Model
    knots: np.ndarray
    keys: list                 # state keys
    seg_of: np.ndarray         # parameter segment of each dynamics interval
    seg_starts: np.ndarray     # start time of each parameter segment
    seg_slices: list           # (a, b, steps, offsets) per segment: intervals a..b-1
    f0: int                    # index of the first dynamics factor in the cache


class ParamNode(NamedTuple):
    """A parameter node of the graph: its group ("fixed", "variable", "sensor"), its GTSAM
    key and the mission it belongs to (None for the vehicle's shared fixed node)."""
    group: str
    key: int
    mission: int | None


@dataclass
class _Graph:
    """A graph being built: its factors, initial values and linear factors' numpy form."""
    graph: gtsam.NonlinearFactorGraph = field(default_factory=gtsam.NonlinearFactorGraph)
    values: gtsam.Values = field(default_factory=gtsam.Values)
    linear: list[fc.LinearTerm] = field(default_factory=list)

    def add_linear(self, term: fc.LinearTerm) -> None:
        self.linear.append(term)
        self.graph.add(term.factor())


@dataclass
class BuiltGraph:
    """The batch graph of a set of missions, ready to be linearised at any ``Values``.

    ``graph`` holds every factor; the dynamics factors read their prediction and Jacobians
    from ``cache``, which :meth:`fill` evaluates for given values (one kernel call per
    mission and parameter segment), so always go through :meth:`error` / :meth:`linearize`.
    ``values`` holds the initial values the build chose; ``linear`` the graph's linear
    factors (priors, surface constraint, random walk) in numpy, in the graph's order.
    """
    layout: fc.ParamLayout
    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    parts: list[MissionPart]
    cache: fc.DynamicsCache
    nodes: list[ParamNode]
    starts: list[list[Start]] = field(default_factory=list)   # per mission, best first
    linear: list[fc.LinearTerm] = field(default_factory=list)

    def fill(self, values: gtsam.Values) -> None:
        """Evaluate the dynamics of every interval at ``values`` into the cache."""
        layout = self.layout
        nodes = {}
        if "fixed" in layout.names:
            nodes["fixed"] = values.atVector(fc.node_key("fixed"))
        for part in self.parts:
            X = np.array([values.atVector(k) for k in part.keys])
            nd = dict(nodes)
            if "sensor" in layout.names:
                nd["sensor"] = values.atVector(fc.node_key("sensor", part.index))
            for j, sl in enumerate(part.seg_slices):
                if sl is None:
                    continue
                a, b, steps, off = sl
                if "variable" in layout.names:
                    nd["variable"] = values.atVector(fc.node_key("variable", part.index, j))
                p = layout.full(nd)
                pred, Jx, Jp = part.model.propagate_many(X[a:b], p, steps, off)
                r0 = part.f0
                self.cache.pred[r0 + a:r0 + b] = pred
                self.cache.Jx[r0 + a:r0 + b] = Jx
                self.cache.Jp[r0 + a:r0 + b] = Jp

    def error(self, values: gtsam.Values) -> float:
        """0.5 x the whitened squared error (robust losses applied) at ``values``."""
        self.fill(values)
        return float(self.graph.error(values))

    def linearize(self, values: gtsam.Values) -> gtsam.GaussianFactorGraph:
        """The whitened linear system at ``values``."""
        self.fill(values)
        return self.graph.linearize(values)

    def node_dims(self) -> list[tuple[int, int]]:
        return [(n.key, self.layout.dim(n.group)) for n in self.nodes]

    def key_dims(self) -> list[tuple[int, int]]:
        """(key, dimension) of every variable: state knots, then parameter nodes."""
        return [(k, 6) for p in self.parts for k in p.keys] + self.node_dims()


def too_short_for_sandwich(bg: BuiltGraph, s: FGSettings) -> bool:
    """Whether ``bg``'s missions have fewer of the sandwich's time blocks
    (``s.batch.sandwich_block``) than its parameters + 2: there the evidence chooses the batch's
    process noise (``FGSettings.batch.adapt_noise``) and the structural test alone decides
    whether the fit explains its fixes (:func:`aqfg.fg.structural_sigma.structural_sigma`)."""
    b = s.batch.sandwich_block or np.inf
    n_blocks = sum(int(np.floor((float(p.knots[-1]) - float(p.knots[0])) / b)) + 1
                   for p in bg.parts)
    return n_blocks < sum(bg.layout.dim(g) for g, _, _ in bg.nodes) + 2


def solution_values(bg: BuiltGraph, result: Result, null: Sequence[str] = ()) -> gtsam.Values:
    """``bg``'s values at the batch solution ``result`` of the same missions and settings:
    the knot states from its tracks, each parameter node from its mission's full
    parameter vector (entries ``result``'s model lacks, such as an effect ``bg`` adds, at
    the nominal of ``bg``'s model; the parameters named in ``null`` at their null value).
    ValueError where the knots differ from the graph's."""
    values = gtsam.Values(bg.values)
    lay = bg.layout
    model = lay.model
    for part, mres in zip(bg.parts, result.missions):
        if len(part.knots) != len(mres.track.t) or \
                np.max(np.abs(part.knots - mres.track.t)) > 1e-6:
            raise ValueError(f"mission {part.mission.name!r}: the fit's knots differ from the "
                             "rebuilt graph's (the fit and this graph must use the same "
                             "settings)")
        for k, x in zip(part.keys, np.column_stack([mres.track.pos, mres.track.vel])):
            values.update(k, x)
    for node in bg.nodes:
        p = result.missions[node.mission or 0].p
        full = model.nominal()
        full[:len(p)] = p
        v = full[lay.idx[node.group]]
        for j, n in enumerate(lay.names[node.group]):
            if n in null:
                v[j] = model.spec(n).null
        values.update(node.key, v)
    return values


def build_graph(missions: list[Mission], *, model: Model | None, effects: tuple, estimate,
                init: dict, settings: FGSettings, fixed_prior: bool = True,
                factors: FactorSource | None = None) -> BuiltGraph:
    """The graph of ``missions`` with its initial values (see :class:`BuiltGraph`), for the
    smoother's ``model``, ``effects``, ``estimate`` (None: the model's default), ``init``
    and ``settings``; ``fixed_prior=False`` leaves out the prior on the shared fixed node
    (:meth:`aqfg.fg.batch.BatchSmoother.build`); ``factors``: the user's own GTSAM
    factors (:mod:`aqfg.fg.user_factors`), added after the built-in ones."""
    models = [mission_model(model, m, effects) for m in missions]
    est = estimate if estimate is not None else default_estimate(models[0], "batch")
    layout = fc.ParamLayout.build(models[0], est, init)
    out = _Graph()
    # search the dynamics' scale only when all three constants are free
    free = set(layout.names.get("fixed", ()))
    grid = {"k", "k_x", "k_yz"} <= free
    search = grid and not ({"k", "k_x", "k_yz"} & set(init))
    parts, guesses, all_starts = _mission_parts(missions, models, layout, grid, out, settings)
    nf = sum(len(p.knots) - 1 for p in parts)
    cache = fc.DynamicsCache(np.zeros((nf, 6)), np.zeros((nf, 6, 6)),
                             np.zeros((nf, 6, len(models[0].dyn_columns()))))
    # parameter nodes (started from the data-driven guess where the user gave no
    # initial value), priors (around the user's / nominal values), random walk
    node_list = _param_nodes(layout, parts, guesses, search, fixed_prior, out, settings, init)
    _model_factors(layout, parts, cache, out.graph, settings)
    if factors is not None:
        keys = GraphKeys(tuple(p.knots for p in parts), tuple(tuple(p.keys) for p in parts),
                         tuple(p.seg_starts for p in parts), layout)
        for f in factors(keys):
            out.graph.add(f)
    return BuiltGraph(layout, out.graph, out.values, parts, cache, node_list, all_starts,
                      out.linear)


def _mission_parts(missions: list[Mission], models: list[Model],
                   layout: fc.ParamLayout, grid: bool, out: _Graph, s: FGSettings
                   ) -> tuple[list[MissionPart], list[Start | None], list[list[Start]]]:
    """Each mission's knots, parameter segments and starting states (the closed-form
    starts, the dynamics' scale searched on ``grid``), with its first-knot prior and
    surface constraint; its starts, best first."""
    parts: list[MissionPart] = []
    nf = 0
    walk = s.graph.walk_sigma and "variable" in layout.names
    guesses: list[Start | None] = []
    all_starts: list[list[Start]] = []
    cur_sig = current_prior(s.graph.prior_sigma)
    for mi, (m, model) in enumerate(zip(missions, models)):
        knots = knot_times(m, s.graph.knot_spacing)
        steps, off = model.steps(m, knots)
        K = len(knots) - 1
        if walk:
            seg_of = np.floor((knots[:-1] - knots[0]) / s.graph.walk_segment).astype(int)
        else:
            seg_of = np.zeros(K, int)
        nseg = int(seg_of.max()) + 1 if K else 1
        seg_starts = knots[0] + s.graph.walk_segment * np.arange(nseg) if walk else knots[:1]
        slices: list[tuple | None] = []
        for j in range(nseg):
            ii = np.nonzero(seg_of == j)[0]
            if not len(ii):
                slices.append(None)
                continue
            a, b = int(ii[0]), int(ii[-1]) + 1
            slices.append((a, b, steps.slice(int(off[a]), int(off[b])), off[a:b + 1] - off[a]))
        keys = [fc.state_key(mi, i) for i in range(len(knots))]
        starts = _starts(model, m, knots, layout.base, grid, (steps, off), cur_sig)
        if starts:
            guess = starts[0]
            X0 = start_states(guess, m, knots)
        else:                       # too few fixes for the closed form
            guess = None
            X0 = initial_states(m, knots)
        guesses.append(guess)
        all_starts.append(starts)
        for k, x in zip(keys, X0):
            out.values.insert(k, x)
        out.add_linear(first_knot_term(m, keys[0], X0[0], s))
        if m.planar:
            for k in keys:
                out.add_linear(fc.surface_term(k, *s.graph.surface_sigma))
        parts.append(MissionPart(mi, m, model, knots, keys, seg_of, seg_starts, slices, nf))
        nf += K
    return parts, guesses, all_starts


def _starts(model: Model, m: Mission, knots: np.ndarray, p: np.ndarray, grid: bool, steps,
            cur_sig) -> list[Start]:
    """:func:`candidate_starts` of ``m``, those of an earlier graph of the same mission
    where its roll-outs are the same: the same knots and dynamics parameters ``p[:N_DYN]``
    on the C++ kernel, which reads no others (:mod:`aqfg.memo`)."""
    def make() -> list[Start]:
        return candidate_starts(model, m, knots, p, search=grid, steps=steps,
                                current_sigma=cur_sig)
    if not model.uses_cpp or model.lookback > 0:
        return make()
    g = model.geometry
    key = ("starts", knots.tobytes(), np.asarray(p[:N_DYN], float).tobytes(), grid, cur_sig,
           np.asarray(g.dirs, float).tobytes(), np.asarray(g.side, float).tobytes(),
           bool(g.planar))
    return list(remember(m, key, make))


def _param_nodes(layout: fc.ParamLayout, parts: list[MissionPart],
                 guesses: list[Start | None], search: bool, fixed_prior: bool, out: _Graph,
                 s: FGSettings, init: dict) -> list[ParamNode]:
    """The parameter nodes, their starting values, priors and random walk."""
    node_list = []
    if "fixed" in layout.names:
        k = fc.node_key("fixed")
        f0 = layout.initial("fixed")
        names = layout.names["fixed"]
        found = [g for g in guesses if g is not None]
        if found and search:
            # the grid point that best explains the fixes (median over missions)
            for n in ("k", "k_x", "k_yz"):
                f0[names.index(n)] = float(np.median([g.fixed[n] for g in found]))
        elif found and "k" in names and "k" not in init and "k_x" not in init:
            rho2 = float(np.median([g.rho for g in found])) ** 2
            f0[names.index("k")] *= rho2     # steady speed ~ sqrt(k / k_x)
        out.values.insert(k, layout.project("fixed", f0))
        if fixed_prior:
            out.add_linear(fc.param_prior_term(layout, "fixed", k, s.graph.prior_scale,
                                               sigma=s.graph.prior_sigma))
        node_list.append(ParamNode("fixed", k, None))
    for part in parts:
        if "variable" in layout.names:
            v0 = layout.initial("variable")
            g0 = guesses[part.index]
            if g0 is not None:
                for n, val in (("theta_e", g0.theta_e), ("s_x", g0.current[0]),
                               ("s_y", g0.current[1])):
                    if n in layout.names["variable"] and n not in init:
                        v0[layout.names["variable"].index(n)] = val
            v0 = layout.project("variable", v0)
            for j in range(len(part.seg_starts)):
                k = fc.node_key("variable", part.index, j)
                out.values.insert(k, v0)
                node_list.append(ParamNode("variable", k, part.index))
                if j == 0:
                    out.add_linear(fc.param_prior_term(layout, "variable", k, s.graph.prior_scale,
                                                       sigma=s.graph.prior_sigma))
                else:
                    sig = np.array([(s.graph.walk_sigma or {}).get(n, 0.0)
                                    for n in layout.names["variable"]])
                    k_prev = fc.node_key("variable", part.index, j - 1)
                    out.add_linear(fc.walk_term(layout, k_prev, k, np.maximum(sig, 1e-9),
                                                s.graph.walk_segment))
        if "sensor" in layout.names:
            k = fc.node_key("sensor", part.index)
            out.values.insert(k, layout.initial("sensor"))
            out.add_linear(fc.param_prior_term(layout, "sensor", k, s.graph.prior_scale,
                                               sigma=s.graph.prior_sigma))
            node_list.append(ParamNode("sensor", k, part.index))
    return node_list


def _model_factors(layout: fc.ParamLayout, parts: list[MissionPart],
                   cache: fc.DynamicsCache, graph: gtsam.NonlinearFactorGraph,
                   s: FGSettings) -> None:
    """The dynamics factors (reading ``cache``) and the measurement factors."""
    noise_cache: dict = {}
    dyn_groups = layout.dyn_groups()
    for part in parts:
        mi = part.index

        key_memo: dict = {}

        def nkeys(groups, seg, mi=mi, memo=key_memo):
            if (groups, seg) not in memo:
                # one sensor node per mission: a fix in a later segment reads it too
                memo[groups, seg] = tuple((g, fc.node_key(g, mi, seg if g == "variable" else 0))
                                          for g in groups)
            return memo[groups, seg]

        for i in range(len(part.knots) - 1):
            dt = float(part.knots[i + 1] - part.knots[i])
            key = (round(dt, 9), part.mission.planar)
            if key not in noise_cache:
                noise_cache[key] = s.graph.process.noise_model(dt, part.mission.planar)
            graph.add(fc.cached_dynamics_factor(cache, part.f0 + i, layout, part.keys[i],
                                                part.keys[i + 1],
                                                nkeys(dyn_groups, int(part.seg_of[i])),
                                                noise_cache[key]))
        meas = Measurements.of(part.mission, s, part.knots[0], part.knots[-1])

        def seg_at(t, part=part):
            if len(part.seg_starts) == 1:
                return 0
            return int(np.clip(np.searchsorted(part.seg_starts, t, side="right") - 1, 0,
                               len(part.seg_starts) - 1))

        groups_of = {st: layout.meas_groups(st) for st in ("gnss", "usbl", "depth")}

        def mkeys(stream, t, part=part, mi=mi, groups_of=groups_of):
            return nkeys(groups_of[stream], seg_at(t))

        def knot_key(i, part=part):
            return part.keys[i]
        for f in measurement_factors(part.model, layout, meas, part.knots, knot_key, mkeys, s):
            graph.add(f)
