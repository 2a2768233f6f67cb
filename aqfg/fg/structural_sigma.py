"""The structural part of the batch fit's sigma (:attr:`FGSettings.batch.structural_sigma`), as
steps that take a result and return a new one: the shift a missing effect would cause,
by the structural test (:mod:`aqfg.fg.structure`), and its check by the refit with that
effect (:func:`cover_refit`)."""
from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np

from aqfg.data.mission import Mission
from aqfg.fg.fastlm import FastSystem
from aqfg.fg.settings import FGSettings
from aqfg.fg.structure import structural_shift
from aqfg.model.params import difference
from aqfg.result import RefitCheck, Result, SigmaStructure

log = logging.getLogger(__name__)

# the structural sigma looks for a missing effect where the block sandwich raised any sigma
# of the fit above the model's (significantly: aqfg.fg.covariance), not only where it
# raised one 3x (the warning's level, batch.MISFIT_INFLATION): docs/independent-vehicle.md
STRUCTURAL_MISFIT = 1.0 + 1e-9


def structural_sigma(res: Result, missions: list[Mission], fs: FastSystem, ev: dict,
                     settings: FGSettings, log_warnings: bool = True,
                     test_always: bool = False) -> Result:
    """:attr:`FGSettings.batch.structural_sigma`: where the batch fit ``res`` (nominal noise) does
    not explain the fixes (the block sandwich raised a sigma above the model's,
    ``STRUCTURAL_MISFIT``, or the data are too short for the sandwich) and the data call
    for a missing effect, ``res`` with the sigma of the heading offset and the current
    widened by the shift that effect would cause
    (:func:`aqfg.fg.structure.structural_shift`, on the batch's numpy system ``fs`` at
    its nominal-noise solution, or the evidence's on short data, evaluation ``ev``);
    its ``sigma_structure`` and a warning say which effect and how much.
    ``test_always``: the test also where the fixes are explained (for
    :attr:`FGSettings.batch.auto_effect`), its result in ``structural_test`` (the sigma
    is widened only where they are not); the test's ranking is recorded there whether or
    not it suggests an effect (``suggested``)."""
    infl = res.sigma_inflation
    # data too short for the sandwich cannot show a misfit by it: the test decides alone
    # there (a 170-s crop of an Otter mission put the current 0.46 m/s off with sigma 0.03,
    # where the effects the test suggested would move it 0.3: docs/independent-vehicle.md)
    misfit = max(infl.values(), default=0.0) > STRUCTURAL_MISFIT or \
        res.too_short_for_sandwich
    if (not settings.batch.structural_sigma or settings.graph.walk_sigma or res.model is None
            or not (misfit or test_always)):
        return res
    sh = structural_shift(missions, fs, ev, res.model, tuple(res.estimated))
    if sh is None:
        return res
    if not misfit or not sh.suggested:
        return dataclasses.replace(res, structural_test=sh)
    sigma = dict(res.sigma)
    per = {m: dict(e) for m, e in res.per_mission.items()}
    before = {n: float(sigma[n]) for n in sh.shift if n in sigma}
    for n, d in sh.shift.items():
        if n in sigma:
            sigma[n] = float(np.hypot(sigma[n], d))
        for e in per.values():
            # a joint fit's per-mission values: the same shift (the largest over them)
            if n in e and e[n].sigma_computed:
                e[n] = dataclasses.replace(e[n], sigma=float(np.hypot(e[n].sigma, d)))
    w = structure_warning(sh.effect, sh.proven, sh.p_robust, sh.shift)
    ss = SigmaStructure(sh.effect, sh.p_robust, dict(sh.shift), sh.proven,
                        [dict(c) for c in sh.ranked], before, w)
    if log_warnings:
        log.warning("fg: %s", w)
    return dataclasses.replace(res, sigma=sigma, info=dict(res.info), per_mission=per,
                               structural_test=sh, sigma_structure=ss,
                               warnings=[*res.warnings, w])


