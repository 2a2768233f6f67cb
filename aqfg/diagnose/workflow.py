"""Model diagnosis: where the model fails, which physical effect is missing, and what adding
it buys. ``diagnose(missions, model=None, effects=()) -> Diagnosis``; the loop that adds
effects one at a time is :func:`aqfg.diagnose.sequence.diagnose_sequence`.

The steps (each in its own module):

1. **Compare** (:mod:`aqfg.diagnose.compare`): fit the model to all fixes (batch factor
   graph); per sensor, measured vs predicted and the normalised residuals.
2. **Hold out and dead-reckon** (:mod:`aqfg.diagnose.heldout`,
   :mod:`aqfg.diagnose.fiteval`): refit on thinned fixes (GNSS one every ``gnss_every`` s,
   every other USBL fix); from each fix of that fit the model alone predicts the held-out
   fixes. Innovations to the next fit fix feed the consistency test
   (:mod:`aqfg.diagnose.consistency`, windowed NIS vs chi-square); a longer ``horizon``
   gives the dead-reckoning error (``rmse``).
3. **Where it fails** (:mod:`aqfg.diagnose.conditions`): rank correlation of the residual
   size with turns, speed, heading, thrust, reverse commands, distance to the station and
   elapsed time, in words.
4. **Which effect** (:mod:`aqfg.fg.score`, :mod:`aqfg.diagnose.linearise`): every
   applicable catalogue effect gets a score (Lagrange-multiplier) test at its null on the
   full fit's linearised graph (no refit), Holm-corrected; a block bootstrap over time
   says how stable the ranking is. The significant ones (and the first whatever its
   score) are refitted in score order (forward selection by the score statistic),
   warm-started from the base fits
   (:mod:`aqfg.diagnose.refit`; the fit to all fixes and the held-out fit in two
   processes with ``jobs > 1``), until one is confirmed or ``max_refit`` were tried;
   then up to ``max_rivals`` significant candidates never refitted whose evidence the
   confirmed one explains away, in case one of them explains the data better (lower BIC).
5. **Verdict** (:mod:`aqfg.diagnose.confirm`): a candidate is *confirmed* when its
   refit's likelihood ratio (Bonferroni over all candidates) and BIC, the direction of its
   estimate against its score, and the held-out fixes (predictive likelihood up,
   dead-reckoning error down) all agree, its estimate is plausible (else "fits, but
   implausible: probably absorbing ...") and the held-out dead-reckoning error beyond the
   fixes' noise falls by at least ``min_gain`` (else "significant but negligible").
   The first confirmed candidate is the *missing* effect;
   every other candidate is tested again with the missing effect in the model (score test
   at its refit) and labelled an *echo* of it (its evidence is gone) or *independent*
   evidence (to add next), with the information it shares with the missing effect (can the
   data tell them apart?). Nothing confirmed and consistent held-out fixes: "nothing
   missing"; inconsistent held-out fixes that no candidate repairs: "something is missing
   that the catalogue does not explain".
   Each candidate's status and the verdict in words: :mod:`aqfg.diagnose.judging`; the
   summary and ``diagnosis.json``: :mod:`aqfg.diagnose.rendering`.

``effects`` are effects the user adds to the model ("add it and watch the error fall"):
the diagnosis then also fits the model without them and reports the before/after
comparison, and keeps looking for anything else missing.

From a notebook::

    from aqfg.data import load_mission
    from aqfg.diagnose import diagnose
    m = load_mission("lake-run-07")
    d = diagnose([m])
    print(d.summary())                       # verdict, consistency, conditions, ranking
    d.best.effect, d.best.estimate()         # the missing effect and its size +- sigma
    report.fig_map(d); report.fig_growth(d)  # matplotlib figures
    d2 = diagnose([m], effects=(d.best.effect,))   # add it: before/after in d2.before
"""
from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from aqfg.data.mission import Mission
from aqfg.diagnose.compare import sensor_series, split_fixes
from aqfg.diagnose.conditions import (
    ConditionEffect,
    adjust,
    condition_signals,
    in_words,
    relate,
)
from aqfg.diagnose.confirm import (
    MIN_GAIN,
    SHARED_MAX,
    Evidence,
    HeldoutGain,
    rivals,
)
from aqfg.diagnose.fiteval import FitEval, blas_threads, default_jobs, evaluate
from aqfg.diagnose.judging import (  # noqa: F401
    effect_covariance,
    judge,
    label_against,
    label_unconfirmed,
    sort_ranking,
    verdict,
)
from aqfg.diagnose.linearise import linear_system
from aqfg.diagnose.rendering import (  # noqa: F401
    diagnosis_json,
    diagnosis_summary,
    json_num,
    json_ready,
    write_diagnosis_json,
)
from aqfg.diagnose.wording import gain_cell, heldout_change, percent_change  # noqa: F401
from aqfg.fg import gnss_noise
from aqfg.fg.common import check_missions, progress_fn
from aqfg.fg.score import (
    Projected,
    ScoreTest,
    bootstrap_ranking,
    holm_log,
    project,
    score_tests,
)
from aqfg.fg.settings import FGSettings
from aqfg.fg.structure import candidate_effects
from aqfg.model.effects import resolve

