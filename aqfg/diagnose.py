"""Model diagnosis: where the model fails, which physical effect is missing, and what adding
it buys (issue 5). ``diagnose(missions, model=None, effects=()) -> Diagnosis``.

The steps (each in its own module):

1. **Compare** (:mod:`aqfg.diagnose_compare`): fit the model to all fixes (batch factor
   graph); per sensor, measured vs predicted and the normalised residuals.
2. **Hold out and dead-reckon** (:mod:`aqfg.diagnose_heldout`): refit on thinned fixes
   (GNSS one every ``gnss_every`` s, every other USBL fix); from each fix of that fit the
   model alone predicts the held-out fixes. Innovations to the next fit fix feed the
   consistency test (:mod:`aqfg.diagnose_consistency`, windowed NIS vs chi-square); a
   longer ``horizon`` gives the dead-reckoning error (``rmse``).
3. **Where it fails** (:mod:`aqfg.diagnose_conditions`): rank correlation of the residual
   size with turns, speed, heading, thrust, reverse commands, distance to the station and
   elapsed time, in words.
4. **Which effect** (:mod:`aqfg.diagnose_score`, :mod:`aqfg.diagnose_linearise`): every
   applicable catalogue effect gets a score (Lagrange-multiplier) test at its null on the
   full fit's linearised graph (no refit), Holm-corrected; the top candidates are refitted
   (likelihood ratio, BIC, predictive likelihood and dead-reckoning error of the held-out
   fixes); a block bootstrap over time says how stable the ranking is.
5. **Verdict**: an effect is *missing* when its refit confirms it: likelihood-ratio test
   p < ``alpha`` (Bonferroni over all candidates, as the refitted ones were picked by their
   scores), BIC lower, and the held-out fixes better predicted (higher predictive
   log-likelihood). The score test screens (which effects to refit) and is reported with
   Holm's correction; far from the truth its linearisation can under-rate an effect that the
   refit then shows (e.g. a thrust lag when the base fit has bent the thrust constants).
   Nothing significant and consistent residuals: "nothing missing". Inconsistent residuals
   that no candidate repairs: "something is missing that the catalogue does not explain".

``effects`` are effects the user adds to the model ("add it and watch the error fall"):
the diagnosis then also fits the model without them and reports the before/after
comparison, and keeps looking for anything else missing.

From a notebook::

    from aqfg.io import load_mission
    from aqfg.diagnose import diagnose
    from aqfg import report
    m = load_mission("lake-run-07")
    d = diagnose([m])
    print(d.summary())                       # verdict, consistency, conditions, ranking
    d.best.effect, d.best.estimate()         # the missing effect and its size +- sigma
    report.fig_map(d); report.fig_growth(d)  # matplotlib figures
    d2 = diagnose([m], effects=(d.best.effect,))   # add it: before/after in d2.before
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy import stats

from .diagnose_compare import SensorSeries, Split, sensor_series, split_fixes
from .diagnose_conditions import (ConditionEffect, adjust, condition_signals, in_words,
                                  relate)
from .diagnose_consistency import ConsistencyTest, nis_test
from .diagnose_heldout import HeldOut, heldout_innovations
from .diagnose_linearise import linear_system
from .diagnose_score import (Projected, ScoreTest, bootstrap_ranking, project, score_tests)
from .effects import BUILTIN, UserEffect, resolve
from .mission import Mission
from .result import Result
from .smoother_batch import BatchSmoother
from .smoother_common import FGSettings, check_missions, mission_model, progress_fn


# ---------------------------------------------------------------- one evaluated model
@dataclass
class FitEval:
    """A model fitted to all fixes (``full``) and to the thinned fixes (``thin``), with the
    held-out innovations of the thinned fit: to the next fit fix (``next_fix``, for the
    consistency test) and over ``horizon`` s (``long``, for the dead-reckoning error)."""
    label: str
    effects: tuple[str, ...]
    full: Result
    thin: Result | None
    next_fix: list[HeldOut] = field(default_factory=list)
    long: list[HeldOut] = field(default_factory=list)
    consistency: ConsistencyTest | None = None
    n_meas: int = 0

    @property
    def cost(self) -> float:
        """Half the sum of squared whitened residuals (GTSAM's error) of the full fit."""
        return float(self.full.info.get("cost", np.nan))

    @property
    def n_params(self) -> int:
        return len(self.full.estimated)

    @property
    def bic(self) -> float:
        """BIC of the full fit, up to a constant shared by all models of the same data:
        ``2 cost + n_params ln(n_meas)``."""
        return 2.0 * self.cost + self.n_params * math.log(max(self.n_meas, 2))

    def _pool(self, which: str, attr: str) -> float:
        hs = getattr(self, which)
        if not hs:
            return float("nan")
        u = np.concatenate([h.used for h in hs])
        e = np.concatenate([h.err for h in hs])[u]
        nz = np.concatenate([h.noise for h in hs])[u]
        if not len(e):
            return float("nan")
        ms = float(np.mean(e ** 2))
        if attr == "raw":
            return math.sqrt(ms)
        return math.sqrt(max(ms - float(np.mean(nz)), 0.0))

    @property
    def rmse(self) -> float:
        """Held-out dead-reckoning error (m, RMS over ``horizon`` s legs), the fixes' own
        noise removed."""
        return self._pool("long", "excess")

    @property
    def rmse_raw(self) -> float:
        """RMS distance (m) between dead-reckoned predictions and held-out fixes."""
        return self._pool("long", "raw")

    @property
    def rmse_next_fix(self) -> float:
        """The same as :attr:`rmse` up to the next fit fix only."""
        return self._pool("next_fix", "excess")

    def values(self, names: Sequence[str]) -> dict:
        r = self.full
        return {n: {"value": float(r.values[n]), "sigma": float(r.sigma.get(n, np.nan))}
                for n in names}

    def to_json(self) -> dict:
        c = self.consistency
        return {"label": self.label, "effects": list(self.effects), "cost": self.cost,
                "bic": self.bic, "rmse": self.rmse, "rmse_raw": self.rmse_raw,
                "rmse_next_fix": self.rmse_next_fix,
                "consistency": c.to_json() if c is not None else None,
                "parameters": self.full.parameters_json()}


@dataclass
class Candidate:
    """One catalogue effect, as ranked: its score test, and its refit when done."""
    effect: str
    params: tuple[str, ...]
    score: ScoreTest
    p_adjusted: float = float("nan")
    refit: FitEval | None = None
    lr: float = float("nan")            # likelihood ratio 2 (cost_base - cost_refit)
    lr_p: float = float("nan")
    dbic: float = float("nan")          # BIC(refit) - BIC(base): negative favours the effect
    dll: float = float("nan")           # held-out predictive log-likelihood, refit - base
    significant: bool = False
    confirmed: bool = False
    bootstrap_first: float = float("nan")

    def estimate(self) -> dict:
        """The effect's parameters with 1-sigma: from the refit when done, else the score
        test's one-step estimate."""
        if self.refit is not None:
            return self.refit.values(self.params)
        return {n: {"value": float(v), "sigma": float(s)}
                for n, v, s in zip(self.params, self.score.estimate, self.score.sigma)}


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

    @property
    def best(self) -> Candidate | None:
        return self.ranking[0] if self.ranking and self.ranking[0].confirmed else None

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
        refitted = [c for c in self.ranking if c.refit is not None]
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
        rb = self.base.rmse
        rank = []
        for c in self.ranking:
            rank.append({
                "effect": c.effect, "score": _num(c.score.statistic),
                "p_value": _num(c.score.p_value), "p_adjusted": _num(c.p_adjusted),
                "log10_p": _num(c.score.log10_p),
                "estimate": {k: {"value": _num(v["value"]), "sigma": _num(v["sigma"])}
                             for k, v in c.estimate().items()},
                "rmse_before": _num(rb), "rmse_after": _num(c.refit.rmse) if c.refit else None,
                "rmse_raw_before": _num(self.base.rmse_raw),
                "rmse_raw_after": _num(c.refit.rmse_raw) if c.refit else None,
                "score_robust": _num(c.score.statistic_robust),
                "p_value_robust": _num(c.score.p_value_robust),
                "lr": _num(c.lr), "lr_p_value": _num(c.lr_p), "delta_bic": _num(c.dbic),
                "delta_heldout_loglik": _num(c.dll),
                "consistent_after": (bool(c.refit.consistency.passed)
                                     if c.refit and c.refit.consistency else None),
                "significant": bool(c.significant), "confirmed": bool(c.confirmed),
                "bootstrap_first": _num(c.bootstrap_first)})
        out = {"missing": bool(self.missing), "ranking": rank,
               "unexplained": bool(self.unexplained), "verdict": self.verdict,
               "missions": [m.name for m in self.missions],
               "model_effects": list(self.base.effects),
               "base": self.base.to_json(),
               "consistency": self.base.consistency.to_json() if self.base.consistency else None,
               "conditions": {"text": self.conditions_text,
                              "tests": [e.to_json() for e in self.conditions]},
               "confidence": self.confidence(),
               "settings": self.settings}
        if self.before is not None:
            out["before"] = self.before.to_json()
            out["added"] = list(self.added)
        return _clean(out)

    def summary(self) -> str:
        """The ranked summary printed by ``aqfg diagnose``."""
        L = [self.verdict]
        if self.confidence_text():
            L.append(self.confidence_text())
        L.append("")
        c = self.base.consistency
        if c is not None:
            L.append(f"Held-out fixes vs the model ({'+'.join(self.base.effects) or 'base model'}): "
                     + c.summary())
        L.append(f"Held-out dead-reckoning error: {self.base.rmse:.2f} m (the fixes' own noise "
                 f"removed; RMS distance to the fixes {self.base.rmse_raw:.2f} m)")
        L.append(self.conditions_text)
        if self.before is not None:
            b, a = self.before, self.base
            L.append("")
            L.append(f"Added {', '.join(self.added)}: held-out dead-reckoning error "
                     f"{b.rmse:.2f} -> {a.rmse:.2f} m ({_pct(b.rmse, a.rmse)}; raw "
                     f"{b.rmse_raw:.2f} -> {a.rmse_raw:.2f} m), consistency "
                     f"{_ok(b.consistency)} -> {_ok(a.consistency)}, BIC {a.bic - b.bic:+.1f}")
            for e in a.full.model.effects:
                if e.name in self.added:
                    for n, v in a.values(e.params).items():
                        L.append(f"    {n} = {v['value']:.4g} +- {v['sigma']:.2g}")
        L.append("")
        L.append(f"{'rank':>4}  {'effect':<18} {'score':>9} {'p (Holm)':>9} {'dBIC':>8} "
                 f"{'dLL held':>9} {'DR error before->after (raw), m':>32}  estimate")
        for i, c in enumerate(self.ranking, 1):
            est = ", ".join(f"{n.split('.')[-1]}={v['value']:.3g}+-{v['sigma']:.2g}"
                            for n, v in c.estimate().items())
            dr = (f"{self.base.rmse:.2f} -> {c.refit.rmse:.2f} ({self.base.rmse_raw:.2f} -> "
                  f"{c.refit.rmse_raw:.2f})" if c.refit else "")
            flag = "*" if c.confirmed else ("?" if c.significant else " ")
            L.append(f"{i:>4}{flag} {c.effect:<18} {c.score.statistic:9.1f} {c.p_adjusted:9.2g} "
                     f"{c.dbic:8.1f} {c.dll:9.1f} {dr:>32}  {est}")
        L.append("(dLL held: change of the held-out fixes' predictive log-likelihood; "
                 "* confirmed by its refit (LR test, BIC, held-out fixes); ? significant "
                 "score, not confirmed. "
                 "Effects below the first can be echoes of it: add the first with --effect "
                 "and diagnose again.)")
        return "\n".join(L)


def _num(x):
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _clean(o):
    if isinstance(o, dict):
        return {k: _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, (np.floating, float)):
        return _num(o)
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.bool_):
        return bool(o)
    return o


