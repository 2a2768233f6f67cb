"""The verdict on each candidate effect of a diagnosis step: its refit's tests
(:func:`judge`), what it is once the missing effect is known (:func:`label_against`,
:func:`label_unconfirmed`), the ranking's order, and the step's verdict in words."""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy import stats

from aqfg.diagnose.confirm import (
    MIN_GAIN,
    SHARED_MAX,
    Evidence,
    direction_agrees,
    fits_but,
    heldout_gain,
    implausible,
    practical_gain,
    wald_statistic,
)
from aqfg.diagnose.fiteval import FitEval
from aqfg.diagnose.wording import heldout_change
from aqfg.fg.score import Projected, shared_information
from aqfg.model.effects import Effect

if TYPE_CHECKING:
    from aqfg.diagnose.workflow import Candidate

# the ranking's order of the statuses (then by conditional p, BIC change and score)
STATUS_ORDER = {"missing": 0, "independent": 1, "implausible": 2, "negligible": 3, "echo": 4,
                "rejected": 5, "untested": 6, "not significant": 7}


def judge(c: Candidate, base: FitEval, n_cands: int, alpha: float, window: float,
           effect: Effect, missions=(), min_gain: float = MIN_GAIN) -> None:
    """Likelihood ratio, BIC, direction and held-out tests of a refitted candidate, the
    plausibility of its estimate and its practical gain (:mod:`aqfg.diagnose.confirm`)."""
    r = c.refit
    assert r is not None, "judged after its refit"
    c.lr = max(2.0 * (base.cost - r.cost), 0.0)
    # Bonferroni over every candidate: valid although the refitted ones were chosen by
    # their scores
    c.lr_p = float(min(1.0, n_cands * stats.chi2.sf(c.lr, len(c.params))))
    c.dbic = r.bic - base.bic
    delta = np.array([r.full.values[n] - r.model.spec(n).null for n in c.params])
    c.wald = wald_statistic(delta, effect_covariance(r.full, c.params))
    c.wald_p = float(min(1.0, n_cands * stats.chi2.sf(c.wald, len(c.params))))
    c.gain = heldout_gain(base.next_fix, r.next_fix, window)
    c.gain_frac = practical_gain(base.rmse, r.rmse) if r.has_heldout else float("nan")
    c.within_noise = bool(r.has_heldout and base.rmse <= 0.0)
    c.to_noise = bool(r.has_heldout and base.rmse > 0.0 and r.rmse <= 0.0)
    c.implausible = implausible(effect, r.values(c.params), missions)
    c.absorbs = effect.absorbs
    c.evidence = Evidence(score=c.significant, lr=c.lr_p < alpha, bic=c.dbic < 0,
                          direction=direction_agrees(c.score.gradient, delta),
                          heldout=bool(np.isfinite(c.gain.dll) and c.gain.dll > 0),
                          dr_error=bool(np.isfinite(r.rmse_raw) and r.rmse_raw < base.rmse_raw),
                          wald=bool(np.isfinite(c.wald_p) and c.wald_p < alpha),
                          plausible=not c.implausible,
                          practical=bool(np.isfinite(c.gain_frac) and c.gain_frac >= min_gain))
    c.confirmed = c.evidence.confirmed


def effect_covariance(res, names) -> np.ndarray:
    """Joint covariance of the parameters ``names`` of a batch fit (first mission's nodes;
    NaN where they sit in different nodes or were not estimated)."""
    model = res.model
    groups = {model.spec(n).group for n in names}
    cov = res.covariance.blocks if res.covariance is not None else {}
    nan = np.full((len(names), len(names)), np.nan)
    if len(groups) != 1 or not all(n in res.estimated for n in names):
        return nan
    g = groups.pop()
    if g not in cov:
        return nan
    in_g = [n for n in res.estimated if model.spec(n).group == g]
    idx = [in_g.index(n) for n in names]
    return np.asarray(cov[g], float)[np.ix_(idx, idx)]