__all__ = ["Candidate", "Diagnosis", "FitEval", "Screen", "candidate_effects", "diagnose",
           "evaluate", "save_diagnosis"]

# what a candidate is, relative to the missing effect (or why it is not)
STATUS_TEXT = {
    "missing": "missing",
    "independent": "independent evidence",
    "echo": "echo",
    "rejected": "not confirmed",
    "implausible": "fits, but implausible",
    "negligible": "significant but negligible",
    "untested": "significant score, not refitted",
    "not significant": "no evidence",
}


@dataclass
class Candidate:
    """One catalogue effect, as ranked: its score test, its refit when done, and what it
    is (``status``: "missing", "echo", "independent", "rejected", "not significant")."""
    effect: str
    params: tuple[str, ...]
    score: ScoreTest
    p_adjusted: float = float("nan")
    refit: FitEval | None = None
    lr: float = float("nan")            # likelihood ratio 2 (cost_base - cost_refit)
    lr_p: float = float("nan")
    wald: float = float("nan")          # Wald statistic of the refit's estimate
    wald_p: float = float("nan")        # its p-value (Bonferroni over the candidates)
    dbic: float = float("nan")          # BIC(refit) - BIC(base): negative favours the effect
    gain: HeldoutGain | None = None     # held-out predictive gain of the refit
    evidence: Evidence | None = None
    significant: bool = False
    confirmed: bool = False             # passes every test on its own (confirm module)
    bootstrap_first: float = float("nan")
    status: str = "not significant"
    conditional: ScoreTest | None = None    # score test with the missing effect added
    p_conditional: float = float("nan")     # its Holm-adjusted p-value
    shared: float = float("nan")            # information shared with the missing effect
    gain_frac: float = float("nan")         # held-out DR error reduction (practical_gain)
    within_noise: bool = False              # the base model already predicts within the noise
    to_noise: bool = False                  # the refit predicts within it, the base did not
    implausible: list[str] = field(default_factory=list)   # estimates outside their range
    absorbs: str = ""                       # what an implausible estimate stands for

    @property
    def dll(self) -> float:
        """Held-out predictive log-likelihood change of the refit (nan if not refitted)."""
        return self.gain.dll if self.gain is not None else float("nan")

    def estimate(self) -> dict:
        """The effect's parameters with 1-sigma: from the refit when done, else the score
        test's one-step estimate."""
        if self.refit is not None:
            return self.refit.values(self.params)
        return {n: {"value": float(v), "sigma": float(s)}
                for n, v, s in zip(self.params, self.score.estimate, self.score.sigma)}

    def gain_text(self) -> str:
        """The held-out gain in words: "-2% held-out error (beyond the fixes' noise)"."""
        if self.refit is None or not np.isfinite(self.gain_frac):
            return "no held-out error"
        if self.within_noise:
            return "the held-out fixes were already predicted within their noise"
        if self.to_noise:
            return "the held-out error beyond the fixes' noise brought within it"
        return f"{-100 * self.gain_frac:+.0f}% held-out error (beyond the fixes' noise)"

    def estimate_text(self) -> str:
        return ", ".join(f"{n.split('.')[-1]} = {v['value']:.3g} +- {v['sigma']:.2g}"
                         for n, v in self.estimate().items())

    def status_text(self, missing: str | None = None) -> str:
        """The status in words, e.g. "echo of linear_drag" or "not confirmed: BIC not
        lower"."""
        s = self.status
        if s == "echo" and missing:
            out = f"echo of {missing}"
        elif s == "independent" and missing:
            out = f"independent of {missing}"
        elif s == "rejected" and self.evidence is not None:
            out = "not confirmed: " + "; ".join(self.evidence.failed())
        elif s == "implausible":
            out = (f"fits, but implausible ({'; '.join(self.implausible)}): probably absorbing "
                   f"{self.absorbs or 'something the catalogue does not hold'}")
        elif s == "negligible":
            out = f"significant but negligible: {self.gain_text()}"
        else:
            out = STATUS_TEXT.get(s, s)
        if missing and s != "missing" and np.isfinite(self.shared) and self.shared >= SHARED_MAX:
            out += f" (not separable from {missing}: shared information {self.shared:.2f})"
        return out


