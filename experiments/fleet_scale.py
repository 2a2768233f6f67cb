"""How the fleet solve (``aqfg fleet``, Dask) scales, and whether it equals the joint fit.

A simulated fleet (default 4 ASVs x 16 missions x 15 min, GNSS every 8 s; the vehicles'
thrust constants 0.85, 0.95, 1.05, 1.15 x nominal, as worn or loaded robots) is written to
a temporary directory first, then fitted:

1. sequentially in one process, per vehicle one ``BatchSmoother.run`` (the joint solve
   alone) and one ``fit_fg`` (the same steps as the fleet's: structural sigma, effect
   step, tracks): wall times and peak memory (a child process);
2. with ``fit_fleet`` (its dead-reckoning refinement off, ``FGSettings.batch.dr_horizon = 0``,
   as the sequential fits) on a ``LocalCluster`` of each ``--workers`` count up to the
   machine's cores: wall time, peak memory per worker, rounds, tasks, compute seconds per
   task (Dask's task stream) and bytes sent back;
3. the counts above the machine's cores projected by the cost model (below) from the
   1-worker run's per-task figures (the measured counts are projected too, beside their
   measurement);
4. one vehicle's missions as whole commands: ``aqfg fleet --workers 1`` over
   ``aqfg fit --no-plots`` (processes, wall times; same missions);
5. time per added mission: one vehicle's missions on 2 workers (slope);
6. agreement of the largest measured run with the sequential joint fits (|difference| /
   sigma over every vehicle's fixed parameters and every mission's own parameters);
7. a projection of 10,000 missions on 100 workers from the same cost model.

Run: ``python experiments/fleet_scale.py`` (``--workers 1,2,4,8,16`` by default; about
20 min on 2 shared cores); ``--quick``: 2 vehicles x 3 missions x 3 min. Writes
experiments/results/fleet_scale.md and fleet_scale_headline.md.
"""
from __future__ import annotations

import argparse
import logging
import math
import os
import resource
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from experiments.common import RESULTS, md_table, run_tasks, write_headline, write_md  # noqa: E402

K_SCALES = (0.85, 0.95, 1.05, 1.15)


# ---------------------------------------------------------------- the cost model
# The fleet solve's cost model: the wall time of ``fit_fleet``
# on W workers from figures measured on a run with fewer.
#
# Measured per run (Dask's task stream and ``FleetResult.stats``):
#
# * ``c_mission``: compute seconds per mission over the joint solve's rounds (its graph
#   built, every "sys"/"step" request, its result), the missions being of one size;
# * ``c_vehicle``: compute seconds of the one-per-vehicle tasks, per vehicle (the structural
#   sigma, the dead-reckoning constants, the final step), and ``c_track`` per mission (its
#   track smoothed under the noise its evidence chooses);
# * ``rounds``: rounds of the joint solve (the vehicles iterate in the same rounds);
# * ``o_task``: the scheduler's overhead per task (empty tasks on the same cluster), paid
#   once per worker and round, and once per one-off task;
# * ``reply_bytes``: bytes the workers send the client, at ``bandwidth`` bytes/s;
# * ``fixed``: what the 1-worker run spent outside all of that (the client's own work,
#   starting and releasing): its wall minus the model's other terms.
#
# The projection at W workers: missions spread evenly (``ceil(M / W)`` per worker, a round
# waits for the fullest), the per-vehicle and per-mission one-off tasks scheduled longest
# first on W workers, plus the overheads. It assumes W free cores (the measured runs on
# a shared machine did not have them: their rows say so).


@dataclass
class Costs:
    missions: int
    vehicles: int
    c_mission: float
    c_vehicle: float
    c_track: float
    rounds: int
    o_task: float
    reply_bytes: float
    fixed: float = 0.0
    bandwidth: float = 125e6        # 1 Gbit/s

    def parts(self, workers: int) -> dict[str, float]:
        """The projected wall of each part (s) on ``workers`` workers."""
        W, M, V = workers, self.missions, self.vehicles
        one_off = [self.c_vehicle] * V + [self.c_track] * M
        return {"missions' rounds": math.ceil(M / W) * self.c_mission,
                "per-vehicle and track tasks": makespan(one_off, W),
                "scheduler": (self.rounds * W + len(one_off)) * self.o_task,
                "replies": self.reply_bytes / self.bandwidth,
                "fixed": self.fixed}

    def wall(self, workers: int) -> float:
        return sum(self.parts(workers).values())


