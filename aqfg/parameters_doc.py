"""``parameters.json`` of a :class:`aqfg.result.Result` (format doc, "Outputs"): the
document, its parts that the fleet's per-vehicle file shares, and reading its values back."""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from aqfg.fg.dr_records import DeadReckoning
    from aqfg.result import BaseFit, EffectStep, Estimate, Result, SigmaStructure

PARAMETERS_FORMAT = "aqfg-parameters/1"
NO_SIGMA = ("no finite 1-sigma: the data do not determine this parameter, or the estimator "
            "computed none")


def effect_step_document(step: EffectStep) -> dict:
    """The fields of ``parameters.json``'s ``auto_effect`` that ``aqfg fit``'s and the
    fleet's share, from a result's ``effect_step``: the effect, whether it was added (and
    why not), its robust p, the costs without and with it, and how far its refit moved the
    heading offset and the current beside the move the test predicted."""
    return {"effect": step.effect, "adopted": bool(step.adopted),
            "p_value_robust": float(step.p_value_robust),
            "cost_before": float(step.cost_before),
            "cost_after": float(step.cost_after),
            **({"moved": {n: float(v) for n, v in step.moved.items()}}
               if step.moved is not None else {}),
            **({"predicted_move": {n: float(v) for n, v in step.predicted_move.items()}}
               if step.predicted_move is not None else {}),
            **({"reason": step.reason} if step.reason else {}),
            **({"untested": True} if step.untested else {})}


def without_effect_document(base: BaseFit) -> dict:
    """``auto_effect.without_effect`` of ``parameters.json`` (``aqfg fit``'s and the
    fleet's): the heading offset and current of the model as given (``base``, the effect
    step's), and each mission's under ``per_mission`` for a joint fit."""
    out: dict = {n: {"value": float(base.values[n]),
                     "sigma": float(base.sigma.get(n, float("nan")))}
                 for n in ("theta_e", "s_x", "s_y") if n in base.values}
    if base.per_mission:
        out["per_mission"] = {
            m: {n: {"value": float(e.value), "sigma": float(e.sigma)}
                for n, e in d.items() if n in ("theta_e", "s_x", "s_y")}
            for m, d in base.per_mission.items()}
    return out


def per_mission_document(per: dict[str, dict[str, Estimate]]) -> dict:
    """Each mission's estimates as ``parameters.json`` writes them (``per_mission``:
    :meth:`aqfg.result.Estimate.document`)."""
    return {m: {n: e.document() for n, e in d.items()} for m, d in per.items()}


def parameters_document(result: Result, provenance: dict | None = None) -> dict:
    """The content of ``parameters.json`` (format doc, "Outputs"): the estimated parameters
    (value, 1-sigma, unit), the fixed parameters the model used (value, unit), per-mission
    values when several missions were fitted, and the provenance. A missing 1-sigma is
    ``null`` with a ``sigma_note``."""
    model = result.model

    def unit(n: str) -> str | None:
        try:
            return model.spec(n).unit if model is not None else None
        except (KeyError, AttributeError):
            return None

    est: dict = {}
    for n in result.estimated:
        s = float(result.sigma.get(n, np.nan))
        e = {"value": float(result.values[n]), "sigma": s if np.isfinite(s) else None,
             "unit": unit(n)}
        if not np.isfinite(s):
            e["sigma_note"] = (result.sigma_notes or {}).get(n) or NO_SIGMA
        est[n] = e
    names = (model.active_names if model is not None and hasattr(model, "active_names")
             else tuple(result.values))
    fixed = {n: {"value": float(result.values[n]), "unit": unit(n)}
             for n in names if n not in result.estimated and n in result.values}
    doc: dict = {"format": PARAMETERS_FORMAT, "method": result.method, "mode": result.mode,
                 "parameters": est, "fixed": fixed}
    if result.per_mission and len(result.missions) > 1:
        doc["per_mission"] = per_mission_document(result.per_mission)
    dr = result.dead_reckoning
    if dr is not None and (dr.segments or dr.current):
        doc["dead_reckoning"] = dead_reckoning_document(dr)
    if result.gnss_noise is not None:
        # the GNSS error's AR(1) sigma and correlation time the fixes were weighted by
        # (aqfg.fg.gnss_noise)
        doc["gnss_noise"] = result.gnss_noise.document()
    tq = result.track_noise_scale
    if result.mode == "batch" and tq:
        # the process-noise factor each mission's trajectory was smoothed with
        # (FGSettings.batch.adapt_track; 1: the model explains the motion between fixes)
        doc["track"] = {"process_noise_scale": {n: float(q) for n, q in tq.items()}}
    jk = result.block_jackknife.document() if result.block_jackknife is not None else None
    if result.mode == "batch" and jk:
        # the spread of the fit without each time block's fixes, which the sigma includes
        # where larger (data too short for the sandwich; aqfg.fg.jackknife)
        doc["block_jackknife"] = jk
    st = result.sigma_structure
    if result.mode == "batch" and st is not None:
        doc["sigma_structure"] = sigma_structure_document(st)
    ae = result.effect_step
    if result.mode == "batch" and ae is not None:
        # the effect the structural test named, whether the fit added it (FGSettings.
        # auto_effect), and the heading offset and current of the model as given
        doc["auto_effect"] = {**effect_step_document(ae),
                              "without_effect": without_effect_document(ae.base)}
    if result.mode == "online" and (result.events is not None
                                    or result.reinit_batches is not None):
        # what the online run did besides its updates: re-initialisations, re-seeds,
        # recoveries, fixes left out (docs/independent-vehicle.md; format doc, "Outputs"),
        # and last the process-noise factor in use
        doc["online"] = online_document(result)
    if result.heading_check:
        # the fitted heading against the accelerometer's (aqfg.identifiability)
        doc["heading_check"] = {m: {"offset_deg": c.offset_deg, "agreement": c.agreement,
                                    "windows": c.windows}
                                for m, c in result.heading_check.items()}
    if provenance is not None:
        doc["provenance"] = provenance
    return doc