def _pct(a: float, b: float) -> str:
    if not (np.isfinite(a) and np.isfinite(b)) or a <= 0:
        return "n/a"
    return f"{100 * (b - a) / a:+.0f}%"


def _ok(c: ConsistencyTest | None) -> str:
    return "n/a" if c is None else ("pass" if c.passed else "FAIL")


# ---------------------------------------------------------------- the steps
def candidate_effects(missions: Sequence[Mission], model_effects=(), extra=(),
                      pool: Sequence | None = None) -> list:
    """The effects to rank: ``pool`` (default: the built-in catalogue) plus ``extra`` (e.g.
    :class:`~aqfg.effects.UserEffect` objects), without duplicates, without those already
    in the model, and only those applicable to at least one mission."""
    have = {resolve(e).name for e in model_effects}
    out = []
    for c in list(BUILTIN.values() if pool is None else pool) + list(extra):
        e = resolve(c)
        if e.name in have or any(e.name == o.name for o in out):
            continue
        if any(e.applicable(m) for m in missions):
            out.append(e)
    return out


def _n_meas(res: Result) -> int:
    n = 0
    for mr in res.missions:
        for k, r in mr.residuals.items():
            if k == "dynamics":
                continue
            n += int(np.size(r.raw))
    return n


def evaluate(missions: list[Mission], splits: list[Split], model, effects, label: str, *,
             settings: FGSettings, horizon: float, window: float, init=None,
             heldout: bool = True) -> FitEval:
    """Fit a model (base + ``effects``) to all fixes and to the thinned fixes, and predict
    the held-out fixes."""
    full = BatchSmoother(model, effects=effects, settings=settings, init=init).run(missions)
    ev = FitEval(label, tuple(e.name for e in full.model.effects), full, None,
                 n_meas=_n_meas(full))
    if not heldout:
        return ev
    thin = BatchSmoother(model, effects=effects, settings=settings,
                         init=_init_from(full)).run([s.fit for s in splits])
    ev.thin = thin
    lin = linear_system([s.fit for s in splits], thin, [], settings=settings)
    for i, s in enumerate(splits):
        mdl = mission_model(thin.model, s.fit)
        kw = dict(model=mdl, fit=s.fit, heldout=s.heldout, mres=thin.missions[i], lin=lin,
                  mission_index=i, estimated=thin.estimated, settings=settings)
        ev.next_fix.append(heldout_innovations(**kw))
        ev.long.append(heldout_innovations(**kw, horizon=horizon))
    t = np.concatenate([h.t[h.used] for h in ev.next_fix])
    nis = np.concatenate([h.nis[h.used] for h in ev.next_fix])
    o = np.argsort(t, kind="stable")
    ev.consistency = nis_test(t[o], nis[o], np.full(len(t), 2.0), window)
    return ev