@dataclass
class Screen:
    """Score tests of the candidates at one fit (``fit``), with the projected linear
    system they came from (reused by the bootstrap and the next step of a sequence)."""
    fit: object
    proj: Projected | None
    tests: list[ScoreTest]
    adjusted: np.ndarray


@dataclass
class Diagnosis:
    """Everything the diagnosis found (plot it from a notebook, or write it with
    :func:`save_diagnosis`)."""
    missions: list[Mission]
    base: FitEval
    ranking: list[Candidate]
    missing: bool
    unexplained: bool
    verdict: str
    conditions: list[ConditionEffect]
    conditions_text: str
    series: dict                                # mission name -> list[SensorSeries]
    before: FitEval | None = None               # the model without the user-added effects
    added: tuple[str, ...] = ()
    settings: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    next_screen: Screen | None = None           # score tests with the missing effect added

    @property
    def best(self) -> Candidate | None:
        """The missing effect (None when nothing is confirmed)."""
        return self.ranking[0] if self.ranking and self.ranking[0].status == "missing" else None

    def labelled(self, status: str) -> list[Candidate]:
        return [c for c in self.ranking if c.status == status]

    def confidence(self) -> dict:
        """How sure the ranking is: the first candidate's share of block-bootstrap
        resamples in which it has the best score (``bootstrap_first``), its rank by score
        alone (``score_rank``: 1 = score and refit agree), and the BIC margin to the second
        refitted candidate (``bic_margin``; > 10 is "very strong" on Kass & Raftery's
        scale)."""
        if not self.ranking:
            return {}
        first = self.ranking[0]
        by_score = sorted(self.ranking, key=lambda c: (c.score.log10_p, -c.score.statistic))
        refitted = sorted((c for c in self.ranking if c.refit is not None),
                          key=lambda c: c.dbic)
        margin = (refitted[1].dbic - refitted[0].dbic) if len(refitted) > 1 else float("nan")
        return {"first": first.effect, "bootstrap_first": first.bootstrap_first,
                "score_rank": 1 + by_score.index(first), "bic_margin": margin}

    def confidence_text(self) -> str:
        c = self.confidence()
        if not c or self.best is None:
            return ""
        agree = ("score test and refit agree" if c["score_rank"] == 1 else
                 f"the refit promotes it from rank {c['score_rank']} by score")
        parts = [agree]
        if np.isfinite(c["bootstrap_first"]):
            parts.append(f"it has the best score in {100 * c['bootstrap_first']:.0f}% of "
                         "time-block bootstrap resamples")
        if np.isfinite(c["bic_margin"]):
            parts.append(f"BIC margin to the next candidate {c['bic_margin']:.1f}")
        return "Confidence in the ranking: " + "; ".join(parts) + "."

    def to_json(self) -> dict:
        """The ``diagnosis.json`` of the format doc (extra keys allowed)."""
        return diagnosis_json(self)

    def summary(self) -> str:
        """The ranked summary printed by ``aqfg diagnose``."""
        return diagnosis_summary(self)


