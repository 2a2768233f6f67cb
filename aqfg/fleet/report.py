"""A fleet run's outputs (format doc, "Outputs"): per vehicle and mission parameters and
tracks, ``fleet.json`` (vehicles x parameters, and which vehicles differ from the rest),
and a self-contained ``fleet.html``."""
from __future__ import annotations

import base64
import html
import io
import math
import os
from pathlib import Path

import numpy as np

from aqfg.distributions import chi2_sf, holm
from aqfg.export import write_result
from aqfg.fleet.solve import FleetResult, fixed_covariance
from aqfg.parameters_doc import (
    PARAMETERS_FORMAT,
    dead_reckoning_document,
    effect_step_document,
    per_mission_document,
    without_effect_document,
)
from aqfg.result import EffectStep, Result


def fixed_names(res: Result) -> tuple[str, ...]:
    local = {n for v in res.per_mission.values() for n in v}
    return tuple(n for n in res.estimated if n not in local)


def differs_from_fleet(values: np.ndarray, covs: np.ndarray, alpha: float = 0.05) -> list[dict]:
    """For each vehicle, a chi-square test of its fixed parameters against the
    inverse-covariance-weighted mean of the OTHER vehicles (leave-one-out, so the two are
    independent): ``d = x_v - m_-v``, ``chi2 = d^T (C_v + C_m)^-1 d`` with ``dim`` degrees
    of freedom; p-values Holm-adjusted over the vehicles. ``values`` (V, d), ``covs``
    (V, d, d). The sigmas are those of the fits: with a model that does not describe the
    vehicle exactly they are optimistic, and small real differences test as significant.
    """
    V, d = values.shape
    out = []
    if V < 2 or d == 0:
        return [{"chi2": None, "dof": d, "p_value": None, "p_holm": None, "differs": None,
                 "z": {}} for _ in range(V)]
    infos = np.array([np.linalg.inv(C) for C in covs])
    for v in range(V):
        others = [j for j in range(V) if j != v]
        Im = infos[others].sum(axis=0)
        Cm = np.linalg.inv(Im)
        m = Cm @ np.einsum("vij,vj->i", infos[others], values[others])
        diff = values[v] - m
        S = covs[v] + Cm
        chi2 = float(diff @ np.linalg.solve(S, diff))
        z = diff / np.sqrt(np.diag(S))
        out.append({"chi2": chi2, "dof": d, "p_value": float(chi2_sf(chi2, d)),
                    "mean_of_others": m.tolist(), "z": z.tolist()})
    for o, ph in zip(out, holm(np.array([o["p_value"] for o in out]))):
        o["p_holm"] = float(ph)
        o["differs"] = bool(ph < alpha)
    return out


def fleet_table(fr: FleetResult) -> dict:
    """``fleet.json``: the vehicles x fixed parameters table (value, sigma), the fleet
    mean and spread, each vehicle's test against the others, per-mission values and, with
    the diagnosis, each mission's verdict."""
    vs = list(fr.results)
    names = fixed_names(fr.results[vs[0]])
    X = np.array([[fr.results[v].values[n] for n in names] for v in vs]).reshape(len(vs), -1)
    C = np.array([fixed_covariance(fr.results[v])
                  for v in vs]).reshape(len(vs), len(names), len(names))
    tests = differs_from_fleet(X, C)
    dirs = {v.name: [m.name for m in v.missions] for v in fr.manifest.vehicles}
    table = {}
    for i, v in enumerate(vs):
        r = fr.results[v]
        t = tests[i]
        table[v] = {
            "parameters": {n: {"value": float(X[i, j]), "sigma": float(np.sqrt(C[i, j, j])),
                               **({"z_vs_others": t["z"][j]} if t["z"] else {})}
                           for j, n in enumerate(names)},
            "test": {k: t[k] for k in ("chi2", "dof", "p_value", "p_holm", "differs")},
            "missions": dict(zip(dirs[v], per_mission_document(r.per_mission).values())),
            "iterations": r.iterations, "converged": r.converged,
            "plausible": r.plausible,
            "cost": r.solve.cost if r.solve is not None else None}
        if fr.diagnosis.get(v):
            table[v]["diagnosis"] = fr.diagnosis[v]
    out = {"format": "aqfg-fleet/1", "manifest": str(fr.manifest.path), "parameters": list(names),
           "vehicles": table,
           "fleet": {"mean": X.mean(axis=0).tolist() if len(vs) else [],
                     "std_between_vehicles": (X.std(axis=0, ddof=1).tolist() if len(vs) > 1
                                              else [None] * len(names))},
           "test": "chi-square of each vehicle's fixed parameters against the "
                   "inverse-covariance-weighted mean of the other vehicles, Holm-adjusted, "
                   "alpha 0.05",
           "run": {k: fr.stats[k] for k in ("rounds", "tasks", "rebuilt", "workers", "seconds")
                   if k in fr.stats}}
    return out


