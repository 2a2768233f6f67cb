"""Benchmark of the factor graph (medians of repeated runs; timings are not tests).

1. The dynamics factor over 1 s of 50 Hz inputs, residual and all Jacobians (target
   <= 5 us for the C++ part):
   * bare C++ (``_kernel.bench_propagate``: a loop inside C++),
   * the kernel called from Python (``Model.propagate``),
   * per factor inside one batched ``propagate_many`` call (what the batch smoother does),
   * through the Python factor: ``CustomFactor.linearize`` of
     :func:`aqfg.fg.factors.dynamics_factor` (kernel + GTSAM bridging + numpy blocks), and
     of the batch smoother's cached factor (GTSAM bridging only).
2. A fixed-lag update with a 24 s window (GNSS every 8 s, ASV, 30 deg heading offset;
   target <= 5 ms median), and the update-error optimisation of the same window measured
   in the same run (target ratio >= 20x), via :func:`aqfg.bench.online_times`.
3. The batch smoother over a 15-minute ASV mission with all six parameters from the
   paper's old values (target <= 3 s), with GNSS at 1 Hz and every 8 s; and its parts
   (graph building, LM iterations, marginal covariances).

Run: ``python experiments/bench_fg.py [--repeat N]`` (default 5; about a minute).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import gtsam  # noqa: E402

from aqfg import bench  # noqa: E402
from aqfg.fg import factors as fc  # noqa: E402
from aqfg.data.mission import with_gnss_every  # noqa: E402
from aqfg.model.vehicle import Model  # noqa: E402
from aqfg.model.params import N_DYN, OLD_PARAMS  # noqa: E402
from aqfg.sim.simulator import simulate  # noqa: E402
from aqfg.fg.fit import fit_fg  # noqa: E402

SIX = ("theta_e", "s_x", "s_y", "k", "k_x", "k_yz")


def med(x) -> float:
    return float(np.median(np.asarray(x, float)))


def per_call(fn, n: int) -> float:
    t0 = time.perf_counter()
    for _ in range(n):
        fn()
    return (time.perf_counter() - t0) / n


def factor_times(repeat: int, n: int = 2000) -> dict:
    """Seconds per dynamics factor (1 s of 50 Hz inputs) by each path; one figure per run."""
    m, tr = simulate("asv", seed=0, duration=120.0)
    model = Model.for_mission(m)
    truth = {k: v for k, v in tr.params.items() if k in model.all_names and isinstance(v, float)}
    lay = fc.ParamLayout.build(model, SIX, truth)
    knots = np.arange(20.0, 101.0, 1.0)                  # 80 one-second segments
    steps, off = model.steps(m, knots)
    one = steps.slice(int(off[0]), int(off[1]))
    assert len(one.h) == 50, len(one.h)
    x0 = np.array([1.0, 2.0, 0.0, 1.0, 0.2, 0.0])
    p = lay.base
    g = model.geometry
    from aqfg import _kernel as K
    args = (x0, np.ascontiguousarray(p[:N_DYN]), one.h, one.warm.astype(np.uint8), one.R,
            one.dem, one.tm, g.dirs, g.side, g.planar)
    X0 = np.tile(x0, (len(knots) - 1, 1))
    k0, k1 = fc.state_key(0, 0), fc.state_key(0, 1)
    nk = tuple((grp, fc.node_key(grp)) for grp in lay.dyn_groups())
    vals = gtsam.Values()
    vals.insert(k0, x0)
    vals.insert(k1, model.propagate(x0, p, one)[0])
    for grp, k in nk:
        vals.insert(k, lay.initial(grp))
    noise = fc.ProcessNoise().noise_model(1.0)
    f_own = fc.dynamics_factor(model, lay, one, k0, k1, nk, noise)
    pred, Jx, Jp = model.propagate_many(X0[:1], p, one, np.array([0, len(one.h)]))
    f_cached = fc.cached_dynamics_factor(fc.DynamicsCache(pred, Jx, Jp), 0, lay, k0, k1, nk,
                                         noise)
    out = {k: [] for k in ("cpp", "python_kernel", "batched", "factor", "cached_factor")}
    K.bench_propagate(*args, n)
    for _ in range(repeat):
        out["cpp"].append(float(K.bench_propagate(*args, n)))
        out["python_kernel"].append(per_call(lambda: model.propagate(x0, p, one), n))
        out["batched"].append(per_call(lambda: model.propagate_many(X0, p, steps, off), 50)
                              / len(X0))
        out["factor"].append(per_call(lambda: f_own.linearize(vals), n))
        out["cached_factor"].append(per_call(lambda: f_cached.linearize(vals), n))
    return out


def total_update_times(repeat: int) -> list[float]:
    """Seconds per whole ``FixedLagSmoother.update`` call after the warm-up (building the
    new factors and kernel steps included), on the same mission as aqfg.bench's gnss8."""
    from aqfg.fg.fit import FixedLagSmoother
    sc = bench.SCENARIOS["gnss8"]
    m, _, init = bench.online_mission(sc)
    out = []
    for _ in range(repeat):
        r = FixedLagSmoother(init=init, window=sc.window_s).run(m)
        sel = r.history.t > r.info["warmup_end"]
        out += list(np.asarray(r.timings["update_total"])[sel])
    return out


