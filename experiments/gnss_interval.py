"""Fig. 10 analog: position error over time for GNSS intervals of 4, 8 and 12 s, with and
without online estimation, and the 95th-percentile error per method.

The scenario of ``online_heading.py`` (paper §V-E uses the trajectory of §V-B): ASV
missions with a 30 deg true heading offset and a seeded current, fixed parameters at their
true values, theta_e = s_x = s_y = 0 initially for both methods. GNSS is thinned to one
fix every 4, 8 or 12 s (the full 1 Hz GNSS stays the truth); the estimation window is the
last three fixes, i.e. 3x the interval, for both methods (update-error: 3 fixes; factor
graph: fixed-lag window of 3x the interval in seconds). "Without estimation": the same
estimator with the parameters held (EKF alone; fixed-lag smoother without parameter
nodes).

Error = horizontal distance between the causal estimate (what the vehicle knew at that
time) and the truth, on a 1 s grid from the first fix. The paper's Fig. 10 marks the level
below which 95 % of the samples fall: reported over the whole mission and after the first
120 s (once the parameters have converged), mean ± std over seeds.

Full run: 20 seeds x 3 intervals, 600 s missions, about 4 min with 2 processes.
``--quick``: 2 seeds, 240 s. Run: ``python experiments/gnss_interval.py [--quick]``.
"""
from __future__ import annotations

import sys
import traceback

import numpy as np

import common as C
from aqfg import evaluate as ev
from aqfg.data.mission import with_gnss_every
from aqfg.sim.simulator import simulate
from online_heading import THETA0, VARIABLE

INTERVALS = (4.0, 8.0, 12.0)
SETTLE = 120.0       # s after the first fix: "converged" part of the mission


def run_online(method: str, mission, init: dict, interval: float):
    window = 3 * interval
    if method == "fg":
        return C.fit("fg", [mission], mode="online", estimate=VARIABLE, init=init,
                     window=window)[0]
    from aqfg.ekf.estimator import UpdateErrorEstimator
    return UpdateErrorEstimator(None, mission, init=init).run_online(
        estimate=VARIABLE, window_fixes=3)


def one(task) -> dict:
    seed, interval, T, keep = task
    full, truth = simulate("asv", seed=seed, duration=T, params={"theta_e": THETA0},
                           gnss_period=1.0)
    m = with_gnss_every(full, interval)
    tp = truth.params
    init = {n: tp[n] for n in ("k", "k_x", "k_yz")}
    grid = C.eval_grid(m)
    out = {"seed": seed, "interval": interval, "stats": {}, "error": {}, "curves": {},
           "growth": {}}
    for method in C.METHODS:
        for case in ("with", "without"):
            try:
                r = (run_online(method, m, init, interval) if case == "with"
                     else C.run_without_estimation(method, m, init, 3 * interval))
            except Exception as e:
                out["error"][f"{method}/{case}"] = f"{type(e).__name__}: {e}"
                traceback.print_exc(file=sys.stderr)
                continue
            e = C.online_errors(r, truth, grid)["causal"]
            late = e["t"] >= e["t"][0] + SETTLE
            out["stats"][(method, case)] = {
                "rmse": e["rmse"], "p95": e["p95"], "p95_late": ev.percentile(e["err"][late]),
                "rmse_late": float(np.sqrt(np.mean(e["err"][late] ** 2)))}
            if case == "with":
                pe = ev.param_errors(r.values, r.sigma, tp, VARIABLE)
                t_h, th, _ = C.history_of(r, "theta_e")
                th_late = np.abs(ev.wrap_angle(th - tp["theta_e"]))[t_h >= e["t"][0] + SETTLE]
                out["stats"][(method, case)].update(
                    z=pe.z, theta_late=float(np.median(th_late)) if len(th_late) else np.nan)
            bf = ev.error_between_fixes(e["t"], e["err"], m.gnss.t)
            sel = bf.t0 >= e["t"][0] + SETTLE
            out["growth"][(method, case)] = float(np.mean(bf.peak[sel])) if sel.any() else np.nan
            if keep:
                out["curves"][(method, case)] = (e["t"] - e["t"][0], e["err"])
    return out


def main(argv=None) -> int:
    return C.monte_carlo_main(__doc__, argv, "gnss_interval", one, lambda S, T: [
        (2000 + s, iv, T, s == 0) for iv in INTERVALS for s in range(S)], write)