def makespan(durations: list[float], workers: int) -> float:
    """Longest-first list scheduling of ``durations`` on ``workers`` workers: the finish."""
    load = [0.0] * workers
    for d in sorted(durations, reverse=True):
        i = load.index(min(load))
        load[i] += d
    return max(load, default=0.0)


def task_seconds(stream: list[dict]) -> dict[str, list[float]]:
    """Compute seconds of a run's tasks (Dask's task stream) by kind: "round" (the joint
    solve's), "structural", "refine", "finish", "track", "mission" (a mission sent to
    another worker) and "other"."""
    out: dict[str, list[float]] = {}
    for t in stream:
        key = str(t.get("key"))
        parts = key.strip("()'\" ").split("-")
        kind = "other"
        if len(parts) >= 3 and parts[0].endswith("aqfg"):
            k = parts[2]
            kind = ("round" if k.isdigit() else "structural" if k.startswith("structural")
                    else "finish" if k.startswith("finish") else k)
        sec = sum(s["stop"] - s["start"] for s in t.get("startstops", ())
                  if s.get("action") == "compute")
        out.setdefault(kind, []).append(sec)
    return out


def costs_of(run: dict, missions: int, vehicles: int) -> Costs:
    """The model's figures from a measured run (``fleet_run``'s dict: ``fr``, ``wall``,
    ``overhead``, ``tasks`` from :func:`task_seconds`), ``fixed`` calibrated on it."""
    st = run["fr"].stats
    ts = run["tasks"]
    per_v = sum(sum(ts.get(k, [])) for k in ("structural", "refine", "finish"))
    c = Costs(missions=missions, vehicles=vehicles,
              c_mission=sum(ts.get("round", [])) / missions,
              c_vehicle=per_v / vehicles,
              c_track=sum(ts.get("track", [])) / missions,
              rounds=int(st["rounds"]), o_task=run["overhead"],
              reply_bytes=float(st["reply_bytes"]))
    workers = int(run["workers"])
    c.fixed = max(run["wall"] - c.wall(workers), 0.0)
    return c


def scaled(c: Costs, missions: int, vehicles: int) -> Costs:
    """The same missions' costs for a fleet of ``missions`` missions of ``vehicles``
    vehicles (per-vehicle work in proportion to missions per vehicle)."""
    per_v = c.c_vehicle * (missions / vehicles) / (c.missions / c.vehicles)
    return Costs(missions=missions, vehicles=vehicles, c_mission=c.c_mission,
                 c_vehicle=per_v, c_track=c.c_track, rounds=c.rounds, o_task=c.o_task,
                 reply_bytes=c.reply_bytes * missions / c.missions, fixed=c.fixed)


# ---------------------------------------------------------------- the runs
def simulate_one(task) -> str:
    from aqfg.data.io import save_mission
    from aqfg.sim import simulate, true_params
    root, vehicle, seed, k_scale, duration, gnss = task
    m, tr = simulate("asv", seed=seed, duration=duration, gnss_period=gnss,
                     params={"k": k_scale * true_params("asv")["k"]})
    m.name = f"{vehicle}-m{seed:04d}"
    return str(save_mission(m, Path(root) / vehicle / m.name, truth=tr))


