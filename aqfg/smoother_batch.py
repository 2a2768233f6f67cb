"""Batch factor-graph smoothing of one or several missions of one vehicle.

MAP estimate of every state knot and the parameter nodes jointly (see :mod:`aqfg.factors`),
with Levenberg-Marquardt driven from Python:

* GTSAM's own optimizers hand every ``CustomFactor`` callback a copy of all ``Values``
  (O(N^2) per iteration, gtsam-notes), so the loop here calls ``graph.linearize`` /
  ``graph.error`` on Values it owns;
* before each linearisation the dynamics of all knots come from ONE batched kernel call per
  (mission, parameter segment) (``Model.propagate_many``); the dynamics factors read those
  results (:func:`aqfg.factors.cached_dynamics_factor`, same maths as the stand-alone factor);
* a METIS ordering is computed once; the parameter marginal covariances come from the Bayes
  tree of the final elimination.

Measured here (2-core shared machine, C++ kernel, 15-min ASV mission, GNSS every 8 s,
1 s knots = 901 states / 1917 factors, all six parameters from the paper's old values;
experiments/bench_fg.py):

* this loop: 6 LM iterations of ~0.06 s, 0.5-0.6 s in all (target <= 3 s); one batched
  ``propagate_many`` costs ~2.3 us per 1-s factor, a cached factor's ``linearize`` ~9 us;
* GTSAM's ``LevenbergMarquardtOptimizer`` on the same graph with stand-alone dynamics
  factors: 0.25 s per iteration (Values copied into every callback), growing as N^2;
* parameter marginals from the final Bayes tree: 6-10 ms (``gtsam.Marginals``: 37 ms);
* Marquardt's diagonal damping (lambda diag(J^T J)) instead of lambda I: with lambda I the
  steps of the weakly observed k, k_x were damped to a crawl (45 iterations on a 5-min
  mission); a closed-form initial heading/current (:func:`initial_guess`) brought typical
  runs from 10-40 iterations to 5-8 and removed a wrong-basin solution.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import gtsam
import numpy as np

from . import factors as fc
from .mission import Mission
from .model import Model
from .params import N_DYN
from .result import MissionResult, ParamHistory, Result, Track
from .smoother_common import (FGSettings, Measurements, check_missions, default_estimate,
                              first_knot_prior, initial_guess, knot_times, measurement_factors,
                              mission_model, piecewise_inertial, progress_fn, residuals)

@dataclass
class _Part:
    """One mission's share of the graph."""
    index: int
    mission: Mission
    model: Model
    knots: np.ndarray
    keys: list                 # state keys
    seg_of: np.ndarray         # parameter segment of each dynamics interval
    seg_starts: np.ndarray     # start time of each parameter segment
    seg_slices: list           # (a, b, steps, offsets) per segment: intervals a..b-1
    f0: int                    # index of the first dynamics factor in the cache