def save_fleet(fr: FleetResult, out_dir: str | os.PathLike, overwrite: bool = False) -> list[Path]:
    """Write the fleet outputs into ``out_dir`` as one set (staged beside it and moved in
    whole, :class:`aqfg.outputs.OutputSet`): ``fleet.json``, ``fleet.html`` and per vehicle
    ``<vehicle>/parameters.json`` (its fixed parameters, ``aqfg-parameters/1``) and
    ``<vehicle>/<mission>/`` (the files of :func:`aqfg.export.write_result`). Refuses to
    replace existing outputs unless ``overwrite``. Returns the files written."""
    from aqfg.outputs import OutputSet, inside, provenance, write_json
    out = Path(out_dir)
    names = ["fleet.json", "fleet.html", *(v.name for v in fr.manifest.vehicles)]
    table = fleet_table(fr)
    written: list[Path] = []
    with OutputSet(out, names, force=overwrite) as stage:
        for v in fr.manifest.vehicles:
            res = fr.results[v.name]
            vdir = inside(stage, stage / v.name)
            vdir.mkdir(parents=True, exist_ok=True)
            entry = table["vehicles"][v.name]
            prov = provenance(method="fg", mode="fleet", effects=res.effects,
                              inputs=[m.path for m in v.missions])
            doc = {
                "format": PARAMETERS_FORMAT, "method": "fg", "mode": "fleet",
                "parameters": {n: {"value": e["value"], "sigma": e["sigma"],
                                   "unit": _unit(res, n)}
                               for n, e in entry["parameters"].items()},
                "provenance": prov}
            dr = res.dead_reckoning
            if dr is not None and dr.segments:
                doc["dead_reckoning"] = dead_reckoning_document(dr)
            if res.effect_step is not None:
                doc["auto_effect"] = effect_document(res.effect_step)
            write_json(vdir / "parameters.json", doc)
            written.append(out / v.name / "parameters.json")
            names_f = fixed_names(res)
            for m, mres in zip(v.missions, res.missions):
                local = res.per_mission.get(mres.name, {})
                est = tuple(names_f) + tuple(local)
                vals = dict(res.values)
                vals.update({n: e.value for n, e in local.items()})
                sig = {n: res.sigma[n] for n in names_f}
                sig.update({n: e.sigma for n, e in local.items()})
                mdir = inside(vdir, vdir / m.name)
                mdir.mkdir(parents=True, exist_ok=True)
                notes = {n: e.note.sigma_note for n, e in local.items()
                         if e.note is not None and e.note.sigma_note}
                write_result(Result("fg", "batch", est, vals, sig, [mres],
                                    sigma_notes=notes or None), mdir,
                             provenance=provenance(method="fg", mode="fleet",
                                                   effects=res.effects, inputs=[m.path]))
                written += [out / v.name / m.name / f for f in sorted(os.listdir(mdir))]
        write_json(stage / "fleet.json", table)
        (stage / "fleet.html").write_text(fleet_html(fr, table), encoding="utf-8")
        written += [out / "fleet.json", out / "fleet.html"]
    return written


def effect_document(step: EffectStep) -> dict:
    """A vehicle's ``parameters.json`` ``auto_effect``: the effect the fleet's step tried,
    whether it was added (and why not), the vehicles whose tests called for it, the costs,
    and each mission's heading offset and current without it."""
    fl = step.fleet
    return {**effect_step_document(step),
            # NaN, like the shared fields: the JSON writer makes it null with a null_reason
            "vehicles_calling": list(fl.vehicles_calling) if fl is not None else [],
            "fleet_cost_before": float(fl.cost_before) if fl is not None else math.nan,
            "fleet_cost_after": float(fl.cost_after) if fl is not None else math.nan,
            "without_effect": without_effect_document(step.base)}


def _unit(res: Result, name: str) -> str | None:
    try:
        return res.model.spec(name).unit if res.model is not None else None
    except (KeyError, AttributeError):
        return None


