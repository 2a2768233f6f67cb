"""What the dead-reckoning refinements did (:mod:`aqfg.fg.dead_reckoning`,
:mod:`aqfg.fg.dr_current`): plain records a :class:`~aqfg.result.Result` carries as
``dead_reckoning`` and ``parameters.json`` reports under the same name."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

CURRENT = ("s_x", "s_y")
NAN = float("nan")


@dataclass(frozen=True)
class CurrentRefit:
    """One mission's current for dead reckoning: the smoother's (``before``) and the
    prediction-error estimate (``after``, m/s, NED north/east) with its sigma, the blocks'
    out-of-sample Huber costs under each, and whether it replaced the smoother's (or why
    not)."""
    mission: str
    blocks: int
    before: tuple[float, float]
    after: tuple[float, float] = (NAN, NAN)
    sigma: tuple[float, float] = (NAN, NAN)
    cost_before: float = NAN
    cost_after: float = NAN
    applied: bool = False
    reason: str = ""

    def document(self) -> dict:
        """The record in ``parameters.json`` (``dead_reckoning.current.<mission>``)."""
        out: dict = {"blocks": self.blocks, "applied": self.applied,
                     "smoother": dict(zip(CURRENT, self.before))}
        if np.all(np.isfinite(self.after)):
            out["refined"] = {n: {"value": v, "sigma": s if np.isfinite(s) else None}
                              for n, v, s in zip(CURRENT, self.after, self.sigma)}
            out["heldout_cost"] = {"smoother": self.cost_before, "refined": self.cost_after}
        if self.reason:
            out["reason"] = self.reason
        return out


@dataclass(frozen=True)
class DeadReckoning:
    """The constants' refinement by ``horizon_s``-s prediction error: the estimated fixed
    parameters it re-estimated (``names``), whether the refined values replaced the
    smoother's (``applied``; else ``reason``), and where it ran (``segments`` > 0): its
    predictions' time blocks and degrees of freedom, the Wald statistic of the move against
    its 1 % threshold, the smoother's values and sigmas (``before``) and the refined ones
    (``after``), the horizontal prediction errors (m, RMS and median absolute) under each;
    then each mission's current (:class:`CurrentRefit`)."""
    horizon_s: float
    names: tuple[str, ...]
    applied: bool = False
    reason: str = ""
    segments: int = 0
    blocks: int = 0
    dof: int = 0
    wald: float = NAN
    wald_threshold: float = NAN
    before: dict[str, float] = field(default_factory=dict)
    sigma_before: dict[str, float] = field(default_factory=dict)
    after: dict[str, float] = field(default_factory=dict)
    sigma_after: dict[str, float] = field(default_factory=dict)
    rms_before_m: float = NAN
    rms_after_m: float = NAN
    median_abs_before_m: float = NAN
    median_abs_after_m: float = NAN
    current: tuple[CurrentRefit, ...] = ()
