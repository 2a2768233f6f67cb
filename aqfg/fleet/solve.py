"""Every vehicle's joint fit on Dask: the client runs each vehicle's Levenberg-Marquardt
loop (:func:`aqfg.fg.schur.joint_lm`) and the workers hold the missions.

Each round, every vehicle still iterating asks all its missions for the same operation; the
rounds of all vehicles go out together as one task per mission, pinned to the worker that
holds the mission's session (first come: spread evenly). A worker that dies has its tasks
re-run elsewhere by Dask; the new worker rebuilds the mission from its path and the loop
goes on (see :class:`aqfg.fg.schur.MissionSession`).
"""
from __future__ import annotations

import functools
import os
import time
import uuid
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from aqfg.fg.fit import auto_effect_applies
from aqfg.fg.schur import Solution, combine, joint_lm
from aqfg.fg.settings import FGSettings
from aqfg.fleet.cluster import FleetError, fleet_client
from aqfg.fleet.manifest import Manifest
from aqfg.fleet.worker import (
    MissionSpec,
    diagnose_op,
    finish_op,
    load,
    memory,
    missions_op,
    refine_op,
    release,
    release_fit,
    structural_op,
    track_op,
)
from aqfg.result import Result

WORKER_WAIT = 60.0      # s a round waits for a worker to (re)join before the run fails
__all__ = ["FleetError", "FleetResult", "fit_fleet"]


@dataclass
class FleetResult:
    """Each vehicle's joint fit (a :class:`Result` shaped as ``BatchSmoother.run``'s) and
    how the run went."""
    manifest: Manifest
    results: dict[str, Result]
    diagnosis: dict[str, dict[str, dict]] = field(default_factory=dict)  # vehicle -> mission
    stats: dict = field(default_factory=dict)


def fit_fleet(manifest: Manifest, client=None, *, workers: int = 2,
              scheduler: str | None = None, settings: FGSettings | None = None,
              effects: Sequence = (), estimate: Sequence[str] | None = None,
              init: dict | None = None, gnss_every: float = 0.0, diagnose: bool = False,
              progress=None, timeout: float | None = None) -> FleetResult:
    """Fit every vehicle of ``manifest`` (its fixed parameters shared by its missions)
    on Dask; equal to ``fit_fg(missions)`` per vehicle (``BatchSmoother(...).run`` and the
    dead-reckoning refinement of the constants, ``settings.batch.dr_horizon``).

    ``client``: a ``dask.distributed.Client``; without one, a client of the scheduler at
    ``scheduler`` or of a new ``LocalCluster`` of ``workers`` processes (one thread each)
    is made for the call and closed after it. ``gnss_every``: keep one GNSS fix every so
    many seconds (``aqfg fit --gnss-every``). ``diagnose``: also run each mission's
    diagnosis (``aqfg diagnose`` on it alone). ``progress``: as for the smoothers (True:
    a line on stderr). ``timeout``: seconds a round may take before the run fails.
    """
    from aqfg.fg.common import progress_fn
    show = progress_fn(progress)
    if client is None:          # a client (and cluster) made here is closed here
        with fleet_client(workers, scheduler) as made:
            return fit_fleet(manifest, made, settings=settings, effects=effects,
                             estimate=estimate, init=init, gnss_every=gnss_every,
                             diagnose=diagnose, progress=progress, timeout=timeout)
    return _fit(client, manifest, settings or FGSettings(), tuple(effects),
                None if estimate is None else tuple(estimate), dict(init or {}),
                float(gnss_every), diagnose, show, timeout)


def _fit(client, manifest, settings, effects, estimate, init, gnss_every, diagnose, show,
         timeout) -> FleetResult:
    # the missions the workers read are kept for this fit (aqfg.fleet.worker.load) and
    # dropped after it, whatever its end
    fit = uuid.uuid4().hex[:12]
    try:
        return _fit_steps(client, manifest, settings, effects, estimate, init, gnss_every,
                          diagnose, show, timeout, fit)
    finally:
        try:
            client.run(release_fit, fit)
        except Exception:  # noqa: BLE001 - a worker gone takes its missions with it
            pass


