"""A diagnosis in words and as ``diagnosis.json``: the ranked summary ``aqfg diagnose``
prints, the JSON document of the format doc, and the JSON conventions (numpy scalars as
Python numbers, non-finite floats as null)."""
from __future__ import annotations

import json
import math
from typing import TYPE_CHECKING, Any, SupportsFloat

import numpy as np

from aqfg.diagnose.confirm import MIN_GAIN
from aqfg.diagnose.consistency import ConsistencyTest
from aqfg.diagnose.wording import gain_cell, heldout_change

if TYPE_CHECKING:
    from aqfg.diagnose.workflow import Candidate, Diagnosis


def diagnosis_json(d: Diagnosis) -> dict:
    """The ``diagnosis.json`` of the format doc (extra keys allowed)."""
    rb = d.base.rmse
    best = d.best.effect if d.best else None
    rank = []
    for c in d.ranking:
        g = c.gain
        rh = c.refit if _ho(c) else None
        rank.append({
            "effect": c.effect, "status": c.status, "status_text": c.status_text(best),
            "score": json_num(c.score.statistic),
            "p_value": json_num(c.score.p_value), "p_adjusted": json_num(c.p_adjusted),
            "log10_p": json_num(c.score.log10_p),
            "estimate": {k: {"value": json_num(v["value"]), "sigma": json_num(v["sigma"])}
                         for k, v in c.estimate().items()},
            "rmse_before": json_num(rb), "rmse_after": json_num(rh.rmse) if rh is not None else None,
            "rmse_raw_before": json_num(d.base.rmse_raw),
            "rmse_raw_after": json_num(rh.rmse_raw) if rh is not None else None,
            "noise_floor": json_num(d.base.noise_floor),
            "heldout_gain": json_num(c.gain_frac),
            "implausible": list(c.implausible),
            "absorbs": c.absorbs or None,
            "score_robust": json_num(c.score.statistic_robust),
            "p_value_robust": json_num(c.score.p_value_robust),
            "lr": json_num(c.lr), "lr_p_value": json_num(c.lr_p), "delta_bic": json_num(c.dbic),
            "wald": json_num(c.wald), "wald_p_value": json_num(c.wald_p),
            "refit_start": c.refit.full.info.get("start") if c.refit else None,
            "delta_heldout_loglik": json_num(c.dll),
            "heldout_p_value": json_num(g.p) if g is not None else None,
            "consistent_after": (bool(c.refit.consistency.passed)
                                 if c.refit and c.refit.consistency else None),
            "failed": c.evidence.failed() if c.evidence is not None else None,
            "p_conditional": json_num(c.p_conditional),
            "shared_with_missing": json_num(c.shared),
            "significant": bool(c.significant), "confirmed": bool(c.confirmed),
            "bootstrap_first": json_num(c.bootstrap_first)})
    out = {"missing": bool(d.missing), "ranking": rank,
           "missing_effect": best,
           "unexplained": bool(d.unexplained), "verdict": d.verdict,
           "missions": [m.name for m in d.missions],
           "model_effects": list(d.base.effects),
           "base": d.base.to_json(),
           "consistency": d.base.consistency.to_json() if d.base.consistency else None,
           "conditions": {"text": d.conditions_text,
                          "tests": [e.to_json() for e in d.conditions]},
           "confidence": d.confidence(),
           "settings": d.settings,
           "timings": d.timings}
    if d.before is not None:
        out["before"] = d.before.to_json()
        out["added"] = list(d.added)
    return json_ready(out)


