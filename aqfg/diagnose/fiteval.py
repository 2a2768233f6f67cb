"""One model evaluated for the diagnosis: fitted to all fixes and to the thinned fixes, and
its predictions of the held-out fixes (dead-reckoning error, consistency test).

:func:`evaluate` does it for one model (:func:`fit_all` then :func:`add_heldout`). A
candidate's fit to all fixes is solved from the base model's fit (:mod:`aqfg.diagnose.refit`)
and from the smoother's global start, in two forked processes with ``jobs > 1``.
"""
from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from aqfg.data.mission import Mission
from aqfg.diagnose.compare import Split
from aqfg.diagnose.consistency import ConsistencyTest, nis_test
from aqfg.diagnose.heldout import HeldOut, heldout_innovations
from aqfg.diagnose.linearise import linear_system
from aqfg.diagnose.refit import WarmBatchSmoother
from aqfg.fg.common import mission_model
from aqfg.fg.settings import FGSettings
from aqfg.model.vehicle import Model
from aqfg.result import Result
from aqfg.threads import blas_threads  # noqa: F401  (re-exported for the diagnosis)


# ---------------------------------------------------------------- one evaluated model
@dataclass
class FitEval:
    """A model fitted to all fixes (``full``) and to the thinned fixes (``thin``), with the
    held-out innovations of the thinned fit: to the next fit fix (``next_fix``, for the
    consistency test) and over ``horizon`` s (``long``, for the dead-reckoning error)."""
    label: str
    effects: tuple[str, ...]
    full: Result
    thin: Result | None
    next_fix: list[HeldOut] = field(default_factory=list)
    long: list[HeldOut] = field(default_factory=list)
    consistency: ConsistencyTest | None = None
    n_meas: int = 0

    @property
    def model(self) -> Model:
        """The fitted model (base + effects), as recorded by the full fit."""
        assert self.full.model is not None, "every estimator records its model"
        return self.full.model

    @property
    def has_heldout(self) -> bool:
        """Whether the thinned fit and its held-out predictions were computed."""
        return bool(self.long)

    @property
    def cost(self) -> float:
        """Half the sum of squared whitened residuals (GTSAM's error) of the full fit."""
        return self.full.cost

    @property
    def n_params(self) -> int:
        return len(self.full.estimated)

    @property
    def bic(self) -> float:
        """BIC of the full fit, up to a constant shared by all models of the same data:
        ``2 cost + n_params ln(n_meas)``."""
        return 2.0 * self.cost + self.n_params * math.log(max(self.n_meas, 2))

    def _pool(self, which: str, attr: str) -> float:
        hs = getattr(self, which)
        if not hs:
            return float("nan")
        u = np.concatenate([h.used for h in hs])
        e = np.concatenate([h.err for h in hs])[u]
        nz = np.concatenate([h.noise for h in hs])[u]
        if not len(e):
            return float("nan")
        ms = float(np.mean(e ** 2))
        if attr == "raw":
            return math.sqrt(ms)
        if attr == "floor":
            return math.sqrt(float(np.mean(nz)))
        return math.sqrt(max(ms - float(np.mean(nz)), 0.0))

    @property
    def rmse(self) -> float:
        """Held-out dead-reckoning error (m, RMS over ``horizon`` s legs), the fixes' own
        noise removed."""
        return self._pool("long", "excess")

    @property
    def rmse_raw(self) -> float:
        """RMS distance (m) between dead-reckoned predictions and held-out fixes."""
        return self._pool("long", "raw")

    @property
    def noise_floor(self) -> float:
        """The RMS distance (m) the held-out fixes' own noise alone gives: ``rmse_raw`` of
        a perfect prediction (:attr:`rmse` is the part of ``rmse_raw`` beyond it)."""
        return self._pool("long", "floor")

    def heldout_text(self) -> str:
        """``rmse_raw`` beside the noise floor, e.g. "1.77 m (noise floor 1.50 m)"."""
        return f"{self.rmse_raw:.2f} m (noise floor {self.noise_floor:.2f} m)"

    @property
    def rmse_next_fix(self) -> float:
        """The same as :attr:`rmse` up to the next fit fix only."""
        return self._pool("next_fix", "excess")

    def values(self, names: Sequence[str]) -> dict:
        r = self.full
        return {n: {"value": float(r.values[n]), "sigma": float(r.sigma.get(n, np.nan))}
                for n in names}

    def to_json(self) -> dict:
        c = self.consistency
        return {"label": self.label, "effects": list(self.effects), "cost": self.cost,
                "bic": self.bic, "rmse": self.rmse, "rmse_raw": self.rmse_raw,
                "noise_floor": self.noise_floor,
                "rmse_next_fix": self.rmse_next_fix,
                "consistency": c.to_json() if c is not None else None,
                "parameters": self.full.parameters_json()}


def _n_meas(res: Result) -> int:
    n = 0
    for mr in res.missions:
        for k, r in mr.residuals.items():
            if k == "dynamics":
                continue
            n += int(np.size(r.raw))
    return n


