"""The joint batch fit of several missions of one vehicle, computed one mission at a time.

The batch graph of missions sharing the vehicle's fixed-parameter node ``f`` (see
:mod:`aqfg.fg.batch`) is an arrowhead: a mission's own state knots and variable/sensor
nodes (its *locals* ``l_i``) touch no other mission, only ``f``. So every linear system of
the batch's Levenberg-Marquardt loop splits: eliminating a mission's (damped) locals
leaves its Schur complement on ``f``, ``S_i = H_ff - H_fl H_ll^-1 H_lf``, and reduced
right-hand side ``eta_i`` (:class:`ReducedSystem`); their sum plus the damping of ``f`` is
the batch's system on ``f`` exactly; its solution ``delta_f`` goes back to each mission,
whose locals' step follows by back-substitution. Accepting or rejecting the step needs
only the sum of the missions' costs. :func:`run_joint` is the batch's loop
(:func:`aqfg.fg.lm.levenberg_marquardt`: same damping, active bounds, stopping rule) on a
system whose every operation is a round of such per-mission requests, so the missions can
live in different processes or machines (:mod:`aqfg.fleet`, through the generator
:func:`joint_lm`); :func:`solve_apart` serves the rounds in this process. Only
``(S_i, eta_i, cost_i)``, a few hundred bytes, travel per mission and round.

A mission whose state was lost (its worker died) is rebuilt and its locals re-solved at
the current ``f`` (:meth:`MissionProblem.solve`); the iteration goes on from there.

At the end the inverse of the summed information is the fixed node's marginal covariance
of the joint fit, and a mission's own marginals follow from its graph plus the information
the rest of the problem holds on ``f`` (:meth:`MissionProblem.result`).
"""
from __future__ import annotations

import time
from collections.abc import Callable, Generator, Sequence
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np

from aqfg.data.mission import Mission
from aqfg.fg import factors as fc
from aqfg.fg.batch import BatchSmoother
from aqfg.fg.common import check_missions
from aqfg.fg.covariance import honest_covariance, sigma_inflation
from aqfg.fg.graph import ParamNode
from aqfg.fg.graph_lm import active_bounds
from aqfg.fg.lm import LMParams, diagonal_floor, levenberg_marquardt
from aqfg.fg.rounds import as_rounds
from aqfg.fg.schur_mission import FIXED, MissionProblem, MissionSession, ReducedSystem
from aqfg.fg.settings import FGSettings
from aqfg.result import Covariance, Estimate, Result, SolveSummary

Request = tuple[str, dict]


@dataclass
class Solution:
    """What :func:`joint_lm` returns for one vehicle."""
    layout: fc.ParamLayout
    f: np.ndarray
    cov_f: np.ndarray
    results: list[Result]
    iterations: int
    trials: int
    converged: bool
    cost: float
    history: list             # (iteration, cost, lambda) of accepted steps
    rounds: int
    recovered: int
    cov_model_f: np.ndarray | None = None     # before the sandwich inflation
    # per mission, its track under the noise its evidence chooses (track, residuals,
    # factor), where its session made it (FGSettings.batch.adapt_track on the numpy path)
    tracks: list | None = None


def _fixed_system(total: ReducedSystem, lam: float, clamps: Sequence = ()) -> np.ndarray:
    """The fixed node's step from the summed reduced system: Marquardt damping
    ``lam * diag`` (floored as the batch's), active-bound rows ``clamps``."""
    d = len(total.eta)
    g = gtsam.GaussianFactorGraph()
    g.add(gtsam.HessianFactor(FIXED, total.H, total.eta, 0.0))
    if lam > 0:
        g.add(gtsam.JacobianFactor(FIXED, np.diag(np.sqrt(lam * diagonal_floor(total.hdiag))),
                                   np.zeros(d), gtsam.noiseModel.Unit.Create(d)))
    for k, A, b in clamps:
        g.add(gtsam.JacobianFactor(k, A, b, gtsam.noiseModel.Unit.Create(len(b))))
    order = gtsam.Ordering()
    order.push_back(FIXED)
    return g.optimize(order).at(FIXED)