class BatchSmoother:
    """Batch MAP smoothing of missions of one vehicle sharing the fixed-parameter node.

    ``BatchSmoother(model=None, effects=(), estimate=None, init=None, settings=None)``;
    ``run(missions) -> Result``. ``estimate`` defaults to all parameters of the model (the
    six base ones plus those of the active effects); ``init`` gives initial values (and the
    values of parameters not estimated).
    """

    def __init__(self, model: Model | None = None, *, effects=(), estimate=None, init=None,
                 settings: FGSettings | None = None, progress=None):
        self.model = model
        self.effects = tuple(effects)
        self.estimate = None if estimate is None else tuple(estimate)
        self.init = dict(init or {})
        self.settings = settings or FGSettings()
        self.progress = progress_fn(progress)

    # ---------------------------------------------------------------- graph
    def _build(self, missions: list[Mission]):
        s = self.settings
        models = [mission_model(self.model, m, self.effects) for m in missions]
        est = self.estimate if self.estimate is not None else default_estimate(models[0], "batch")
        layout = fc.ParamLayout.build(models[0], est, self.init)
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        parts: list[_Part] = []
        noise_cache: dict = {}
        nf = 0
        dyn_rows = []          # (part, interval) per cache row, to allocate the cache
        walk = s.walk_sigma and "variable" in layout.names
        guesses = []
        for mi, (m, model) in enumerate(zip(missions, models)):
            knots = knot_times(m, s.knot_spacing)
            steps, off = model.steps(m, knots)
            K = len(knots) - 1
            if walk:
                seg_of = np.floor((knots[:-1] - knots[0]) / s.walk_segment).astype(int)
            else:
                seg_of = np.zeros(K, int)
            nseg = int(seg_of.max()) + 1 if K else 1
            seg_starts = knots[0] + s.walk_segment * np.arange(nseg) if walk else knots[:1]
            slices = []
            for j in range(nseg):
                ii = np.nonzero(seg_of == j)[0]
                if not len(ii):
                    slices.append(None)
                    continue
                a, b = int(ii[0]), int(ii[-1]) + 1
                slices.append((a, b, steps.slice(int(off[a]), int(off[b])), off[a:b + 1] - off[a]))
            keys = [fc.state_key(mi, i) for i in range(len(knots))]
            guess = initial_guess(model, m, knots, layout.base)
            X0 = guess.X
            guesses.append(guess)
            for k, x in zip(keys, X0):
                values.insert(k, x)
            graph.add(first_knot_prior(m, keys[0], X0[0], s))
            if m.planar:
                for k in keys:
                    graph.add(fc.surface_factor(k, *s.surface_sigma))
            parts.append(_Part(mi, m, model, knots, keys, seg_of, seg_starts, slices, nf))
            nf += K
        cache = fc.DynamicsCache(np.zeros((nf, 6)), np.zeros((nf, 6, 6)),
                                 np.zeros((nf, 6, len(models[0].dyn_columns()))))
        # parameter nodes (started from the data-driven guess where the user gave no
        # initial value), priors (around the user's / nominal values), random walk
        node_list = []
        if "fixed" in layout.names:
            k = fc.node_key("fixed")
            f0 = layout.initial("fixed")
            names = layout.names["fixed"]
            rho2 = float(np.median([g.speed_scale for g in guesses])) ** 2
            if "k" in names and "k" not in self.init and "k_x" not in self.init:
                f0[names.index("k")] *= rho2     # steady speed ~ sqrt(k / k_x)
            values.insert(k, layout.project("fixed", f0))
            graph.add(fc.param_prior(layout, "fixed", k, s.prior_scale, sigma=s.prior_sigma))
            node_list.append(("fixed", k, None))
        for part in parts:
            if "variable" in layout.names:
                v0 = layout.initial("variable")
                g0 = guesses[part.index]
                for n, val in (("theta_e", g0.theta_e), ("s_x", g0.current[0]),
                               ("s_y", g0.current[1])):
                    if n in layout.names["variable"] and n not in self.init:
                        v0[layout.names["variable"].index(n)] = val
                v0 = layout.project("variable", v0)
                for j in range(len(part.seg_starts)):
                    k = fc.node_key("variable", part.index, j)
                    values.insert(k, v0)
                    node_list.append(("variable", k, part.index))
                    if j == 0:
                        graph.add(fc.param_prior(layout, "variable", k, s.prior_scale, sigma=s.prior_sigma))
                    else:
                        sig = np.array([(s.walk_sigma or {}).get(n, 0.0)
                                        for n in layout.names["variable"]])
                        graph.add(fc.walk_factor(layout, fc.node_key("variable", part.index, j - 1),
                                                 k, np.maximum(sig, 1e-9), s.walk_segment))
            if "sensor" in layout.names:
                k = fc.node_key("sensor", part.index)
                values.insert(k, layout.initial("sensor"))
                graph.add(fc.param_prior(layout, "sensor", k, s.prior_scale, sigma=s.prior_sigma))
                node_list.append(("sensor", k, part.index))
        # dynamics and measurement factors
        dyn_groups = layout.dyn_groups()
        for part in parts:
            mi = part.index

            def nkeys(groups, seg, mi=mi):
                return tuple((g, fc.node_key(g, mi, seg)) for g in groups)

            for i in range(len(part.knots) - 1):
                dt = float(part.knots[i + 1] - part.knots[i])
                key = (round(dt, 9), part.mission.planar)
                if key not in noise_cache:
                    noise_cache[key] = s.process.noise_model(dt, part.mission.planar)
                graph.add(fc.cached_dynamics_factor(cache, part.f0 + i, layout, part.keys[i],
                                                    part.keys[i + 1],
                                                    nkeys(dyn_groups, int(part.seg_of[i])),
                                                    noise_cache[key]))
            meas = Measurements.of(part.mission, s, part.knots[0], part.knots[-1])

            def seg_at(t, part=part):
                return int(np.clip(np.searchsorted(part.seg_starts, t, side="right") - 1, 0,
                                   len(part.seg_starts) - 1))

            def mkeys(stream, t, part=part, mi=mi):
                return nkeys(layout.meas_groups(stream), seg_at(t))
            for f in measurement_factors(part.model, layout, meas, part.knots,
                                         lambda i, part=part: part.keys[i], mkeys, s):
                graph.add(f)
        return layout, graph, values, parts, cache, node_list

    def _fill(self, layout, parts, cache, values) -> None:
        """Evaluate the dynamics of every interval at ``values`` (one kernel call per
        mission and parameter segment) into ``cache``."""
        nodes = {}
        if "fixed" in layout.names:
            nodes["fixed"] = values.atVector(fc.node_key("fixed"))
        for part in parts:
            X = np.array([values.atVector(k) for k in part.keys])
            nd = dict(nodes)
            if "sensor" in layout.names:
                nd["sensor"] = values.atVector(fc.node_key("sensor", part.index))
            for j, sl in enumerate(part.seg_slices):
                if sl is None:
                    continue
                a, b, steps, off = sl
                if "variable" in layout.names:
                    nd["variable"] = values.atVector(fc.node_key("variable", part.index, j))
                p = layout.full(nd)
                pred, Jx, Jp = part.model.propagate_many(X[a:b], p, steps, off)
                r0 = part.f0
                cache.pred[r0 + a:r0 + b] = pred
                cache.Jx[r0 + a:r0 + b] = Jx
                cache.Jp[r0 + a:r0 + b] = Jp

    # ---------------------------------------------------------------- solve
    def run(self, missions) -> Result:
        missions = check_missions(missions)
        s = self.settings
        t_start = time.perf_counter()
        self.progress(0.0, "building the graph")
        layout, graph, values, parts, cache, node_list = self._build(missions)
        t_built = time.perf_counter()
        node_dims = [(k, layout.dim(g)) for g, k, _ in node_list]
        all_keys = [(k, 6) for p in parts for k in p.keys] + node_dims

        def project(vals):
            for g, k, _ in node_list:
                v = vals.atVector(k)
                pv = layout.project(g, v)
                if np.any(pv != v):
                    vals.update(k, pv)
            return vals

        self._fill(layout, parts, cache, values)
        err = graph.error(values)
        gfg = graph.linearize(values)
        ordering = gtsam.Ordering.MetisGaussianFactorGraph(gfg)
        lam, it_times, n_it, n_trials = 1e-3, [], 0, 0
        converged = False
        for it in range(s.max_iterations):
            t_it = time.perf_counter()
            hdiag = _hessian_diagonal(gfg, all_keys)
            accepted = False
            while lam < 1e10:
                n_trials += 1
                damped = gfg.clone()
                for k, d in all_keys:
                    damped.add(gtsam.JacobianFactor(k, np.diag(np.sqrt(lam * hdiag[k])),
                                                    np.zeros(d), gtsam.noiseModel.Unit.Create(d)))
                delta = damped.eliminateMultifrontal(ordering).optimize()
                clamps = _active_bounds(layout, node_list, values, delta)
                if clamps:
                    # active set: parameters pushed through a bound go exactly to it and the
                    # rest of the step is re-solved consistently (a bare projection made LM
                    # crawl: 59 iterations with a drag term pinned at zero)
                    for k, A, b in clamps:
                        damped.add(gtsam.JacobianFactor(k, A, b, gtsam.noiseModel.Unit.Create(len(b))))
                    delta = damped.eliminateMultifrontal(ordering).optimize()
                cand = project(values.retract(delta))
                self._fill(layout, parts, cache, cand)
                err_c = graph.error(cand)
                if err_c <= err:
                    accepted = True
                    break
                lam *= 10.0
            n_it += 1
            if not accepted:
                self._fill(layout, parts, cache, values)
                break
            gain = err - err_c
            values, err = cand, err_c
            lam = max(lam / 10.0, 1e-9)
            gfg = graph.linearize(values)       # cache holds the dynamics at `values`
            it_times.append(time.perf_counter() - t_it)
            self.progress(min(0.95, 0.05 + 0.9 * (it + 1) / s.max_iterations),
                          f"iteration {it + 1}: cost {err:.6g} (lambda {lam:.0e})")
            if gain < max(s.rel_tol * err, s.abs_tol):
                converged = True
                break
        # marginal covariances of the parameter nodes from the undamped Bayes tree
        t_cov = time.perf_counter()
        bt = gfg.eliminateMultifrontal(ordering)
        cov = {k: bt.marginalCovariance(k) for _, k, _ in node_list}
        t_end = time.perf_counter()
        res = self._result(layout, values, parts, node_list, cov)
        res.timings = {"batch": [t_end - t_start], "build": [t_built - t_start],
                       "iteration": it_times, "covariance": [t_end - t_cov]}
        res.info.update({"iterations": n_it, "trials": n_trials, "converged": converged,
                         "cost": float(err), "n_states": sum(len(p.keys) for p in parts),
                         "n_factors": int(graph.size()), "kernel": "cpp" if parts[0].model.uses_cpp
                         else "numpy", "settings": s})
        self.progress(1.0, f"done: {n_it} iterations, {t_end - t_start:.2f} s")
        return res

    # ---------------------------------------------------------------- result
    def _result(self, layout, values, parts, node_list, cov) -> Result:
        s = self.settings
        model0 = parts[0].model
        val_of = {k: values.atVector(k) for _, k, _ in node_list}
        sig_of = {k: np.sqrt(np.maximum(np.diag(c), 0.0)) for k, c in cov.items()}
        mres, per_mission = [], {}
        hist = None
        for part in parts:
            mi = part.index

            def p_seg(j, mi=mi):
                nd = {}
                for g in layout.groups:
                    nd[g] = val_of[fc.node_key(g, mi, j if g == "variable" else 0)]
                return layout.full(nd)
            nseg = len(part.seg_starts)
            p_segments = [p_seg(j) for j in range(nseg)]

            def p_at(t, part=part, p_segments=p_segments):
                j = int(np.clip(np.searchsorted(part.seg_starts, t, side="right") - 1, 0, nseg - 1))
                return p_segments[j]
            X = np.array([values.atVector(k) for k in part.keys])
            track = Track(part.knots.copy(), X[:, :3], X[:, 3:])
            inertial = piecewise_inertial(part.model, part.mission, p_segments, part.seg_starts)
            res = residuals(part.model, part.mission, track, p_at, s)
            res["dynamics"] = _dynamics_residuals(part, X, p_segments, s)
            mres.append(MissionResult(part.mission.name, track, inertial, p_segments[-1], res))
            pm = {}
            for g in ("variable", "sensor"):
                if g in layout.names:
                    k = fc.node_key(g, mi, nseg - 1 if g == "variable" else 0)
                    for n, v, sg in zip(layout.names[g], val_of[k], sig_of[k]):
                        pm[n] = {"value": float(v), "sigma": float(sg)}
            per_mission[part.mission.name] = pm
            if nseg > 1 and "variable" in layout.names and mi == 0:
                names = layout.names["variable"]
                ks = [fc.node_key("variable", mi, j) for j in range(nseg)]
                hist = ParamHistory(part.seg_starts.copy(), names,
                                    np.array([val_of[k] for k in ks]),
                                    np.array([sig_of[k] for k in ks]))
        # reported values: fixed node + first mission's variable/sensor nodes (all missions
        # are in info["per_mission"] and in each MissionResult.p)
        values_d = dict(zip(model0.all_names, map(float, mres[0].p)))
        sigma_d = {}
        for g, k, mi in node_list:
            if mi not in (None, 0):
                continue
            if g == "variable" and k != fc.node_key("variable", 0, len(parts[0].seg_starts) - 1):
                continue
            for n, sg in zip(layout.names[g], sig_of[k]):
                sigma_d[n] = float(sg)
        return Result(method="fg", mode="batch", estimated=layout.estimated, values=values_d,
                      sigma=sigma_d, missions=mres, history=hist,
                      info={"per_mission": per_mission,
                            "covariance": {g: cov[k].tolist() for g, k, mi in node_list
                                           if mi in (None, 0)}},
                      effects=tuple(e.name for e in model0.effects), model=model0)


