"""What runs on a Dask worker: a mission's session, built from its path on first use and
kept in the worker process between rounds (keyed by run, vehicle and mission), and the
missions it has read, kept for the rest of the fit (keyed by fit, path and GNSS thinning):
the joint solve, the structural sigma, the effect step's second solve, the dead-reckoning
constants, the tracks and the diagnosis then read each mission once per worker, and the
kernel steps and closed-form starts remembered for a mission object
(:mod:`aqfg.memo`) serve the later graphs of the same mission."""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from aqfg.fg.schur import MissionProblem, MissionSession
from aqfg.fg.settings import FGSettings

_SESSIONS: dict[tuple, MissionSession] = {}
_MISSIONS: dict[tuple, object] = {}         # (fit, path, gnss_every) -> Mission


@dataclass(frozen=True)
class MissionSpec:
    """Everything a worker needs to build a mission's graph: its path (read on the
    worker), and the fit's options."""
    run: str
    vehicle: str
    index: int
    name: str
    path: str
    fixed_prior: bool
    settings: FGSettings
    effects: tuple = ()
    estimate: tuple | None = None
    init: dict = field(default_factory=dict)
    gnss_every: float = 0.0
    # the structural sigma checked by a refit with the effect it rests on
    # (aqfg.fg.fit.refit_structure): the fits returned, not the model-as-given fit of an
    # effect step, as aqfg fit's batch
    refit: bool = False
    fit: str = ""                # the fit_fleet call: the missions read are kept for it

    @property
    def key(self) -> tuple:
        return (self.run, self.vehicle, self.index)


def _kept(spec: MissionSpec) -> tuple:
    """The key of ``spec``'s mission among those kept for its fit."""
    return spec.fit, spec.path, spec.gnss_every


def load(spec: MissionSpec):
    """The mission of ``spec`` as this worker read it for the fit (read on first use; sent
    to another worker by Dask, a copy in memory instead of a second reading of its files)."""
    key = _kept(spec)
    m = _MISSIONS.get(key)
    if m is None:
        m = _MISSIONS[key] = _read(spec)
    return m


def _read(spec: MissionSpec):
    from aqfg.data.io import load_mission
    from aqfg.data.mission import with_gnss_every
    try:
        m = load_mission(spec.path)
    except FileNotFoundError as e:
        raise FileNotFoundError(f"{e} (read on worker {_address()}: the missions must be on a "
                                "file system the workers share)") from None
    return with_gnss_every(m, spec.gnss_every) if spec.gnss_every else m


def smoother(spec: MissionSpec):
    from aqfg.fg.batch import BatchSmoother
    return BatchSmoother(None, effects=spec.effects, estimate=spec.estimate,
                         init=spec.init, settings=spec.settings)


def mission_op(spec: MissionSpec, op: str, args: dict) -> dict:
    """Serve one request of :func:`aqfg.fg.schur.joint_lm` for the mission ``spec``."""
    t0 = time.perf_counter()
    sess = _SESSIONS.get(spec.key)
    built = sess is None
    if sess is None:
        sess = MissionSession(MissionProblem(smoother(spec), load(spec),
                                             fixed_prior=spec.fixed_prior))
        _SESSIONS[spec.key] = sess
    reply = sess.handle(op, args)
    if op == "result":
        _SESSIONS.pop(spec.key, None)
    reply.update(worker=_address(), built=built, seconds=time.perf_counter() - t0)
    return reply


def missions_op(items: list) -> list[dict]:
    """Serve a round's requests ``[(spec, op, args), ...]`` for the missions this worker
    holds (one task per worker and round: the scheduler's cost is per task). A mission
    whose request fails answers ``{"error": text}``."""
    out = []
    for spec, op, args in items:
        try:
            out.append(mission_op(spec, op, args))
        except (OSError, ValueError, KeyError, RuntimeError, np.linalg.LinAlgError) as e:
            out.append({"error": f"{type(e).__name__}: {e}"})
    return out


def _vehicle(specs: list[MissionSpec], result, sent: list | None = None) -> list:
    """A vehicle's missions (those ``sent`` from other workers, None where not, kept
    here for the fit; the others read here) and its joint fit ``result`` given the model it
    was fitted with (in place)."""
    from aqfg.fg.common import mission_model
    for spec, m in zip(specs, sent or ()):
        if m is not None:
            _MISSIONS.setdefault(_kept(spec), m)
    missions = [load(spec) for spec in specs]
    result.model = mission_model(None, missions[0], specs[0].effects)
    return missions


def structural_op(specs: list[MissionSpec], result, sent: list | None = None):
    """A vehicle's joint fit with the model it was fitted with and the structural part of
    its sigma (:func:`structural`); the missions ``sent`` from the workers that hold them,
    the others read here."""
    return structural(specs, _vehicle(specs, result, sent), result)


def refine_op(specs: list[MissionSpec], result):
    """A vehicle's joint fit with its thrust/drag constants re-estimated by prediction
    error over its missions (:func:`aqfg.fg.dead_reckoning.refine`, from the joint fit's
    states), as ``aqfg fit`` does once for the fit it returns."""
    from aqfg.fg import dead_reckoning
    return dead_reckoning.refine(result, _vehicle(specs, result),
                                 specs[0].settings.batch.dr_horizon)