def online_document(result: Result) -> dict:
    """``parameters.json``'s ``online``: the online run's events, its batch
    re-initialisations and the USBL fixes it left out (those it keeps), then the
    process-noise factor in use (:attr:`Result.process_noise_scale`)."""
    out: dict = {}
    if result.events is not None:
        out["events"] = [e.document() for e in result.events]
    if result.reinit_batches is not None:
        out["reinit_batches"] = [b.document() for b in result.reinit_batches]
    if result.rejected_usbl is not None:
        out["rejected_usbl"] = list(result.rejected_usbl)
    if result.process_noise_scale is not None:
        out["process_noise_scale"] = result.process_noise_scale
    return out


def sigma_structure_document(st: SigmaStructure) -> dict:
    """``parameters.json``'s ``sigma_structure``: the structural part of the batch's sigma."""
    # the shift of the variable parameters the missing effect the data call for most
    # would cause, included in their sigma (FGSettings.batch.structural_sigma)
    out = {"effect": st.effect, "p_value_robust": float(st.p_value_robust),
           "shift": {n: float(v) for n, v in st.shift.items()},
           "proven": bool(st.proven),
           "sigma_before": {n: float(v) for n, v in st.sigma_before.items()}}
    if st.refit is not None:
        # the fit again with the effect (aqfg.fg.fit.refit_structure)
        out["refit"] = st.refit.document()
    return out


def dead_reckoning_document(dr: DeadReckoning) -> dict:
    """The ``dead_reckoning`` entry of ``parameters.json``: whether the thrust/drag
    constants were refined by prediction error (:mod:`aqfg.fg.dead_reckoning`), the
    smoother's own values, and the prediction errors before and after (or why they were
    not tried); each mission's current for dead reckoning (:mod:`aqfg.fg.dr_current`)."""
    out: dict = {"horizon_s": dr.horizon_s, "applied": bool(dr.applied)}
    if dr.segments:                   # the constants' refinement ran
        out.update({
            "smoother": {n: {"value": v, "sigma": _finite_or_none(dr.sigma_before.get(n))}
                         for n, v in dr.before.items()},
            "prediction_error_m": {"median_before": dr.median_abs_before_m,
                                   "median_after": dr.median_abs_after_m},
            "wald": _finite_or_none(dr.wald), "wald_threshold": dr.wald_threshold})
    if not dr.applied:
        if dr.segments:
            out["refined"] = {n: {"value": v, "sigma": _finite_or_none(dr.sigma_after.get(n))}
                              for n, v in dr.after.items()}
        out["reason"] = dr.reason
    if dr.current:
        # each mission's current by prediction error (aqfg.fg.dr_current)
        out["current"] = {c.mission: c.document() for c in dr.current}
    return out


def _finite_or_none(x) -> float | None:
    return float(x) if x is not None and np.isfinite(x) else None


def read_parameter_values(doc: dict) -> dict[str, float]:
    """``{name: value}`` from a parameters.json document (estimated and fixed), in the
    current layout or the earlier flat one ``{name: {"value": v, "sigma": s}}``."""
    if "parameters" in doc and isinstance(doc["parameters"], dict):
        entries = {**doc.get("fixed", {}), **doc["parameters"]}
    else:
        entries = {k: v for k, v in doc.items() if k not in ("provenance", "null_reasons")}
    out = {}
    for name, e in entries.items():
        v = e.get("value") if isinstance(e, dict) else e
        if v is None:
            raise ValueError(f"entry {name!r} has no \"value\"")
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ValueError(f"value of {name!r} must be a number, got {v!r}")  # noqa: TRY004
        out[name] = float(v)
    return out
