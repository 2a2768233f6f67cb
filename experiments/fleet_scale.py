"""How the fleet solve (``aqfg fleet``, Dask) scales, and whether it equals the joint fit.

A simulated fleet (default 4 ASVs x 25 missions x 15 min, GNSS every 8 s; the vehicles'
thrust constants 0.85, 0.95, 1.05, 1.15 x nominal, as worn or loaded robots) is written to
a temporary directory first, then fitted:

1. sequentially in one process, one ``BatchSmoother.run`` per vehicle (``aqfg fit`` of
   each vehicle's missions): wall time and peak memory (a child process);
2. with ``fit_fleet`` (its dead-reckoning refinement off, ``FGSettings.batch.dr_horizon = 0``:
   the joint solve is what is compared) on a ``LocalCluster`` of 1 and of 2 worker processes: wall time,
   peak memory per worker, rounds, tasks, compute seconds per task and bytes sent back;
3. time per added mission: one vehicle's 5, 10, ... missions on 2 workers (slope);
4. agreement of the 2-worker run with the sequential joint fits (|difference| / sigma
   over every vehicle's fixed parameters and every mission's own parameters);
5. a projection of 10,000 missions on 100 workers from the measured per-task compute,
   the number of rounds, the reply sizes and the scheduler's per-task overhead (measured
   with empty tasks on the same cluster).

Run: ``python experiments/fleet_scale.py`` (about 30 min on 2 shared cores);
``--quick``: 2 vehicles x 3 missions x 3 min. Writes experiments/results/fleet_scale.md
and fleet_scale_headline.md.
"""
from __future__ import annotations

import argparse
import logging
import os
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from experiments.common import RESULTS, md_table, run_tasks, write_headline, write_md  # noqa: E402

K_SCALES = (0.85, 0.95, 1.05, 1.15)


def simulate_one(task) -> str:
    from aqfg.data.io import save_mission
    from aqfg.sim import simulate, true_params
    root, vehicle, seed, k_scale, duration, gnss = task
    m, tr = simulate("asv", seed=seed, duration=duration, gnss_period=gnss,
                     params={"k": k_scale * true_params("asv")["k"]})
    m.name = f"{vehicle}-m{seed:04d}"
    return str(save_mission(m, Path(root) / vehicle / m.name, truth=tr))


def sequential(paths_by_vehicle: dict) -> dict:
    """One BatchSmoother.run per vehicle in this (child) process: results, time, peak RSS."""
    from aqfg.data.io import load_mission
    from aqfg.fg.batch import BatchSmoother
    t0 = time.perf_counter()
    out, per = {}, {}
    for v, paths in paths_by_vehicle.items():
        t = time.perf_counter()
        r = BatchSmoother().run([load_mission(p) for p in paths])
        per[v] = time.perf_counter() - t
        out[v] = {"values": r.values, "sigma": r.sigma, "per_mission": r.info["per_mission"],
                  "iterations": r.iterations}
    return {"results": out, "seconds": time.perf_counter() - t0, "per_vehicle": per,
            "peak": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024}


def in_child(fn, arg):
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor
    with ProcessPoolExecutor(1, mp_context=mp.get_context("spawn")) as ex:
        return ex.submit(fn, arg).result()


def noop(i):
    return i


def fleet_run(manifest_path: Path, workers: int) -> dict:
    from distributed import Client, LocalCluster

    from aqfg.fg.settings import FGSettings
    from aqfg.fleet import fit_fleet, load_manifest
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                      dashboard_address=None, silence_logs=logging.ERROR) as lc, Client(lc) as c:
        t0 = time.perf_counter()
        # the joint solve alone, as the sequential BatchSmoother.run it is compared with
        # (the dead-reckoning refinement after it is one task per vehicle)
        fr = fit_fleet(load_manifest(manifest_path), c, progress=True,
                       settings=FGSettings().with_(batch={"dr_horizon": 0.0}))
        wall = time.perf_counter() - t0
        # the scheduler's overhead per task: 2000 empty tasks
        t1 = time.perf_counter()
        c.gather(c.map(noop, range(2000), pure=False))
        overhead = (time.perf_counter() - t1) / 2000
    return {"fr": fr, "wall": wall, "overhead": overhead}