def write(res, args, S, T, started) -> None:
    import matplotlib.pyplot as plt
    out = args.out
    rows = []
    for iv in INTERVALS:
        rr = [r for r in res if r["interval"] == iv]
        for mi, m in enumerate(C.METHODS):
            g = lambda case, k: [r["stats"].get((m, case), {}).get(k, np.nan) for r in rr]
            gr = lambda case: [r["growth"].get((m, case), np.nan) for r in rr]
            z = np.array([r["stats"].get((m, "with"), {}).get("z", np.full(3, np.nan))
                          for r in rr])
            c = ev.consistency(z)
            rows.append([f"{iv:.0f} s" if mi == 0 else "", C.LABEL[m],
                         C.pm(g("without", "p95")), C.pm(g("with", "p95")),
                         C.pm(g("without", "p95_late")), C.pm(g("with", "p95_late")),
                         C.pm(g("with", "rmse_late")), C.pm(gr("without")), C.pm(gr("with")),
                         C.med(np.degrees(g("with", "theta_late"))),
                         f"{c['rms']:.2f} / {100 * c['within2']:.0f} %"])
    t1 = C.md_table(["GNSS interval", "method", "95th pct without est. [m]",
                     "95th pct with est. [m]", f"95th pct without, after {SETTLE:.0f} s [m]",
                     f"95th pct with, after {SETTLE:.0f} s [m]",
                     f"RMSE with, after {SETTLE:.0f} s [m]",
                     "mean peak error between fixes without [m]",
                     "mean peak error between fixes with [m]",
                     f"median abs theta_e error after {SETTLE:.0f} s [deg], median [p10, p90]",
                     "final theta_e, s_x, s_y error/sigma: RMS / within 2 sigma"], rows)
    fails = [f"- seed {r['seed']} interval {r['interval']:.0f} s, {k}: {e}" for r in res
             for k, e in r["error"].items()]
    body = f"""
Position error of the causal estimate for GNSS intervals {", ".join(f"{i:.0f}" for i in
INTERVALS)} s (paper §V-E, Fig. 10). {S} ASV missions of {T:.0f} s per interval (the same
seeds for every interval), 30 deg true heading offset, window = 3 x interval for both
methods, fixed parameters at truth, theta_e = s = 0 initially. 95th percentile of the
error samples on a 1 s grid from the first fix, over the whole mission and after the first
{SETTLE:.0f} s; peak error between fixes averaged over the intervals after {SETTLE:.0f} s.
Mean ± standard deviation over seeds. Honesty of the sigma: final theta_e, s_x, s_y error
divided by the reported sigma, pooled over seeds.

{t1}

Failures: {chr(10).join(fails) if fails else "none"}

Figures: `gnss_interval_error.png` (seed 0, error over time per interval, 95th-percentile
lines), `gnss_interval_p95.png` (95th percentile vs interval, every seed).
"""
    C.write_md(out, "gnss_interval", "Fig. 10 analog: position error vs GNSS interval", body,
               args, started)
    C.write_headline(out, "gnss_interval", C.md_table(
        ["GNSS interval", "method", "95th pct without est. [m]", "95th pct with est. [m]",
         f"95th pct with, after {SETTLE:.0f} s [m]", "error/sigma: RMS / within 2 sigma"],
        [[r[0], r[1], r[2], r[3], r[5], r[10]] for r in rows]), args)

    fig, axs = plt.subplots(len(INTERVALS), 1, figsize=(7.5, 6.5), sharex=True)
    for ax, iv in zip(axs, INTERVALS):
        r0 = next((r for r in res if r["interval"] == iv and r["curves"]), None)
        if r0 is None:
            continue
        for m in C.METHODS:
            for case, ls, lw in (("without", ":", 0.8), ("with", "-", 0.9)):
                if (m, case) not in r0["curves"]:
                    continue
                t, e = r0["curves"][(m, case)]
                ax.plot(t, e, ls, color=C.COLOR[m], lw=lw,
                        label=f"{C.LABEL[m]}, {case} est.")
                if case == "with":
                    ax.axhline(ev.percentile(e), color=C.COLOR[m], lw=0.8, ls="--")
        ax.set_ylabel("error [m]")
        ax.set_title(f"GNSS every {iv:.0f} s (dashed: 95th percentile with estimation)",
                     fontsize=8)
        ax.set_ylim(0, None)
    axs[0].legend(fontsize=6, ncol=2)
    axs[-1].set_xlabel("time since first fix [s]")
    C.save_fig(fig, out, "gnss_interval_error", args)

    fig, ax = plt.subplots(figsize=(6, 3.2))
    for mi, m in enumerate(C.METHODS):
        for case, mk in (("without", "x"), ("with", "o")):
            for j, iv in enumerate(INTERVALS):
                v = [r["stats"].get((m, case), {}).get("p95", np.nan) for r in res
                     if r["interval"] == iv]
                x = iv + (mi - 0.5) * 0.6 + (0.15 if case == "with" else -0.15)
                ax.plot(np.full(len(v), x), v, mk, color=C.COLOR[m], ms=3, alpha=0.6, mfc="none",
                        label=f"{C.LABEL[m]}, {case} est." if j == 0 else None)
    ax.set_xticks(INTERVALS)
    ax.set_xlabel("GNSS interval [s]")
    ax.set_ylabel("95th pct causal error [m]")
    ax.set_yscale("log")
    ax.legend(fontsize=6)
    C.save_fig(fig, out, "gnss_interval_p95", args)


if __name__ == "__main__":
    sys.exit(main())
