"""Figs. 7/8 analog: online estimation of [theta_e, s_x, s_y] with GNSS every 8 s and a 30 deg
initial heading error, factor graph vs update-error.

ASV missions (true fixed parameters of the paper's ASV.3, held at their true values: the
paper runs online estimation with the offline-optimal fixed parameters); true heading
offset 30 deg, current 0.07-0.13 m/s in a seeded direction; GNSS kept once every 8 s, all
of it kept for the truth. Both methods start from theta_e = s_x = s_y = 0:

* factor graph: :class:`aqfg.fg.fit.FixedLagSmoother`, window 24 s (3 fixes), update
  after each fix; "without estimation" = the same smoother with no parameter node;
* update-error: :meth:`aqfg.ekf.estimator.UpdateErrorEstimator.run_online`, window = last 3 fixes
  (24 s), optimisation after each fix (the paper's settings), its default past correction
  (re-run of each optimised window); "without estimation" = the EKF alone;
* update-error with a 6-fix (48 s) window: an extra row, because the estimator's own
  Monte Carlo (tests/test_update_error.py) found the paper's 3-fix window noisy here.

Reported per method over the seeds: RMSE and 95th percentile of the causal position
estimate (what the vehicle knew at each time, 1 s grid from the first fix), the same after
the final past-trajectory correction, when the heading estimate is within 5 deg of the truth
for good, final parameter errors and error / reported sigma.

Fig. 8 analog (past-trajectory correction): each mission cut at its 5th fix (32 s); the
past with parameters held (before) vs the past re-traced with the parameters estimated by
then (after): update-error delays its first optimisation to that fix (window = all 5
fixes, as the paper did for the figure) and re-runs the whole past; the factor graph runs
as usual and re-traces the past (``corrected_track``).

Full run: 20 seeds, 600 s missions, about 2 min with 2 processes. ``--quick``: 2 seeds,
240 s. Run: ``python experiments/online_heading.py [--quick] [--seeds N] [--jobs J]``.
"""
from __future__ import annotations

import sys
import time
import traceback

import numpy as np

import common as C
from aqfg import evaluate as ev
from aqfg.data.mission import with_gnss_every
from aqfg.sim.simulator import simulate

GNSS_EVERY = 8.0
WINDOW_FIXES = 3
THETA0 = np.radians(30.0)
TOL = np.radians(5.0)
K_PAST = 5           # Fig. 8: the cut after this many fixes
SETTLE = 120.0       # s after the first fix: median |theta_e error| after it
VARIABLE = ("theta_e", "s_x", "s_y")


# the two methods with the paper's window, and the update-error method with a longer
# window (its tests found the paper's 3-fix window noisy on these missions, 6 fixes not)
METHODS = C.METHODS + ("update-error-6",)


def run_online(method: str, mission, init: dict, window: float):
    """One method's online run, returns (Result, seconds). Past-trajectory correction as
    each method does it by default (update-error: re-run of each optimised window)."""
    if method == "fg":
        return C.fit("fg", [mission], mode="online", estimate=VARIABLE, init=init, window=window)
    t0 = time.perf_counter()
    from aqfg.ekf.estimator import UpdateErrorEstimator
    r = UpdateErrorEstimator(None, mission, init=init).run_online(
        estimate=VARIABLE, window_fixes=6 if method == "update-error-6" else WINDOW_FIXES)
    return r, time.perf_counter() - t0


def past_correction(method: str, mission, truth, init: dict) -> dict:
    """Fig. 8: RMSE of the past before / after the first correction, cut at fix K_PAST."""
    tf = np.unique(mission.fix_times())
    t_cut = float(tf[K_PAST - 1])
    cut = C.truncate(mission, t_cut)
    grid = np.arange(tf[0], t_cut + 1e-9, 1.0)
    if method == "fg":
        from aqfg.fg.fit import FixedLagSmoother
        before = FixedLagSmoother(None, estimate=(), init=init, window=24.0).run(cut)
        before_tr = before.missions[0].filtered
        fl = FixedLagSmoother(None, estimate=VARIABLE, init=init, window=24.0)
        r = fl.run(cut)
        after_tr = r.missions[0].track
        theta = r.values["theta_e"]
    else:
        from aqfg.ekf.estimator import UpdateErrorEstimator
        r = UpdateErrorEstimator(None, cut, init=init).run_online(
            estimate=VARIABLE, window_fixes=K_PAST - 1, min_fixes=K_PAST - 1, correct="all")
        before_tr, after_tr = r.missions[0].filtered, r.missions[0].track
        theta = r.values["theta_e"]
    out = {"t_cut": t_cut, "theta_e": theta}
    for key, tr in (("before", before_tr), ("after", after_tr)):
        _, e = ev.position_error(tr, truth, grid)
        out[key] = float(np.sqrt(np.mean(e ** 2)))
        out[key + "_xy"] = np.asarray(tr.pos[:, :2])[(tr.t <= t_cut + 1e-9)][::2]
    return out


