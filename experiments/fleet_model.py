"""The fleet solve's cost model (experiments/fleet_scale.py): the wall time of ``fit_fleet``
on W workers from figures measured on a run with fewer.

Measured per run (Dask's task stream and ``FleetResult.stats``):

* ``c_mission``: compute seconds per mission over the joint solve's rounds (its graph
  built, every "sys"/"step" request, its result), the missions being of one size;
* ``c_vehicle``: compute seconds of the one-per-vehicle tasks, per vehicle (the structural
  sigma, the dead-reckoning constants, the final step), and ``c_track`` per mission (its
  track smoothed under the noise its evidence chooses);
* ``rounds``: rounds of the joint solve (the vehicles iterate in the same rounds);
* ``o_task``: the scheduler's overhead per task (empty tasks on the same cluster), paid
  once per worker and round, and once per one-off task;
* ``reply_bytes``: bytes the workers send the client, at ``bandwidth`` bytes/s;
* ``fixed``: what the 1-worker run spent outside all of that (the client's own work,
  starting and releasing): its wall minus the model's other terms.

The projection at W workers: missions spread evenly (``ceil(M / W)`` per worker, a round
waits for the fullest), the per-vehicle and per-mission one-off tasks scheduled longest
first on W workers, plus the overheads. It assumes W free cores (the measured runs on
a shared machine did not have them: their rows say so).
"""
from __future__ import annotations

import math
from dataclasses import dataclass


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