def sequential(paths_by_vehicle: dict) -> dict:
    """Per vehicle in this (child) process, one BatchSmoother.run and one fit_fg (the
    fleet's steps, its settings): results, times (missions read included), peak RSS."""
    from aqfg.data.io import load_mission
    from aqfg.fg import fit_fg
    from aqfg.fg.batch import BatchSmoother
    from aqfg.fg.settings import FGSettings
    out, per = {}, {}
    t_batch = t_fit = 0.0
    for v, paths in paths_by_vehicle.items():
        t = time.perf_counter()
        r = BatchSmoother().run([load_mission(p) for p in paths])
        per[v] = time.perf_counter() - t
        t_batch += per[v]
        out[v] = {"values": r.values, "sigma": r.sigma, "per_mission": r.per_mission,
                  "iterations": r.iterations}
        t = time.perf_counter()
        fit_fg([load_mission(p) for p in paths], settings=FGSettings().with_(batch={"dr_horizon": 0.0}))
        t_fit += time.perf_counter() - t
    return {"results": out, "seconds": t_batch, "fit_seconds": t_fit, "per_vehicle": per,
            "peak": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024}


def in_child(fn, arg):
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor
    with ProcessPoolExecutor(1, mp_context=mp.get_context("spawn")) as ex:
        return ex.submit(fn, arg).result()


def noop(i):
    return i


def fleet_run(manifest_path: Path, workers: int) -> dict:
    from distributed import Client, LocalCluster, get_task_stream

    from aqfg.fg.settings import FGSettings
    from aqfg.fleet import fit_fleet, load_manifest
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                      dashboard_address=None, silence_logs=logging.ERROR) as lc, Client(lc) as c:
        c.wait_for_workers(workers)
        t0 = time.perf_counter()
        # the dead-reckoning refinement off, as the sequential fits it is compared with
        with get_task_stream(c) as ts:
            fr = fit_fleet(load_manifest(manifest_path), c, progress=True,
                           settings=FGSettings().with_(batch={"dr_horizon": 0.0}))
        wall = time.perf_counter() - t0
        # the scheduler's overhead per task: 2000 empty tasks
        t1 = time.perf_counter()
        c.gather(c.map(noop, range(2000), pure=False))
        overhead = (time.perf_counter() - t1) / 2000
    return {"fr": fr, "wall": wall, "overhead": overhead, "workers": workers,
            "tasks": task_seconds(ts.data)}


