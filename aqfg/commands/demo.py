"""``aqfg demo``: the main job, end to end, on a built-in simulated mission.

1. simulate a 10-minute ASV mission whose physics has an effect the base model lacks;
2. fit it with GNSS thinned to one fix every 8 s, by the factor graph and by the paper's
   update-error method, and compare their dead-reckoning ("inertial") error with the truth;
3. diagnose the fit: where the model fails and which catalogue effect is missing;
4. add the effect the diagnosis names, refit, and show the error fall.

Everything goes to ``--out`` (mission, fits, diagnosis report); only step 2's error table
reads the simulated truth, and says so.
"""
from __future__ import annotations

import sys
import time
from functools import partial
from pathlib import Path

import numpy as np

DEMO_SEED = 11
# propellers 40 % weaker backwards (aqfg.sim.cases)
DEMO_EFFECT: dict[str, float | dict[str, float]] = {"reverse_thrust": 0.6}
GNSS_EVERY = 8.0
DEMO_OUTPUTS = ("mission", "fit-fg", "fit-update-error", "diagnosis", "diagnosis-with-*",
                "fit-fg-with-*")


def _say(msg: str) -> None:
    print(msg, flush=True)


def run(args) -> int:
    from aqfg.commands.common import input_warnings
    from aqfg.commands.diagnose import finish_json
    from aqfg.outputs import OutputSet, provenance

    out = Path(args.out)
    outs = OutputSet(out, DEMO_OUTPUTS, force=args.force)
    outs.check()
    with outs as stage:
        _demo(out, stage)
        finish_json(stage, provenance(inputs=[], warnings=input_warnings()))
    _say(f"open {out / 'diagnosis' / 'report.html'}")
    return 0