def _joint_sandwich(reps: list[dict], total: ReducedSystem, dim: int) -> dict | None:
    """The joint block sandwich on the fixed node from the missions' reduced block
    gradients (same blocks, centring and scale as :func:`aqfg.fg.covariance.block_sandwich`
    on the joint graph); None when there are too few blocks."""
    parts = [r["sandwich"] for r in reps]
    # each mission's blocks are its own (ids from its own start, shifted past the others'):
    # missions are independent, so their blocks are separate samples of the score
    offsets = np.cumsum([0] + [int(p["ids"].max()) + 1 if len(p["ids"]) else 0
                               for p in parts])
    nb = int(offsets[-1])
    n_p = dim + sum(int(p["n_p"]) for p in parts)
    if nb < n_p + 2:
        return None
    scale = nb / max(nb - n_p, 1)
    gt = np.zeros((dim, nb))
    for p, o in zip(parts, offsets):
        if dim:
            np.add.at(gt.T, p["ids"] + o, p["G"].T)
    zf = np.linalg.solve(total.H, gt) if dim else np.zeros((0, nb))
    zc = zf - zf.mean(axis=1, keepdims=True)
    return {"zf": zf, "scale": scale, "cov_f": scale * zc @ zc.T, "dof": nb - n_p,
            "offsets": [int(o) for o in offsets[:-1]]}


class _FleetLM:
    """:class:`aqfg.fg.lm.LMSystem` of missions held elsewhere, each call one or more
    rounds of requests (:class:`MissionSession`) through ``ask(requests) -> replies``. A
    point is ``(f, trial)``: the fixed node's value and the trial whose candidate it is
    (None: the start). A trial: "sys" (each mission's damped Schur complement, committing
    the point's candidate) -> the fixed node's step -> "step" (locals by back-substitution,
    their bounds, the candidate's cost); redone where a mission was lost."""

    def __init__(self, n: int, layout: fc.ParamLayout, ask: Callable[[list[Request]], list[dict]],
                 lam0: float):
        self.n, self.layout, self.ask, self.lam0 = n, layout, ask, lam0
        self.dim = layout.dim("fixed")
        self.nodes = [ParamNode("fixed", FIXED, None)]
        self.trials = 0                       # id of the last trial
        self.holds: int | None = None         # the trial whose candidate the missions hold
        self.recovered = 0
        self.kept: tuple | None = None        # (point, lam, systems) of a "sys" round unused

    def sys(self, x: tuple[np.ndarray, int | None], lam: float,
            extra: Sequence[dict] | None = None) -> list[dict]:
        """One "sys" round at ``x`` damped by ``lam`` (``extra``: more arguments, per
        mission): the missions' replies."""
        self.trials += 1
        commit = x[1] if x[1] != self.holds else None
        args = {"f": x[0], "lam": lam, "trial": self.trials, "commit": commit,
                "start": self.trials == 1}
        reps = self.ask([("sys", {**args, **e}) for e in (extra or [{}] * self.n)])
        self.holds = x[1]
        self.recovered += sum(bool(r["recovered"]) for r in reps)
        return reps

    def cost(self, x) -> float:
        systems = [r["system"] for r in self.sys(x, self.lam0)]
        self.kept = (x, self.lam0, systems)
        return ReducedSystem.total(systems).cost

    def linearize(self, x) -> None:
        """(The missions linearise where they are asked for a "sys" at a new point.)"""

    def trial(self, x, lam: float):
        while True:
            if self.kept is not None and self.kept[0] is x and self.kept[1] == lam:
                systems = self.kept[2]
            else:
                systems = [r["system"] for r in self.sys(x, lam)]
            self.kept = None
            total = ReducedSystem.total(systems)
            out = self._step(x[0], lam, systems, total)
            if out is not None:
                return (out[0], self.trials), out[1], total.cost
            # a mission was lost: redo the trial

    def _step(self, f: np.ndarray, lam: float, systems: list[ReducedSystem],
              total: ReducedSystem) -> tuple[np.ndarray, float] | None:
        """The candidate ``f`` and its cost, or None where a mission was lost."""
        layout = self.layout
        df = _fixed_system(total, lam)
        vals = gtsam.Values()
        vals.insert(FIXED, f)
        dv = gtsam.VectorValues()
        dv.insert(FIXED, df)
        fclamps = active_bounds(layout, self.nodes, vals, dv)
        f_new = layout.project("fixed", f + df)
        mode = "probe" if fclamps else "try"
        reps = self.ask([("step", {"trial": self.trials, "delta_f": df, "f_new": f_new,
                                   "mode": mode})] * self.n)
        if any(r.get("lost") for r in reps):
            return None
        clamped = [i for i, r in enumerate(reps) if "clamped" in r]
        if fclamps or clamped:
            for i in clamped:
                systems[i] = reps[i]["clamped"]
            df = _fixed_system(ReducedSystem.total(systems), lam, fclamps)
            f_new = layout.project("fixed", f + df)
            reps = self.ask([("step", {"trial": self.trials, "delta_f": df, "f_new": f_new,
                                       "mode": "final"})] * self.n)
            if any(r.get("lost") for r in reps):
                return None
        return f_new, float(sum(r["cost"] for r in reps))


