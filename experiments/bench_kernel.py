"""Benchmark of the C++ dynamics kernel: one factor = 1 s of 50 Hz inputs, state and all Jacobians.

Target: ``propagate`` over 50 steps with 2 thrusters, residual and all Jacobians,
<= 5 us. Prints, per scenario, the median (p10, p90) time per call

* timed inside C++ (``_kernel.bench_propagate``: a loop of calls, no Python overhead),
* called from Python (``_kernel.propagate``, argument checks and result arrays included),
* of the numpy reference ``aqfg.model.reference.propagate``,

and the ratios. Each figure is over several runs (batches); the machine is shared, so read
medians. Run: ``python experiments/bench_kernel.py [--quick]``.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

try:
    import aqfg  # noqa: F401
except ImportError:  # run from a checkout without PYTHONPATH
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from aqfg import _kernel as K  # noqa: E402
from aqfg.data.importers.frames import euler_to_quat  # noqa: E402
from aqfg.model import reference as ref  # noqa: E402
from aqfg.model.params import N_DYN, vector  # noqa: E402
from aqfg.model.vehicle import LAG_LOOKBACK, quat_to_rot  # noqa: E402

RATE = 50.0  # Hz


def inputs(n_thr: int, seconds: float, warm_seconds: float, planar: bool, seed: int = 0):
    """Steps of a plausible manoeuvre: gentle roll/pitch, turning yaw, smooth commands."""
    rng = np.random.default_rng(seed)
    n_w, n = int(round(warm_seconds * RATE)), int(round(seconds * RATE))
    m = n_w + n
    t = 100.0 + np.arange(m) / RATE
    roll = 0.05 * np.sin(0.7 * t) if planar else 0.1 * np.sin(0.7 * t)
    pitch = 0.03 * np.cos(0.5 * t) if planar else 0.2 * np.cos(0.5 * t)
    yaw = 0.3 * t + 0.2 * np.sin(0.2 * t)
    R = quat_to_rot(euler_to_quat(roll, pitch, yaw)).reshape(m, 9)
    u = np.clip(0.6 + 0.5 * np.sin(0.9 * t[:, None] + rng.uniform(0, 6, n_thr)), -1, 1)
    dem = u * np.abs(u)
    steps = ref.Steps(h=np.full(m, 1.0 / RATE), warm=np.arange(m) < n_w, R=R, dem=dem, tm=t)
    dirs = np.tile([1.0, 0.0, 0.0], (n_thr, 1))
    side = np.where(np.arange(n_thr) < n_thr // 2, -1.0, 1.0)
    geom = ref.Geometry(dirs=dirs, side=side, planar=planar)
    x0 = np.array([10.0, -5.0, 0.0 if planar else 3.0, 1.2, 0.1, 0.0 if planar else 0.05])
    return x0, steps, geom


def all_effects(tau: float) -> np.ndarray:
    return vector({"theta_e": 0.1, "s_x": 0.2, "s_y": -0.1, "thrust_asymmetry.ratio": 1.1,
                   "reverse_thrust.ratio": 0.7, "thrust_lag.tau": tau,
                   "linear_drag.c_x": 0.2, "linear_drag.c_yz": 0.3,
                   "heading_drift.rate": 0.002, "current_drift.ds_x": 1e-3,
                   "current_drift.ds_y": -1e-3, "wind_drag.a_n": 0.05,
                   "wind_drag.a_e": -0.03})[:N_DYN]


SCENARIOS = [
    # name, thrusters, planar, params, warm-up seconds
    ("ASV, base model (target case)", 2, True, vector()[:N_DYN], 0.0),
    ("ASV, all effects, tau = 0", 2, True, all_effects(0.0), 0.0),
    ("ASV, all effects, tau = 0.3 s + 5 s warm-up", 2, True, all_effects(0.3), LAG_LOOKBACK),
    ("AUV 3-D, base model, 5 thrusters", 5, False, vector()[:N_DYN], 0.0),
    ("AUV 3-D, all effects, 5 thrusters, tau = 0", 5, False, all_effects(0.0), 0.0),
]


def pct(x) -> tuple[float, float, float]:
    return tuple(float(v) for v in np.percentile(x, [50, 10, 90]))


def fmt(stats, unit=1e-6) -> str:
    m, lo, hi = (s / unit for s in stats)
    return f"{m:8.2f} ({lo:7.2f} .. {hi:7.2f})"


def bench(name, n_thr, planar, p, warm_s, runs, reps):
    x0, s, g = inputs(n_thr, 1.0, warm_s, planar)
    args = (x0, p, s.h, s.warm.astype(np.uint8), s.R, s.dem, s.tm, g.dirs, g.side, planar)
    K.bench_propagate(*args, reps)  # warm caches
    cpp = [K.bench_propagate(*args, reps) for _ in range(runs)]
    py = []
    for _ in range(runs):
        t0 = time.perf_counter()
        for _ in range(reps // 4):
            K.propagate(*args)
        py.append((time.perf_counter() - t0) / (reps // 4))
    npy = []
    for _ in range(max(3, runs // 3)):
        t0 = time.perf_counter()
        ref.propagate(x0, p, s, g)
        npy.append(time.perf_counter() - t0)
    # same answer (the tests hold this to 1e-9; here only as a sanity check)
    d = max(float(np.abs(a - b).max()) for a, b in zip(K.propagate(*args), ref.propagate(x0, p, s, g)))
    return pct(cpp), pct(py), pct(npy), d


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer runs (a smoke test)")
    a = ap.parse_args(argv)
    runs, reps = (5, 400) if a.quick else (25, 4000)
    print(f"propagate over 1 s of {RATE:.0f} Hz inputs (50 steps; warm-up steps extra), "
          f"x1 + Jx (6x6) + Jp (6x{N_DYN}); {runs} runs")
    print("times in us: median (p10 .. p90)\n")
    hdr = f"{'scenario':46s} {'C++ loop':>27s} {'from Python':>27s} {'numpy ref':>27s}  ref/C++  ref/py  max|diff|"
    print(hdr)
    print("-" * len(hdr))
    target = None
    for sc in SCENARIOS:
        cpp, py, npy, d = bench(*sc, runs, reps)
        target = target or cpp[0]
        print(f"{sc[0]:46s} {fmt(cpp)} {fmt(py)} {fmt(npy)}  {npy[0] / cpp[0]:7.0f}  "
              f"{npy[0] / py[0]:6.0f}  {d:.1e}")
    print(f"\ntarget case (ASV, base model, 2 thrusters): {target * 1e6:.2f} us per factor in C++ "
          f"(goal <= 5 us: {'met' if target <= 5e-6 else 'NOT met'})")

    # many segments per call, and rollout, per factor / per step
    x0, s, g = inputs(2, 1.0, 0.0, True)
    Kseg = 200
    cat = lambda v: np.concatenate([v] * Kseg)
    args = (np.tile(x0, (Kseg, 1)), vector()[:N_DYN], cat(s.h), cat(s.warm).astype(np.uint8),
            cat(s.R), cat(s.dem), cat(s.tm), np.arange(Kseg + 1, dtype=np.int64) * len(s.h),
            g.dirs, g.side, True)
    tm = []
    for _ in range(runs):
        t0 = time.perf_counter()
        K.propagate_many(*args)
        tm.append((time.perf_counter() - t0) / Kseg)
    print(f"propagate_many, {Kseg} factors per call: {fmt(pct(tm))} us per factor")
    x0, s, g = inputs(2, 600.0, 0.0, True)
    tr = []
    for _ in range(runs):
        t0 = time.perf_counter()
        K.rollout(x0, vector()[:N_DYN], s.h, s.warm.astype(np.uint8), s.R, s.dem, s.tm, g.dirs,
                  g.side, True)
        tr.append((time.perf_counter() - t0) / len(s.h))
    print(f"rollout, 10 min at {RATE:.0f} Hz: {fmt(pct(tr), 1e-9)} ns per step")
    return 0


if __name__ == "__main__":
    sys.exit(main())