def _fit_steps(client, manifest, settings, effects, estimate, init, gnss_every, diagnose,
               show, timeout, fit: str) -> FleetResult:
    t0 = time.perf_counter()
    # stats: {by_op: {op: [missions served, compute seconds, reply bytes]}, ...}
    stats: dict[str, Any] = {"rounds": 0, "tasks": 0, "rebuilt": 0, "task_seconds": 0.0,
                             "reply_bytes": 0, "request_bytes": 0, "round_seconds": []}
    # (vehicle, mission index) -> the worker that holds it: where it was read, for every
    # solve and per-vehicle step of the fit
    where: dict[tuple, str] = {}
    specs, results, tracks = _solve_fleet(client, manifest, settings, effects, estimate,
                                          init, gnss_every, show, timeout, stats,
                                          refit=not auto_effect_applies(settings, estimate),
                                          fit=fit, where=where)
    if auto_effect_applies(settings, estimate):
        specs, results, tracks = fleet_effect(client, manifest, settings, effects, init,
                                              gnss_every, show, timeout, stats, specs, results,
                                              tracks, fit=fit, where=where)
    if settings.batch.dr_horizon > 0 or settings.batch.adapt_track:
        # the constants to dead-reckon with, per vehicle over its missions, and the
        # missions' tracks under the noise their evidence chooses, as aqfg fit does
        # (aqfg.fg.dead_reckoning, FGSettings.batch.adapt_track): once, for the fits returned
        show(0.99, f"dead-reckoning constants and tracks of {len(results)} vehicles")
        t_dr = time.perf_counter()
        results = _finish(client, specs, results, tracks, timeout, where)
        stats["dead_reckoning_seconds"] = time.perf_counter() - t_dr
    stats["memory"] = _memory(client)
    stats["workers"] = len(_workers(client))
    diag = {}
    if diagnose:
        show(0.99, f"diagnosing {manifest.n_missions} missions")
        diag = _diagnose(client, specs, timeout, where)
    stats["seconds"] = time.perf_counter() - t0
    show(1.0, f"done: {len(results)} vehicles, {manifest.n_missions} missions, "
              f"{stats['rounds']} rounds, {stats['seconds']:.1f} s")
    return FleetResult(manifest, results, diag, stats)


def _chunks(client, pending: dict, specs: dict, where: dict) -> dict[str, list]:
    """A round's requests by worker, ``worker -> [(vehicle, spec, op, args)]``: each mission
    on the worker that holds it (``where``, by vehicle and mission index); those held by
    none placed largest first on the worker holding the least data (``where`` updated), so
    that a round's workers finish together."""
    alive = _alive_workers(client)
    size = {spec.key[1:]: _mission_bytes(spec.path) for v in pending for spec in specs[v]}
    place = [spec for v in pending for spec in specs[v] if where.get(spec.key[1:]) not in alive]
    for spec in sorted(place, key=lambda sp: -size[sp.key[1:]]):
        where[spec.key[1:]] = _least_loaded(alive, where, size)
    chunks: dict[str, list] = {}               # worker -> [(vehicle, spec, op, args)]
    for v, reqs in pending.items():
        for spec, (op, args) in zip(specs[v], reqs):
            chunks.setdefault(where[spec.key[1:]], []).append((v, spec, op, args))
    return chunks


@functools.lru_cache(maxsize=4096)
def _mission_bytes(path: str) -> int:
    """A mission's size on disk (bytes; its directory's files, or the file), what its
    solve's cost grows with; 1 where it cannot be read here (the workers read it)."""
    try:
        if os.path.isdir(path):
            return max(sum(e.stat().st_size for e in os.scandir(path) if e.is_file()), 1)
        return max(os.path.getsize(path), 1)
    except OSError:
        return 1


def _gather(futs: dict, timeout, stats: dict, show, iters: dict, gens: dict,
            sols: dict) -> dict:
    """A round's replies by mission key as its tasks complete (progress shown per task);
    :class:`FleetError` naming the missions of a task that failed or timed out."""
    from distributed import as_completed
    n_round = sum(len(items) for items in futs.values())
    done = 0
    replies: dict = {}
    try:
        for fut in as_completed(list(futs), timeout=timeout):
            items = futs[fut]
            try:
                reps = fut.result()
            except Exception as e:             # re-raised with context
                names = ", ".join(f"{v}/{spec.name}" for v, spec, _, _ in items[:4])
                raise FleetError(f"a task for missions {names}"
                                 f"{' ...' if len(items) > 4 else ''} failed: "
                                 f"{type(e).__name__}: {e}") from e
            for (v, spec, _, _), r in zip(items, reps):
                if "error" in r:
                    raise FleetError(f"vehicle {v!r}, mission {spec.name!r} ({spec.path}): "
                                     f"{r['error']}")
                replies[spec.key] = r
            done += len(items)
            stats["tasks"] += 1
            its = ", ".join(f"{x} {iters[x]}" for x in gens if x not in sols)
            show(min(0.99, len(sols) / len(gens)),
                 f"round {stats['rounds']}: {done}/{n_round} missions done; "
                 f"iterations: {its or '-'}")
    except TimeoutError:
        raise FleetError(f"round {stats['rounds']} took longer than {timeout} s") from None
    return replies