# ---------------------------------------------------------------- the steps
def screen(missions: list[Mission], fit, cands: list, settings: FGSettings,
           n_blocks: int = 20) -> Screen:
    """Score tests of ``cands`` at the full fit ``fit`` (a :class:`~aqfg.result.Result`),
    Holm-adjusted."""
    if not cands:
        return Screen(fit, None, [], np.zeros(0))
    lin = linear_system(missions, fit, cands, settings=settings)
    proj = project(lin)
    tests = score_tests(proj, {c.name: tuple(c.params) for c in cands}, n_blocks=n_blocks)
    return Screen(fit, proj, tests, holm_log(np.array([t.log10_p for t in tests])))


def diagnose(missions: Sequence[Mission] | Mission, model=None, effects: Sequence = (), **kw
             ) -> Diagnosis:
    """:func:`diagnose_step` with the BLAS thread pool limited to one thread (see
    :func:`aqfg.diagnose.fiteval.blas_threads`); the arguments are :func:`diagnose_step`'s."""
    with blas_threads(1):
        return diagnose_step(missions, model, effects, **kw)


def _held_out_splits(missions: list[Mission], settings: FGSettings, gnss_every: float):
    """The held-out GNSS fixes' 1-sigma (m; None: their stated sigma) and each mission's
    split into fit and held-out fixes (GNSS one every ``gnss_every`` s). The sigma is
    ``settings.graph.gnss_noise``'s where that is a :class:`~aqfg.fg.gnss_noise.GnssNoise`, the
    stated one where it is None, else the stated one unless the fixes' wander shows it too
    large (:func:`~aqfg.fg.gnss_noise.judged_sigma`: a stated sigma far above it would
    hide any dead-reckoning error)."""
    gn = settings.graph.gnss_noise
    sigma = (None if gn is None else gn.sigma if isinstance(gn, gnss_noise.GnssNoise) else
             gnss_noise.judged_sigma(missions, settings.online.kinematic_q,
                                     settings.graph.sensors.gnss_sigma))
    return sigma, [split_fixes(m, gnss_every, sigma) for m in missions]


def _screen_of(missions: list[Mission], base: FitEval, cands: list,
               base_screen: Screen | None, settings: FGSettings, n_blocks: int) -> Screen:
    """The score tests of ``cands`` at the base fit: ``base_screen`` where it holds those of
    that very fit, else computed."""
    if (base_screen is not None and base_screen.fit is base.full
            and [t.effect for t in base_screen.tests] == [c.name for c in cands]):
        return base_screen
    return screen(missions, base.full, cands, settings, n_blocks)


def _fit_settings(settings: FGSettings, jobs: int, heldout_sigma: float | None) -> dict:
    """The fits' settings as recorded in ``diagnosis.json`` (after the tests' own)."""
    return {"knot_spacing": settings.graph.knot_spacing, "sigma_a": settings.graph.process.sigma_a,
            "jobs": jobs, "heldout_gnss_sigma": heldout_sigma}


