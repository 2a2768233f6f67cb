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
from aqfg.fg.batch import (
    BatchSmoother,
    GraphLM,
    ParamNode,
    active_bounds,
    diagonal_floor,
    hessian_diagonal,
)
from aqfg.fg.common import FGSettings, check_missions
from aqfg.fg.covariance import honest_covariance, sigma_inflation
from aqfg.fg.lm import LMParams, levenberg_marquardt
from aqfg.fg.rounds import as_rounds
from aqfg.result import Result

FIXED = fc.node_key("fixed")
_PIN = 1e8          # whitened weight holding the fixed node during a mission's own solve

Request = tuple[str, dict]


@dataclass
class ReducedSystem:
    """Information on the fixed node after eliminating a mission's locals.

    ``H`` (d, d) and ``eta`` (d,): the linear system ``H delta_f = eta`` (whitened
    Gauss-Newton information, parameter units); ``cost``: 0.5 x the whitened squared error
    at the linearisation point; ``hdiag`` (d,): diagonal of ``J_f^T J_f`` before the
    elimination, unfloored (the batch's Marquardt damping scale, summed over missions).
    """
    H: np.ndarray
    eta: np.ndarray
    cost: float
    hdiag: np.ndarray

    def __add__(self, other: ReducedSystem) -> ReducedSystem:
        return ReducedSystem(self.H + other.H, self.eta + other.eta, self.cost + other.cost,
                             self.hdiag + other.hdiag)

    @classmethod
    def total(cls, systems: Sequence[ReducedSystem]) -> ReducedSystem:
        out = systems[0]
        for s in systems[1:]:
            out = out + s
        return out


