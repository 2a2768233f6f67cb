"""``aqfg demo``: the main job, end to end, on a built-in simulated mission.

One story, in order:

1. simulate a 10-minute ASV mission whose physics has an effect the paper's model lacks;
2. the model as given: fit it by the factor graph, GNSS thinned to one fix every 8 s; the
   fit says it does not explain the fixes;
3. what is missing: the diagnosis names the effect;
4. the model with it: both methods, factor graph and the paper's update-error EKF, fitted
   side by side on the same footing (same fixes, same model, same parameters, same start),
   with and without the effect, and their model-only tracks compared with the truth.

Everything goes to ``--out``: the mission, each fit, the diagnoses (``report.html``) and
``demo.json``, the table the console prints (only that table reads the simulated truth).
"""
from __future__ import annotations

import contextlib
import logging
import sys
import time
from pathlib import Path

DEMO_SEED = 11
# propellers 40 % weaker backwards (aqfg.sim.cases)
DEMO_EFFECT: dict[str, float | dict[str, float]] = {"reverse_thrust": 0.6}
GNSS_EVERY = 8.0
DEMO_OUTPUTS = ("mission", "fit-fg", "fit-update-error", "diagnosis", "diagnosis-with-*",
                "fit-fg-with-*", "fit-update-error-with-*", "demo.json")
SIX = ("theta_e", "s_x", "s_y", "k", "k_x", "k_yz")
# the library's own warnings of the fits: the demo tells them in the story, once
QUIET = ("aqfg.fg", "aqfg.ekf", "aqfg.diagnose")


def _say(msg: str) -> None:
    print(msg, flush=True)


def run(args) -> int:
    from aqfg.commands.common import input_warnings
    from aqfg.commands.diagnose import finish_json
    from aqfg.outputs import OutputSet, provenance

    out = Path(args.out)
    outs = OutputSet(out, DEMO_OUTPUTS, force=args.force)
    outs.check()
    with outs as stage, _quiet(QUIET):
        _demo(out, stage)
        finish_json(stage, provenance(inputs=[], warnings=input_warnings()))
    _say(f"open {out / 'diagnosis' / 'report.html'}")
    return 0


@contextlib.contextmanager
def _quiet(names):
    loggers = [logging.getLogger(n) for n in names]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.ERROR)
    try:
        yield
    finally:
        for lg, lv in zip(loggers, levels):
            lg.setLevel(lv)


def table_lines(rows: list[dict]) -> list[str]:
    """The side-by-side table of ``demo.json``'s rows, as printed."""
    names = ("k", "k_x", "k_yz", "theta_e")
    lines = [f"{'model':<22} {'method':<13} {'RMSE (m)':>8}  "
             + " ".join(f"{n:>7}" for n in names) + f"  {'time':>6}"]
    for r in rows:
        v = r.get("values") or {}
        cols = " ".join(f"{v[n]:7.3g}" if n in v else f"{'':>7}" for n in names)
        took = f"{r['seconds']:5.1f}s" if r.get("seconds") is not None else ""
        lines.append(f"{r['model']:<22} {r['method']:<13} {r['track_rmse_m']:8.2f}  {cols}  "
                     f"{took:>6}")
    return lines


def _demo(out: Path, stage: Path) -> None:
    """The four steps, writing into ``stage``; messages name the final place ``out``."""
    from aqfg.data.io import load_truth, save_mission
    from aqfg.data.mission import with_gnss_every
    from aqfg.model.vehicle import Model
    from aqfg.outputs import write_json
    from aqfg.sim.simulator import simulate

    t_start = time.perf_counter()
    _say("1/4 simulating a 10-minute ASV mission (GNSS 1 Hz, IMU 50 Hz, motors 10 Hz) whose "
         "propellers push less backwards than forwards: physics the paper's model lacks ...")
    mission, truth = simulate("asv", seed=DEMO_SEED, duration=600.0, effects=DEMO_EFFECT)
    save_mission(mission, stage / "mission", truth=truth)
    loaded = load_truth(stage / "mission")   # evaluation only: estimators never see it
    assert loaded is not None, "the mission was saved with its truth"
    truth = loaded
    thin = with_gnss_every(mission, GNSS_EVERY)
    assert thin.gnss is not None and mission.gnss is not None      # the ASV has GNSS
    _say(f"    wrote {out / 'mission'}; every fit uses one GNSS fix every {GNSS_EVERY:.0f} s "
         f"({len(thin.gnss.t)} of {len(mission.gnss.t)})")
    model = Model.for_mission(mission)
    rows: list[dict] = []

    def fit(method: str, effects: tuple[str, ...]) -> dict:
        return _fit(method, effects, thin, mission, truth, model, stage, out, rows)

    _say("2/4 the model as given: the factor graph fits the paper's six parameters "
         "(aqfg fit --no-auto-effect) ...")
    fg0 = fit("fg", ())
    _say(f"    its model-only track from the first fix is {fg0['track_rmse_m']:.2f} m RMS off "
         "the truth, and the fit says why:")
    for w in fg0["warnings"]:
        _say(f"    - {w}")

    diag, eff, after = _diagnose_missing(mission, stage)

    with_eff = (eff,) if eff is not None else ()
    _say("4/4 both methods side by side, on the same fixes, model and start"
         + (f", as given and with {eff} (aqfg fit --effect {eff})" if eff else "") + " ...")
    fit("update-error", ())
    if eff is not None:
        fit("fg", with_eff)
        fit("update-error", with_eff)
    shown = _compare(model, mission, truth, rows, eff)
    write_json(stage / "demo.json", {
        "gnss_every": GNSS_EVERY, "hidden": list(DEMO_EFFECT), "missing": eff,
        "heldout_rmse_m": [diag.base.rmse, after.base.rmse] if after is not None else None,
        "rows": [{k: v for k, v in r.items() if k != "warnings"} for r in shown],
        "fit_warnings": fg0["warnings"]})
    _say(f"done in {time.perf_counter() - t_start:.0f} s; the table is {out / 'demo.json'}")