def run_joint(n: int, settings: FGSettings, ask: Callable[[list[Request]], list[dict]],
              progress: Callable[[str], None] | None = None) -> Solution:
    """The batch's Levenberg-Marquardt loop (:func:`aqfg.fg.lm.levenberg_marquardt` on
    :class:`_FleetLM`) over ``n`` missions served by ``ask(requests) -> replies`` (one
    request per mission, for :meth:`MissionSession.handle`), then the undamped system at
    the solution: the fixed node's covariance and each mission's result."""
    rounds = 0

    def counted(reqs: list[Request]) -> list[dict]:
        nonlocal rounds
        rounds += 1
        return ask(reqs)
    opened = counted([("open", {})] * n)
    layout = opened[0]["layout"]
    dim = layout.dim("fixed")
    f = np.median(np.array([r["f0"] for r in opened], float), axis=0) if dim else np.zeros(0)
    params = LMParams.of(settings)
    system = _FleetLM(n, layout, counted, params.lambda_initial)
    x: tuple[np.ndarray, int | None] = (f, None)

    def report(it: int, cost: float, lam: float) -> None:
        if progress is not None:
            progress(f"iteration {it}: cost {cost:.6g} (lambda {lam:.0e})")
    if dim:
        out = levenberg_marquardt(system, x, params, report)
        x = out.x
        iterations, converged, history = out.iterations, out.converged, out.history
    else:       # no fixed parameter estimated: no iteration, the missions at their start
        iterations, converged = 0, True
        history = [(0, system.cost(x), params.lambda_initial)]
    trials = system.trials
    # ---- the undamped system at the solution: covariances, then each mission's result
    block = settings.batch.sandwich_block
    reps = system.sys(x, 0.0, [{"sandwich": (float(r["t0"]), block) if block else None}
                               for r in opened])
    systems = [r["system"] for r in reps]
    total = ReducedSystem.total(systems)
    cov_f = np.linalg.inv(total.H) if dim else np.zeros((0, 0))
    cov_model_f = cov_f
    sw = _joint_sandwich(reps, total, dim) if block else None
    if sw is not None and dim:
        cov_f = honest_covariance({FIXED: cov_f}, {FIXED: sw["cov_f"]}, sw["dof"])[FIXED]
    reps = counted([("result", {"f": x[0], "others": (total.H - si.H) if dim else None,
                                "sandwich": None if sw is None
                                else {**sw, "offset": sw["offsets"][i]}})
                    for i, si in enumerate(systems)])
    return Solution(layout, x[0], cov_f, [r["result"] for r in reps], iterations, trials,
                    converged, float(total.cost), history, rounds, system.recovered, cov_model_f,
                    [r.get("track") for r in reps])