def label_against(ranking: list[Candidate], best: Candidate, cond: dict,
                  proj: Projected, alpha: float) -> None:
    """Mark ``best`` missing and every other candidate by what it is with it in the model:
    fits but implausible/negligible, ``independent`` (its conditional score test ``cond``
    {effect: (test, Holm-adjusted p)} still significant), an ``echo`` (significant before
    only) or not significant; with the information it shares with ``best`` (on ``proj``)."""
    assert best.refit is not None
    best.status = "missing"
    for c in ranking:
        if c is best:
            continue
        c.conditional, c.p_conditional = cond.get(c.effect, (None, float("nan")))
        c.shared = shared_information(proj, best.params, c.params)
        if fits_but(c):
            c.status = fits_but(c)
        elif np.isfinite(c.p_conditional) and c.p_conditional < alpha:
            c.status = "independent"
        elif c.significant:
            c.status = "echo"
        else:
            c.status = "not significant"


def label_unconfirmed(ranking: list[Candidate]) -> None:
    """Nothing confirmed: each candidate fits but implausible/negligible, not significant,
    rejected by its refit, or significant and not refitted (``untested``)."""
    for c in ranking:
        c.status = (fits_but(c) or ("not significant" if not c.significant else
                                     "rejected" if c.refit is not None else "untested"))


def sort_ranking(ranking: list[Candidate]) -> None:
    """Order the candidates in place: by status (:data:`STATUS_ORDER`), the independent
    ones by conditional p, then by BIC change (refitted first) and score."""
    ranking.sort(key=lambda c: (STATUS_ORDER[c.status],
                                c.p_conditional if c.status == "independent" else 0.0,
                                c.dbic if c.refit is not None else np.inf,
                                c.score.log10_p))


def verdict(base: FitEval, ranking: list[Candidate], best: Candidate | None,
             cand_of: dict) -> tuple[str, bool]:
    cons = base.consistency
    if best is not None:
        r = best.refit
        g = best.gain
        assert r is not None and g is not None, "a confirmed effect was refitted"
        v = (f"Missing: {best.effect} ({cand_of[best.effect].description}): "
             f"{best.estimate_text()}. Score test p = {best.p_adjusted:.2g} (Holm); refit: "
             f"likelihood-ratio p = {best.lr_p:.2g}, dBIC = {best.dbic:.1f}; held-out fixes "
             f"better predicted (log-likelihood {g.dll:+.1f}, paired test p = {g.p:.2g}); "
             f"{heldout_change(base, r)}.")
        if cons is not None and cons.passed:
            v += (" The model was already consistent with the held-out fixes; the effect "
                  "still predicts them better.")
        echoes = [c.effect for c in ranking if c.status == "echo"]
        indep = [c for c in ranking if c.status == "independent"]
        insep = [c for c in ranking if c is not best and np.isfinite(c.shared)
                 and c.shared >= SHARED_MAX and (c.significant or c.status == "independent")]
        if echoes:
            v += (f" Echoes of {best.effect} (their evidence is gone once it is in the model): "
                  f"{', '.join(echoes)}.")
        if indep:
            v += (f" Independent evidence with {best.effect} in the model: "
                  + ", ".join(f"{c.effect} (p = {c.p_conditional:.2g})" for c in indep)
                  + f"; add {best.effect} and diagnose again (or use --auto).")
        if insep:
            v += (f" The data cannot tell {best.effect} apart from "
                  + ", ".join(f"{c.effect} (shared information {c.shared:.2f})" for c in insep)
                  + ": the choice rests on the refits.")
        after = r.consistency
        unexplained = False
        if after is not None and not after.passed and not indep:
            unexplained = True
            v += (" The held-out fixes are still not consistent with it added, and no other "
                  "candidate keeps independent evidence: something the catalogue does not "
                  "explain is missing as well.")
        return v, unexplained
    rejected = [c for c in ranking if c.status == "rejected"]
    why = ""
    fits_but = [c for c in ranking if c.status in ("implausible", "negligible")]
    if fits_but:
        why += " " + " ".join(f"{c.effect} ({c.estimate_text()}) {c.status_text()}."
                              for c in fits_but)
    if rejected:
        why += " " + " ".join(f"{c.effect} has a significant score but is {c.status_text()}."
                              for c in rejected[:3])
    if cons is not None and not cons.passed:
        return ("Something is missing that the catalogue does not explain: the held-out "
                "fixes are not consistent with the model, and no candidate effect is "
                "confirmed as plausible and of practical use." + why), True
    what = ("no candidate effect that is plausible and matters" if fits_but else
            "no candidate effect is confirmed")
    return (f"Nothing missing: {what}, and the held-out fixes are consistent with the "
            "model." + why), False