def one(task) -> dict:
    seed, T, keep = task
    full, truth = simulate("asv", seed=seed, duration=T, params={"theta_e": THETA0},
                           gnss_period=1.0)
    m = with_gnss_every(full, GNSS_EVERY)
    tp = truth.params
    init = {n: tp[n] for n in ("k", "k_x", "k_yz")}          # theta_e = s = 0 (nominal)
    grid = C.eval_grid(m)
    window = WINDOW_FIXES * GNSS_EVERY
    out = {"seed": seed, "t0": float(grid[0]), "truth": {n: tp[n] for n in VARIABLE}, "with": {}, "without": {},
           "hist": {}, "z": {}, "final_err": {}, "t_conv": {}, "seconds": {}, "past": {},
           "error": {}, "tracks": {}}
    r0_by = {}
    for method in METHODS:
        try:
            r, sec = run_online(method, m, init, window)
            base = "fg" if method == "fg" else "update-error"
            if base not in r0_by:
                r0_by[base] = C.run_without_estimation(base, m, init, window)
            r0 = r0_by[base]
            out["with"][method] = {k: {kk: v[kk] for kk in ("rmse", "p95")}
                                   for k, v in C.online_errors(r, truth, grid).items()}
            out["without"][method] = {k: {kk: v[kk] for kk in ("rmse", "p95")}
                                      for k, v in C.online_errors(r0, truth, grid).items()}
            t_h, th, sg = C.history_of(r, "theta_e")
            out["hist"][method] = (t_h, th, sg)
            th_err = ev.wrap_angle(th - tp["theta_e"])
            out["t_conv"][method] = C.converged_at(t_h, th_err, TOL) - float(grid[0])
            late = t_h >= grid[0] + SETTLE
            out["theta_late"] = out.get("theta_late", {})
            out["theta_late"][method] = (float(np.median(np.abs(th_err[late]))) if late.any()
                                         else np.nan)
            pe = ev.param_errors(r.values, r.sigma, tp, VARIABLE)
            out["final_err"][method] = dict(zip(VARIABLE, pe.error))
            out["z"][method] = dict(zip(VARIABLE, pe.z))
            out["seconds"][method] = sec
            if method in C.METHODS:
                out["past"][method] = past_correction(method, m, truth, init)
            if keep:
                e_with = C.online_errors(r, truth, grid)["causal"]
                e_wo = C.online_errors(r0, truth, grid)["causal"]
                out["tracks"][method] = {
                    "with": r.missions[0].filtered.pos[:, :2][::5],
                    "without": r0.missions[0].filtered.pos[:, :2][::5],
                    "err_with": (e_with["t"], e_with["err"]),
                    "err_without": (e_wo["t"], e_wo["err"])}
        except Exception as e:
            out["error"][method] = f"{type(e).__name__}: {e}"
            traceback.print_exc(file=sys.stderr)
    if keep:
        out["tracks"]["truth"] = truth.pos[::10, :2]
        out["tracks"]["fixes"] = m.gnss.ne
        out["tracks"]["truth_t"] = truth.t[::10]
    return out


def main(argv=None) -> int:
    return C.monte_carlo_main(__doc__, argv, "online_heading", one,
                              lambda S, T: [(1000 + s, T, s == 0) for s in range(S)], write)