def joint_lm(n: int, settings: FGSettings, progress: Callable[[str], None] | None = None
             ) -> Generator[list[Request], list[dict], Solution]:
    """:func:`run_joint` as a generator: it yields a list of ``n`` requests ``(op, args)``
    (one per mission, for :meth:`MissionSession.handle`) and is sent the list of replies;
    it returns the :class:`Solution`. The rounds of several vehicles can so be served
    together (:mod:`aqfg.fleet`)."""
    def run(ask: Callable[[list[Request]], list[dict]]) -> Solution:
        return run_joint(n, settings, ask, progress)
    return (yield from as_rounds(run))


def combine(sol: Solution, timings: dict | None = None) -> Result:
    """One :class:`Result` for the vehicle, shaped as :meth:`BatchSmoother.run`'s: the
    fixed node's values and sigma, the first mission's variable/sensor values, every
    mission's in ``per_mission`` and its MissionResult in ``missions``."""
    layout, results = sol.layout, sol.results
    r0 = results[0]
    values, sigma = dict(r0.values), dict(r0.sigma)
    names_f = layout.names.get("fixed", ())
    sigma_model = dict(r0.sigma_model)
    cm = sol.cov_model_f if sol.cov_model_f is not None else sol.cov_f
    for i, n in enumerate(names_f):
        values[n] = float(sol.f[i])
        sigma[n] = float(np.sqrt(max(sol.cov_f[i, i], 0.0)))
        sigma_model[n] = float(np.sqrt(max(cm[i, i], 0.0)))
    per_mission: dict[str, dict[str, Estimate]] = {}
    plaus: dict = {}
    for r in results:
        per_mission.update(r.per_mission)
        plaus.update(r.plausibility)
    cov = dict(r0.covariance.blocks) if r0.covariance is not None else {}
    if names_f:
        cov["fixed"] = np.array(sol.cov_f, dtype=float)
    info: dict[str, Any] = {
        "rounds": sol.rounds, "recovered": sol.recovered, "solver": "schur"}
    return Result(method="fg", mode="batch", estimated=layout.estimated, values=values,
                  sigma=sigma, missions=[r.missions[0] for r in results], history=r0.history,
                  info=info, timings=dict(timings or {}), effects=r0.effects, model=None,
                  covariance=Covariance(cov), sigma_model=sigma_model, per_mission=per_mission,
                  plausible=all(r.plausible is not False for r in results), plausibility=plaus,
                  solve=SolveSummary(sol.converged, sol.cost, sol.iterations, sol.trials),
                  sigma_inflation=sigma_inflation(sigma, sigma_model))


def drive(gen: Generator[list[Request], list[dict], Solution],
          serve: Callable[[list[Request]], list[dict]]) -> Solution:
    """Run a :func:`joint_lm` generator, serving each round with ``serve``; its result."""
    reqs = next(gen)
    while True:
        try:
            reqs = gen.send(serve(reqs))
        except StopIteration as stop:
            return stop.value


def solve_apart(smoother: BatchSmoother, missions: Sequence[Mission],
                progress: Callable[[str], None] | None = None) -> Result:
    """The joint batch fit of ``missions`` computed mission by mission in this process
    (the iteration :mod:`aqfg.fleet` distributes); equals ``smoother.run(missions)``."""
    t0 = time.perf_counter()
    missions = check_missions(missions)
    sessions = [MissionSession(MissionProblem(smoother, m, fixed_prior=(i == 0)))
                for i, m in enumerate(missions)]

    def serve(reqs):
        return [s.handle(op, args) for s, (op, args) in zip(sessions, reqs)]
    sol = run_joint(len(sessions), smoother.settings, serve, progress)
    return combine(sol, {"batch": [time.perf_counter() - t0]})
