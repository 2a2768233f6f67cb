"""The candidate effects a diagnosis (or a fit's structural test) ranks, and the Holm
adjustment of their p-values."""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from aqfg.data.mission import Mission
from aqfg.model.effects import BUILTIN, Effect, resolve


def candidate_effects(missions: Sequence[Mission], model_effects=(), extra=(),
                      pool: Sequence | None = None) -> list:
    """The effects to rank: ``pool`` (default: the built-in catalogue) plus ``extra`` (e.g.
    :class:`~aqfg.model.effects.UserEffect` objects), without duplicates, without those already
    in the model, and only those applicable to at least one mission."""
    have = {resolve(e).name for e in model_effects}
    out: list[Effect] = []
    for c in list(BUILTIN.values() if pool is None else pool) + list(extra):
        e = resolve(c)
        if e.name in have or any(e.name == o.name for o in out):
            continue
        if any(e.applicable(m) for m in missions):
            out.append(e)
    return out


def holm_log(log10_p: np.ndarray) -> np.ndarray:
    """Holm-adjusted p-values from log10 p-values (exact for tiny p)."""
    m = len(log10_p)
    o = np.argsort(log10_p)
    adj = np.empty(m)
    run = -np.inf
    for k, i in enumerate(o):
        run = max(run, min(0.0, math.log10(m - k) + log10_p[i]))
        adj[i] = 10 ** run
    return adj
