"""The information a mission's side of the joint fit (:mod:`aqfg.fg.schur`) hands the
joint loop: its Schur complement on the vehicle's fixed-parameter node."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from aqfg.fg import factors as fc

FIXED = fc.node_key("fixed")


@dataclass
class ReducedSystem:
    """Information on the fixed node after eliminating a mission's locals.

    ``H`` (d, d) and ``eta`` (d,): the linear system ``H delta_f = eta`` (whitened
    Gauss-Newton information, parameter units); ``cost``: 0.5 x the whitened squared error
    at the linearisation point; ``hdiag`` (d,): diagonal of ``J_f^T J_f`` before the
    elimination, unfloored (the batch's Marquardt damping scale, summed over missions).
    """
    H: np.ndarray
    eta: np.ndarray
    cost: float
    hdiag: np.ndarray

    def __add__(self, other: ReducedSystem) -> ReducedSystem:
        return ReducedSystem(self.H + other.H, self.eta + other.eta, self.cost + other.cost,
                             self.hdiag + other.hdiag)

    @classmethod
    def total(cls, systems: Sequence[ReducedSystem]) -> ReducedSystem:
        out = systems[0]
        for s in systems[1:]:
            out = out + s
        return out
