"""Refits warm-started from an earlier fit.

A candidate's refit is the base model plus one effect. Started from scratch it re-runs the
whole solve, and can settle in another local optimum than the base fit did, so that the
likelihood ratio measures the optimiser's luck rather than the effect (docs/diagnosis.md).
Started from the base fit's optimum (states, and every parameter they share, the effect's
own parameters at their null), the refit can only lower the cost from the base optimum,
and needs fewer iterations than a full solve.
"""
from __future__ import annotations

import numpy as np

from aqfg.data.mission import Mission
from aqfg.fg.batch import BatchSmoother, BuiltGraph
from aqfg.fg.common import interp_states
from aqfg.result import Result


def apply_start(bg: BuiltGraph, start: Result) -> None:
    """Set the initial values of ``bg`` from the fit ``start``: knot states interpolated
    on its tracks (exact where the knots coincide), parameter nodes from its parameter
    vectors by name (names it does not have keep the build's values, e.g. a new effect's
    null), projected onto the bounds."""
    if len(start.missions) != len(bg.parts):
        raise ValueError(f"warm start: {len(start.missions)} fitted missions for "
                         f"{len(bg.parts)} in the graph")
    names = tuple(start.model.all_names) if start.model is not None else ()
    for part, mres in zip(bg.parts, start.missions):
        X = interp_states(mres.track, part.knots)
        for k, x in zip(part.keys, X):
            bg.values.update(k, x)
    layout = bg.layout
    for g, key, mi in bg.nodes:
        p = start.missions[mi or 0].p
        v = bg.values.atVector(key).copy()
        for j, n in enumerate(layout.names[g]):
            if n in names:
                v[j] = float(p[names.index(n)])
        bg.values.update(key, layout.project(g, v))


class WarmBatchSmoother(BatchSmoother):
    """:class:`BatchSmoother` started from ``start`` (see :func:`apply_start`); keeps the
    graph it built (``built``) so that the diagnosis can linearise it again without a
    rebuild."""

    def __init__(self, model=None, *, start: Result | None = None, **kw):
        super().__init__(model, **kw)
        self.start = start
        self.built: BuiltGraph | None = None

    def build(self, missions: list[Mission], *, fixed_prior: bool = True) -> BuiltGraph:
        bg = super().build(missions, fixed_prior=fixed_prior)
        if self.start is not None:
            apply_start(bg, self.start)
            # the start's basin was chosen by its own fit: no other heading starts
            bg.starts = []
        self.built = bg
        return bg


def knots_match(bg: BuiltGraph, res: Result) -> bool:
    return all(len(p.knots) == len(m.track.t) and np.max(np.abs(p.knots - m.track.t)) < 1e-6
               for p, m in zip(bg.parts, res.missions))