def batch_times(repeat: int, gnss_every: float, duration: float = 900.0) -> dict:
    m, tr = simulate("asv", seed=0, duration=duration)
    m = with_gnss_every(m, gnss_every)
    out = {k: [] for k in ("total", "build", "iterations", "iteration", "covariance", "z")}
    for _ in range(repeat):
        t0 = time.perf_counter()
        r = fit_fg([m], estimate=SIX, init=dict(OLD_PARAMS))
        out["total"].append(time.perf_counter() - t0)
        out["build"].append(r.timings["build"][0])
        out["iterations"].append(r.iterations)
        out["iteration"].append(med(r.timings["iteration"]))
        out["covariance"].append(r.timings["covariance"][0])
    out["z"] = {n: (r.values[n] - tr.params[n]) / r.sigma[n] for n in SIX}
    out["n_states"] = r.info["n_states"]
    out["n_factors"] = r.info["n_factors"]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args(argv)
    rep = args.repeat
    say = lambda msg: print(f"[bench_fg] {msg} ...", file=sys.stderr, flush=True)

    say("dynamics factor")
    f = factor_times(rep)
    say("fixed-lag update and update-error optimisation (24 s window)")
    o = bench.online_times(bench.SCENARIOS["gnss8"], repeat=rep)
    say("batch, GNSS 1 Hz")
    b1 = batch_times(rep, 1.0)
    say("batch, GNSS every 8 s")
    b8 = batch_times(rep, 8.0)

    us = lambda x: f"{1e6 * med(x):.2f} us"
    print(f"\n## Factor graph benchmark (medians of {rep} runs)\n")
    print("| dynamics factor, 1 s of 50 Hz inputs, residual + all Jacobians | median |")
    print("|---|---|")
    print(f"| bare C++ (loop inside C++) | {us(f['cpp'])} |")
    print(f"| kernel called from Python (Model.propagate) | {us(f['python_kernel'])} |")
    print(f"| per factor in one propagate_many call (batch smoother) | {us(f['batched'])} |")
    print(f"| through the Python factor (CustomFactor.linearize, own kernel call) | {us(f['factor'])} |")
    print(f"| cached factor of the batch smoother (CustomFactor.linearize) | {us(f['cached_factor'])} |")
    fl, fl_all, ue = med(o["fl_update"]), med(o["fl_update_all"]), med(o["ue_opt"])
    tot = total_update_times(rep)
    print(f"\n| online, ASV, GNSS every 8 s, window 24 s | median |\n|---|---|")
    print(f"| fixed-lag update after warm-up | {1e3 * fl:.2f} ms (p90 "
          f"{1e3 * np.percentile(o['fl_update'], 90):.2f}) |")
    print(f"| fixed-lag update, all (warm-up included) | {1e3 * fl_all:.2f} ms (p90 "
          f"{1e3 * np.percentile(o['fl_update_all'], 90):.2f}) |")
    print(f"| whole update() call after warm-up (new factors, kernel steps, solve, marginals) "
          f"| {1e3 * med(tot):.2f} ms (p90 {1e3 * np.percentile(tot, 90):.2f}) |")
    print(f"| update-error optimisation of the same window | {1e3 * ue:.2f} ms "
          f"({med(o['ue_nevals']):.0f} evaluations of {1e3 * med(o['ue_eval']):.3f} ms) |")
    print(f"| ratio update-error / fixed-lag (same run) | {ue / fl:.1f}x (whole call: "
          f"{ue / med(tot):.1f}x) |")
    print(f"\n| batch, 15-min ASV mission, six parameters from the old values | GNSS 1 Hz | GNSS 8 s |")
    print("|---|---|---|")
    for k, lab, fmt in (("total", "total", "{:.2f} s"), ("build", "graph building", "{:.3f} s"),
                        ("iterations", "LM iterations", "{:.0f}"),
                        ("iteration", "time per iteration", "{:.3f} s"),
                        ("covariance", "marginal covariances", "{:.4f} s")):
        print(f"| {lab} | {fmt.format(med(b1[k]))} | {fmt.format(med(b8[k]))} |")
    print(f"| states / factors | {b1['n_states']} / {b1['n_factors']} | "
          f"{b8['n_states']} / {b8['n_factors']} |")
    print(f"| (estimate - truth) / sigma | "
          + ", ".join(f"{n} {z:+.1f}" for n, z in b1["z"].items()) + " | "
          + ", ".join(f"{n} {z:+.1f}" for n, z in b8["z"].items()) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