def _base_fits(missions: list[Mission], splits: list, model, effects: tuple,
               base_eval: FitEval | None, ev_kw: dict, prog) -> tuple[FitEval, FitEval | None]:
    """The evaluation of the model with ``effects`` (``base_eval`` when given), and without
    them where some were added (None otherwise)."""
    names = tuple(e.name for e in effects)
    prog(0.02, "fitting the model")
    label = "with " + "+".join(names) if effects else "model"
    base = base_eval if base_eval is not None else evaluate(missions, splits, model, effects,
                                                            label, **ev_kw)
    before = None
    if effects and base_eval is None:
        prog(0.1, "fitting the model without the added effects")
        before = evaluate(missions, splits, model, (), "without " + "+".join(names), **ev_kw)
    return base, before


def _rank(scr: Screen, cands: list, alpha: float, n_boot: int, n_blocks: int
          ) -> list[Candidate]:
    """The candidates of the score tests ``scr``, significant below ``alpha`` (Holm), with
    their block-bootstrap share of first places, best score first."""
    ranking: list[Candidate] = []
    if scr.tests:
        eff_params = {c.name: tuple(c.params) for c in cands}
        assert scr.proj is not None, "a screen with tests has its projected system"
        boot = (bootstrap_ranking(scr.proj, eff_params, n_boot=n_boot, n_blocks=n_blocks)
                if n_boot else {})
        for t, a in zip(scr.tests, scr.adjusted):
            ranking.append(Candidate(t.effect, t.params, t, float(a),
                                     significant=bool(a < alpha),
                                     bootstrap_first=boot.get(t.effect, float("nan"))))
        ranking.sort(key=lambda c: (c.score.log10_p, -c.score.statistic))
    return ranking


@dataclass(frozen=True)
class _Refits:
    """How one diagnosis step refits a candidate and judges it: the missions and their
    held-out splits, the model with the step's ``effects``, the base evaluation it starts
    from, the candidate effects by name, the number of candidates (for Bonferroni) and the
    tests' settings."""
    missions: list[Mission]
    splits: list
    model: Any
    effects: tuple
    base: FitEval
    cand_of: dict
    n_cands: int
    alpha: float
    window: float
    min_gain: float
    jobs: int
    ev_kw: dict

    def refit(self, c: Candidate) -> None:
        """Refit with ``c``'s effect added (warm-started from the base) and judge it."""
        effect = self.cand_of[c.effect]
        c.refit = evaluate(self.missions, self.splits, self.model, self.effects + (effect,),
                           f"+{c.effect}", start=self.base, jobs=self.jobs, **self.ev_kw)
        judge(c, self.base, self.n_cands, self.alpha, self.window, effect, self.missions,
              self.min_gain)


def _first_confirmed(ranking: list[Candidate], rf: _Refits, k: int, prog) -> Candidate | None:
    """Refit the first ``k`` candidates in score order (forward selection by the score
    statistic) until one is confirmed; that one, or None."""
    for i, c in enumerate(ranking[:k]):
        prog(0.3 + 0.5 * i / k, f"refitting with {c.effect}")
        rf.refit(c)
        if c.confirmed:
            return c
    return None


def _settle_missing(best: Candidate, ranking: list[Candidate], cands: list, rf: _Refits,
                    settings: FGSettings, n_blocks: int, max_rivals: int, prog
                    ) -> tuple[Candidate, Screen, dict]:
    """The others' score tests with ``best`` in the model; the significant candidates
    never refitted whose evidence it explains away (at most ``max_rivals``, two rounds) are
    refitted, and one confirmed with a lower BIC replaces it. Returns the missing effect,
    the score tests with it in the model and those as {effect: (test, Holm-adjusted p)}."""
    prog(0.85, f"testing the others with {best.effect} added")
    assert best.refit is not None
    swaps = 0
    while True:
        others = [c for c in cands if c.name != best.effect]
        assert best.refit is not None
        next_scr = screen(rf.missions, best.refit.full, others, settings, n_blocks)
        cond = {t.effect: (t, a) for t, a in zip(next_scr.tests, next_scr.adjusted)}
        rival = rivals(ranking, best, cond, rf.alpha, max_rivals) if swaps < 2 else []
        for c in rival:
            prog(0.87, f"refitting {c.effect}, which {best.effect} explains away")
            rf.refit(c)
        better = [c for c in rival if c.confirmed and c.dbic < best.dbic]
        if not better:
            return best, next_scr, cond
        best = min(better, key=lambda c: c.dbic)     # the one the echo stood for
        swaps += 1