class MissionProblem:
    """One mission's share of the joint fit: its batch graph (built once) and the
    operations on it that the distributed loop needs.

    ``fixed_prior``: whether this mission's graph carries the prior on the fixed node (give
    it to exactly one mission of the vehicle, so that the prior counts once).
    """

    def __init__(self, smoother: BatchSmoother, mission: Mission, *, fixed_prior: bool):
        self.smoother = smoother
        self.settings: FGSettings = smoother.settings
        self.name = mission.name
        self.bg = smoother.build(check_missions([mission]), fixed_prior=fixed_prior)
        layout = self.bg.layout
        self.dim = layout.dim("fixed")
        self.key_dims = self.bg.key_dims()
        self.locals = [n for n in self.bg.nodes if n.group != "fixed"]
        gfg = self.bg.linearize(self.bg.values)
        if self.dim:
            self.ordering = gtsam.Ordering.ColamdConstrainedLastGaussianFactorGraph(
                gfg, gtsam.KeyVector([FIXED]))
            self.local_ordering = gtsam.Ordering()
            for i in range(self.ordering.size() - 1):
                self.local_ordering.push_back(self.ordering.at(i))
            self._pin = gtsam.JacobianFactor(FIXED, _PIN * np.eye(self.dim), np.zeros(self.dim),
                                             gtsam.noiseModel.Unit.Create(self.dim))
        else:
            self.ordering = self.local_ordering = gtsam.Ordering.MetisGaussianFactorGraph(gfg)

    @property
    def layout(self) -> fc.ParamLayout:
        return self.bg.layout

    def initial_values(self) -> gtsam.Values:
        return gtsam.Values(self.bg.values)

    def initial_fixed(self) -> np.ndarray:
        """The fixed node's starting value the batch build chose for this mission alone."""
        return self.bg.values.atVector(FIXED) if self.dim else np.zeros(0)

    def fixed_of(self, values: gtsam.Values) -> np.ndarray:
        return values.atVector(FIXED) if self.dim else np.zeros(0)

    def with_fixed(self, values: gtsam.Values, f: np.ndarray) -> gtsam.Values:
        out = gtsam.Values(values)
        if self.dim:
            out.update(FIXED, np.asarray(f, float))
        return out

    # ---------------------------------------------------------------- one LM trial
    def linearize(self, values: gtsam.Values, filled: bool = False
                  ) -> tuple[gtsam.GaussianFactorGraph, dict, np.ndarray]:
        """The linear system at ``values`` (``filled``: the dynamics cache already holds
        them), the damping scale of every key, and the unfloored one of the fixed node."""
        gfg = self.bg.graph.linearize(values) if filled else self.bg.linearize(values)
        raw = hessian_diagonal(gfg, self.key_dims, floor=False)
        hdiag = {k: diagonal_floor(v) for k, v in raw.items()}
        return gfg, hdiag, raw.get(FIXED, np.zeros(0))

    def reduce(self, gfg: gtsam.GaussianFactorGraph, hdiag: dict, lam: float, cost: float,
               hdiag_f: np.ndarray, clamps: Sequence = ()
               ) -> tuple[gtsam.GaussianBayesNet, ReducedSystem]:
        """Damp the locals by ``lam * hdiag`` (the fixed node is damped by the caller, on
        the sum), add ``clamps`` (active bounds of the locals), eliminate the locals: the
        Bayes net of the locals given ``f`` and the Schur complement on ``f``."""
        damped = gfg.clone()
        if lam > 0:
            for k, d in self.key_dims:
                if k != FIXED:
                    damped.add(gtsam.JacobianFactor(k, np.diag(np.sqrt(lam * hdiag[k])),
                                                    np.zeros(d), gtsam.noiseModel.Unit.Create(d)))
        for k, A, b in clamps:
            damped.add(gtsam.JacobianFactor(k, A, b, gtsam.noiseModel.Unit.Create(len(b))))
        if not self.dim:
            bn = damped.eliminateSequential(self.ordering)
            return bn, ReducedSystem(np.zeros((0, 0)), np.zeros(0), float(cost), np.zeros(0))
        bn, rest = damped.eliminatePartialSequential(self.local_ordering)
        H, eta = rest.hessian()
        return bn, ReducedSystem(np.asarray(H), np.asarray(eta), float(cost), hdiag_f)

    def back_substitute(self, bn: gtsam.GaussianBayesNet, delta_f: np.ndarray
                        ) -> gtsam.VectorValues:
        """The locals' step given the fixed node's step (and the fixed node's step)."""
        given = gtsam.VectorValues()
        if self.dim:
            given.insert(FIXED, np.asarray(delta_f, float))
            delta = bn.optimize(given)
            if not delta.exists(FIXED):
                delta.insert(FIXED, np.asarray(delta_f, float))
            return delta
        return bn.optimize()

    def local_clamps(self, values: gtsam.Values, delta: gtsam.VectorValues) -> list:
        return active_bounds(self.layout, self.locals, values, delta)

    def candidate(self, values: gtsam.Values, delta: gtsam.VectorValues, f_new: np.ndarray
                  ) -> tuple[gtsam.Values, float]:
        """The projected candidate ``values + delta`` with the fixed node set to ``f_new``
        (the client's projected value) and its cost; the dynamics cache then holds it."""
        cand = self._project(values.retract(delta), f_new)
        return cand, self.bg.error(cand)

    def _project(self, values: gtsam.Values, f: np.ndarray) -> gtsam.Values:
        for g, k, _ in self.locals:
            v = values.atVector(k)
            pv = self.layout.project(g, v)
            if np.any(pv != v):
                values.update(k, pv)
        if self.dim:
            values.update(FIXED, np.asarray(f, float))
        return values

    # ---------------------------------------------------------------- recovery, result
    def solve(self, f: np.ndarray, start: gtsam.Values | None = None
              ) -> tuple[gtsam.Values, float]:
        """The mission's locals at fixed parameters ``f`` (the batch's LM with ``f`` held,
        from ``start``, default the build's initial values): values and cost."""
        f = np.asarray(f, float)
        values = self._project(self.with_fixed(start if start is not None else self.bg.values, f), f)
        system = GraphLM(self.bg, self.ordering, self.locals, lambda vals: self._project(vals, f),
                         self._pin if self.dim else None)
        out = levenberg_marquardt(system, values, LMParams.of(self.settings))
        return out.x, out.cost

    def knot_start(self) -> float:
        return float(self.bg.parts[0].knots[0])

    def param_dim(self) -> int:
        """Dimension of this mission's own parameter nodes."""
        return sum(self.layout.dim(n.group) for n in self.locals)

    def sandwich_part(self, gfg: gtsam.GaussianFactorGraph, t0: float, block: float) -> dict:
        """This mission's share of the batch's block sandwich (:func:`aqfg.fg.covariance.
        block_sandwich`) at the undamped system ``gfg``: per time block ``j`` (ids from
        this mission's start ``t0``) the gradient ``g_j = A_j^T b_j`` of its rows that touch a state,
        reduced onto the fixed node, ``gt_j = g_f,j - H_fl H_ll^-1 g_l,j``; and, kept for
        :meth:`result`, the rows of ``H_ll^-1 g_l`` and ``H_ll^-1 H_lf`` of its parameter
        nodes. With ``Z_f = S^-1 sum gt`` (all missions), ``Z = H^-1 G`` of the joint
        system is ``Z_f`` on the fixed node and ``H_ll^-1 (g_l - H_lf Z_f)`` here."""
        import scipy.sparse.linalg as spla

        from aqfg.fg.covariance import block_gradients
        key_time = {k: float(t) for k, t in zip(self.bg.parts[0].keys, self.bg.parts[0].knots)}
        bgr = block_gradients(gfg, self.key_dims, key_time, t0, block)
        A, col0, G, ids = bgr.A, bgr.col0, bgr.G, bgr.ids
        n = A.shape[1]
        H = (A.T @ A).tocsc()
        fc_ = np.arange(col0[FIXED], col0[FIXED] + self.dim) if self.dim else np.zeros(0, int)
        lc = np.setdiff1d(np.arange(n), fc_)
        Hll = H[lc][:, lc].tocsc()
        Hlf = H[lc][:, fc_].toarray()
        X = spla.splu(Hll, permc_spec="COLAMD").solve(np.column_stack([G[lc], Hlf]))
        Y, K = X[:, :len(ids)], X[:, len(ids):]
        gt = G[fc_] - Hlf.T @ Y
        pos = {int(cc): i for i, cc in enumerate(lc)}
        prow = {k: [pos[col0[k] + j] for j in range(self.layout.dim(g))] for g, k, _ in self.locals}
        self._sw = {"ids": ids, "Y": {k: Y[r_] for k, r_ in prow.items()},
                    "K": {k: K[r_] for k, r_ in prow.items()}}
        return {"ids": ids, "G": gt, "n_p": self.param_dim()}

    def local_sandwich(self, zf: np.ndarray, scale: float, offset: int = 0
                       ) -> dict[int, np.ndarray]:
        """Sandwich covariances of this mission's parameter nodes given the joint ``Z_f``
        (d x all blocks), the joint's ``scale`` and where this mission's blocks start among
        the joint's (see :meth:`sandwich_part`)."""
        sw: dict[str, Any] = self._sw
        out = {}
        for k, Yk in sw["Y"].items():
            z = -sw["K"][k] @ zf if self.dim else np.zeros((len(Yk), zf.shape[1]))
            z[:, sw["ids"] + offset] += Yk
            z = z - z.mean(axis=1, keepdims=True)
            out[k] = scale * z @ z.T
        return out

    def result(self, values: gtsam.Values, others: np.ndarray | None = None,
               sandwich: dict | None = None) -> Result:
        """This mission's result at ``values``: track, inertial re-trace, residuals and the
        marginal covariances of its nodes, given the information ``others`` (d, d) that the
        rest of the joint problem (other missions, the prior if not in this graph) holds on
        the fixed node."""
        gfg = self.bg.linearize(values)
        if self.dim and others is not None:
            gfg.add(gtsam.HessianFactor(FIXED, np.asarray(others, float), np.zeros(self.dim), 0.0))
        bt = gfg.eliminateMultifrontal(self.ordering)
        cov_model = {k: bt.marginalCovariance(k) for _, k, _ in self.bg.nodes}
        cov_sw = None
        if sandwich is not None and getattr(self, "_sw", None) is not None:
            cov_sw = self.local_sandwich(sandwich["zf"], sandwich["scale"],
                                         int(sandwich.get("offset", 0)))
            cov_sw[FIXED] = sandwich["cov_f"]
        cov = honest_covariance(cov_model, cov_sw, sandwich["dof"] if sandwich else None)
        res = self.smoother.make_result(self.layout, values, self.bg.parts, self.bg.nodes, cov)
        res.info["sigma_model"] = {n: float(np.sqrt(max(C[i, i], 0.0)))
                                   for g, k, _ in self.bg.nodes if g != "fixed"
                                   for C in [cov_model[k]]
                                   for i, n in enumerate(self.layout.names[g])}
        verdicts = self.smoother.check_plausibility(self.bg, values)
        res.info["plausibility"] = {self.name: verdicts[0].as_dict()}
        res.info["plausible"] = all(v.plausible for v in verdicts)
        return res