def _demo(out: Path, stage: Path) -> None:
    """The four steps, writing into ``stage``; messages name the final place ``out``."""
    from aqfg.data.io import load_truth, save_mission
    from aqfg.data.mission import with_gnss_every
    from aqfg.ekf.estimator import fit_update_error
    from aqfg.evaluate import inertial_rmse
    from aqfg.fg.common import FGSettings
    from aqfg.fg.fit import fit_fg
    from aqfg.model.params import OLD_PARAMS
    from aqfg.model.vehicle import Model
    from aqfg.outputs import provenance
    from aqfg.plots import plot_fit
    from aqfg.result import write_result
    from aqfg.sim.simulator import simulate

    def save_fit(res, name: str, missions) -> None:
        d = stage / name
        d.mkdir()
        write_result(res, d, missions, provenance=provenance(
            method=res.method, mode=res.mode, effects=res.effects,
            settings={"gnss_every": GNSS_EVERY}, inputs=[out / "mission"]))
        plot_fit(res, missions, d)

    t_start = time.perf_counter()

    _say("1/4 simulating a 10-minute ASV mission (GNSS 1 Hz, IMU 50 Hz, motors 10 Hz) with a "
         "hidden effect the base model lacks ...")
    mission, truth = simulate("asv", seed=DEMO_SEED, duration=600.0, effects=DEMO_EFFECT)
    save_mission(mission, stage / "mission", truth=truth)
    loaded = load_truth(stage / "mission")   # evaluation only: estimators never see it
    assert loaded is not None, "the mission was saved with its truth"
    truth = loaded
    thin = with_gnss_every(mission, GNSS_EVERY)
    assert thin.gnss is not None and mission.gnss is not None      # the ASV has GNSS
    _say(f"    wrote {out / 'mission'}; the fits use one GNSS fix every {GNSS_EVERY:.0f} s "
         f"({len(thin.gnss.t)} of {len(mission.gnss.t)})")

    _say("2/4 fitting all six parameters: factor graph (batch) and update-error EKF (offline) "
         "...")
    _say("    (the paper's model as given, as `aqfg fit --no-auto-effect`; without the flag "
         "the fit adds by itself the effect its structural test finds missing)")
    fits = {}
    for label, fit in (("fg", partial(fit_fg, settings=FGSettings(auto_effect=False))),
                       ("update-error", fit_update_error)):
        t0 = time.perf_counter()
        res = fit([thin], mode="batch")
        fits[label] = (res, time.perf_counter() - t0)
        save_fit(res, f"fit-{label}", [thin])
    model = Model.for_mission(mission)
    p_old = model.nominal(OLD_PARAMS)
    p_true = model.nominal({k: v for k, v in truth.params.items() if k in model.all_names})
    # (parameters, RMSE m, their values, time taken)
    rows: list[tuple[str, float, dict[str, float] | None, str]] = [
        ("paper's old parameters", inertial_rmse(model, mission, p_old, truth), None, "")]
    for label, (res, dt) in fits.items():
        p = res.missions[0].p
        rows.append((f"{label} estimate", inertial_rmse(res.model or model, mission, p, truth),
                     res.values, f"{dt:.1f} s"))
    rows.append(("true parameters (+ hidden)", inertial_rmse(model, mission, p_true, truth),
                 None, ""))
    _say("    dead-reckoning from the first fix, RMSE vs the simulated truth:")
    _say(f"    {'parameters':<30} {'RMSE (m)':>9}  {'k':>6} {'k_x':>6} {'k_yz':>6} "
         f"{'theta_e':>8}  time")
    for name, e, vals, took in rows:
        v = vals or {}
        cols = " ".join(f"{v[n]:6.3g}" if n in v else f"{'':>6}" for n in ("k", "k_x", "k_yz"))
        th = f"{v['theta_e']:8.3f}" if "theta_e" in v else f"{'':>8}"
        _say(f"    {name:<30} {e:9.2f}  {cols} {th}  {took}")
    _say(f"    (truth: k={truth.params['k']:.3g}, k_x={truth.params['k_x']:.3g}, "
         f"k_yz={truth.params['k_yz']:.3g}, theta_e={truth.params['theta_e']:.3f})")

    _say("3/4 diagnosing: consistency of held-out fixes, conditions, score test of every "
         "catalogue effect, refit of the top candidates ...")
    from aqfg.diagnose.workflow import diagnose, save_diagnosis
    diag = diagnose([mission], gnss_every=GNSS_EVERY)
    save_diagnosis(diag, stage / "diagnosis")
    _say("\n".join("    " + line for line in diag.summary().splitlines()))

    if diag.best is not None:
        eff = diag.best.effect
        _say(f"4/4 adding '{eff}' to the model and refitting (aqfg fit --effect {eff}) ...")
        after = diagnose([mission], effects=(eff,), gnss_every=GNSS_EVERY)
        save_diagnosis(after, stage / f"diagnosis-with-{eff}")
        b, a = diag.base, after.base
        from aqfg.diagnose.wording import heldout_change
        _say(f"    {heldout_change(b, a)}; "
             f"consistency test {'passed' if b.consistency and b.consistency.passed else 'failed'}"
             f" -> {'passed' if a.consistency and a.consistency.passed else 'failed'}")
        for n, v in a.values(tuple(p for e in a.model.effects if e.name == eff
                                   for p in e.params)).items():
            true = truth.params.get(n, np.nan)
            _say(f"    {n} = {v['value']:.4g} +- {v['sigma']:.2g}   (true: {true:.4g})")
        refit = fit_fg([thin], mode="batch", effects=(eff,))
        save_fit(refit, f"fit-fg-with-{eff}", [thin])
        e_before = rows[1][1]
        e_after = inertial_rmse(refit.model or model, mission, refit.missions[0].p, truth)
        _say(f"    factor graph with {eff}: dead-reckoning RMSE vs the truth {e_before:.2f} m -> "
             f"{e_after:.2f} m (k={refit.values['k']:.3g}, k_x={refit.values['k_x']:.3g}, "
             f"k_yz={refit.values['k_yz']:.3g})")
    else:
        _say("4/4 the diagnosis found nothing missing: no effect to add.")
    _say(f"done in {time.perf_counter() - t_start:.0f} s")


if __name__ == "__main__":  # pragma: no cover
    from aqfg.cli import main
    sys.exit(main(["demo", *sys.argv[1:]]))
