"""Diagnosis sweep: the diagnose -> add -> refit loop on simulated missions with one hidden
effect, on missions with none, and on the independent-vehicle missions of tests/data.

1. For every case of :mod:`aqfg.sim.cases` (one hidden effect, its size and mission
   documented there) and every seed, run :func:`aqfg.diagnose.sequence.diagnose_sequence`
   on the model without the effect and record: is the true effect the first one added (the
   single-step diagnosis' "missing" effect), what else the loop adds, the held-out
   dead-reckoning error of the bare model, after adding the true effect and at the end, the
   consistency of the held-out fixes, and the estimate vs the truth.
2. Missions without a hidden effect (ASV with GNSS; AUV with USBL and depth only, like a
   submerged REMUS mission): the loop must add nothing.
3. The Otter (Fossen's 6-DOF model) and REMUS missions of tests/data: the sequence, the
   estimates against the ``[truth]`` table, the final held-out error as a share of the bare
   model's, and whether ``aqfg fit --model model.json`` (batch and online: the learned
   effects, the vehicle's parameters as initial values / held online) re-traces the mission
   (the inertial track from the first fix) closer to the truth than the bare model.

Acceptance (issue "learn the vehicle in one command"): on each Otter mission the sequence
holds linear_drag and reverse_thrust, on otter-dev-yawdrift also heading_drift (rate within
3 sigma of truth), on otter-dev-current-weakprop also thrust_asymmetry with a ratio below 1;
final held-out error <= 40 % of the bare model's; nothing added without a hidden effect;
on remus-dev-a nothing that does not lower the held-out error; the learned model re-traces
closer to the truth.

Run: ``python experiments/diagnosis_sweep.py [--seeds 10] [--jobs 2] [--quick]``; prints the
tables and writes ``experiments/out/diagnosis_sweep.md`` / ``.json`` (plus the reports of the
tests/data missions), and a copy of the tables to ``experiments/results/diagnosis_sweep.md``
(``--only-independent``: ``results/diagnosis_independent.md``).
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import common as C
import numpy as np

from aqfg.diagnose.sequence import diagnose_sequence, save_sequence
from aqfg.sim.cases import CASES, simulate_case

OUT = Path(__file__).resolve().parent / "out"
DATA = Path(__file__).resolve().parents[1] / "tests" / "data"
INDEPENDENT = ("otter-example", "otter-dev-calm-a", "otter-dev-calm-b",
               "otter-dev-current-weakprop", "otter-dev-yawdrift", "remus-dev-a")
NONE_AUV = "none-auv"


def _sim(effect, seed, duration):
    if effect == NONE_AUV:
        from aqfg.sim.simulator import simulate
        return simulate("auv", seed=seed, duration=duration, gnss_period=None, usbl=True)
    return simulate_case(effect, seed, duration)


def one(task) -> dict:
    effect, seed, duration = task
    m, truth = _sim(effect, seed, duration)
    t0 = time.perf_counter()
    seq = diagnose_sequence([m], jobs=1, n_boot=100)
    dt = time.perf_counter() - t0
    d0 = seq[0]
    top = d0.ranking[0] if d0.ranking else None
    added = list(seq.added)
    rec = {"effect": effect or "none", "seed": seed, "time": dt,
           "step_times": seq.timings["steps"], "added": added,
           "first": added[0] if added else None,
           "top": top.effect if top else None, "missing": d0.missing,
           "rmse_before": seq.bare.rmse, "rmse_raw_before": seq.bare.rmse_raw,
           "consistent_before": bool(seq.bare.consistency.passed),
           "rmse_final": seq.final.rmse, "rmse_raw_final": seq.final.rmse_raw,
           "consistent_final": bool(seq.final.consistency.passed)}
    if effect is not None and effect in CASES:
        st = next((s for s in seq.steps if s.effect == effect), None)
        if st is not None:
            rec.update(rmse_after=st.rmse_after, rmse_raw_after=st.rmse_raw_after,
                       consistent_after=st.consistent_after, estimate=st.estimate,
                       truth={k: truth.params[k] for k in st.estimate})
    return rec


# ---------------------------------------------------------------- tests/data missions
def independent(name: str) -> dict:
    """The loop on one tests/data mission, its estimates against the truth table, and the
    learned model reused by a batch and an online fit."""
    from aqfg.data.io import load_mission, load_truth
    from aqfg.evaluate import rmse
    from aqfg.fg.fit import fit_fg
    m = load_mission(DATA / name)
    truth = load_truth(DATA / name)
    t0 = time.perf_counter()
    seq = diagnose_sequence([m], jobs=2)
    dt = time.perf_counter() - t0
    save_sequence(seq, OUT / f"diagnosis-{name}", overwrite=True)
    mf = seq.model_file()
    rec = {"mission": name, "time": dt, "step_times": seq.timings["steps"],
           "added": list(seq.added), "stopped": seq.stopped,
           "rmse_bare": seq.bare.rmse, "rmse_raw_bare": seq.bare.rmse_raw,
           "rmse_final": seq.final.rmse, "rmse_raw_final": seq.final.rmse_raw,
           "consistent_final": bool(seq.final.consistency.passed),
           "steps": [s.to_json() for s in seq.steps], "summary": seq.summary(),
           "truth": {k: v for k, v in truth.params.items() if isinstance(v, (int, float))},
           "model_file": mf.to_json()}
    # the learned model reused: batch (everything estimated from the model's values) and
    # online (the vehicle's parameters held at the model's values)
    for mode in ("batch", "online"):
        bare = fit_fg([m], mode=mode)
        learned = fit_fg([m], mode=mode, effects=mf.effects, init=mf.init())
        rec[f"retrace_{mode}"] = {
            "bare": rmse(bare.missions[0].inertial, truth),
            "model": rmse(learned.missions[0].inertial, truth),
            "track_bare": rmse(bare.missions[0].track, truth),
            "track_model": rmse(learned.missions[0].track, truth)}
    return rec


def _fmt_est(st: dict) -> str:
    return ", ".join(f"{n.split('.')[-1]} {v['value']:.3g}±{v['sigma']:.1g}"
                     for n, v in st["estimate"].items())


def independent_md(recs: list[dict]) -> list[str]:
    out = ["## Independent-vehicle missions (tests/data)", "",
           ("`aqfg diagnose M --auto` (`diagnose_sequence`); held-out DR error: bare -> final "
           "(fixes' noise removed; raw in brackets); re-trace: RMS distance (m) of the "
           "inertial track (model alone from the first fix) to the truth, bare model vs "
           "`aqfg fit --model model.json`, batch and online."), "",
           ("| mission | sequence (estimate ± sigma) | held-out DR error (m) | final/bare | "
           "consistent | re-trace batch bare -> model | re-trace online bare -> model | "
           "time per step (s) |"), "|---|---|---|---|---|---|---|---|"]
    for r in recs:
        seq = "; ".join(f"{s['effect']} ({_fmt_est(s)})" for s in r["steps"]) or "nothing"
        ratio = r["rmse_final"] / r["rmse_bare"] if r["rmse_bare"] > 0 else float("nan")
        rb, ro = r["retrace_batch"], r["retrace_online"]
        out.append(f"| {r['mission']} | {seq} | {r['rmse_bare']:.2f} -> {r['rmse_final']:.2f} "
                   f"({r['rmse_raw_bare']:.2f} -> {r['rmse_raw_final']:.2f}) | "
                   f"{100 * ratio:.0f} % | {'yes' if r['consistent_final'] else 'no'} | "
                   f"{rb['bare']:.1f} -> {rb['model']:.1f} | {ro['bare']:.1f} -> "
                   f"{ro['model']:.1f} | {', '.join(f'{t:.0f}' for t in r['step_times'])} |")
    out += ["", ("Truth (the `[truth]` tables; the Otter's reverse thrust is about 58 % of "
            "forward, its surge damping linear, README of tests/data):"), ""]
    for r in recs:
        tr = {k: v for k, v in r["truth"].items() if "." in k}
        if tr:
            out.append(f"- {r['mission']}: " + ", ".join(f"{k} = {v:.4g}" for k, v in tr.items()))
    for r in recs:
        out += ["", f"`{r['mission']}`:", "", "```", r["summary"], "```"]
    return out + [""]


# ---------------------------------------------------------------- simulated table
def table(recs: list[dict]) -> str:
    rows = [("| hidden effect | seeds | first added | also added (seeds) | DR error bare -> with it "
            "-> final (m, median) | reduction >= 30 % | consistent before / after it / final "
            "| estimate (median) vs truth | time per step (s, median) |"),
            "|---|---|---|---|---|---|---|---|---|"]
    names = list(CASES) + ["none", NONE_AUV]
    for eff in names:
        rs = [r for r in recs if r["effect"] == eff]
        if not rs:
            continue
        n = len(rs)
        b = np.array([r["rmse_before"] for r in rs])
        f = np.array([r["rmse_final"] for r in rs])
        steps = np.median([t for r in rs for t in r["step_times"]])
        extras: dict = {}
        for r in rs:
            for e in r["added"]:
                if e != eff:
                    extras[e] = extras.get(e, 0) + 1
        extra = ", ".join(f"{k} ({v})" for k, v in sorted(extras.items())) or "–"
        cb = sum(r["consistent_before"] for r in rs)
        cf = sum(r["consistent_final"] for r in rs)
        if eff in ("none", NONE_AUV):
            nothing = sum(not r["added"] for r in rs)
            rows.append(f"| {eff} | {n} | nothing added in {nothing}/{n} | {extra} | "
                        f"{np.median(b):.2f} | – | {cb}/{n} / – / {cf}/{n} | – | {steps:.1f} |")
            continue
        first = sum(r["first"] == eff for r in rs)
        a = np.array([r.get("rmse_after", np.nan) for r in rs])
        red = np.sum((b - a) / b >= 0.30)
        ca = sum(bool(r.get("consistent_after")) for r in rs)
        est = ""
        ests = [r for r in rs if "estimate" in r]
        if ests:
            keys = list(ests[0]["estimate"])
            est = ", ".join(f"{k.split('.')[-1]} {np.median([e['estimate'][k]['value'] for e in ests]):.3g} "
                            f"({ests[0]['truth'][k]:.3g})" for k in keys)
        rows.append(f"| {eff} | {n} | {first}/{n} | {extra} | {np.median(b):.2f} -> "
                    f"{np.nanmedian(a):.2f} -> {np.median(f):.2f} | {red}/{n} | "
                    f"{cb}/{n} / {ca}/{n} / {cf}/{n} | {est} | {steps:.1f} |")
    return "\n".join(rows)


def main(argv=None) -> int:
    ap = C.parser(__doc__, 10)
    ap.add_argument("--effects", nargs="+", default=None, help="only these cases (and none)")
    ap.add_argument("--no-independent", action="store_true",
                    help="skip the tests/data missions")
    ap.add_argument("--only-independent", action="store_true",
                    help="only the tests/data missions")
    ap.add_argument("--reuse", action="store_true",
                    help="reuse the records of the last runs (…_records.json for the simulated "
                         "missions, …_independent.json for tests/data) instead of running")
    args = ap.parse_args(argv)
    seeds = C.n_seeds(args, 10)
    duration = 300.0 if args.quick else 600.0
    effects = args.effects or list(CASES)
    tasks = [(e, s, duration) for e in effects for s in range(seeds)]
    tasks += [(None, s, duration) for s in range(seeds)]
    tasks += [(NONE_AUV, s, duration) for s in range(max(1, seeds // 2))]
    if args.reuse or args.only_independent:
        tasks = []
    t0 = time.perf_counter()
    OUT.mkdir(parents=True, exist_ok=True)
    suffix = "_quick" if args.quick else ""
    rec_file = OUT / f"diagnosis_sweep{suffix}_records.json"
    recs: list = []
    if args.only_independent:
        pass
    elif args.reuse and rec_file.exists():
        recs = json.loads(rec_file.read_text())
        seeds = len({r["seed"] for r in recs})
    else:
        recs = C.run_tasks(one, tasks, jobs=args.jobs, label="diagnosis sweep")
        with open(rec_file, "w") as f:
            json.dump(recs, f, indent=1,
                      default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))
    md = [(f"# Diagnosis sweep: the diagnose -> add -> refit loop ({seeds} seeds, "
          f"{duration:.0f}-s simulated missions; tests/data missions)"), ""]
    if recs:
        md += [("Hidden effect present in the simulated truth, absent from the model; "
               "`diagnose_sequence` adds effects until nothing more is confirmed. 'DR "
               "error': held-out dead-reckoning error (fits on GNSS every 8 s and every "
               "other USBL fix; 60-s legs; fixes' own noise removed): bare model -> after "
               "the true effect was added -> final model. 'none-auv': a submerged AUV "
               "with USBL and depth only. Sizes and missions: aqfg/sim/cases.py."), "",
               table(recs), ""]
    ind = None
    ind_file = OUT / f"diagnosis_sweep{suffix}_independent.json"
    if args.reuse and ind_file.exists():
        ind = json.loads(ind_file.read_text())
    elif not args.no_independent:
        names = INDEPENDENT[:2] if args.quick else INDEPENDENT
        ind = [independent(n) for n in names if (DATA / n / "mission.toml").exists()]
        with open(ind_file, "w") as f:
            json.dump(ind, f, indent=1,
                      default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))
    if ind:
        md += independent_md(ind)
    md.append(f"total time {time.perf_counter() - t0:.0f} s")
    text = "\n".join([C.stamp(argv), "", *md])
    (OUT / f"diagnosis_sweep{suffix}.md").write_text(text)
    # experiments/out/ is not versioned; the full run and the tests/data run are results
    result = "diagnosis_independent.md" if args.only_independent and ind else \
        "diagnosis_sweep.md" if recs and ind and not args.effects else None
    if not args.quick and result:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        (Path(args.out) / result).write_text(text)
    with open(OUT / f"diagnosis_sweep{suffix}.json", "w") as f:
        json.dump({"records": recs, "independent": ind}, f, indent=1,
                  default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