def _active_bounds(layout, node_list, values, delta, weight: float = 1e8) -> list:
    """Constraints ``(key, A, b)`` fixing the step of parameters that it would push
    beyond their bounds: ``delta_j = bound_j - v_j`` (whitened by ``weight``)."""
    out = []
    for g, k, _ in node_list:
        v = values.atVector(k)
        d = delta.at(k)
        lo, hi = layout.bounds(g)
        new = v + d
        hit = (new < lo) | (new > hi)
        if not np.any(hit):
            continue
        idx = np.flatnonzero(hit)
        A = np.zeros((len(idx), len(v)))
        A[np.arange(len(idx)), idx] = weight
        target = np.where(new[idx] < lo[idx], lo[idx], hi[idx]) - v[idx]
        out.append((k, A, weight * target))
    return out


def _hessian_diagonal(gfg: gtsam.GaussianFactorGraph, key_dims) -> dict:
    """Diagonal of the Gauss-Newton Hessian A^T A per key (Marquardt's damping scale),
    from the whitened sparse Jacobian (columns in sorted key order, then b)."""
    ij = gfg.sparseJacobian_()
    col = ij[1].astype(np.int64) - 1
    d = np.bincount(col, weights=ij[2] ** 2)
    out, c = {}, 0
    for k, n in sorted(key_dims):
        v = d[c:c + n] if c + n <= len(d) else np.zeros(n)
        out[k] = np.maximum(v, 1e-9 * max(float(v.max(initial=0.0)), 1.0))
        c += n
    return out


def _dynamics_residuals(part: _Part, X: np.ndarray, p_segments, s: FGSettings):
    """Whitened dynamics residuals x[i+1] - f(x[i], p) per interval (diagnostics)."""
    from .result import Residuals
    raw = np.zeros((len(part.knots) - 1, 6))
    for j, sl in enumerate(part.seg_slices):
        if sl is None:
            continue
        a, b, steps, off = sl
        pred = part.model.propagate_many(X[a:b], p_segments[j], steps, off)[0]
        raw[a:b] = X[a + 1:b + 1] - pred
    norm = np.zeros_like(raw)
    for i in range(len(raw)):
        dt = part.knots[i + 1] - part.knots[i]
        L = np.linalg.cholesky(s.process.cov(dt, part.mission.planar))
        norm[i] = np.linalg.solve(L, raw[i])
    return Residuals(part.knots[1:].copy(), raw, norm)