def heldout_loglik_change(base: FitEval, other: FitEval) -> float:
    """Change of the predictive log-likelihood of the held-out fixes (next-fix innovations)
    from ``base`` to ``other``, over the fixes both count (outliers left out by either are
    left out of both)."""
    tot = 0.0
    n = 0
    for hb, ho in zip(base.next_fix, other.next_fix):
        kb = {(s, round(t, 6)): ll for s, t, ll, u in zip(hb.sensor, hb.t, hb.loglik, hb.used) if u}
        for s, t, ll, u in zip(ho.sensor, ho.t, ho.loglik, ho.used):
            k = (s, round(t, 6))
            if u and k in kb:
                tot += ll - kb[k]
                n += 1
    return float(tot) if n else float("nan")


def _init_from(res: Result) -> dict:
    """Initial values for a related fit: the estimates of ``res``."""
    return {n: float(res.values[n]) for n in res.estimated}


def diagnose(missions: Sequence[Mission] | Mission, model=None, effects: Sequence = (), *,
             candidates: Sequence | None = None, extra_candidates: Sequence = (),
             gnss_every: float = 8.0, horizon: float = 60.0, window: float = 60.0,
             alpha: float = 0.01, n_refit: int = 4, max_refit: int = 5, n_boot: int = 200,
             n_blocks: int = 20, memory: float = 8.0, settings: FGSettings | None = None,
             progress=None) -> Diagnosis:
    """Diagnose which effect the model (``model`` + ``effects``) is missing for ``missions``.

    ``candidates``: effects to rank (default: every applicable catalogue effect not in the
    model) plus ``extra_candidates`` (e.g. a :class:`~aqfg.effects.UserEffect`).
    ``gnss_every`` (s): GNSS thinning of the held-out fits; ``horizon`` (s): dead-reckoning
    legs for the held-out error; ``window`` (s): NIS test windows; ``alpha``: significance
    level (after Holm's correction); the top ``n_refit`` candidates by score, and up to
    ``max_refit`` significant ones, are refitted. ``memory`` (s): how far back conditions
    are averaged before each residual.
    """
    import time
    prog = progress_fn(progress)
    missions = check_missions(missions)
    settings = settings or FGSettings()
    effects = tuple(effects)
    timings: dict = {}
    t0 = time.perf_counter()
    splits = [split_fixes(m, gnss_every) for m in missions]
    ev_kw = dict(settings=settings, horizon=horizon, window=window)

    prog(0.02, "fitting the model")
    label = "with " + "+".join(resolve(e).name for e in effects) if effects else "model"
    base = evaluate(missions, splits, model, effects, label, **ev_kw)
    timings["base"] = time.perf_counter() - t0
    before = None
    if effects:
        prog(0.1, "fitting the model without the added effects")
        before = evaluate(missions, splits, model, (), "without " + "+".join(
            resolve(e).name for e in effects), **ev_kw)

    # score tests on the full fit's linearised graph
    prog(0.2, "score tests")
    t1 = time.perf_counter()
    cands = candidate_effects(missions, base.full.model.effects, extra_candidates, candidates)
    ranking: list[Candidate] = []
    if cands:
        lin = linear_system(missions, base.full, cands, settings=settings)
        proj = project(lin)
        eff_params = {c.name: tuple(c.params) for c in cands}
        tests = score_tests(proj, eff_params, n_blocks=n_blocks)
        adj = _holm_log(np.array([t.log10_p for t in tests]))
        boot = bootstrap_ranking(proj, eff_params, n_boot=n_boot, n_blocks=n_blocks) if n_boot else {}
        for t, a in zip(tests, adj):
            ranking.append(Candidate(t.effect, t.params, t, float(a),
                                     significant=bool(a < alpha),
                                     bootstrap_first=boot.get(t.effect, float("nan"))))
        ranking.sort(key=lambda c: (c.score.log10_p, -c.score.statistic))
    timings["score"] = time.perf_counter() - t1

    # refit the top candidates
    t2 = time.perf_counter()
    n_sig = sum(c.significant for c in ranking)
    k = min(len(ranking), max(n_refit, min(n_sig, max_refit)))
    init = _init_from(base.full)
    for i, c in enumerate(ranking[:k]):
        prog(0.3 + 0.6 * i / max(k, 1), f"refitting with {c.effect}")
        eff_obj = next(x for x in cands if x.name == c.effect)
        c.refit = evaluate(missions, splits, model, effects + (eff_obj,), f"+{c.effect}",
                           init=init, **ev_kw)
        c.lr = max(2.0 * (base.cost - c.refit.cost), 0.0)
        # Bonferroni over every candidate: valid although the refitted ones were chosen by
        # their scores
        c.lr_p = float(min(1.0, len(ranking) * stats.chi2.sf(c.lr, len(c.params))))
        c.dbic = c.refit.bic - base.bic
        c.dll = heldout_loglik_change(base, c.refit)
        c.confirmed = bool(c.lr_p < alpha and c.dbic < 0 and c.dll > 0)
    timings["refit"] = time.perf_counter() - t2
    # final order: refitted candidates by BIC (confirmed first), then the rest by score
    refitted = sorted(ranking[:k], key=lambda c: (not c.confirmed, c.dbic))
    ranking = refitted + ranking[k:]

    # where it fails
    prog(0.92, "relating residuals to conditions")
    conds, series = _conditions(missions, splits, base, memory)
    text = in_words(conds)

    missing = bool(ranking and ranking[0].confirmed)
    cons = base.consistency
    unexplained = False
    if missing:
        best = ranking[0]
        after = best.refit.consistency
        verdict = (f"Missing: {best.effect} ({resolve_description(best.effect, cands)}). "
                   f"Score test p = {best.p_adjusted:.2g} (Holm); refit: likelihood-ratio "
                   f"p = {best.lr_p:.2g}, dBIC = {best.dbic:.1f}; "
                   f"held-out dead-reckoning error {base.rmse:.2f} -> {best.refit.rmse:.2f} m "
                   f"({_pct(base.rmse, best.refit.rmse)}; RMS distance to the held-out fixes, "
                   f"their noise included: {base.rmse_raw:.2f} -> {best.refit.rmse_raw:.2f} m).")
        if cons is not None and cons.passed:
            verdict += (" It is small: the model was already consistent with the held-out "
                        "fixes.")
        if after is not None and not after.passed:
            unexplained = True
            verdict += (" The held-out fixes are still not consistent with it: something else "
                        "is missing as well (rerun with --effect " + best.effect + ").")
    elif cons is not None and not cons.passed:
        unexplained = True
        verdict = ("Something is missing that the catalogue does not explain: the held-out "
                   "fixes are not consistent with the model, and no candidate effect is "
                   "confirmed by a refit.")
    else:
        verdict = ("Nothing missing: no candidate effect is confirmed by a refit, and the "
                   "held-out fixes are consistent with the model.")
    timings["total"] = time.perf_counter() - t0
    prog(1.0, "done")
    sett = {"gnss_every": gnss_every, "horizon": horizon, "window": window, "alpha": alpha,
            "n_refit": n_refit, "n_blocks": n_blocks, "n_boot": n_boot, "memory": memory,
            "knot_spacing": settings.knot_spacing, "sigma_a": settings.process.sigma_a}
    return Diagnosis(missions, base, ranking, missing, unexplained, verdict, conds, text,
                     series, before, tuple(resolve(e).name for e in effects), sett, timings)