def _label(ranking: list[Candidate], best: Candidate | None, scr: Screen, cands: list,
           rf: _Refits, settings: FGSettings, n_blocks: int, max_rivals: int, prog
           ) -> tuple[Candidate | None, Screen | None]:
    """Each candidate's status, and the ranking in its final order; where one was confirmed
    (``best``), the missing effect settled first (:func:`_settle_missing`). Returns the
    missing effect (None: none) and the score tests with it in the model."""
    next_scr = None
    if best is not None:
        assert scr.proj is not None
        best, next_scr, cond = _settle_missing(best, ranking, cands, rf, settings, n_blocks,
                                               max_rivals, prog)
        label_against(ranking, best, cond, scr.proj, rf.alpha)
    else:
        label_unconfirmed(ranking)
    sort_ranking(ranking)
    return best, next_scr


def diagnose_step(missions: Sequence[Mission] | Mission, model=None, effects: Sequence = (), *,
             candidates: Sequence | None = None, extra_candidates: Sequence = (),
             gnss_every: float = 8.0, horizon: float = 60.0, window: float = 60.0,
             alpha: float = 0.01, min_gain: float = MIN_GAIN, n_refit: int = 1,
             max_refit: int = 4, max_rivals: int = 2, n_boot: int = 200,
             n_blocks: int = 20, memory: float = 8.0, settings: FGSettings | None = None,
             jobs: int | None = None, progress=None, base_eval: FitEval | None = None,
             base_screen: Screen | None = None) -> Diagnosis:
    """Diagnose which effect the model (``model`` + ``effects``) is missing for ``missions``.

    ``candidates``: effects to rank (default: every applicable catalogue effect not in the
    model) plus ``extra_candidates`` (e.g. a :class:`~aqfg.model.effects.UserEffect`).
    ``gnss_every`` (s): GNSS thinning of the held-out fits; ``horizon`` (s): dead-reckoning
    legs for the held-out error; ``window`` (s): NIS test windows and the time blocks of
    the held-out predictive test; ``alpha``: significance level of every test (after the
    corrections named in the module docstring); ``min_gain``: the fraction by which the
    held-out dead-reckoning error beyond the fixes' noise must fall for an effect to be
    named missing (:data:`~aqfg.diagnose.confirm.MIN_GAIN`). The candidates with a significant score,
    and the top ``n_refit`` whatever their score, are refitted best score first until one
    is confirmed, at most ``max(n_refit, max_refit)`` of them; then at most ``max_rivals``
    significant candidates never refitted whose evidence the confirmed one explains away are
    refitted, and one of them confirmed with a lower BIC is the missing effect instead.
    ``memory`` (s): how far back conditions are averaged before each residual. ``jobs``:
    processes for a refit (default 2 where two CPUs are available; 1 = no worker).
    ``base_eval`` / ``base_screen``: the model's evaluation and score tests when already
    computed (the previous step of a sequence).
    """
    prog = progress_fn(progress)
    missions = check_missions(missions)
    # the nominal process noise: a noise chosen to explain the fixes would hide the
    # misfit the diagnosis is there to show (batch.adapt_noise None would choose it on short data)
    settings = (settings or FGSettings()).with_(batch={"adapt_noise": False,
                                                          "adapt_track": False})
    effects = tuple(resolve(e) for e in effects)
    jobs = default_jobs() if jobs is None else max(1, int(jobs))
    timings: dict = {}
    t0 = time.perf_counter()
    noise, splits = _held_out_splits(missions, settings, gnss_every)
    ev_kw: dict[str, Any] = {"settings": settings, "horizon": horizon, "window": window}
    base, before = _base_fits(missions, splits, model, effects, base_eval, ev_kw, prog)
    timings["base"] = time.perf_counter() - t0

    # score tests on the full fit's linearised graph
    prog(0.2, "score tests")
    t1 = time.perf_counter()
    cands = candidate_effects(missions, base.model.effects, extra_candidates, candidates)
    cand_of = {c.name: c for c in cands}
    scr = _screen_of(missions, base, cands, base_screen, settings, n_blocks)
    ranking = _rank(scr, cands, alpha, n_boot, n_blocks)
    timings["score"] = time.perf_counter() - t1

    # refit the significant candidates in score order, warm-started from the base fits,
    # until one is confirmed
    t2 = time.perf_counter()
    rf = _Refits(missions, splits, model, effects, base, cand_of, len(ranking), alpha, window,
                 min_gain, jobs, ev_kw)
    n_sig = sum(c.significant for c in ranking)
    best = _first_confirmed(ranking, rf, min(len(ranking), max(n_refit, min(n_sig, max_refit))),
                            prog)
    timings["refit"] = time.perf_counter() - t2

    # the missing effect, and what the others are once it is in the model
    t3 = time.perf_counter()
    best, next_scr = _label(ranking, best, scr, cands, rf, settings, n_blocks, max_rivals, prog)
    timings["conditional"] = time.perf_counter() - t3

    # where it fails
    prog(0.92, "relating residuals to conditions")
    conds, series = _conditions(missions, base, memory)
    verdict_text, unexplained = verdict(base, ranking, best, cand_of)
    timings["total"] = time.perf_counter() - t0
    prog(1.0, "done")
    sett = {"gnss_every": gnss_every, "horizon": horizon, "window": window, "alpha": alpha,
            "min_gain": min_gain, "max_refit": max_refit, "max_rivals": max_rivals,
            "n_blocks": n_blocks, "n_boot": n_boot, "memory": memory,
            **_fit_settings(settings, jobs, noise)}
    return Diagnosis(missions, base, ranking, best is not None, unexplained, verdict_text,
                     conds, in_words(conds), series, before,
                     tuple(e.name for e in effects) if base_eval is None else (), sett,
                     timings, next_scr)