def finish_op(specs: list[MissionSpec], result, tracks: list | None = None):
    """A vehicle's final joint fit (:func:`refine_op`'s): its missions' tracks replaced by
    ``tracks`` (:func:`track_op`'s, one per mission; None: as they are) and what its data
    cannot determine marked so (:func:`aqfg.identifiability.settle`, which reads those
    tracks; its warnings in ``identifiability_warnings``), as ``aqfg fit`` does."""
    from aqfg.identifiability import settle
    missions = _vehicle(specs, result)
    if tracks is not None:
        q = {}
        for mr, (track, residuals, scale) in zip(result.missions, tracks):
            mr.track, mr.residuals, q[mr.name] = track, residuals, scale
        result.track_noise_scale = q
    # what the data cannot determine, as aqfg fit says it (the accelerometer check needs
    # the missions, which are here)
    result.identifiability_warnings = tuple(settle(result, missions))
    return result


def structural(specs: list[MissionSpec], missions: list, result):
    """The structural part of the sigma of a vehicle's joint fit, as ``aqfg fit``'s batch
    (:func:`aqfg.fg.structural_sigma.structural_sigma`): its missions' graph built on the worker, the
    numpy system evaluated at the joint solution (the smoothed states and each mission's
    parameters)."""
    from aqfg.fg.batch import BatchSmoother, solution_values, too_short_for_sandwich
    from aqfg.fg.fastlm import FastSystem
    from aqfg.fg.fit import auto_effect_applies, refit_structure
    from aqfg.fg.structural_sigma import structural_sigma
    st = specs[0].settings
    if not st.batch.structural_sigma or result.model is None:
        return result
    bg = BatchSmoother(None, effects=specs[0].effects, estimate=result.estimated,
                       settings=st).build(missions)
    fs = FastSystem.build(bg, st)
    if fs is None:
        return result
    try:
        values = solution_values(bg, result)
    except ValueError:
        return result                          # not the graph the joint fit solved
    X, th = fs.from_values(values)
    result.too_short_for_sandwich = too_short_for_sandwich(bg, st)
    # the test also where the fixes are explained, for the fleet's effect step
    # (aqfg.fleet.solve.fleet_effect), as aqfg fit's batch
    result = structural_sigma(result, missions, fs, fs.evaluate(X, th), st,
                              test_always=auto_effect_applies(st, specs[0].estimate))
    if specs[0].refit:
        result = refit_structure(result, missions, None, specs[0].effects, specs[0].estimate,
                                 specs[0].init, st)
    return result


def track_op(spec: MissionSpec, p: np.ndarray) -> tuple:
    """The mission's track and residuals smoothed again with its parameters held at ``p``
    (the joint fit's full vector for it: the smoother's constants and current, not those
    refined for dead reckoning) under the process noise its evidence chooses, and that
    noise's factor, as ``aqfg fit``'s batch does
    (:attr:`FGSettings.batch.adapt_track`)."""
    from aqfg.fg.batch import smooth_track
    return smooth_track(load(spec), p, effects=spec.effects, settings=spec.settings)


def diagnose_op(spec: MissionSpec) -> dict:
    """The diagnosis verdict of one mission alone (``aqfg diagnose``'s workflow)."""
    from aqfg.diagnose.workflow import diagnose
    # jobs=1: a Dask worker process is daemonic and may not start the refits' own
    # processes; the parallelism here is one mission per worker
    d = diagnose([load(spec)], effects=spec.effects, gnss_every=spec.gnss_every or 8.0,
                 jobs=1, progress=False)
    best = d.best
    return {"verdict": d.verdict, "missing": bool(d.missing),
            "best": None if best is None else best.effect}


def n_sessions(vehicle: str | None = None) -> int:
    """How many missions this worker holds (of every run; of ``vehicle`` only if given)."""
    return sum(1 for k in _SESSIONS if vehicle is None or k[1] == vehicle)


def _drop(store: dict, first: str) -> int:
    """Drop the entries of ``store`` whose key starts with ``first``; how many there were."""
    keys = [k for k in store if k[0] == first]
    for k in keys:
        del store[k]
    return len(keys)


def release(run: str) -> int:
    """Drop the sessions of ``run`` from this worker; how many there were."""
    return _drop(_SESSIONS, run)


def release_fit(fit: str) -> int:
    """Drop the missions this worker read for the fit ``fit``; how many there were."""
    return _drop(_MISSIONS, fit)


def n_missions_read(fit: str | None = None) -> int:
    """How many missions this worker keeps (of every fit; of ``fit`` only if given)."""
    return sum(1 for k in _MISSIONS if fit is None or k[0] == fit)


def memory() -> dict:
    """This process's resident and peak resident memory (bytes)."""
    import resource

    import psutil
    return {"rss": psutil.Process().memory_info().rss,
            "peak": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024}


def _address() -> str:
    try:
        from distributed import get_worker
        return get_worker().address
    except (ImportError, ValueError):
        return "local"