class MissionSession:
    """A mission's state between rounds of :func:`joint_lm` (kept wherever the mission
    lives): the current values and linearisation, and the pending trial.

    ``handle(op, args) -> reply`` serves the requests ("open", "sys", "step", "result").
    A session created afresh in the middle of a run (its worker died) re-solves its locals
    at the client's ``f`` on "sys" and answers "lost" to a "step" it did not prepare.
    """

    def __init__(self, problem: MissionProblem):
        self.p = problem
        self.values = problem.initial_values()
        self.cost: float | None = None
        # (gfg, hdiag, hdiag_f) at self.values
        self.lin: tuple[gtsam.GaussianFactorGraph, dict, np.ndarray] | None = None
        self.trial: int | None = None       # id of the prepared trial
        self.bn: gtsam.GaussianBayesNet | None = None
        self._lam = 0.0
        self.system: ReducedSystem | None = None
        self.cand: tuple[int, gtsam.Values, float] | None = None    # (trial, values, cost)
        self.compute = 0.0                  # s spent in handle()

    def handle(self, op: str, args: dict) -> dict:
        t0 = time.perf_counter()
        try:
            return getattr(self, "_" + op)(**args)
        finally:
            self.compute += time.perf_counter() - t0

    def _open(self) -> dict:
        return {"f0": self.p.initial_fixed(), "layout": self.p.layout, "name": self.p.name,
                "t0": self.p.knot_start()}

    def _sys(self, f: np.ndarray, lam: float, trial: int, commit: int | None = None,
             start: bool = False, sandwich: tuple[float, float] | None = None) -> dict:
        p = self.p
        filled = False
        if commit is not None and self.cand is not None and self.cand[0] == commit:
            _, self.values, self.cost = self.cand
            self.lin, filled = None, True
        self.cand = None
        recovered = False
        if p.dim and not np.array_equal(p.fixed_of(self.values), np.asarray(f, float)):
            if start:
                self.values = p.with_fixed(self.values, f)
            else:
                self.values, self.cost = p.solve(f, self.values)
                filled, recovered = False, True
            self.lin = None
        if self.lin is None:
            if self.cost is None or not filled:
                self.cost = p.bg.error(self.values)
            self.lin = p.linearize(self.values, filled=True)
        assert self.cost is not None
        gfg, hdiag, hdiag_f = self.lin
        self.bn, self.system = p.reduce(gfg, hdiag, lam, self.cost, hdiag_f)
        self.trial, self._lam = trial, lam
        out = {"system": self.system, "recovered": recovered}
        if sandwich is not None:                # (t0, block): the final, undamped system
            out["sandwich"] = p.sandwich_part(gfg, *sandwich)
        return out

    def _step(self, trial: int, delta_f: np.ndarray, f_new: np.ndarray, mode: str) -> dict:
        """``mode``: "try" (clamp the locals if the step crosses their bounds, else evaluate
        the candidate), "probe" (only clamp), "final" (evaluate with the clamps set)."""
        p = self.p
        if self.trial != trial or self.bn is None:
            return {"lost": True}
        delta = p.back_substitute(self.bn, delta_f)
        if mode != "final":
            clamps = p.local_clamps(self.values, delta)
            if clamps:
                assert self.lin is not None and self.cost is not None   # set with self.bn
                gfg, hdiag, hdiag_f = self.lin
                self.bn, self.system = p.reduce(gfg, hdiag, self._lam, self.cost, hdiag_f, clamps)
                return {"clamped": self.system}
            if mode == "probe":
                return {"ok": True}
        cand, err = p.candidate(self.values, delta, f_new)
        self.cand = (trial, cand, err)      # the dynamics cache now holds the candidate
        return {"cost": err}

    def _result(self, f: np.ndarray, others: np.ndarray | None,
                sandwich: dict | None = None) -> dict:
        p = self.p
        if p.dim and not np.array_equal(p.fixed_of(self.values), np.asarray(f, float)):
            self.values, self.cost = p.solve(f, self.values)      # a fresh session
            sandwich = None
        res = p.result(self.values, others, sandwich)
        res.model = None
        return {"result": res}


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
    block = settings.sandwich_block
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
                    converged, float(total.cost), history, rounds, system.recovered, cov_model_f)


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
    mission's in ``info["per_mission"]`` and its MissionResult in ``missions``."""
    layout, results = sol.layout, sol.results
    r0 = results[0]
    values, sigma = dict(r0.values), dict(r0.sigma)
    names_f = layout.names.get("fixed", ())
    sigma_model = dict(r0.info.get("sigma_model", {}))
    cm = sol.cov_model_f if sol.cov_model_f is not None else sol.cov_f
    for i, n in enumerate(names_f):
        values[n] = float(sol.f[i])
        sigma[n] = float(np.sqrt(max(sol.cov_f[i, i], 0.0)))
        sigma_model[n] = float(np.sqrt(max(cm[i, i], 0.0)))
    per_mission: dict = {}
    plaus: dict = {}
    for r in results:
        per_mission.update(r.info.get("per_mission", {}))
        plaus.update(r.info.get("plausibility", {}))
    cov = dict(r0.info.get("covariance", {}))
    if names_f:
        cov["fixed"] = sol.cov_f.tolist()
    info: dict[str, Any] = {
        "per_mission": per_mission, "covariance": cov, "iterations": sol.iterations,
        "trials": sol.trials, "converged": sol.converged, "cost": sol.cost,
        "rounds": sol.rounds, "recovered": sol.recovered, "solver": "schur",
        "sigma_model": sigma_model,
        "sigma_inflation": sigma_inflation(sigma, sigma_model),
        "plausibility": plaus, "plausible": all(r.info.get("plausible", True) for r in results)}
    return Result(method="fg", mode="batch", estimated=layout.estimated, values=values,
                  sigma=sigma, missions=[r.missions[0] for r in results], history=r0.history,
                  info=info, timings=dict(timings or {}), effects=r0.effects, model=None)


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