def _advance(pending: dict, specs: dict, replies: dict, where: dict, built_once: set,
             stats: dict, gens: dict, sols: dict) -> dict:
    """Each vehicle's replies sent to its :func:`joint_lm` generator: its next requests, or
    its solution into ``sols`` when it has finished (the round's figures into ``stats``)."""
    new_pending = {}
    for v, reqs in pending.items():
        out = []
        for spec in specs[v]:
            r = replies[spec.key]
            where[spec.key[1:]] = r.pop("worker")
            if r.pop("built"):
                stats["rebuilt"] += spec.key in built_once
                built_once.add(spec.key)
            sec = r.pop("seconds")
            stats["task_seconds"] += sec
            by = stats.setdefault("by_op", {}).setdefault(reqs[0][0], [0, 0.0, 0])
            by[0] += 1
            by[1] += sec
            out.append(r)
        nbytes = _size(out)
        stats["by_op"][reqs[0][0]][2] += nbytes
        stats["reply_bytes"] += nbytes
        stats["request_bytes"] += _size(reqs)
        try:
            new_pending[v] = gens[v].send(out)
        except StopIteration as stop:
            sols[v] = stop.value
    return new_pending


def _solve_fleet(client, manifest, settings, effects, estimate, init, gnss_every, show,
                 timeout, stats: dict, refit: bool = False, fit: str = "",
                 where: dict | None = None) -> tuple[dict, dict[str, Result], dict[str, list]]:
    """Every vehicle's joint fit with the model ``effects``: the rounds of
    :func:`aqfg.fg.schur.joint_lm` on the workers, then per vehicle its structural sigma
    (one task each; the dead-reckoning constants and tracks come once, after the effect
    step, in :func:`_finish`). ``(specs, results, tracks)``, by vehicle (``tracks``: the
    missions' tracks their sessions smoothed under their evidence's noise, for the
    vehicles where every session made one); ``stats`` accumulates the
    run's figures, ``where`` (vehicle, mission index) -> worker. ``fit``: the fit_fleet call
    whose missions the workers keep."""
    run = uuid.uuid4().hex[:12]
    where = {} if where is None else where
    specs = {v.name: [MissionSpec(run, v.name, i, m.name, str(m.path), i == 0, settings,
                                  effects, estimate, init, gnss_every, refit, fit)
                      for i, m in enumerate(v.missions)] for v in manifest.vehicles}
    iters = {v: 0 for v in specs}

    def counter(v):
        def bump(msg: str) -> None:
            iters[v] += 1
        return bump
    gens = {v: joint_lm(len(ms), settings, counter(v)) for v, ms in specs.items()}
    pending = {v: next(g) for v, g in gens.items()}
    sols: dict[str, Solution] = {}
    built_once: set = set()
    while pending:
        stats["rounds"] += 1
        t_round = time.perf_counter()
        chunks = _chunks(client, pending, specs, where)
        futs = {client.submit(missions_op, [c[1:] for c in items], pure=False, workers=[w],
                              allow_other_workers=True, retries=2,
                              key=f"aqfg-{run}-{stats['rounds']}-{i}"): items
                for i, (w, items) in enumerate(chunks.items())}
        replies = _gather(futs, timeout, stats, show, iters, gens, sols)
        t_client = time.perf_counter()
        stats["round_seconds"].append(t_client - t_round)
        pending = _advance(pending, specs, replies, where, built_once, stats, gens, sols)
        stats["client_seconds"] = stats.get("client_seconds", 0.0) + time.perf_counter() - t_client
    client.run(release, run)
    results = {v: combine(sols[v]) for v in specs}
    made = {v: sols[v].tracks or [] for v in specs}
    tracks = {v: t for v, t in made.items() if t and all(x is not None for x in t)}
    effect_names = tuple(getattr(e, "name", e) for e in effects)
    for r in results.values():
        r.effects = effect_names               # the model's effects, for the outputs
    if settings.batch.structural_sigma:
        # the structural sigma, as aqfg fit's batch (FGSettings.batch.structural_sigma), whose
        # test the fleet's effect step reads: one task per vehicle
        t_st = time.perf_counter()
        results = _per_vehicle(client, structural_op, specs, results, timeout,
                               "the structural sigma", where,
                               lambda v, home: (results[v], _sent(client, specs[v], where, home)))
        stats["structural_seconds"] = (stats.get("structural_seconds", 0.0)
                                       + time.perf_counter() - t_st)
    return specs, results, tracks