def diagnose_sequence(missions, model=None, effects: Sequence = (), max_steps: int = 4,
                      **kw) -> list[Diagnosis]:
    """Diagnose, add the confirmed best effect, diagnose again, ... until nothing more is
    found or ``max_steps`` diagnoses have run. Returns the diagnoses in order; the effects
    added are ``[d.best.effect for d in out if d.best]``."""
    out: list[Diagnosis] = []
    effects = tuple(effects)
    for _ in range(max_steps):
        d = diagnose(missions, model, effects, **kw)
        out.append(d)
        if d.best is None:
            break
        eff = next(c for c in candidate_effects(missions, effects, kw.get("extra_candidates", ()),
                                                kw.get("candidates"))
                   if c.name == d.best.effect)
        effects = effects + (eff,)
    return out


def resolve_description(name: str, cands) -> str:
    for c in cands:
        if c.name == name:
            return c.description
    return ""


def _holm_log(log10_p: np.ndarray) -> np.ndarray:
    """Holm-adjusted p-values from log10 p-values (exact for tiny p)."""
    m = len(log10_p)
    o = np.argsort(log10_p)
    adj = np.empty(m)
    run = -np.inf
    for k, i in enumerate(o):
        run = max(run, min(0.0, math.log10(m - k) + log10_p[i]))
        adj[i] = 10 ** run
    return adj


def _conditions(missions, splits, base: FitEval, memory: float):
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

    from .report import write_report
    out = Path(out_dir)
    targets = [out / "diagnosis.json", out / "report.html"]
    existing = [str(p) for p in targets if p.exists()]
    if existing and not overwrite:
        raise FileExistsError(f"refusing to overwrite {', '.join(existing)} (pass --force)")
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "diagnosis.json", "w") as f:
        json.dump(diag.to_json(), f, indent=2)
    write_report(diag, out / "report.html", plots=plots)
    return out