def pyplot():
    """matplotlib's pyplot on the Agg backend (files only), as the report draws with it."""
    import matplotlib
    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    return plt


def _png(fig) -> str:
    plt = pyplot()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def fleet_html(fr: FleetResult, table: dict) -> str:
    """The report: the spread of each fixed parameter across vehicles (value +- 2 sigma,
    the fleet mean), the table, each vehicle's test, and the missions' verdicts."""
    plt = pyplot()
    names = table["parameters"]
    vs = list(table["vehicles"])
    esc = html.escape
    parts = ["<!doctype html><meta charset='utf-8'><title>aqfg fleet</title>",
             ("<style>body{font-family:sans-serif;max-width:1100px;margin:auto}"
             "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:3px 8px;"
             "text-align:right}td:first-child{text-align:left}.bad{color:#b00}</style>"),
             f"<h1>Fleet: {len(vs)} vehicles, {fr.manifest.n_missions} missions</h1>",
             (f"<p>Manifest {esc(str(fr.manifest.path))}. Each vehicle's fixed parameters "
             "are fitted jointly over all its missions (the missions' own heading offset, "
             "current and sensor parameters apart).</p>")]
    if names:
        fig, axes = plt.subplots(1, len(names), figsize=(3.2 * len(names), 3.0), squeeze=False)
        for j, n in enumerate(names):
            ax = axes[0, j]
            x = [table["vehicles"][v]["parameters"][n]["value"] for v in vs]
            s = [table["vehicles"][v]["parameters"][n]["sigma"] for v in vs]
            ax.errorbar(range(len(vs)), x, yerr=2 * np.asarray(s), fmt="o", capsize=3)
            ax.axhline(table["fleet"]["mean"][j], color="0.5", ls="--", lw=1)
            ax.set_xticks(range(len(vs)), vs, rotation=45, ha="right")
            ax.set_title(n)
        fig.suptitle("fixed parameters by vehicle (+-2 sigma; dashed: fleet mean)")
        parts.append(f"<img alt='parameter spread' src='data:image/png;base64,{_png(fig)}'>")
    head = "".join(f"<th>{esc(n)}</th>" for n in names)
    parts.append(f"<h2>Vehicles</h2><table><tr><th>vehicle</th>{head}<th>chi2 (dof)</th>"
                 "<th>p (Holm)</th><th>differs from the others</th><th>iterations</th></tr>")
    for v in vs:
        e = table["vehicles"][v]
        cells = "".join(f"<td>{p['value']:.5g} &plusmn; {p['sigma']:.2g}</td>"
                        for p in e["parameters"].values())
        t = e["test"]
        chi = "-" if t["chi2"] is None else f"{t['chi2']:.1f} ({t['dof']})"
        ph = "-" if t["p_holm"] is None else f"{t['p_holm']:.3g}"
        dif = "-" if t["differs"] is None else ("<b class='bad'>yes</b>" if t["differs"] else "no")
        parts.append(f"<tr><td>{esc(v)}</td>{cells}<td>{chi}</td><td>{ph}</td><td>{dif}</td>"
                     f"<td>{e['iterations']}"
                     f"{'' if e.get('plausible', True) else ' <b class=bad>implausible</b>'}"
                     "</td></tr>")
    parts.append("</table><p>Test: " + esc(table["test"]) + ". The sigmas are the fits' "
                 "model sigmas; where the model does not describe a vehicle exactly they are "
                 "optimistic. 'implausible': a mission's solution failed the batch's "
                 "plausibility checks; the fleet solves from the closed-form start only, "
                 "where <code>aqfg fit</code> would also try other heading starts.</p>")
    parts.append("<h2>Missions</h2><table><tr><th>vehicle</th><th>mission</th>"
                 "<th>own parameters</th><th>diagnosis</th></tr>")
    dirs = {v.name: [m.name for m in v.missions] for v in fr.manifest.vehicles}
    for v in vs:
        e = table["vehicles"][v]
        for mname, pm in zip(dirs[v], e["missions"].values()):
            own = ", ".join(f"{esc(n)} {x['value']:.4g} &plusmn; {x['sigma']:.2g}"
                            for n, x in pm.items())
            verdict = e.get("diagnosis", {}).get(mname, {}).get("verdict", "(not run: --diagnose)")
            parts.append(f"<tr><td>{esc(v)}</td><td>{esc(mname)}</td><td>{own}</td>"
                         f"<td style='text-align:left'>{esc(verdict)}</td></tr>")
    parts.append("</table>")
    return "\n".join(parts)