def resolve_description(name: str, cands) -> str:
    for c in cands:
        if c.name == name:
            return c.description
    return ""


def _conditions(missions, base: FitEval, memory: float):
    """Residual series of the base model related to the conditions of each mission."""
    series = {}
    effects: list[ConditionEffect] = []
    per_series: dict[str, list] = {}
    for i, m in enumerate(missions):
        mres = base.full.missions[i]
        sig = condition_signals(m, mres.track, float(mres.p[0]))
        ss = sensor_series(mres)
        series[m.name] = ss
        for s in ss:
            per_series.setdefault(f"fit {s.sensor}", []).append(
                (s.t, s.nis / np.maximum(s.dof, 1), sig))
        if base.next_fix:
            h = base.next_fix[i]
            u = h.used
            per_series.setdefault("held-out fixes", []).append((h.t[u], h.nis[u] / 2.0, sig))
    for name, parts in per_series.items():
        for t, y, sig in parts:
            effects += relate(name, t, y, sig, memory=memory)
    return adjust(effects), series


# ---------------------------------------------------------------- output
def save_diagnosis(diag: Diagnosis, out_dir, overwrite: bool = False, plots: bool = True):
    """Write ``diagnosis.json`` and a self-contained ``report.html`` into ``out_dir``."""
    from pathlib import Path

    from aqfg.diagnose.report import write_report
    out = write_diagnosis_json(diag.to_json(), Path(out_dir), ("report.html",), overwrite)
    write_report(diag, out / "report.html", plots=plots)
    return out