def fleet_effect(client, manifest, settings, effects, init, gnss_every, show, timeout,
                 stats: dict, specs: dict, results: dict[str, Result], tracks: dict,
                 fit: str = "", where: dict | None = None
                 ) -> tuple[dict, dict[str, Result], dict[str, list]]:
    """:attr:`FGSettings.batch.auto_effect` for a fleet: where the vehicles' structural tests
    call for an effect of the vehicle's dynamics, every vehicle is fitted again with the
    one most of them call for (:func:`aqfg.fleet.effect.choose`); one model serves the
    fleet, so that its vehicles' constants compare. Kept where it lowers the fleet's cost,
    every vehicle's fit is plausible and every mission's heading offset and current stay
    within 3 sigma (:func:`aqfg.fleet.effect.judge`); otherwise the model as given, saying
    why. Each vehicle's ``effect_step`` records the step. Returns the chosen fits'
    ``(specs, results, tracks)`` (:func:`_solve_fleet`)."""
    from aqfg.fleet import effect as fe
    pick = fe.choose(results, effects)
    if pick is None:
        return specs, results, tracks
    show(0.99, f"the fits call for {pick['effect']}: every vehicle again with it")
    try:
        specs2, new, tracks2 = _solve_fleet(client, manifest, settings, (*effects, pick["effect"]),
                                   None, init, gnss_every, show, timeout, stats, refit=True,
                                   fit=fit, where=where)
    except FleetError as e:
        fe.record(results, pick, None, f"its fit failed ({e})")
        return specs, results, tracks
    why = fe.judge(results, new, pick["effect"])
    fe.record(results, pick, new, why)
    return (specs, results, tracks) if why else (specs2, new, tracks2)


def _finish(client, specs: dict, results: dict[str, Result], tracks: dict[str, list],
            timeout, where: dict) -> dict[str, Result]:
    """Every vehicle's final fit, as ``aqfg fit`` finishes its own: the dead-reckoning
    constants (:func:`refine_op`, on the worker that holds most of its missions), then
    :func:`finish_op` with each mission's track under the noise its evidence chooses: the
    one its session smoothed with the result (``tracks``), or else one smoothed where the
    mission is (:func:`track_op`, from the joint fit's parameters); Dask moves the replies
    between the workers."""
    def args(v: str, home: list[str] | None) -> tuple:
        spec0 = specs[v][0]
        refined = client.submit(refine_op, specs[v], results[v], pure=False, retries=2,
                                key=f"aqfg-{spec0.run}-refine-{v}", workers=home,
                                allow_other_workers=True)
        made = tracks.get(v)
        if spec0.settings.batch.adapt_track and made is None:
            made = [client.submit(track_op, s, mr.p, pure=False, retries=2,
                                  key=f"aqfg-{s.run}-track-{v}-{s.index}",
                                  workers=_home([s], where), allow_other_workers=True)
                    for s, mr in zip(specs[v], results[v].missions)]
        return refined, made
    return _per_vehicle(client, finish_op, specs, results, timeout,
                        "the dead-reckoning constants or tracks", where, args)


def _sent(client, specs: list[MissionSpec], where: dict, home: list[str] | None) -> list:
    """A vehicle's missions held by other workers than ``home``, as futures of
    :func:`~aqfg.fleet.worker.load` there (None for those ``home`` holds or no worker does)."""
    out: list = []
    for s in specs:
        w = where.get(s.key[1:])
        out.append(None if w is None or [w] == home else
                   client.submit(load, s, pure=False, retries=2, workers=[w],
                                 allow_other_workers=True,
                                 key=f"aqfg-{s.run}-mission-{s.vehicle}-{s.index}"))
    return out


