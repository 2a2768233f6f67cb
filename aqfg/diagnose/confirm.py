"""When is a candidate effect confirmed? The tests a refit must pass, as pure functions.

The **score** test at the null (full fit, Holm over the candidates) ranks the candidates
and says which way the data pull each one; the candidates are refitted in that order (the
significant ones, and the first whatever its score: far from the truth the linearisation
can under-rate an effect that its refit shows). A refitted candidate is *confirmed* only
when the other views of the evidence agree:

2. **likelihood ratio** of its refit (Bonferroni over all candidates: valid although the
   refitted ones were chosen by their scores) is significant, the BIC is lower, and the
   **Wald** test of the refit's estimate (its own, misfit-robust covariance) agrees: a
   refit whose cost fell while its effect stayed near the null found a better optimum for
   another reason;
3. **direction**: the refit moves the parameters the way the score pulls them,
   ``g^T (theta_refit - theta_null) > 0``. Score, Wald and LR tests are asymptotically
   equivalent only near the null; a refit that lands on the other side (a weak starboard
   propeller "estimated" stronger) is using the effect to absorb something else;
4. **held-out prediction**: the fixes the thinned fit never saw are better predicted: the
   predictive log-likelihood of the held-out fixes rises and the dead-reckoning error to
   them falls. This is a cross-validation check, not a second significance test (the score
   and LR tests carry the significance): for nested models an extra parameter that is not
   there *lowers* the expected held-out log-likelihood (its estimation noise, about half a
   unit per parameter; Stone 1977, cross-validation and AIC), so a rise says the effect
   predicts, not only fits. A paired t test of the gain over time blocks (Diebold &
   Mariano 1995, batch-means variance) is reported beside it; it is not required, as its
   few blocks give it little power against effects that act in a few manoeuvres
   (docs/diagnosis.md).

A candidate that passes these tests is still not named *missing* unless it is

5. **plausible**: every estimate lies in its parameter's plausible range
   (:meth:`~aqfg.model.effects.Effect.plausible_range`: a real vehicle's values; a lever arm
   within a declared hull). Outside it the effect fits, but stands for something else, which
   the catalogue names (``Effect.absorbs``: a lever arm far outside the hull is usually a
   time offset of the fixes) -- "fits, but implausible";
6. **of practical use**: the held-out dead-reckoning error beyond the fixes' noise falls by
   at least ``min_gain`` (:data:`MIN_GAIN`, 10 %; :func:`practical_gain`). A model already
   within the noise of the held-out fixes has nothing left to gain -- "significant but
   negligible".

The remaining candidates are labelled relative to the one chosen (the *missing* effect):
an *echo* has a significant score at the base model but none once the missing effect is
in the model (its score test at the missing effect's refit); *independent* evidence stays
significant after that conditioning. :func:`~aqfg.fg.score.shared_information` says
whether the data can tell two effects apart at all.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

SHARED_MAX = 0.9   # above: "cannot be separated" (joint sigma inflated > 3x, 1/sqrt(1-r2))
MIN_GAIN = 0.10    # the held-out DR error must fall by this fraction for "missing" (setting min_gain)


def practical_gain(rmse_before: float, rmse_after: float) -> float:
    """Fraction by which the held-out dead-reckoning error beyond the fixes' noise falls
    (``1 - after / before``; 1 when the error falls to within the noise). 0 when the base
    model is already within the noise (nothing to gain); NaN without held-out fixes."""
    if not (np.isfinite(rmse_before) and np.isfinite(rmse_after)):
        return float("nan")
    if rmse_before <= 0.0:
        return 0.0
    return float(1.0 - rmse_after / rmse_before)


def implausible(effect, values: dict, missions=()) -> list[str]:
    """The estimates of ``effect`` (``{name: {"value", ...}}``) outside their plausible
    range (:meth:`~aqfg.model.effects.Effect.implausible`), in words, e.g.
    ``"ratio = 1.63 outside [0.3, 1.5]"``; empty when all are plausible."""
    return effect.implausible({n: float(v["value"]) for n, v in values.items()}, missions)


@dataclass
class HeldoutGain:
    """Paired comparison of two models' predictions of the same held-out fixes.

    ``dll``: total change of the predictive log-likelihood (other - base) over ``n`` fixes
    both models count; ``blocks`` time blocks; ``t``: t statistic of the block sums;
    ``p``: one-sided p-value (other predicts better)."""
    dll: float
    n: int
    blocks: int
    t: float
    p: float


def heldout_gain(base_next_fix, other_next_fix, window: float = 60.0) -> HeldoutGain:
    """Held-out predictive gain of ``other`` over ``base`` (lists of
    :class:`~aqfg.diagnose.heldout.HeldOut`, one per mission, next-fix innovations),
    over the fixes both count (outliers left out by either are left out of both),
    blocked by ``window`` s per mission."""
    d, blk = [], []
    nb = 0
    for hb, ho in zip(base_next_fix, other_next_fix):
        kb = {(s, round(float(t), 6)): ll
              for s, t, ll, u in zip(hb.sensor, hb.t, hb.loglik, hb.used) if u}
        tt, dd = [], []
        for s, t, ll, u in zip(ho.sensor, ho.t, ho.loglik, ho.used):
            k = (s, round(float(t), 6))
            if u and k in kb:
                tt.append(float(t))
                dd.append(float(ll - kb[k]))
        if not tt:
            continue
        ta = np.asarray(tt)
        b = np.floor((ta - ta.min()) / window).astype(int)
        d.append(np.asarray(dd))
        blk.append(b + nb)
        nb += int(b.max()) + 1
    if not d:
        return HeldoutGain(float("nan"), 0, 0, float("nan"), float("nan"))
    da, blka = np.concatenate(d), np.concatenate(blk)
    sums = np.bincount(blka, da)
    sums = sums[np.bincount(blka) > 0]
    B = len(sums)
    total = float(da.sum())
    if B < 3:
        return HeldoutGain(total, len(da), B, float("nan"), float("nan"))
    sd = float(np.std(sums, ddof=1))
    if sd <= 0:
        t = np.inf if total > 0 else (-np.inf if total < 0 else 0.0)
    else:
        t = float(np.mean(sums) / (sd / np.sqrt(B)))
    return HeldoutGain(total, len(da), B, t, float(stats.t.sf(t, B - 1)))


def direction_agrees(gradient: np.ndarray | None, delta: np.ndarray) -> bool:
    """Does the refit move the parameters (``delta`` from their null) the way the score
    ``gradient`` pulls them (``g^T delta > 0``)? True when there is no score to compare."""
    if gradient is None:
        return True
    g = np.asarray(gradient, float)
    delta = np.asarray(delta, float)
    if not np.any(delta != 0):          # the refit did not move: nothing to confirm
        return False
    return bool(g @ delta > 0)


@dataclass
class Evidence:
    """The verdict of each test on one refitted candidate (see the module docstring)."""
    score: bool
    lr: bool
    bic: bool
    direction: bool
    heldout: bool
    dr_error: bool
    wald: bool = True
    plausible: bool = True
    practical: bool = True

    @property
    def statistical(self) -> bool:
        """Every statistical test but the score's significance (which only orders the
        refits)."""
        return all((self.lr, self.wald, self.bic, self.direction, self.heldout, self.dr_error))

    @property
    def confirmed(self) -> bool:
        """The statistical tests, a plausible estimate and a practical gain."""
        return self.statistical and self.plausible and self.practical

    def failed(self) -> list[str]:
        """What stands against the effect, in words."""
        why = {"lr": "refit likelihood ratio not significant",
               "wald": "refit estimate not significantly off its null",
               "bic": "BIC not lower",
               "direction": "refit moves against the score's direction",
               "heldout": "held-out fixes not better predicted",
               "dr_error": "held-out dead-reckoning error not lower",
               "plausible": "estimate implausible",
               "practical": "held-out dead-reckoning error not lowered enough to matter"}
        return [why[k] for k in why if not getattr(self, k)]


def wald_statistic(delta: np.ndarray, cov: np.ndarray) -> float:
    """``delta^T cov^-1 delta`` (pseudo-inverse: parameters pinned at a bound carry no
    information)."""
    delta = np.asarray(delta, float)
    if not len(delta) or not np.all(np.isfinite(cov)):
        return float("nan")
    return float(delta @ np.linalg.pinv(np.asarray(cov, float)) @ delta)


def rivals(ranking: list, best, cond: dict, alpha: float, n: int) -> list:
    """Significant candidates (of ``ranking``, best score first) never refitted whose
    evidence ``best`` explains away (their Holm-adjusted score p-value with ``best`` in the
    model, ``cond[effect][1]``, is not below ``alpha``), at most ``n``: one of them may be
    the effect ``best`` stood in for (a late GNSS imitates a thrust lag), and is named
    missing instead when its refit is confirmed with a lower BIC."""
    out = []
    for c in ranking:
        if c is best or c.refit is not None or not c.significant:
            continue
        p = cond.get(c.effect, (None, float("nan")))[1]
        if not (np.isfinite(p) and p < alpha):
            out.append(c)
    return out[:n]


def fits_but(c) -> str:
    """"implausible" or "negligible" for a candidate whose refit passes the statistical
    tests but not the plausibility or the practical-gain test (its ``evidence``), else
    ""."""
    e = c.evidence
    if e is None or not e.statistical:
        return ""
    return "implausible" if not e.plausible else "negligible" if not e.practical else ""
