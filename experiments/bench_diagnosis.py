"""Benchmark: one diagnosis step on a 15-minute mission, and a user effect's fit against the
same physics built in.

1. ``diagnose`` on tests/data/otter-example (900 s, GNSS 1 Hz, USBL 4.5 s): the first step
   (the bare model fitted from scratch: all fixes, thinned fixes, held-out predictions;
   score tests; refits until one candidate is confirmed; the others tested with it added)
   and the second step as ``--auto`` runs it (the base model is the first step's refit).
   Wall time and CPU time (this process and its forked workers), ``jobs`` 2 and 1.
2. A batch fit of a simulated 900-s ASV mission (GNSS every 8 s) with a hidden constant
   wind force: the built-in ``wind_drag`` (C++ kernel) against the same force written as a
   :class:`~aqfg.model.effects.UserEffect`, vectorised and per sample (numpy kernel,
   :mod:`aqfg.model.batched`), and a user linear drag against the built-in one.

The machine is shared (load average printed beside each figure): CPU times are the
steadier measure. Run: ``python experiments/bench_diagnosis.py [--repeat 3] [--quick]``;
writes ``experiments/results/bench_diagnosis.md``.
"""
from __future__ import annotations

import argparse
import os
import resource
import sys
import time
from pathlib import Path

import common as C
import numpy as np

from aqfg.data.io import load_mission
from aqfg.data.mission import with_gnss_every
from aqfg.diagnose.workflow import diagnose
from aqfg.fg.fit import fit_fg
from aqfg.model.effects import UserEffect
from aqfg.sim.simulator import simulate

DATA = Path(__file__).resolve().parents[1] / "tests" / "data"


def _cpu() -> float:
    a = resource.getrusage(resource.RUSAGE_SELF)
    b = resource.getrusage(resource.RUSAGE_CHILDREN)
    return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime


def _timed(fn):
    load = os.getloadavg()[0]
    w, c = time.perf_counter(), _cpu()
    out = fn()
    return out, time.perf_counter() - w, _cpu() - c, load


def _wind_vec(v, R, d, tm, q):
    out = np.zeros((len(v), 3))
    out[:, 0], out[:, 1] = q[0], q[1]
    return out


def _wind_one(v, R, d, tm, q):
    return np.array([q[0], q[1], 0.0])


def _drag_vec(v, R, d, tm, q):
    vb = np.einsum("nji,nj->ni", R, v)
    return -np.einsum("nij,nj->ni", R, np.array([q[0], q[1], q[1]]) * vb)


USER_WIND = UserEffect("user_wind", ("a_n", "a_e"), accel=_wind_vec, null=(0.0, 0.0),
                       lower=(-2.0, -2.0), upper=(2.0, 2.0), scale=(0.05, 0.05),
                       vectorized=True)
USER_WIND_ONE = UserEffect("user_wind", ("a_n", "a_e"), accel=_wind_one, null=(0.0, 0.0),
                           lower=(-2.0, -2.0), upper=(2.0, 2.0), scale=(0.05, 0.05))
USER_DRAG = UserEffect("user_drag", ("c_x", "c_yz"), accel=_drag_vec, null=(0.0, 0.0),
                       lower=(0.0, 0.0), upper=(10.0, 10.0), scale=(0.3, 0.3), vectorized=True)


def bench_step(repeat: int, jobs: int, duration: float | None) -> list[dict]:
    m = load_mission(DATA / "otter-example")
    rows = []
    for _ in range(repeat):
        d1, w1, c1, l1 = _timed(lambda: diagnose([m], jobs=jobs))
        best = d1.best
        d2, w2, c2, l2 = _timed(lambda best=best, d1=d1: diagnose(
            [m], effects=(best.effect,), jobs=jobs, base_eval=best.refit,
            base_screen=d1.next_screen))
        rows.append({"jobs": jobs, "step1_wall": w1, "step1_cpu": c1, "step1_load": l1,
                     "step2_wall": w2, "step2_cpu": c2, "step2_load": l2,
                     "found": (best.effect, d2.best.effect if d2.best else None),
                     "timings1": d1.timings, "timings2": d2.timings})
    return rows