def _per_vehicle(client, op, specs: dict, results: dict[str, Result], timeout, what: str,
                 where: dict | None = None, args=None) -> dict[str, Result]:
    """``op(specs[v], *args(v, home))`` (default ``op(specs[v], results[v])``) for every
    vehicle, one task each on the workers (``home``: the one that holds most of its
    missions, ``where``, while it lives; futures among the arguments are resolved by Dask
    where the task runs); a failure or a timeout raises :class:`FleetError` naming the
    vehicle and ``what``."""
    from distributed import as_completed
    out = dict(results)
    futs = {}
    for i, v in enumerate(results):
        home = _home(specs[v], where)
        futs[client.submit(op, specs[v], *(args(v, home) if args else (results[v],)),
                           pure=False, retries=2, key=f"aqfg-{specs[v][0].run}-{op.__name__}-{i}",
                           workers=home, allow_other_workers=True)] = v
    try:
        for fut in as_completed(list(futs), timeout=timeout):
            v = futs[fut]
            try:
                out[v] = fut.result()
            except Exception as e:                 # re-raised with context
                raise FleetError(f"vehicle {v!r}: {what} failed: {type(e).__name__}: {e}"
                                 ) from e
    except TimeoutError:
        raise FleetError(f"{what} took longer than {timeout} s") from None
    return out


def _home(specs: list[MissionSpec], where: dict | None) -> list[str] | None:
    """The worker that holds most of a vehicle's missions (``[address]``), None where
    none is known."""
    held = [where[s.key[1:]] for s in specs if where and s.key[1:] in where]
    return [max(sorted(set(held)), key=held.count)] if held else None


def _diagnose(client, specs, timeout, where: dict | None = None) -> dict:
    futs = {(v, s.name): client.submit(diagnose_op, s, pure=False, retries=2,
                                       workers=_home([s], where), allow_other_workers=True)
            for v, ms in specs.items() for s in ms}
    out: dict = {}
    for (v, name), fut in futs.items():
        try:
            out.setdefault(v, {})[name] = fut.result(timeout=timeout)
        except Exception as e:  # noqa: BLE001 - a verdict, not the run
            out.setdefault(v, {})[name] = {"verdict": f"diagnosis failed: {e}",
                                           "missing": None, "best": None}
    return out


def _workers(client) -> list[str]:
    return sorted(client.scheduler_info(n_workers=-1)["workers"])


def _alive_workers(client, wait: float = WORKER_WAIT) -> list[str]:
    """The workers now; if there is none, those that (re)join within ``wait`` s. A worker
    the scheduler dropped under load (missed heartbeats) is restarted by its nanny: on a
    loaded 2-core machine a one-worker run once found none between two rounds and
    failed."""
    alive = _workers(client)
    if not alive:
        try:
            client.wait_for_workers(1, timeout=wait)
        except Exception:  # noqa: BLE001 - none came: _least_loaded says so
            return []
        alive = _workers(client)
    return alive


def _least_loaded(alive: list[str], where: dict, size: dict | None = None) -> str:
    """The live worker holding the least: summed ``size`` of its missions (by vehicle and
    mission index; 1 each where not given)."""
    if not alive:
        raise FleetError("no Dask worker is running")
    held = {w: 0 for w in alive}
    for k, w in where.items():
        if w in held:
            held[w] += (size or {}).get(k, 1)
    return min(alive, key=lambda w: (held[w], w))


def _memory(client) -> dict:
    try:
        return client.run(memory)
    except Exception:  # noqa: BLE001 - statistics only
        return {}


def _size(obj) -> int:
    import pickle
    try:
        return len(pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL))
    except Exception:  # noqa: BLE001 - statistics only
        return 0


def vehicle_arrays(fr: FleetResult) -> tuple[list[str], tuple[str, ...], np.ndarray, np.ndarray]:
    """Vehicles, fixed-parameter names, values (V, d) and covariances (V, d, d)."""
    vs = list(fr.results)
    names = tuple(n for n in fr.results[vs[0]].estimated
                  if n not in next(iter(fr.results[vs[0]].per_mission.values()), {}))
    X = np.array([[fr.results[v].values[n] for n in names] for v in vs])
    C = np.array([fixed_covariance(fr.results[v]) for v in vs])
    return vs, names, X, C


def fixed_covariance(r: Result) -> np.ndarray:
    """The covariance of a vehicle's fit's fixed parameters (0 x 0 where it has none)."""
    c = r.covariance.block("fixed") if r.covariance is not None else None
    return np.zeros((0, 0)) if c is None else c
