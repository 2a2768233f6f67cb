"""One mission's side of the joint batch fit computed one mission at a time
(:mod:`aqfg.fg.schur`): its graph with the fixed node held apart, the Schur complement of
its locals on the fixed node (:class:`ReducedSystem`), the back-substitution of a step,
its own solve at a given fixed node and its share of the result; :class:`MissionSession`
serves the joint loop's requests for it (in this process or in a fleet worker)."""
from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import gtsam
import numpy as np

from aqfg.data.mission import Mission
from aqfg.fg import factors as fc
from aqfg.fg.batch import BatchSmoother
from aqfg.fg.common import check_missions
from aqfg.fg.covariance import honest_covariance
from aqfg.fg.fastlm import FastSystem
from aqfg.fg.graph_lm import GraphLM, active_bounds, hessian_diagonal
from aqfg.fg.lm import LMParams, diagonal_floor, levenberg_marquardt
from aqfg.fg.schur_fast import FastSession
from aqfg.fg.schur_system import FIXED, ReducedSystem
from aqfg.fg.settings import FGSettings
from aqfg.result import Result

_PIN = 1e8          # whitened weight holding the fixed node during a mission's own solve


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
        # the numpy form of the graph (None: outside its shape, the GTSAM path serves)
        self.fs = FastSystem.build(self.bg, self.settings) if self.settings.solver.fast_lm else None
        self._orders: tuple | None = None
        if self.dim:
            self._pin = gtsam.JacobianFactor(FIXED, _PIN * np.eye(self.dim), np.zeros(self.dim),
                                             gtsam.noiseModel.Unit.Create(self.dim))

    def _orderings(self) -> tuple:
        """The elimination orderings (all keys, the fixed node last; the locals alone),
        made on first use: the numpy path needs them only for the result."""
        if self._orders is None:
            gfg = self.bg.linearize(self.bg.values)
            if self.dim:
                order = gtsam.Ordering.ColamdConstrainedLastGaussianFactorGraph(
                    gfg, gtsam.KeyVector([FIXED]))
                local = gtsam.Ordering()
                for i in range(order.size() - 1):
                    local.push_back(order.at(i))
                self._orders = (order, local)
            else:
                order = gtsam.Ordering.MetisGaussianFactorGraph(gfg)
                self._orders = (order, order)
        return self._orders

    @property
    def ordering(self) -> gtsam.Ordering:
        return self._orderings()[0]

    @property
    def local_ordering(self) -> gtsam.Ordering:
        return self._orderings()[1]

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
        res.sigma_model = {n: float(np.sqrt(max(C[i, i], 0.0)))
                           for g, k, _ in self.bg.nodes if g != "fixed"
                           for C in [cov_model[k]]
                           for i, n in enumerate(self.layout.names[g])}
        verdicts = self.smoother.check_plausibility(self.bg, values)
        res.plausibility = {self.name: verdicts[0].as_dict()}
        res.plausible = all(v.plausible for v in verdicts)
        return res


class MissionSession:
    """A mission's state between rounds of :func:`joint_lm` (kept wherever the mission
    lives): the current values and linearisation, and the pending trial.

    ``handle(op, args) -> reply`` serves the requests ("open", "sys", "step", "result"):
    on the mission's numpy system where its graph has that form
    (:class:`aqfg.fg.schur_fast.FastSession`, which also returns the mission's adapted
    track with its result), else on its GTSAM graph.
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
        # the numpy system's session where the mission's graph has its form
        self.fast = FastSession(problem, problem.fs) if problem.fs is not None else None

    def handle(self, op: str, args: dict) -> dict:
        t0 = time.perf_counter()
        try:
            if self.fast is not None and op != "open":
                return getattr(self.fast, op)(**args)
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