def commands(tmp: Path, paths: list[str]) -> dict:
    """One vehicle's missions as whole commands (processes, wall s): ``aqfg fit
    --no-plots`` of them jointly, and ``aqfg fleet`` of a one-vehicle manifest on 1 and
    on 2 workers."""
    import subprocess

    from aqfg.fleet import write_manifest
    man = write_manifest(tmp / "one.toml", {"one": [str(Path(p).relative_to(tmp)) for p in paths]})
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    runs = {"fit": ["fit", "--no-plots", *paths], "fleet1": ["fleet", "--workers", "1", str(man)],
            "fleet2": ["fleet", "--workers", "2", str(man)]}
    out = {}
    for name, argv in runs.items():
        t = time.perf_counter()
        subprocess.run([sys.executable, "-m", "aqfg", *argv[:1], "-q", "--out",
                        str(tmp / f"cmd-{name}"), *argv[1:]], check=True, env=env, cwd=ROOT)
        out[name] = time.perf_counter() - t
    return out


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
                got = r.per_mission[m][n].value
                worst_m = max(worst_m, abs(got - e.value) / e.sigma)
    return worst_f, worst_m


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--vehicles", type=int, default=4)
    ap.add_argument("--missions", type=int, default=16, help="per vehicle")
    ap.add_argument("--duration", type=float, default=900.0, help="s per mission")
    ap.add_argument("--gnss-period", type=float, default=8.0)
    ap.add_argument("--quick", action="store_true", help="2 vehicles x 3 missions x 180 s")
    ap.add_argument("--workers", default="1,2,4,8,16",
                    help="worker counts, comma-separated: those up to the machine's cores "
                         "measured, the others projected (1 is always measured)")
    ap.add_argument("--out", default=str(RESULTS))
    args = ap.parse_args(argv)
    args.seeds, args.jobs = None, 2
    try:
        args.worker_counts = sorted({1, *(int(w) for w in args.workers.split(","))})
    except ValueError:
        ap.error(f"--workers: comma-separated whole numbers, not {args.workers!r}")
    if min(args.worker_counts) < 1:
        ap.error("--workers: counts of at least 1")
    args.cores = os.cpu_count() or 1
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
        for w in args.worker_counts:
            if w <= args.cores:
                print(f"fleet on {w} worker(s) ...", file=sys.stderr)
                runs[w] = fleet_run(man, w)
        print("one vehicle as commands: aqfg fit, aqfg fleet ...", file=sys.stderr)
        cmds = commands(tmp, by_v[names[0]])
        # time per added mission: one vehicle, growing, on 2 workers
        sizes = sorted({max(2, args.missions // 5), max(3, args.missions // 2), args.missions})
        grow = []
        for n in sizes:
            mp_ = write_manifest(tmp / f"grow-{n}.toml",
                                 {names[0]: [str(Path(p).relative_to(tmp)) for p in by_v[names[0]][:n]]})
            grow.append((n, fleet_run(mp_, 2)["wall"]))
        slope = float(np.polyfit([g[0] for g in grow], [g[1] for g in grow], 1)[0])
        args.load_after = os.getloadavg()[0]
        body = report(args, names, seq, runs, grow, slope, t_sim, cmds)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    write_md(Path(args.out), "fleet_scale", "Fleet solve on Dask: scaling and agreement",
             body, args, started)
    head = body.split("\n\n## ")[0]
    write_headline(Path(args.out), "fleet_scale", head, args)
    return 0


def report(args, names, seq, runs, grow, slope, t_sim, cmds) -> str:
    n_m = args.vehicles * args.missions
    top = max(runs)
    rt = runs[top]

    def peak(r):
        mem = r["fr"].stats.get("memory", {})
        return max((m["peak"] for m in mem.values()), default=float("nan")) / 2**20
    rows = [["sequential `BatchSmoother.run` per vehicle (the joint solve alone)",
             f"{seq['seconds']:.1f}", "1.00", "-", f"{seq['peak'] / 2**20:.0f}", "-", "(reference)"],
            ["sequential `fit_fg` per vehicle (the fleet's steps)", f"{seq['fit_seconds']:.1f}",
             f"{seq['seconds'] / seq['fit_seconds']:.2f}", "1.00", "-", "-", "-"]]
    for w, r in sorted(runs.items()):
        st = r["fr"].stats
        fe, me = agreement(r["fr"], seq)
        rows.append([f"`fit_fleet`, LocalCluster of {w} worker process(es)", f"{r['wall']:.1f}",
                     f"{seq['seconds'] / r['wall']:.2f}", f"{seq['fit_seconds'] / r['wall']:.2f}",
                     f"{peak(r):.0f}", f"{st['rounds']} / {st['tasks']}", f"{fe:.1e} / {me:.1e}"])
    st = rt["fr"].stats
    by = st["by_op"]                                  # op -> [tasks, seconds, reply bytes]
    iters = {v: rt["fr"].results[v].iterations for v in names}
    seq_it = {v: seq["results"][v]["iterations"] for v in names}
    c1 = costs_of(runs[1], n_m, args.vehicles)
    # ---- the worker counts: measured where the machine has the cores, all projected
    scale_rows = []
    for w in args.worker_counts:
        meas = f"{runs[w]['wall']:.1f}" if w in runs else "-"
        scale_rows.append([w, "measured" if w in runs else "projected", meas,
                           f"{c1.wall(w):.1f}"])
    c64 = scaled(c1, 64, 4)
    w_lo, w_hi = 2, 16
    s64 = c64.wall(w_lo) / c64.wall(w_hi)
    proj_rows = [[w, f"{c64.wall(w):.1f}",
                  " / ".join(f"{v:.1f}" for v in c64.parts(w).values())] for w in args.worker_counts]
    ratio1 = cmds["fleet1"] / cmds["fit"]
    ratio2 = cmds["fleet2"] / cmds["fit"]
    # ---- 10,000 missions on 100 workers
    big = scaled(c1, 10_000, 100)
    by_rows = "\n".join(f"| {op} | {v[0]} | {1e3 * v[1] / v[0]:.1f} | {v[2] / v[0]:.0f} |"
                        for op, v in by.items())
    tk = runs[1]["tasks"]
    task_rows = "\n".join(f"| {k} | {len(v)} | {1e3 * sum(v) / max(len(v), 1):.1f} |"
                          for k, v in sorted(tk.items()))
    return f"""
{args.vehicles} simulated ASVs x {args.missions} missions x {args.duration / 60:.0f} min
(GNSS every {args.gnss_period:.0f} s; {n_m} missions), thrust constants
{', '.join(f'{k:.2f}' for k in K_SCALES[:args.vehicles])} x nominal. The machine:
{args.cores} cores, shared; its 1-minute load average (`uptime`) before / after the run:
{args.load_before:.1f} / {args.load_after:.1f}. Where the load exceeds the cores, other work
shared them and the wall times are upper bounds; the ratios below come from this one run.

{md_table(["run", "wall s", "speed-up vs `BatchSmoother.run`", "speed-up vs `fit_fg`",
           "peak MB (per worker)", "rounds / tasks (one per worker and round)",
           "max abs diff / sigma vs the joint solve: fixed / missions' own"], rows)}

1 worker vs the sequential `fit_fg` (the same steps): **{seq['fit_seconds'] / runs[1]['wall']:.2f}x**
the speed. Iterations per vehicle, fleet / sequential (the same Levenberg-Marquardt
iterates): {', '.join(f'{v} {iters[v]}/{seq_it[v]}' for v in names)}.

## One vehicle as whole commands

{args.missions} missions of {names[0]} (processes, wall s, start-up and outputs included):
`aqfg fit --no-plots` {cmds['fit']:.1f}; `aqfg fleet --workers 1` {cmds['fleet1']:.1f}
(**{ratio1:.2f}x** the fit's wall); `aqfg fleet --workers 2` {cmds['fleet2']:.1f}
({ratio2:.2f}x).

## Worker counts: measured and projected

The cost model (in `experiments/fleet_scale.py`) from the 1-worker run's figures: per mission
{c1.c_mission:.2f} s of compute in the joint solve's rounds, {c1.c_track:.2f} s for its track;
per vehicle {c1.c_vehicle:.2f} s (structural sigma, dead-reckoning constants, final step);
{c1.rounds} rounds; {1e3 * c1.o_task:.2f} ms scheduler overhead per task; {c1.fixed:.1f} s
outside those (the 1-worker run's calibration). A projection assumes as many free cores
as workers; a measured row on a shared machine did not have them.

{md_table(["workers", "row", f"measured wall s ({n_m} missions)", "model wall s"], scale_rows)}

64 missions (4 vehicles x 16 of this kind), projected (parts: missions' rounds /
per-vehicle and track tasks / scheduler / replies / fixed, s):

{md_table(["workers", "projected wall s", "parts"], proj_rows)}

From {w_lo} to {w_hi} workers on 64 missions: **{s64:.1f}x** (projected).

## Time per added mission

One vehicle's first n missions on 2 workers (wall s):
{', '.join(f'n={n}: {t:.1f}' for n, t in grow)}; slope **{slope:.2f} s per added mission**.

## Cost per task and communication ({top}-worker run)

| request | missions served | compute ms per mission (mean) | bytes back per mission |
|---|---|---|---|
{by_rows}

Tasks of the 1-worker run by kind (Dask's task stream):

| kind | tasks | compute ms per task (mean) |
|---|---|---|
{task_rows}

"open" builds the mission's graph from its path; "sys" returns its damped Schur complement
on the fixed node (3 x 3 here), "step" back-substitutes the locals and returns the
candidate's cost, "result" returns tracks, inertial re-trace and residuals. Requests:
{st['request_bytes'] / max(st['tasks'], 1):.0f} B per task. The scheduler's overhead per task
(2000 empty tasks on the same cluster): {1e3 * rt['overhead']:.2f} ms.

## Projection: 10,000 missions on 100 workers

100 vehicles x 100 missions of this kind, the cost model above: **{big.wall(100) / 60:.0f} min**
(parts, s: {' / '.join(f'{k} {v:.0f}' for k, v in big.parts(100).items())}). A round waits
for its slowest worker, so the estimate assumes missions of similar length spread evenly.
Simulating the missions took {t_sim:.0f} s (not included above).
"""


if __name__ == "__main__":
    sys.exit(main())
