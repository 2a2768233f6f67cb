"""Factors of the user's own in the batch graph: GTSAM is the graph's vocabulary.

A *factor source* is a function ``source(keys) -> iterable of gtsam factors`` given a
:class:`GraphKeys`, which names the graph's variables: each mission's state knots
(``gtsam.Vector`` of 6: position NED m, velocity NED m/s) and its parameter nodes
(``gtsam.Vector`` s; :meth:`GraphKeys.param` says which node and entry holds a parameter).
``BatchSmoother(..., factors=source)`` adds them to the graph it builds and solves them
with the rest on GTSAM's linearisation (the numpy form of the graph holds only the
built-in factors). Example, a known position at t = 120 s (a surveyed mooring)::

    def mooring(keys):
        key, t = keys.state(120.0)
        noise = gtsam.noiseModel.Diagonal.Sigmas([0.2, 0.2, 0.2, 1e3, 1e3, 1e3])
        return [gtsam.PriorFactorVector(key, np.r_[12.0, -40.0, 0.0, 0, 0, 0], noise)]

A DVL's velocity is the same with the velocity entries measured and the position free.
"""
from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from aqfg.fg import factors as fc


@dataclass(frozen=True)
class GraphKeys:
    """The keys of a batch graph being built (see the module docstring).

    ``knots[i]``: mission ``i``'s knot times (s, the mission's clock); ``state_keys[i]``
    their keys; ``layout``: which parameter sits in which node.
    """
    knots: tuple[np.ndarray, ...]
    state_keys: tuple[tuple[int, ...], ...]
    seg_starts: tuple[np.ndarray, ...]
    layout: fc.ParamLayout

    def state(self, t: float, mission: int = 0, tol: float = 0.5) -> tuple[int, float]:
        """The key and time of the state knot of ``mission`` nearest ``t`` (s); a
        ValueError when none lies within ``tol`` s (the knots are about 1 s apart and
        include every fix time)."""
        kn = self.knots[mission]
        i = int(np.argmin(np.abs(kn - t)))
        if abs(kn[i] - t) > tol:
            raise ValueError(f"no state knot of mission {mission} within {tol:g} s of t = {t:g} s "
                             f"(knots span {kn[0]:g} .. {kn[-1]:g} s)")
        return self.state_keys[mission][i], float(kn[i])

    def param(self, name: str, mission: int = 0, t: float | None = None) -> tuple[int, int]:
        """(node key, index in the node's vector) of estimated parameter ``name``: the
        vehicle's fixed node, mission ``mission``'s variable node (the segment holding
        ``t`` when the variable parameters are a random walk) or its sensor node."""
        for group, names in self.layout.names.items():
            if name in names:
                seg = 0
                if group == "variable" and t is not None:
                    seg = max(int(np.searchsorted(self.seg_starts[mission], t, side="right")) - 1, 0)
                return fc.node_key(group, mission, seg), list(names).index(name)
        raise KeyError(f"{name!r} is not an estimated parameter of this graph "
                       f"(estimated: {', '.join(n for ns in self.layout.names.values() for n in ns)})")


FactorSource = Callable[[GraphKeys], Iterable]