def structure_warning(effect: str, proven: bool, p_robust: float, shift: dict[str, float],
                      moved: dict[str, float] | None = None) -> str:
    """The structural sigma's warning: which effect and how far it moves the heading offset
    and the current (its first-order ``shift``; with ``moved``, the refit's move beside it),
    which the sigma includes (the larger of the two)."""
    def words(d: dict[str, float]) -> str:
        parts = []
        if "theta_e" in d:
            parts.append(f"theta_e by {np.degrees(d['theta_e']):.2g} deg")
        cur = [d[n] for n in ("s_x", "s_y") if n in d]
        if cur:
            parts.append(f"the current by {math.sqrt(sum(c * c for c in cur)):.2g} m/s")
        return " and ".join(parts) or "the estimates"
    verb = "call for" if proven else "suggest (do not prove)"
    how = (f"refitted with it, {words(moved)} move (to first order {words(shift)}); sigma "
           "includes the larger" if moved is not None else
           f"with it {words(shift)} would move; sigma includes that shift")
    return (f"the data {verb} the effect {effect} (robust score test p = {p_robust:.2g}): "
            f"{how} (try --effect {effect}, or `aqfg diagnose`)")


def cover_refit(res: Result, new: Result | None, why: str = "") -> Result:
    """``res`` with its variable parameters' sigmas (top level and each mission's) widened
    to hold their exact move to ``new``, the fit again with the effect of its structural
    sigma (``sigma_structure``), where that move exceeds the first-order shift they hold;
    used where ``new`` is plausible and lowers the cost. The record:
    ``sigma_structure.refit``; the structural warning says the move."""
    ss = res.sigma_structure
    assert ss is not None

    def checked(check: RefitCheck) -> Result:
        return dataclasses.replace(res, sigma_structure=dataclasses.replace(ss, refit=check))
    if new is None:
        return checked(RefitCheck(ss.effect, failed=why or "no solution"))
    cost = new.cost
    if new.plausible is False:
        return checked(RefitCheck(ss.effect, cost, not_used="implausible"))
    if not cost < res.cost:
        return checked(RefitCheck(ss.effect, cost, not_used="it does not lower the cost"))
    first = ss.shift
    names: list[str] = [n for n in ("theta_e", "s_x", "s_y")
                        if n in res.sigma and n in new.values]
    move: dict[str, float] = {n: abs(difference(n, new.values[n], res.values[n])) for n in names}
    before = {n: float(res.sigma[n]) for n in names}
    sigma = dict(res.sigma)
    for n in names:
        sigma[n] = _cover(sigma[n], move[n], first.get(n, 0.0))
    per = {m: dict(e) for m, e in res.per_mission.items()}
    for m, est_m in per.items():
        for n in names:
            em, en = est_m.get(n), new.per_mission.get(m, {}).get(n)
            if em is not None and en is not None and em.sigma_computed:
                d = abs(difference(n, en.value, em.value))
                est_m[n] = dataclasses.replace(em, sigma=_cover(em.sigma, d, first.get(n, 0.0)))
                move[f"{m}:{n}"] = d
    w = structure_warning(ss.effect, True, float(ss.p_value_robust), first,
                          moved={n: move[n] for n in names})
    checked_ss = dataclasses.replace(ss, refit=RefitCheck(ss.effect, cost, move, before),
                                     warning=w)
    return dataclasses.replace(res, sigma=sigma, info=dict(res.info), per_mission=per,
                               sigma_structure=checked_ss,
                               warnings=[w if x == ss.warning else x for x in res.warnings])


def _cover(sigma: float, move: float, first: float) -> float:
    """``sigma`` (which holds the first-order shift ``first`` in quadrature) widened to
    hold the exact ``move`` instead, where that is larger."""
    if not move > first:
        return float(sigma)
    return float(math.sqrt(sigma * sigma + move * move - first * first))