def agreement(fr, seq) -> tuple[float, float]:
    """max |fleet - joint| / sigma over the fixed parameters, and over the missions' own."""
    worst_f, worst_m = 0.0, 0.0
    for v, s in seq["results"].items():
        r = fr.results[v]
        local = {n for pm in s["per_mission"].values() for n in pm}
        for n, x in s["values"].items():
            if n in s["sigma"] and n not in local:
                worst_f = max(worst_f, abs(r.values[n] - x) / s["sigma"][n])
        for m, pm in s["per_mission"].items():
            for n, e in pm.items():
                got = r.info["per_mission"][m][n]["value"]
                worst_m = max(worst_m, abs(got - e["value"]) / e["sigma"])
    return worst_f, worst_m


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--vehicles", type=int, default=4)
    ap.add_argument("--missions", type=int, default=25, help="per vehicle")
    ap.add_argument("--duration", type=float, default=900.0, help="s per mission")
    ap.add_argument("--gnss-period", type=float, default=8.0)
    ap.add_argument("--quick", action="store_true", help="2 vehicles x 3 missions x 180 s")
    ap.add_argument("--out", default=str(RESULTS))
    args = ap.parse_args(argv)
    args.seeds, args.jobs = None, 2
    if args.quick:
        args.vehicles, args.missions, args.duration = 2, 3, 180.0
    started = time.perf_counter()
    args.load_before = os.getloadavg()[0]
    from aqfg.fleet import write_manifest
    tmp = Path(tempfile.mkdtemp(prefix="aqfg-fleet-"))
    try:
        names = [f"asv-{i + 1}" for i in range(args.vehicles)]
        tasks = [(str(tmp), v, 1000 * (i + 1) + j, K_SCALES[i % len(K_SCALES)], args.duration,
                  args.gnss_period) for i, v in enumerate(names) for j in range(args.missions)]
        t = time.perf_counter()
        paths = run_tasks(simulate_one, tasks, jobs=2, label="simulate")
        t_sim = time.perf_counter() - t
        by_v = {v: [p for p in paths if Path(p).parent.name == v] for v in names}
        man = write_manifest(tmp / "fleet.toml", {v: [str(Path(p).relative_to(tmp)) for p in ps]
                                                  for v, ps in by_v.items()})
        print("sequential joint fits ...", file=sys.stderr)
        seq = in_child(sequential, by_v)
        runs = {}
        for w in (1, 2):
            print(f"fleet on {w} worker(s) ...", file=sys.stderr)
            runs[w] = fleet_run(man, w)
        # time per added mission: one vehicle, growing, on 2 workers
        sizes = sorted({max(2, args.missions // 5), max(3, args.missions // 2), args.missions})
        grow = []
        for n in sizes:
            mp_ = write_manifest(tmp / f"grow-{n}.toml",
                                 {names[0]: [str(Path(p).relative_to(tmp)) for p in by_v[names[0]][:n]]})
            grow.append((n, fleet_run(mp_, 2)["wall"]))
        slope = float(np.polyfit([g[0] for g in grow], [g[1] for g in grow], 1)[0])
        args.load_after = os.getloadavg()[0]
        body = report(args, names, seq, runs, grow, slope, t_sim)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    write_md(Path(args.out), "fleet_scale", "Fleet solve on Dask: scaling and agreement",
             body, args, started)
    head = body.split("\n\n## ")[0]
    write_headline(Path(args.out), "fleet_scale", head, args)
    return 0


def report(args, names, seq, runs, grow, slope, t_sim) -> str:
    n_m = args.vehicles * args.missions
    r1, r2 = runs[1], runs[2]

    def peak(r):
        mem = r["fr"].stats.get("memory", {})
        return max((m["peak"] for m in mem.values()), default=float("nan")) / 2**20
    rows = [["sequential joint fits (1 process, `BatchSmoother.run` per vehicle)",
             f"{seq['seconds']:.0f}", "1.00", f"{seq['peak'] / 2**20:.0f}", "-", "(reference)"]]
    for w in (1, 2):
        r = runs[w]
        st = r["fr"].stats
        fe, me = agreement(r["fr"], seq)
        rows.append([f"`fit_fleet`, LocalCluster of {w} worker process(es)", f"{r['wall']:.0f}",
                     f"{seq['seconds'] / r['wall']:.2f}", f"{peak(r):.0f}",
                     f"{st['rounds']} / {st['tasks']}", f"{fe:.1e} / {me:.1e}"])
    st = r2["fr"].stats
    by = st["by_op"]                                  # op -> [tasks, seconds, reply bytes]
    iters = {v: r2["fr"].results[v].iterations for v in names}
    seq_it = {v: seq["results"][v]["iterations"] for v in names}
    it_tasks = sum(by[o][0] for o in ("sys", "step") if o in by)
    t_iter = sum(by[o][1] for o in ("sys", "step") if o in by) / max(it_tasks, 1)
    b_iter = sum(by[o][2] for o in ("sys", "step") if o in by) / max(it_tasks, 1)
    t_open = by["open"][1] / by["open"][0]
    t_res = by["result"][1] / by["result"][0]
    b_res = by["result"][2] / by["result"][0]
    rounds = st["rounds"]
    it_rounds = rounds - 2                            # all but "open" and "result"
    # ---- projection: 10,000 missions (100 vehicles x 100) on 100 workers
    N, W = 10_000, 100
    per_worker = N / W
    overhead = r2["overhead"]
    t_compute = per_worker * (t_open + it_rounds * t_iter + t_res)
    t_sched = rounds * W * overhead                  # one task per worker and round
    t_results = N * b_res / 125e6                     # 1 Gbit/s into the client
    # the client's own work per mission and round (summing, stepping, bookkeeping)
    client_per_mission = st["client_seconds"] / max(rounds * n_m, 1)
    t_client = rounds * N * client_per_mission
    proj = t_compute + t_sched + t_results + t_client
    return f"""
{args.vehicles} simulated ASVs x {args.missions} missions x {args.duration / 60:.0f} min
(GNSS every {args.gnss_period:.0f} s; {n_m} missions), thrust constants
{', '.join(f'{k:.2f}' for k in K_SCALES[:args.vehicles])} x nominal. The machine's 1-minute
load average ({os.cpu_count()} cores) before / after the run: {args.load_before:.1f} /
{args.load_after:.1f}; above the worker count, other work shared the cores and the wall
times are upper bounds.

{md_table(["run", "wall s", "speed-up vs sequential", "peak MB (per worker)",
           "rounds / tasks (one per worker and round)",
           "max abs diff / sigma vs the joint fit: fixed / missions' own"], rows)}

2 workers vs 1 worker: **{r1['wall'] / r2['wall']:.2f}x** faster. Iterations per vehicle,
fleet / sequential (the same Levenberg-Marquardt iterates):
{', '.join(f'{v} {iters[v]}/{seq_it[v]}' for v in names)}.

## Time per added mission

One vehicle's first n missions on 2 workers (wall s):
{', '.join(f'n={n}: {t:.1f}' for n, t in grow)}; slope **{slope:.2f} s per added mission**.

## Cost per task and communication (2-worker run)

| task | tasks | compute ms per task (mean) | bytes back per task |
|---|---|---|---|
{chr(10).join(f"| {op} | {v[0]} | {1e3 * v[1] / v[0]:.1f} | {v[2] / v[0]:.0f} |" for op, v in by.items())}

"open" builds the mission's graph from its path; "sys" returns its damped Schur complement
on the fixed node (3 x 3 here), "step" back-substitutes the locals and returns the
candidate's cost, "result" returns tracks, inertial re-trace and residuals. Requests:
{st['request_bytes'] / max(st['tasks'], 1):.0f} B per task. The scheduler's overhead per task
(2000 empty tasks on the same cluster): {1e3 * overhead:.2f} ms.

## Projection: 10,000 missions on 100 workers

100 vehicles x 100 missions of this kind, {rounds} rounds as measured (the vehicles iterate
in the same rounds; the slowest sets the count), {per_worker:.0f} missions per worker:

| part | estimate |
|---|---|
| compute per worker: missions x (build + {it_rounds} rounds x {1e3 * t_iter:.0f} ms + result) \
| {t_compute:.0f} s |
| scheduler: {rounds} rounds x {W} tasks (one per worker) x {1e3 * overhead:.2f} ms | {t_sched:.0f} s |
| the client: {rounds} rounds x 10,000 missions x {1e3 * client_per_mission:.2f} ms | {t_client:.0f} s |
| results into the client at 1 Gbit/s ({b_res / 1e3:.0f} kB per mission) | {t_results:.0f} s |
| **total** | **{proj / 60:.0f} min** |

While iterating, 10,000 replies of {b_iter:.0f} B are {N * b_iter / 1e6:.1f} MB per round
into the client. A round waits for its slowest worker, so the estimate assumes missions of
similar length spread evenly. Simulating the missions
took {t_sim:.0f} s (not included above).
"""


if __name__ == "__main__":
    sys.exit(main())
