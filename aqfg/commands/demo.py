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
from pathlib import Path

import numpy as np

DEMO_SEED = 11
DEMO_EFFECT = {"reverse_thrust": 0.6}   # propellers 40 % weaker backwards (aqfg.diagnose_cases)
GNSS_EVERY = 8.0


def _say(msg: str) -> None:
    print(msg, flush=True)


def run(args) -> int:
    from ..evaluate import inertial_rmse
    from ..io import load_truth, save_mission
    from ..mission import with_gnss_every
    from ..model import Model
    from ..params import OLD_PARAMS
    from ..result import save_result
    from ..sim import simulate

    out = Path(args.out)
    if out.exists() and any(out.iterdir()) and not args.force:
        raise FileExistsError(f"refusing to write into non-empty {out} (pass --force)")
    t_start = time.perf_counter()

    _say("1/4 simulating a 10-minute ASV mission (GNSS 1 Hz, IMU 50 Hz, motors 10 Hz) with a "
         "hidden effect the base model lacks ...")
    mission, truth = simulate("asv", seed=DEMO_SEED, duration=600.0, effects=DEMO_EFFECT)
    save_mission(mission, out / "mission", truth=truth, overwrite=args.force)
    truth = load_truth(out / "mission")     # evaluation only: estimators never see it
    thin = with_gnss_every(mission, GNSS_EVERY)
    _say(f"    wrote {out / 'mission'}; the fits use one GNSS fix every {GNSS_EVERY:.0f} s "
         f"({len(thin.gnss.t)} of {len(mission.gnss.t)})")

    _say("2/4 fitting all six parameters: factor graph (batch) and update-error EKF (offline) ...")
    from ..ekf import fit_update_error
    from ..plots import plot_fit
    from ..smoother import fit_fg
    fits = {}
    for label, fit in (("fg", fit_fg), ("update-error", fit_update_error)):
        t0 = time.perf_counter()
        res = fit([thin], mode="batch")
        fits[label] = (res, time.perf_counter() - t0)
        d = out / f"fit-{label}"
        save_result(res, d, overwrite=args.force)
        plot_fit(res, [thin], d)
    model = Model.for_mission(mission)
    p_old = model.nominal(OLD_PARAMS)
    p_true = model.nominal({k: v for k, v in truth.params.items() if k in model.all_names})
    rows = [("paper's old parameters", inertial_rmse(model, mission, p_old, truth), None, "")]
    for label, (res, dt) in fits.items():
        p = res.missions[0].p
        rows.append((f"{label} estimate", inertial_rmse(res.model or model, mission, p, truth),
                     res.values, f"{dt:.1f} s"))
    rows.append(("true parameters (+ hidden)", inertial_rmse(model, mission, p_true, truth),
                 None, ""))
    _say("    dead-reckoning from the first fix, RMSE vs the simulated truth:")
    _say(f"    {'parameters':<30} {'RMSE (m)':>9}  {'k':>6} {'k_x':>6} {'k_yz':>6} "
         f"{'theta_e':>8}  time")
    for name, e, vals, dt in rows:
        v = vals or {}
        cols = " ".join(f"{v[n]:6.3g}" if n in v else f"{'':>6}" for n in ("k", "k_x", "k_yz"))
        th = f"{v['theta_e']:8.3f}" if "theta_e" in v else f"{'':>8}"
        _say(f"    {name:<30} {e:9.2f}  {cols} {th}  {dt}")
    _say(f"    (truth: k={truth.params['k']:.3g}, k_x={truth.params['k_x']:.3g}, "
         f"k_yz={truth.params['k_yz']:.3g}, theta_e={truth.params['theta_e']:.3f})")

    _say("3/4 diagnosing: consistency of held-out fixes, conditions, score test of every "
         "catalogue effect, refit of the top candidates ...")
    from ..diagnose import diagnose, save_diagnosis
    diag = diagnose([mission], gnss_every=GNSS_EVERY)
    save_diagnosis(diag, out / "diagnosis", overwrite=args.force)
    _say("\n".join("    " + line for line in diag.summary().splitlines()))

    if diag.best is not None:
        eff = diag.best.effect
        _say(f"4/4 adding '{eff}' to the model and refitting (aqfg fit --effect {eff}) ...")
        after = diagnose([mission], effects=(eff,), gnss_every=GNSS_EVERY)
        save_diagnosis(after, out / f"diagnosis-with-{eff}", overwrite=args.force)
        b, a = diag.base, after.base
        _say(f"    held-out dead-reckoning error {b.rmse:.2f} m -> {a.rmse:.2f} m; "
             f"consistency test {'passed' if b.consistency and b.consistency.passed else 'failed'}"
             f" -> {'passed' if a.consistency and a.consistency.passed else 'failed'}")
        for n, v in a.values(tuple(p for e in a.full.model.effects if e.name == eff
                                   for p in e.params)).items():
            _say(f"    {n} = {v['value']:.4g} +- {v['sigma']:.2g}   (true: {truth.params.get(n, np.nan):.4g})")
        refit = fit_fg([thin], mode="batch", effects=(eff,))
        save_result(refit, out / f"fit-fg-with-{eff}", overwrite=args.force)
        plot_fit(refit, [thin], out / f"fit-fg-with-{eff}")
        e_before = rows[1][1]
        e_after = inertial_rmse(refit.model or model, mission, refit.missions[0].p, truth)
        _say(f"    factor graph with {eff}: dead-reckoning RMSE vs the truth {e_before:.2f} m -> "
             f"{e_after:.2f} m (k={refit.values['k']:.3g}, k_x={refit.values['k_x']:.3g}, "
             f"k_yz={refit.values['k_yz']:.3g})")
    else:
        _say("4/4 the diagnosis found nothing missing: no effect to add.")
    _say(f"done in {time.perf_counter() - t_start:.0f} s; open {out / 'diagnosis' / 'report.html'}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    from ..cli import main
    sys.exit(main(["demo", *sys.argv[1:]]))