def diagnosis_summary(d: Diagnosis) -> str:
    """The ranked summary printed by ``aqfg diagnose``."""
    L = [d.verdict]
    if d.confidence_text():
        L.append(d.confidence_text())
    L.append("")
    cons = d.base.consistency
    if cons is not None:
        L.append(f"Held-out fixes vs the model ({'+'.join(d.base.effects) or 'base model'}): "
                 + cons.summary())
    L.append(f"Held-out RMS distance to the fixes: {d.base.heldout_text()}; "
             + (f"dead-reckoning error beyond the noise {d.base.rmse:.2f} m"
                if d.base.rmse > 0 else "within the noise"))
    L.append(d.conditions_text)
    if d.before is not None:
        b, a = d.before, d.base
        L.append("")
        L.append(f"Added {', '.join(d.added)}: {heldout_change(b, a)}, consistency "
                 f"{_ok(b.consistency)} -> {_ok(a.consistency)}, BIC {a.bic - b.bic:+.1f}")
        for e in a.model.effects:
            if e.name in d.added:
                for n, v in a.values(e.params).items():
                    L.append(f"    {n} = {v['value']:.4g} +- {v['sigma']:.2g}")
    L.append("")
    best = d.best.effect if d.best else None
    L.append(f"{'rank':>4}  {'effect':<18} {'score':>9} {'p (Holm)':>9} {'dBIC':>8} "
             f"{'dLL held':>9} {'held-out RMS before->after (gain)':>34}  estimate; status")
    for i, c in enumerate(d.ranking, 1):
        est = ", ".join(f"{n.split('.')[-1]}={v['value']:.3g}+-{v['sigma']:.2g}"
                        for n, v in c.estimate().items())
        rh = c.refit if _ho(c) else None
        dr = (f"{d.base.rmse_raw:.2f} -> {rh.rmse_raw:.2f} m ({gain_cell(c)})"
              if rh is not None else "")
        flag = "*" if c.status == "missing" else " "
        L.append(f"{i:>4}{flag} {c.effect:<18} {c.score.statistic:9.1f} {c.p_adjusted:9.2g} "
                 f"{c.dbic:8.1f} {c.dll:9.1f} {dr:>34}  {est}; {c.status_text(best)}")
    gs = d.settings.get("heldout_gnss_sigma")
    src = (f"GNSS fixes steadier than stated: {gs:.2f} m" if gs is not None
           else "the fixes' stated sigma")
    L.append(f"(noise floor of the held-out fixes {d.base.noise_floor:.2f} m, {src}; gain: "
             "fall of the dead-reckoning error beyond it, at least "
             f"{100 * d.settings.get('min_gain', MIN_GAIN):.0f}% for a missing effect)")
    L.append("(* the missing effect: score, refit (LR, BIC, direction) and held-out fixes "
             "agree, its estimate is plausible and its gain matters. dLL held: change of "
             "the held-out fixes' predictive log-likelihood. "
             "An echo's evidence is gone once the missing effect is in the model; "
             "independent evidence remains: add the missing effect and diagnose again, "
             "or use --auto.)")
    return "\n".join(L)


def _ho(c: Candidate) -> bool:
    return c.refit is not None and c.refit.has_heldout


def json_num(x: SupportsFloat | None) -> float | None:
    """``x`` as a JSON number: a float, or None (null) for None, NaN and infinities."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def json_ready(o: Any) -> Any:
    """``o`` with numpy scalars as Python numbers and non-finite floats as None, nested
    dicts/lists/tuples included (tuples become lists), ready for ``json.dumps``."""
    if isinstance(o, dict):
        return {k: json_ready(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [json_ready(v) for v in o]
    if isinstance(o, (np.floating, float)):
        return json_num(o)
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.bool_):
        return bool(o)
    return o


def _ok(c: ConsistencyTest | None) -> str:
    return "n/a" if c is None else ("pass" if c.passed else "FAIL")


def write_diagnosis_json(doc: dict, out, others: tuple[str, ...], overwrite: bool):
    """``out/diagnosis.json`` from ``doc``, refusing (unless ``overwrite``) where it or one of
    the ``others`` files written beside it exists; returns ``out``."""
    targets = [out / "diagnosis.json", *(out / n for n in others)]
    existing = [str(p) for p in targets if p.exists()]
    if existing and not overwrite:
        raise FileExistsError(f"refusing to overwrite {', '.join(existing)} (pass --force)")
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "diagnosis.json", "w") as f:
        json.dump(doc, f, indent=2)
    return out