def write(res, args, S, T, started) -> None:
    import matplotlib.pyplot as plt
    out = args.out
    M = METHODS
    rows = []
    for m in M:
        g = lambda case, k, q: [r[case].get(m, {}).get(k, {}).get(q, np.nan) for r in res]
        tc = np.array([r["t_conv"].get(m, np.nan) for r in res])
        rows.append([C.LABEL[m],
                     C.pm(g("without", "causal", "rmse")), C.pm(g("with", "causal", "rmse")),
                     C.pm(g("without", "causal", "p95")), C.pm(g("with", "causal", "p95")),
                     C.pm(g("with", "corrected", "rmse")),
                     f"{C.med(tc, 0)} ({np.isfinite(tc).sum()}/{len(tc)})"])
    t1 = C.md_table(["method", "causal RMSE without est. [m]", "causal RMSE with est. [m]",
                     "95th pct without [m]", "95th pct with [m]",
                     "corrected-track RMSE [m]",
                     "heading within 5 deg for good after [s] (converged/seeds)"], rows)
    prow = []
    for m in M:
        fe = {n: [r["final_err"].get(m, {}).get(n, np.nan) for r in res] for n in VARIABLE}
        z = np.array([[r["z"].get(m, {}).get(n, np.nan) for n in VARIABLE] for r in res])
        c = ev.consistency(z)
        lt = [r.get("theta_late", {}).get(m, np.nan) for r in res]
        prow.append([C.LABEL[m], C.med(np.degrees(lt), 2),
                     C.pm(np.degrees(fe["theta_e"]), 2), C.pm(fe["s_x"], 3),
                     C.pm(fe["s_y"], 3), f"{c['rms']:.2f}", f"{100 * c['within2']:.0f} %",
                     c["n"]])
    t2 = C.md_table(["method", f"median abs theta_e error after {SETTLE:.0f} s [deg], "
                     "median [p10, p90] over seeds", "final theta_e error [deg]", "final s_x error [m/s]",
                     "final s_y error [m/s]", "RMS error/sigma", "within 2 sigma", "n"], prow)
    crow = []
    for m in C.METHODS:
        b = [r["past"].get(m, {}).get("before", np.nan) for r in res]
        a = [r["past"].get(m, {}).get("after", np.nan) for r in res]
        th = [np.degrees(ev.wrap_angle(r["past"].get(m, {}).get("theta_e", np.nan)
                                       - r["truth"]["theta_e"])) for r in res]
        crow.append([C.LABEL[m], C.pm(b), C.pm(a), C.pm(th, 1)])
    t3 = C.md_table(["method", f"past RMSE before correction [m]",
                     "past RMSE after correction [m]", "theta_e error at the cut [deg]"], crow)
    trow = [[C.LABEL[m], C.med([r["seconds"].get(m, np.nan) for r in res])] for m in M]
    t4 = C.md_table(["method", "wall time per mission [s]"], trow)
    fails = [f"- seed {r['seed']}, {m}: {e}" for r in res for m, e in r["error"].items()]
    nconv = [f"- seed {r['seed']} {m}: heading never within 5 deg for good (final error "
             f"{np.degrees(r['final_err'][m]['theta_e']):.1f} deg)"
             for r in res for m in M if m in r["t_conv"] and not np.isfinite(r["t_conv"][m])]
    body = f"""
Online estimation of theta_e, s_x, s_y (paper §V-B, Figs. 7-8). {S} ASV missions of
{T:.0f} s, true heading offset 30 deg, GNSS used once every {GNSS_EVERY:.0f} s (all of it
kept as truth), fixed parameters held at their true values, both methods from
theta_e = s_x = s_y = 0; window 3 fixes = {WINDOW_FIXES * GNSS_EVERY:.0f} s for both
(plus the update-error method with a 6-fix window).
"Causal" = the estimate the vehicle had at each time (1 s grid from the first fix);
"corrected" = the whole track after the final past-trajectory correction.
Mean ± standard deviation over seeds; convergence time as median [p10, p90].

## Position error, with and without online estimation (Fig. 7 analog)

{t1}

## Final parameters and honesty of the reported sigma

{t2}

## Past-trajectory correction after the first estimate (Fig. 8 analog)

Mission cut at its {K_PAST}th fix; past from the first fix to the cut.

{t3}

## Wall time (median [p10, p90])

{t4}

## Failures / no convergence

{chr(10).join(fails) if fails else "- no method raised"}
{chr(10).join(nconv) if nconv else "- every run converged"}

Figures: `online_heading_map.png` (seed 0, Fig. 7), `online_heading_theta.png` (theta_e
estimates of every seed vs truth), `online_heading_error.png` (seed 0 position error),
`online_heading_past.png` (Fig. 8).
"""
    C.write_md(out, "online_heading", "Figs. 7/8 analog: online heading/current estimation",
               body, args, started)
    C.write_headline(out, "online_heading", t1 + "\n\n" + C.md_table(
        ["method", "median abs theta_e error after 120 s [deg]", "final theta_e error [deg]",
         "final error/sigma: RMS", "within 2 sigma"],
        [[r[0], r[1], r[2], r[5], r[6]] for r in prow]) + "\n\nPast-trajectory correction "
        f"(Fig. 8), mission cut at fix {K_PAST}:\n\n" + t3, args)

    r0 = next((r for r in res if r["tracks"]), None)
    if r0 is not None:
        tr = r0["tracks"]
        fig, axs = plt.subplots(1, 2, figsize=(8, 3.8))
        for ax, m in zip(axs, M):
            ax.plot(*tr["truth"][:, ::-1].T, "k-", lw=1.5, label="truth")
            ax.plot(*tr["fixes"][:, ::-1].T, "o", mfc="none", color="tab:green", ms=3,
                    label="GNSS fixes used")
            if m in tr:
                ax.plot(*tr[m]["without"][:, ::-1].T, "-", color=C.COLOR["none"], lw=0.8,
                        label="without estimation")
                ax.plot(*tr[m]["with"][:, ::-1].T, "-", color=C.COLOR[m], lw=0.8,
                        label="with online estimation")
            ax.set_title(C.LABEL[m], fontsize=9)
            ax.set_aspect("equal", "datalim")
            ax.set_xlabel("east [m]")
        axs[0].set_ylabel("north [m]")
        axs[0].legend(fontsize=6)
        C.save_fig(fig, out, "online_heading_map", args)

        fig, ax = plt.subplots(figsize=(7, 3))
        for m in M:
            if m not in tr:
                continue
            for key, ls in (("err_without", ":"), ("err_with", "-")):
                t, e = tr[m][key]
                ax.plot(t - t[0], e, ls, color=C.COLOR[m], lw=0.8,
                        label=f"{C.LABEL[m]}, {'with' if key == 'err_with' else 'without'} est.")
        ax.set_xlabel("time since first fix [s]")
        ax.set_ylabel("causal position error [m]")
        ax.legend(fontsize=7)
        C.save_fig(fig, out, "online_heading_error", args)

    fig, ax = plt.subplots(figsize=(7, 3))
    for m in M:
        for i, r in enumerate(res):
            if m not in r["hist"]:
                continue
            t, th, _ = r["hist"][m]
            if not len(t):
                continue
            ax.plot(t - r["t0"],
                    np.degrees(ev.wrap_angle(th - r["truth"]["theta_e"])), "-",
                    color=C.COLOR[m], lw=0.6, alpha=0.5, label=C.LABEL[m] if i == 0 else None)
    ax.axhspan(-5, 5, color="0.9")
    ax.set_ylim(-40, 20)
    ax.set_xlim(0, 200)
    ax.set_xlabel("time since first fix [s]")
    ax.set_ylabel("theta_e estimate - truth [deg]")
    ax.legend(fontsize=7)
    ax.set_title("heading error estimate, every seed (grey band: 5 deg)", fontsize=9)
    C.save_fig(fig, out, "online_heading_theta", args)

    if r0 is not None and r0["past"]:
        fig, axs = plt.subplots(1, 2, figsize=(8, 3.5))
        tt = r0["tracks"]
        for ax, m in zip(axs, M):
            p = r0["past"].get(m)
            if p is None:
                continue
            sel = tt["truth_t"] <= p["t_cut"] + 1e-9
            ax.plot(*tt["truth"][sel][:, ::-1].T, "k-", lw=1.5, label="truth")
            fx = tt["fixes"][: K_PAST]
            ax.plot(*fx[:, ::-1].T, "o", mfc="none", color="tab:green", ms=4, label="fixes")
            ax.plot(*p["before_xy"][:, ::-1].T, "-", color=C.COLOR["none"], lw=1,
                    label=f"before ({p['before']:.1f} m RMSE)")
            ax.plot(*p["after_xy"][:, ::-1].T, "-", color=C.COLOR[m], lw=1,
                    label=f"after ({p['after']:.1f} m RMSE)")
            ax.set_title(f"{C.LABEL[m]}: past re-traced at fix {K_PAST}", fontsize=9)
            ax.set_aspect("equal", "datalim")
            ax.legend(fontsize=6)
            ax.set_xlabel("east [m]")
        axs[0].set_ylabel("north [m]")
        C.save_fig(fig, out, "online_heading_past", args)


if __name__ == "__main__":
    sys.exit(main())