def fit_all(missions: list[Mission], model, effects, label: str, *, settings: FGSettings,
            start: FitEval | None = None, log_warnings: bool = True) -> FitEval:
    """The model (base + ``effects``) fitted to all fixes; ``start``: an evaluation of a
    related model (e.g. the base model when ``effects`` adds a candidate) whose fit starts
    this one (:mod:`aqfg.diagnose.refit`); ``log_warnings``: the fit's warnings to the log
    too (always in its ``warnings``)."""
    sm = WarmBatchSmoother(model, effects=effects, settings=settings,
                           start=start.full if start is not None else None)
    sm.log_warnings = log_warnings
    full = sm.run(missions)
    assert full.model is not None, "the batch smoother records its model"
    return FitEval(label, tuple(e.name for e in full.model.effects), full, None,
                   n_meas=_n_meas(full))


def add_heldout(ev: FitEval, splits: list[Split], model, effects, *, settings: FGSettings,
                horizon: float, window: float, start: FitEval | None = None) -> FitEval:
    """Fit the model to the thinned fixes (started from ``start``'s thinned fit, else from
    ``ev``'s full fit) and predict the held-out fixes: fills ``ev.thin``, ``next_fix``,
    ``long`` and ``consistency``."""
    th = WarmBatchSmoother(model, effects=effects, settings=settings,
                           start=start.thin if start is not None and start.thin is not None
                           else ev.full)
    th.log_warnings = False
    thin = th.run([s.fit for s in splits])
    ev.thin = thin
    ev.next_fix, ev.long = [], []
    lin = linear_system([s.fit for s in splits], thin, [], settings=settings, built=th.built)
    for i, s in enumerate(splits):
        mdl = mission_model(thin.model, s.fit)
        kw: dict[str, Any] = {"model": mdl, "fit": s.fit, "heldout": s.heldout,
                              "mres": thin.missions[i], "lin": lin, "mission_index": i,
                              "estimated": thin.estimated, "settings": settings}
        ev.next_fix.append(heldout_innovations(**kw))
        ev.long.append(heldout_innovations(**kw, horizon=horizon))
    t = np.concatenate([h.t[h.used] for h in ev.next_fix])
    nis = np.concatenate([h.nis[h.used] for h in ev.next_fix])
    o = np.argsort(t, kind="stable")
    ev.consistency = nis_test(t[o], nis[o], np.full(len(t), 2.0), window)
    return ev


def evaluate(missions: list[Mission], splits: list[Split], model, effects, label: str, *,
             settings: FGSettings, horizon: float, window: float,
             start: FitEval | None = None, heldout: bool = True, jobs: int = 1) -> FitEval:
    """:func:`fit_all`, then (``heldout``) :func:`add_heldout`, the thinned fit started from
    the fit to all fixes.

    With a ``start`` (a candidate's refit: ``start`` is the base model), the fit to all
    fixes is solved twice, from the base fit (warm) and from the smoother's own global
    start (cold), and the lower cost is kept (``info["start"]`` says which): from the base
    optimum a refit cannot lose the base model's basin, from the global start it can reach
    the effect's own basin when the base model's is a different one (the bare model of a
    vehicle with linear drag can settle where thrust and drag nearly vanish, and adding the
    drag there changes nothing). With ``jobs > 1`` the two solves run in two forked
    processes at once."""
    if start is None:
        ev = fit_all(missions, model, effects, label, settings=settings)
    else:
        args = {"missions": missions, "model": model, "effects": effects, "label": label,
                "start": start, "kw": {"settings": settings}}
        if jobs > 1 and fork_available():
            warm, cold = _pool(args, ("warm", "cold"))
        else:
            _JOBS["args"] = args
            try:
                warm, cold = _work("warm"), _work("cold")
            finally:
                _JOBS.clear()
        for e in (warm, cold):
            e.full.model = mission_model(model, missions[0], effects)
        ev = cold if cold.cost < warm.cost - 1e-6 else warm
        ev.full.info["start"] = "global start" if ev is cold else "base fit"
        ev.full.info["cost_other_start"] = (warm if ev is cold else cold).cost
    if heldout:
        add_heldout(ev, splits, model, effects, settings=settings, horizon=horizon,
                    window=window)
    return ev


# ---------------------------------------------------------------- two processes
_JOBS: dict = {}     # the work of evaluate, inherited by forked workers


def _work(part: str) -> FitEval:
    """Worker: a candidate's fit to all fixes from the base fit (``"warm"``) or from the
    smoother's global start (``"cold"``), without its model object (a user effect's
    callable need not pickle)."""
    a = _JOBS["args"]
    # (a candidate's refits keep their warnings in Result.warnings: logged, the base
    # fit's misfit warning came seven times, each advising `aqfg diagnose`, inside it)
    ev = fit_all(a["missions"], a["model"], a["effects"], a["label"],
                 settings=a["kw"]["settings"], start=a["start"] if part == "warm" else None,
                 log_warnings=False)
    ev.full.model = None
    return ev


def fork_available() -> bool:
    import multiprocessing as mp
    return "fork" in mp.get_all_start_methods()


def _pool(args: dict, parts: tuple[str, ...]) -> list:
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor
    _JOBS["args"] = args
    try:
        with ProcessPoolExecutor(max_workers=len(parts),
                                 mp_context=mp.get_context("fork")) as ex:
            return list(ex.map(_work, parts))
    finally:
        _JOBS.clear()


def default_jobs() -> int:
    """Worker processes for a refit: 2 when this process may use two CPUs or more."""
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:          # pragma: no cover - not on Linux
        n = os.cpu_count() or 1
    return max(1, min(2, n))