def bench_user(repeat: int, duration: float) -> list[dict]:
    m, _ = simulate("asv", seed=3, duration=duration, effects={"wind_drag": [0.04, 0.03]})
    m = with_gnss_every(m, 8.0)
    md, _ = simulate("asv", seed=3, duration=duration,
                     effects={"linear_drag.c_x": 1.0, "linear_drag.c_yz": 0.5},
                     params={"s_x": 0.0, "s_y": 0.0})
    md = with_gnss_every(md, 8.0)
    cases = [("wind_drag (built-in, C++)", m, ("wind_drag",)),
             ("user wind, vectorized", m, (USER_WIND,)),
             ("user wind, per sample", m, (USER_WIND_ONE,)),
             ("linear_drag (built-in, C++)", md, ("linear_drag",)),
             ("user linear drag, vectorized", md, (USER_DRAG,))]
    out = []
    for label, mission, eff in cases:
        n = 1 if "per sample" in label else repeat
        ws, cs, its, loads = [], [], [], []
        for _ in range(n):
            r, w, c, ld = _timed(lambda mission=mission, eff=eff: fit_fg([mission], effects=eff))
            ws.append(w); cs.append(c); its.append(r.iterations); loads.append(ld)
        est = {k: round(float(v), 4) for k, v in r.values.items()
               if k.startswith(("wind_drag.", "user_wind.", "linear_drag.", "user_drag."))
               and k.split(".")[0] in [getattr(e, "name", e) for e in eff]}
        out.append({"case": label, "wall": float(np.median(ws)), "cpu": float(np.median(cs)),
                    "iterations": its[0], "load": float(np.median(loads)), "estimate": est,
                    "repeats": n})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="1 repeat, 300-s user-effect mission")
    args = ap.parse_args(argv)
    rep = 1 if args.quick else args.repeat
    dur = 300.0 if args.quick else 900.0
    t0 = time.perf_counter()
    steps = bench_step(rep, 2, None) + bench_step(1 if args.quick else max(1, rep - 1), 1, None)
    users = bench_user(rep, dur)
    L = ["# Diagnosis and user-effect benchmark", "",
         (f"`python experiments/bench_diagnosis.py{' --quick' if args.quick else ''}`; "
         f"{os.cpu_count()} CPUs, shared with other work (1-min load average at the start of "
         "each run in the table). CPU = this process and its worker processes."), "",
         "## One diagnosis step, otter-example (900 s, GNSS 1 Hz, USBL)", "",
         "| jobs | step 1: wall / CPU (s) | load | step 2: wall / CPU (s) | load | found |",
         "|---|---|---|---|---|---|"]
    for r in steps:
        L.append(f"| {r['jobs']} | {r['step1_wall']:.1f} / {r['step1_cpu']:.1f} | "
                 f"{r['step1_load']:.1f} | {r['step2_wall']:.1f} / {r['step2_cpu']:.1f} | "
                 f"{r['step2_load']:.1f} | {' then '.join(x or 'nothing' for x in r['found'])} |")
    t1 = steps[0]["timings1"]
    L += ["", "Step 1 wall time by phase (first run): " + ", ".join(
        f"{k} {v:.1f} s" for k, v in t1.items()), "",
        (f"## Fit with a user effect vs the same physics built in ({dur:.0f}-s ASV mission, "
        "GNSS every 8 s)"), "",
        "| model | wall (s, median) | CPU (s) | load | LM iterations | estimate | ratio to built-in (CPU) |",
        "|---|---|---|---|---|---|---|"]
    base = {"wind": users[0]["cpu"], "drag": users[3]["cpu"]}
    for u in users:
        b = base["drag" if "linear" in u["case"] else "wind"]
        L.append(f"| {u['case']} | {u['wall']:.2f} | {u['cpu']:.2f} | {u['load']:.1f} | "
                 f"{u['iterations']} | {u['estimate']} | {u['cpu'] / b:.1f}x |")
    L += ["", f"total {time.perf_counter() - t0:.0f} s"]
    text = "\n".join([C.stamp(argv), "", *L])
    print(text)
    if not args.quick:
        C.RESULTS.mkdir(parents=True, exist_ok=True)
        (C.RESULTS / "bench_diagnosis.md").write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