def _fit(method: str, effects: tuple[str, ...], thin, mission, truth, model, stage: Path,
         out: Path, rows: list[dict]) -> dict:
    """One fit of the side-by-side: every parameter of the model estimated, nothing
    added by the fit itself (``--no-auto-effect``), written to fit-METHOD[-with-E]; its row
    of the table is added to ``rows``."""
    from aqfg.commands.common import strip_advice
    from aqfg.ekf.estimator import fit_update_error
    from aqfg.evaluate import inertial_rmse
    from aqfg.export import write_result
    from aqfg.fg.fit import fit_fg
    from aqfg.fg.settings import FGSettings
    from aqfg.outputs import provenance
    from aqfg.plots import plot_fit
    est = SIX + tuple(f"{e}.ratio" for e in effects)
    t0 = time.perf_counter()
    if method == "fg":
        res = fit_fg([thin], mode="batch", effects=effects, estimate=est,
                     settings=FGSettings().with_(batch={"auto_effect": False}))
    else:
        res = fit_update_error([thin], mode="batch", effects=effects, estimate=est)
    dt = time.perf_counter() - t0
    name = f"fit-{method}" + "".join(f"-with-{e}" for e in effects)
    (stage / name).mkdir()
    write_result(res, stage / name, [thin], provenance=provenance(
        method=res.method, mode=res.mode, effects=res.effects,
        settings={"gnss_every": GNSS_EVERY, "estimate": list(est)},
        inputs=[out / "mission"]))
    plot_fit(res, [thin], stage / name)
    row = {"model": f"with {' + '.join(effects)}" if effects else "as given",
           "method": method, "dir": name,
           "track_rmse_m": inertial_rmse(res.model or model, mission, res.missions[0].p,
                                         truth),
           "values": {n: float(res.values[n]) for n in est}, "seconds": dt,
           "warnings": [strip_advice(w) for w in res.warnings]}
    rows.append(row)
    return row


def _diagnose_missing(mission, stage: Path):
    """Step 3: the diagnosis of the model as given, and again with the effect it finds
    missing; ``(diagnosis, effect or None, diagnosis with it or None)``."""
    from aqfg.diagnose.wording import heldout_change
    from aqfg.diagnose.workflow import diagnose, save_diagnosis
    _say("3/4 what is missing: diagnosing (held-out fixes, conditions, a score test of every "
         "catalogue effect, refits of the top ones) ...")
    diag = diagnose([mission], gnss_every=GNSS_EVERY)
    save_diagnosis(diag, stage / "diagnosis")
    _say(f"    {diag.verdict}")
    if diag.conditions_text:
        _say(f"    {diag.conditions_text}")
    eff = diag.best.effect if diag.best is not None else None
    after = None
    if eff is not None:
        after = diagnose([mission], effects=(eff,), gnss_every=GNSS_EVERY)
        save_diagnosis(after, stage / f"diagnosis-with-{eff}")
        ok = {True: "passes", False: "fails"}
        b, a = diag.base, after.base
        _say(f"    with {eff} in the model: {heldout_change(b, a)}; the consistency test "
             f"{ok[bool(b.consistency and b.consistency.passed)]} -> "
             f"{ok[bool(a.consistency and a.consistency.passed)]}")
    return diag, eff, after


def _compare(model, mission, truth, rows: list[dict], eff) -> list[dict]:
    """Step 4's table: the model-only tracks of the paper's old values, the fits and the
    true values against the truth (printed; returned as rows)."""
    from aqfg.evaluate import inertial_rmse
    from aqfg.model.params import OLD_PARAMS
    p_old = model.nominal(OLD_PARAMS)
    p_true = model.nominal({k: v for k, v in truth.params.items() if k in model.all_names})
    shown = [{"model": "paper's old values", "method": "", "track_rmse_m":
              inertial_rmse(model, mission, p_old, truth)},
             *sorted(rows, key=lambda r: (r["model"] != "as given", r["method"] != "fg")),
             {"model": "true values (+ hidden)", "method": "", "values": {
                 n: float(truth.params[n]) for n in ("k", "k_x", "k_yz", "theta_e")},
              "track_rmse_m": inertial_rmse(model, mission, p_true, truth)}]
    _say("    model-only track from the first fix (the paper's inertial trajectory), RMSE vs "
         "the simulated truth:")
    for line in table_lines(shown):
        _say("    " + line)
    if eff is not None:
        truth_ratio = truth.params.get(f"{eff}.ratio")
        for r in (r for r in rows if r["model"] != "as given"):
            _say(f"    {r['method']}: {eff}.ratio = {r['values'][f'{eff}.ratio']:.3f}"
                 + (f" (true {truth_ratio:.3f})" if truth_ratio is not None else ""))
    return shown


if __name__ == "__main__":  # pragma: no cover
    from aqfg.cli import main
    sys.exit(main(["demo", *sys.argv[1:]]))
