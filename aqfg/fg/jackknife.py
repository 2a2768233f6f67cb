"""The block jackknife of a short batch fit: the fit again with each time block's fixes
left out, and each sigma widened to the spread of those refits where that is larger.

On data too short for the block sandwich (fewer 60-s blocks than the parameters + 2:
:func:`aqfg.fg.batch.too_short_for_sandwich`) nothing else measures how far a model that
is not the vehicle moves the estimates: the Hessian sigma assumes the model is right. The
delete-one-block jackknife (Künsch 1989) needs no more blocks than it has refits, and a
refit left without one block's fixes moves as far as that block pulled the fit.
Measurements: docs/independent-vehicle.md.
"""
from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Callable, Sequence

import numpy as np

from aqfg.data.mission import Mission, samples
from aqfg.model.params import difference
from aqfg.result import BlockJackknife, Result

BLOCK = 30.0        # s, the shortest block left out
MIN_BLOCKS = 4      # fewer: the jackknife's spread is itself too uncertain to report
MAX_BLOCKS = 8      # refits at most (each is a batch solve)


def blocks(mission: Mission) -> np.ndarray:
    """The edges (s) of the jackknife's blocks over ``mission``'s fix times: as many equal
    blocks as fit ``BLOCK`` s each, at most ``MAX_BLOCKS``; empty where fewer than
    ``MIN_BLOCKS`` fit or a block would hold no fix."""
    tf = mission.fix_times()
    if len(tf) < 2:
        return np.zeros(0)
    k = min(MAX_BLOCKS, int((tf[-1] - tf[0]) // BLOCK))
    if k < MIN_BLOCKS:
        return np.zeros(0)
    edges = np.linspace(tf[0], tf[-1], k + 1)
    edges[-1] = np.nextafter(tf[-1], np.inf)
    held = np.histogram(tf, edges)[0]
    return edges if np.all(held > 0) else np.zeros(0)


def refits(missions: Sequence[Mission], n_params: int, sandwich_block: float = 60.0) -> int:
    """How many refits :func:`widen` makes after a batch fit of ``missions`` estimating
    ``n_params`` parameters (for the cost estimate): one per block where the fit is one
    mission's and too short for the sandwich (fewer ``batch.sandwich_block``-s blocks from the
    first fix to the end of the inputs than the parameters + 2, as
    :func:`aqfg.fg.graph.too_short_for_sandwich` counts them), else 0."""
    if len(missions) != 1 or not sandwich_block > 0:
        return 0
    m = missions[0]
    tf = m.fix_times()
    tf = tf[(tf >= m.t0) & (tf <= m.t1)]
    start = float(tf[0]) if len(tf) else m.t0
    if int(max(m.t1 - start, 0.0) // sandwich_block) + 1 >= n_params + 2:
        return 0
    return max(len(blocks(m)) - 1, 0)


def without_fixes(mission: Mission, t_from: float, t_to: float) -> Mission:
    """A copy of ``mission`` without its GNSS and USBL fixes at ``t_from <= t < t_to``
    (s); the inputs, the depth and the other fixes kept."""
    out = copy.copy(mission)
    for name in ("gnss", "usbl"):
        s = getattr(mission, name)
        if s is not None:
            setattr(out, name, samples(s, ~((s.t >= t_from) & (s.t < t_to))))
    return out


def jackknife_sigma(full: dict[str, float], replicates: list[dict[str, float]]
                    ) -> dict[str, float]:
    """The delete-one-block jackknife's sigma of each of ``full``'s parameters from the
    ``replicates`` (each the fit without one block): sqrt((K-1)/K sum (x_i - mean)^2),
    K the replicates; from each replicate's difference from ``full``
    (:func:`aqfg.model.params.difference`: the heading offset's wrapped)."""
    k = len(replicates)
    out = {}
    for n, v in full.items():
        d = np.array([difference(n, float(r[n]), float(v)) for r in replicates if n in r])
        if len(d) != k or not np.all(np.isfinite(d)):
            continue
        out[n] = float(math.sqrt((k - 1) / k * float(np.sum((d - d.mean()) ** 2))))
    return out


def widen(res: Result, mission: Mission, refit: Callable[[Mission], Result]) -> Result:
    """``res`` (a one-mission batch fit too short for the sandwich) with its sigmas widened
    to the block jackknife's where that is larger: ``refit`` fits a mission with
    ``res``'s model. Its ``block_jackknife`` records the blocks, the jackknife's
    sigmas and the former ones (``sigma_before``, of the widened parameters); a refit
    that fails leaves the sigmas as they were and says why."""
    edges = blocks(mission)
    if not len(edges):
        return res
    reps = []
    for a, b in zip(edges[:-1], edges[1:]):
        try:
            r = refit(without_fixes(mission, float(a), float(b)))
        except Exception as e:  # noqa: BLE001 -- an optional widening; the fit stands
            return dataclasses.replace(res, block_jackknife=BlockJackknife(
                len(edges) - 1, failed=f"{type(e).__name__}: {e}"[:200]))
        reps.append({n: float(r.values[n]) for n in res.estimated if n in r.values})
    sj = jackknife_sigma({n: float(res.values[n]) for n in res.estimated}, reps)
    before = {}
    sigma = dict(res.sigma)
    for n, s in sj.items():
        if n in sigma and not s <= sigma[n]:
            before[n] = float(sigma[n])
            sigma[n] = s
    warnings = list(res.warnings)
    moved = [n for n in ("theta_e", "s_x", "s_y") if n in before and sj[n] > 2.0 * before[n]]
    if moved:
        parts = [f"theta_e {math.degrees(before['theta_e']):.2g} -> "
                 f"{math.degrees(sj['theta_e']):.2g} deg" if n == "theta_e" else
                 f"{n} {before[n]:.2g} -> {sj[n]:.2g} m/s" for n in moved]
        warnings = [*warnings, (
            f"these fixes are too short to test the model; leaving out each of "
            f"{len(edges) - 1} {edges[1] - edges[0]:.0f}-s blocks of fixes moved the fit by "
            f"more than its sigma claimed: sigma widened to the block jackknife's "
            f"({', '.join(parts)})")]
    return dataclasses.replace(res, sigma=sigma, info=dict(res.info), warnings=warnings,
                               block_jackknife=BlockJackknife(
                                   len(edges) - 1, float(edges[1] - edges[0]), sj, before))
