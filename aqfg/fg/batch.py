"""Batch factor-graph smoothing of one or several missions of one vehicle.

MAP estimate of every state knot and the parameter nodes jointly (see :mod:`aqfg.fg.factors`),
with Levenberg-Marquardt driven from Python:

* GTSAM's own optimizers hand every ``CustomFactor`` callback a copy of all ``Values``
  (O(N^2) per iteration, gtsam-notes), so the loop here calls ``graph.linearize`` /
  ``graph.error`` on Values it owns;
* before each linearisation the dynamics of all knots come from ONE batched kernel call per
  (mission, parameter segment) (``Model.propagate_many``); the dynamics factors read those
  results (:func:`aqfg.fg.factors.cached_dynamics_factor`, same maths as the stand-alone factor);
* a METIS ordering is computed once; the parameter marginal covariances come from the Bayes
  tree of the final elimination;
* Marquardt's diagonal damping (lambda diag(J^T J)), not lambda I, and a closed-form initial
  heading/current searched over the thrust/drag scale (:func:`aqfg.fg.init.candidate_starts`).

What each of these buys, measured: docs/architecture.md, "Measurements (design decisions)".
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace

import gtsam
import numpy as np

from aqfg.data.mission import Mission
from aqfg.fg import factors as fc
from aqfg.fg import noise, observability, plausibility
from aqfg.fg.basins import (
    MISFIT_INFLATION as MISFIT_INFLATION,
)
from aqfg.fg.basins import (
    ambiguity_margin as ambiguity_margin,
)
from aqfg.fg.basins import (
    ambiguity_variance,
    as_good_a_basin,
    basin_rank,
    basin_spread,
    basin_summary,
    batch_warnings,
    sigma_by_name,
    widen_by_profile,
)
from aqfg.fg.batch_result import batch_result
from aqfg.fg.common import (
    check_missions,
    mission_model,
    outliers,
    progress_fn,
)
from aqfg.fg.covariance import block_sandwich, honest_covariance, sigma_inflation
from aqfg.fg.fastlm import FastSystem, levenberg_marquardt_fast
from aqfg.fg.graph import (
    BuiltGraph,
    MissionPart,
    ParamNode,
    build_graph,
    too_short_for_sandwich,
)
from aqfg.fg.graph import (
    solution_values as solution_values,
)
from aqfg.fg.graph_lm import (
    GraphLM as GraphLM,
)
from aqfg.fg.graph_lm import LMOutcome, fast_covariance, finish_fast, levenberg_marquardt
from aqfg.fg.graph_lm import (
    active_bounds as active_bounds,
)
from aqfg.fg.graph_lm import (
    diagonal_floor as diagonal_floor,
)
from aqfg.fg.graph_lm import (
    hessian_diagonal as hessian_diagonal,
)
from aqfg.fg.plausibility import Plausibility
from aqfg.fg.settings import FGSettings
from aqfg.fg.starts import (
    alternative_starts,
    evaluable_values,
    given_start,
    high_sway,
    plausibility_verdicts,
)
from aqfg.fg.user_factors import FactorSource
from aqfg.model.vehicle import Model
from aqfg.result import Result, SolveSummary, Track
from aqfg.threads import blas_threads

log = logging.getLogger(__name__)


class BatchSmoother:
    """Batch MAP smoothing of missions of one vehicle sharing the fixed-parameter node.

    ``BatchSmoother(model=None, effects=(), estimate=None, init=None, settings=None)``;
    ``run(missions) -> Result``. ``estimate`` defaults to all parameters of the model (the
    six base ones plus those of the active effects); ``init`` gives initial values (and the
    values of parameters not estimated).
    """

    def __init__(self, model: Model | None = None, *, effects=(), estimate=None, init=None,
                 settings: FGSettings | None = None, progress=None,
                 also_start: dict[str, float] | None = None,
                 factors: FactorSource | None = None):
        """``also_start``: estimated parameter values to solve from as well (states from
        the fixes), e.g. an online estimate; the lower cost among plausible solutions wins
        as for the heading basins. ``factors``: GTSAM factors of the user's own on the
        graph's states and parameters (:mod:`aqfg.fg.user_factors`); the graph is then
        solved on GTSAM's linearisation (``solver.fast_lm`` off)."""
        self.factors = factors
        self.also_start = dict(also_start) if also_start else None
        self.log_warnings = True           # Result.warnings also to the log (WARNING)
        self.fast_solution: tuple | None = None   # (FastSystem, evaluation) of the last run
        self.short_solution: tuple | None = None  # the same where too short for the sandwich
        # the model-only re-trace of each mission in the result; False: left empty where
        # one parameter vector serves the mission, for a caller that changes the parameters
        # and re-traces itself (fit_fg after the dead-reckoning refinement)
        self.inertial = True
        # True: run() leaves the tracks at the nominal noise and the caller smooths them
        # (smooth_tracks) after using the fit's states (fit_fg's dead-reckoning refinement
        # starts from them, as the fleet's does)
        self.defer_track = False
        self._track_job: tuple | None = None
        self.model = model
        self.effects = tuple(effects)
        self.estimate = None if estimate is None else tuple(estimate)
        self.init = dict(init or {})
        self.settings = settings or FGSettings()
        if factors is not None:          # the numpy form holds the built-in factors only
            self.settings = self.settings.with_(solver={"fast_lm": False})
        self.progress = progress_fn(progress)

    # ---------------------------------------------------------------- graph
    def build(self, missions: list[Mission], *, fixed_prior: bool = True) -> BuiltGraph:
        """The graph of ``missions`` with its initial values (see :class:`BuiltGraph`).

        ``fixed_prior=False`` leaves out the prior on the shared fixed node, for a caller
        that builds missions apart and must count that prior once (:mod:`aqfg.fg.schur`).
        """
        return build_graph(missions, model=self.model, effects=self.effects,
                           estimate=self.estimate, init=self.init,
                           settings=self.settings, fixed_prior=fixed_prior,
                           factors=self.factors)

    # ---------------------------------------------------------------- solve
    def run(self, missions) -> Result:
        """The batch fit of ``missions`` (single-threaded BLAS: the matrices are small and
        a thread pool on a loaded machine made the closed-form start 20-60x slower)."""
        with blas_threads(1):
            return self._run(missions)

    def _run(self, missions) -> Result:
        missions = check_missions(missions)
        s = self.settings
        self._track_job = None
        t_start = time.perf_counter()
        self.progress(0.0, "building the graph")
        bg = self.build(missions)
        t_built = time.perf_counter()
        sol, verdicts, basins = self._search_basins(bg, _first_solve(bg, s, self.progress, self.init))
        out, fs = sol.out, sol.fs
        slips = [v.slip_deg for v in verdicts if v.slip_deg is not None]
        held = None
        if not all(v.plausible for v in verdicts):
            held = self._hold_sway(missions, bg, basins, verdicts)
            if held is not None:
                if self.log_warnings:
                    for x in held.warnings:
                        log.warning("fg: %s", x)
                return held if self.defer_track else self.smooth_tracks(held)
        elif slips and max(slips) > plausibility.SUSPECT_SLIP:
            held = self._hold_sway(missions, bg, basins, verdicts)
        # marginal covariances of the parameter nodes from the undamped Bayes tree
        t_cov = time.perf_counter()
        cov_model, cov = _covariances(bg, sol, s)
        t_end = time.perf_counter()
        res = self.make_result(bg.layout, out.values, bg.parts, bg.nodes, cov)
        res.timings = {"batch": [t_end - t_start], "build": [t_built - t_start],
                       "iteration": out.it_times, "covariance": [t_end - t_cov]}
        _sigma_info(res, bg, cov_model, s)
        _ambiguity_info(res, basins, out.cost, len(bg.parts))
        if sol.short and s.batch.heading_profile and fs is not None and out.fast is not None:
            widen_by_profile(res, fs, bg, bg.nodes, out.values, s)
        res.solve = SolveSummary(
            out.converged, float(out.cost), out.iterations, out.trials,
            hit_iteration_limit=(not out.converged) and out.iterations >= s.solver.max_iterations)
        _verdict_info(res, bg, verdicts)
        if held is not None:
            _held_sway_info(res, held, out.cost, slips)
        if self.log_warnings:
            for w in res.warnings:
                log.warning("fg: %s", w)
        res.process_noise_scale = sol.q_scale
        res.process_noise_measured = sol.q_measured
        res.process_noise_evidence = sol.q_tried
        res.info.update({"n_states": sum(len(p.keys) for p in bg.parts),
                         "n_factors": int(bg.graph.size()),
                         "kernel": "cpp" if bg.parts[0].model.uses_cpp else "numpy",
                         "settings": s})
        self._track_job = None
        # the nominal-noise solution on the numpy system (aqfg.fg.structural_sigma.structural_sigma)
        self.fast_solution = ((fs, out.fast) if sol.q_scale == 1.0 and fs is not None
                              and out.fast is not None else None)
        # data too short for the sandwich: its solution at the evidence's noise, for the
        # structural sigma (the only misfit check left there, aqfg.fg.structural_sigma.structural_sigma)
        self.short_solution = ((fs, out.fast) if sol.short and fs is not None
                               and out.fast is not None else None)
        res.too_short_for_sandwich = bool(sol.short)
        if s.batch.adapt_track and self.fast_solution is not None:
            self._track_job = (fs, out, bg.layout, bg.parts, bg.nodes, cov)
        if not self.defer_track:
            self.smooth_tracks(res)
        self.progress(1.0, f"done: {out.iterations} iterations, {t_end - t_start:.2f} s")
        return res

    def _search_basins(self, bg: BuiltGraph, sol: _Solve
                       ) -> tuple[_Solve, list[Plausibility], list[dict]]:
        """The first solve ``sol`` against those from the other starts worth trying
        (:meth:`_alternatives`, ``also_start``): the chosen one (a plausible solution before
        an implausible one, then the lower cost or the larger evidence), its plausibility
        verdicts and every basin's summary (``Result.basins``)."""
        s, fs, out = self.settings, sol.fs, sol.out
        # where the evidence chooses the noise, basins are ranked by their evidence, each
        # under the noise its own misfit asks for (noise.basin_evidence): the peak height
        # under the noise one basin chose favours a sliding hull on a short crop, which
        # ranked a basin 43 deg off 7 lower in cost and 14.5 lower in evidence
        # (docs/independent-vehicle.md)
        le_out = np.nan
        if sol.adapt and s.batch.rank_by_evidence and fs is not None and out.fast is not None:
            le_out = fs.log_evidence(out.fast)
        by_ev = bool(np.isfinite(le_out))
        q_out = sol.q_scale
        verdicts = self.check_plausibility(bg, out.values)
        basins = [basin_summary(bg, out, verdicts, "user start" if "theta_e" in self.init
                                else "closed-form start" if all(bg.starts)
                                else "null heading start (no closed form)")]
        if by_ev:
            basins[0].update(log_evidence=float(le_out), process_noise_scale=q_out)
        for label, alt in [*alternative_starts(bg, verdicts, self.init, sol.short),
                           *given_start(bg, self.also_start)]:
            o = levenberg_marquardt(bg, alt, sol.ordering, s, None, fs)
            le_o, q_o = np.nan, q_out
            if by_ev and fs is not None and o.fast is not None:
                le_o, q_o, Xo, tho = noise.basin_evidence(fs, *fs.from_values(o.values),
                                                          o.fast, s)
                if q_o != q_out:
                    o = finish_fast(fs, o, Xo, tho, s)
                    assert o.fast is not None       # the numpy path's evaluation
                    le_o = fs.log_evidence(o.fast)
            v = self.check_plausibility(bg, o.values)
            basins.append(basin_summary(bg, o, v, label))
            if by_ev:
                basins[-1].update(log_evidence=float(le_o), process_noise_scale=q_o)
            # (lower by more than round-off: a start that ends in the same basin keeps the
            # first solution and its iterates)
            if np.isfinite(le_o) and np.isfinite(le_out):
                lower = le_o > le_out + 1e-6 * max(abs(le_out), 1.0)
            else:
                lower = o.cost < out.cost - 1e-6 * max(abs(out.cost), 1.0)
            if (all(x.plausible for x in v) and not all(x.plausible for x in verdicts)) or \
                    (all(x.plausible for x in v) == all(x.plausible for x in verdicts)
                     and lower):
                out, verdicts, le_out, q_out = o, v, le_o, q_o
            if by_ev and fs is not None:
                fs.set_process_scale(q_out)
        if not by_ev:
            return replace(sol, out=out), verdicts, basins
        # each basin's cost on the chosen one's scale, by evidence: the chosen one's
        # cost plus its evidence lead (what the ambiguity margin compares)
        for bas in basins:
            le_b = bas.get("log_evidence", np.nan)
            bas["rank"] = float(out.cost + (le_out - le_b)) \
                if np.isfinite(le_b) and np.isfinite(le_out) else float(bas["cost"])
        # the noise measured is the chosen basin's (the first basin's may differ: a
        # 20-s batch of heldout-231 chose a basin at q = 1 after the first asked 64,
        # and an online smoother replaying that solution at 64 ran 24 deg from it)
        return replace(sol, out=out, q_scale=q_out, q_measured=q_out), verdicts, basins

    def smooth_tracks(self, res: Result) -> Result:
        """:attr:`FGSettings.batch.adapt_track`: the tracks and their residuals of the result
        ``res`` of the last :meth:`run` (in place) from the states smoothed again with the
        parameters held at the fit, under the process-noise factor of the largest evidence
        of the states given them; ``res`` as it is where that does not apply (the setting
        off, the GTSAM path, a noise already chosen by the evidence)."""
        job, self._track_job = self._track_job, None
        if job is None:
            return res
        fs, out, layout, parts, node_list, cov = job
        s = self.settings
        t0 = time.perf_counter()
        X0, th = fs.from_values(out.values)
        q, Xq, tried = noise.track_noise_search(fs, X0, th, out.fast, s)
        res.track_noise_scale = {p.mission.name: float(v) for p, v in zip(parts, q)}
        res.track_noise_evidence = tried
        if np.any(q != 1.0):
            fs.set_process_scale(1.0, per_part=q)
            X, *_ = levenberg_marquardt_fast(fs, None, s, start=(Xq, th), hold_params=True)
            fs.set_process_scale(1.0)
            tracked = self.make_result(layout, fs.to_values(X, th, out.values), parts,
                                       node_list, cov)
            for mr, mt in zip(res.missions, tracked.missions):
                mr.track, mr.residuals = mt.track, mt.residuals
        res.timings["track"] = [time.perf_counter() - t0]
        return res

    # ---------------------------------------------------------------- basins
    def check_plausibility(self, bg: BuiltGraph, values: gtsam.Values) -> list[Plausibility]:
        """Physical plausibility of every mission's part of a solution."""
        return plausibility_verdicts(bg, values)

    def _hold_sway(self, missions, bg: BuiltGraph, basins: list[dict],
                   verdicts: list[Plausibility]) -> Result | None:
        """No start gave a plausible solution and the sway drag is estimated: the fixes alone
        prefer a hull sliding sideways (k_yz near zero), which no vessel does on a held
        course. Solve again with k_yz held at the high sway-drag start's value (at least ten
        times the surge drag; above that the slip is near zero whatever its value) and
        return that fit, if it is plausible, with a warning and the free fit's basins."""
        lay = bg.layout
        if not {"k_x", "k_yz"} <= set(lay.estimated) or "k_yz" in self.init \
                or not bg.starts or not all(bg.starts):
            return None
        sway = high_sway(bg.starts[0])
        if not sway:
            return None
        st = sway[0]
        init = {**self.init, "k_yz": st.fixed["k_yz"], "k": st.fixed["k"], "k_x": st.fixed["k_x"]}
        sm = BatchSmoother(self.model, effects=self.effects,
                           estimate=tuple(n for n in lay.estimated if n != "k_yz"), init=init,
                           settings=self.settings)
        sm.log_warnings = False
        sm.defer_track = True
        res = sm.run(missions)
        if not res.plausible:
            return None
        self._track_job = sm._track_job
        # its numpy system too, for the structural sigma (aqfg.fg.structural_sigma.structural_sigma): a
        # held-sway fit went without it, and its current sat 7 sigma off on a GNSS-only
        # weak-propeller Otter (docs/independent-vehicle.md)
        self.fast_solution = sm.fast_solution
        self.short_solution = sm.short_solution
        slip = max((v.slip_deg or 0.0) for v in verdicts)
        if slip >= 1.0:
            why = (f"slid sideways through the water ({slip:.0f} deg off the thrust axis on "
                   "held courses), which no hull does")
        else:
            # implausible for another reason than a slip it shows (say which)
            reasons = sorted({r for v in verdicts for r in v.reasons})
            why = f"was implausible ({'; '.join(reasons) or 'no start gave a plausible fit'})"
        w = (f"the free fit {why}: k_yz held at {st.fixed['k_yz']:.3g} "
             f"(sway drag {st.fixed['k_yz'] / st.fixed['k_x']:.0f}x the surge drag, where the "
             "slip is near zero whatever its value); run `aqfg diagnose` for the missing physics")
        res.warnings = [w, *res.warnings]
        res.info["held_sway"] = {"k_yz": float(st.fixed["k_yz"]), "free_fit_basins": basins}
        return res

    # ---------------------------------------------------------------- result
    def make_result(self, layout: fc.ParamLayout, values: gtsam.Values, parts: list[MissionPart],
                    node_list: list[ParamNode], cov: dict[int, np.ndarray]) -> Result:
        """The :class:`Result` of a solution ``values`` of the graph of ``parts``, with the
        parameter nodes' covariances ``cov`` ({key: covariance}, the parameters' units)."""
        return batch_result(layout, values, parts, node_list, cov, self.settings, self.inertial)


def smooth_track(mission: Mission, p: np.ndarray, *, model: Model | None = None, effects=(),
                 settings: FGSettings | None = None) -> tuple[Track, dict, float]:
    """The track of ``mission`` smoothed with every parameter held at the full vector ``p``
    under the process noise its evidence chooses (:attr:`FGSettings.batch.adapt_track`, as the
    batch's own tracks), for a fit whose states came from elsewhere (the fleet's joint
    solve). Returns the track, its residuals and the process-noise factor."""
    s = (settings or FGSettings()).with_(batch={"adapt_track": True, "adapt_noise": False,
                                                   "sandwich_block": 0.0})
    names = mission_model(model, mission, effects).all_names
    bs = BatchSmoother(model, effects=effects, estimate=(), settings=s,
                       init={n: float(v) for n, v in zip(names, p)})
    bs.inertial = False
    bs.log_warnings = False
    res = bs.run([mission])
    mr = res.missions[0]
    return mr.track, mr.residuals, float((res.track_noise_scale or {}).get(mission.name, 1.0))


@dataclass
class _Solve:
    """A batch run's solution between its steps: the numpy system (None on the GTSAM
    path), the elimination ordering (GTSAM path), the LM outcome, whether the data are
    too short for the sandwich and whether the evidence chooses the process noise, and
    that noise: its factor, the factors tried (factor -> log-evidence) and the one measured
    (None where not measured)."""
    fs: FastSystem | None
    ordering: gtsam.Ordering | None
    out: LMOutcome
    short: bool
    adapt: bool
    q_scale: float = 1.0
    q_tried: dict = field(default_factory=dict)
    q_measured: float | None = None


def _first_solve(bg: BuiltGraph, s: FGSettings, progress, init: dict) -> _Solve:
    """LM from the graph's initial values (where the model cannot be evaluated there, from
    the first start where it can: :func:`~aqfg.fg.starts.evaluable_values`), then the
    process noise its evidence chooses (:attr:`FGSettings.batch.adapt_noise`) or measures
    (:attr:`FGSettings.batch.measure_noise`)."""
    fs = FastSystem.build(bg, s) if s.solver.fast_lm else None
    ordering = None if fs is not None else \
        gtsam.Ordering.MetisGaussianFactorGraph(bg.linearize(bg.values))
    out = levenberg_marquardt(bg, bg.values, ordering, s, progress, fs)
    if not np.isfinite(out.cost):
        # (LM takes no step from a start whose cost is not finite; the other starts are
        # evaluated only then)
        values = evaluable_values(bg, (lambda v: fs.evaluate(*fs.from_values(v))["cost"])
                                  if fs is not None else bg.graph.error, init)
        if values is not bg.values:
            out = levenberg_marquardt(bg, values, ordering, s, progress, fs)
    q_scale, q_tried = 1.0, dict[float, float]()
    # too short for the sandwich's time blocks (it needs n_p + 2): the evidence-chosen
    # noise is the honest sigma there (docs/independent-vehicle.md)
    short = too_short_for_sandwich(bg, s)
    adapt = short if s.batch.adapt_noise is None else s.batch.adapt_noise
    q_measured = None
    if (adapt or s.batch.measure_noise) and fs is not None and out.fast is not None:
        # how much process noise the model needs (aqfg.fg.noise): a model that is not
        # the vehicle's bends the parameters under the nominal noise; measured only
        # (batch.measure_noise), the solution stays the nominal one
        X0, th0 = fs.from_values(out.values)
        q_ev, Xq, thq, q_tried = noise.evidence_search(fs, X0, th0, out.fast, s)
        q_measured = q_ev
        if adapt:
            q_scale = q_ev
            if q_scale != 1.0:
                out = finish_fast(fs, out, Xq, thq, s)
        else:
            # back to the nominal noise and its solution (the search leaves the system
            # at the factor it chose; one converged LM pass refreshes the evaluation)
            q_tried = {}
            fs.set_process_scale(1.0)
            out = finish_fast(fs, out, X0, th0, s)
    return _Solve(fs, ordering, out, short, adapt, q_scale, q_tried, q_measured)


def _covariances(bg: BuiltGraph, sol: _Solve, s: FGSettings) -> tuple[dict, dict]:
    """The parameter nodes' covariances at the solution: the model's (the undamped
    Hessian's) and the honest one (with the sandwich's, :func:`honest_covariance`)."""
    out, fs, layout, node_list = sol.out, sol.fs, bg.layout, bg.nodes
    # each mission's blocks are its own: its times shifted past the previous missions'
    key_time, shift = {}, 0.0
    for part in bg.parts:
        t_first = float(part.knots[0])
        key_time.update({k: shift + float(t) - t_first for k, t in zip(part.keys, part.knots)})
        # next mission from a block boundary: its blocks start at its own start, as in
        # the fleet's per-mission solve (aqfg.fg.schur)
        b = s.batch.sandwich_block or 1.0
        shift += b * (np.floor((float(part.knots[-1]) - t_first) / b) + 2.0)
    if out.fast is not None:
        assert fs is not None           # the numpy path ran: its system was built
        cov_model, cov_sw = fast_covariance(fs, out.fast, node_list, layout, key_time, s)
    else:
        gfg = out.gfg
        assert gfg is not None          # the GTSAM path ran: its linearisation
        try:
            bt = gfg.eliminateMultifrontal(sol.ordering)
            cov_model = {k: bt.marginalCovariance(k) for _, k, _ in node_list}
        except RuntimeError:
            # the undamped system is singular: no parameter is determined by the Hessian
            cov_model = {k: np.diag(np.full(layout.dim(g), np.inf)) for g, k, _ in node_list}
        cov_sw = block_sandwich(gfg, bg.key_dims(), key_time, [n.key for n in node_list],
                                s.batch.sandwich_block) if s.batch.sandwich_block else None
    cov = honest_covariance(cov_model, cov_sw[0] if cov_sw else None,
                            cov_sw[1] if cov_sw else None)
    return cov_model, cov


def _sigma_info(res: Result, bg: BuiltGraph, cov_model: dict, s: FGSettings) -> None:
    """The model's sigmas, the honest ones' inflation over them and each parameter's
    observability verdict into ``res``."""
    layout, parts = bg.layout, bg.parts
    res.sigma_model = {n: float(v) for n, v in
                       sigma_by_name(layout, bg.nodes, cov_model).items()}
    res.sigma_inflation = sigma_inflation(res.sigma, res.sigma_model)
    prior_sigma = {n: s.graph.prior_sigma.get(n, s.graph.prior_scale * parts[0].model.spec(n).scale)
                   for n in layout.estimated}
    res.observability = observability.verdicts(
        parts[0].model, [p.mission for p in parts], layout.estimated, res.sigma,
        res.sigma_model, prior_sigma)
    per = observability.mission_verdicts(parts[0].model, [p.mission for p in parts],
                                         layout.estimated)
    if per:
        res.observability_per_mission = per


def _ambiguity_info(res: Result, basins: list[dict], err: float, n_missions: int) -> None:
    """The basins (``res.basins``) and those as good as the chosen one (cost ``err``,
    ``res.ambiguous``); the sigmas widened by their spread where there are any."""
    res.basins = basins
    ok = [b for b in basins if b["plausible"]]
    best = min((basin_rank(b) for b in ok), default=None)
    res.ambiguous = [b for b in ok if best is not None and b["cost"] != err
                     and as_good_a_basin(b, best, basins[0])]
    if not res.ambiguous:
        return
    # the sigma of a multimodal fit: the chosen basin's, widened by the spread of
    # the basins that fit as well (a sigma of one basin claimed 17 deg at a heading
    # 130 deg off: docs/independent-vehicle.md)
    extra = ambiguity_variance(res.values, res.ambiguous, float(err))
    res.sigma_unimodal = {n: res.sigma[n] for n in extra if n in res.sigma}
    res.sigma.update({n: float(np.hypot(v, np.sqrt(extra[n])))
                      for n, v in res.sigma_unimodal.items()})
    for name, pm in res.per_mission.items():
        th = pm.get("theta_e")
        if th is not None and n_missions > 1:
            d2 = basin_spread({"theta_e": th.value},
                              [({"theta_e": b["theta_e"][name]}, basin_rank(b))
                               for b in res.ambiguous if name in b["theta_e"]],
                              float(err))["theta_e"]
            pm["theta_e"] = replace(th, sigma=float(np.hypot(th.sigma, np.sqrt(d2))))


def _verdict_info(res: Result, bg: BuiltGraph, verdicts: list[Plausibility]) -> None:
    """Plausibility, the outliers and the warnings (the iteration limit's from
    ``res.solve``) into ``res``."""
    res.plausible = all(v.plausible for v in verdicts)
    res.plausibility = {bg.parts[i].mission.name: v.as_dict()
                        for i, v in enumerate(verdicts)}
    res.outliers = {mr.name: outliers(mr.residuals) for mr in res.missions}
    n_out = sum(len(v) for o in res.outliers.values() for v in o.values())
    res.warnings = batch_warnings(res)
    if n_out:
        res.warnings.append(f"{n_out} fixes more than 5 sigma from the fit were "
                            "down-weighted as outliers (listed in Result.outliers)")


def _held_sway_info(res: Result, held: Result, err: float, slips: list[float]) -> None:
    """A plausible but sliding fit (cost ``err``, ``slips`` deg): the non-sliding
    alternative ``held`` said in ``res.info``, not chosen."""
    th_f, th_h = res.values.get("theta_e"), held.values.get("theta_e")
    # named when it explains the fixes almost as well (cost within 50 %): on the
    # Otter crops +19-28 %; on aqfg's simulator, whose vehicle does slide, +200 %
    c_h = held.cost
    if th_f is not None and th_h is not None and c_h <= 1.5 * float(err) and \
            abs(float(np.angle(np.exp(1j * (th_f - th_h))))) > np.radians(10.0):
        res.info["alternative_held_sway"] = {
            "values": dict(held.values), "sigma": dict(held.sigma),
            "sigma_unimodal": {**held.sigma, **held.sigma_unimodal},
            "cost": held.cost, "cost_free": float(err)}
        res.warnings.append(
            f"the fit slides {max(slips):.0f} deg off the thrust axis on held courses; "
            f"with the sway drag held high (no sliding) theta_e is "
            f"{np.degrees(th_h):.1f} deg instead of {np.degrees(th_f):.1f} deg "
            f"(cost {held.cost:.1f} against {err:.1f}): if this hull "
            f"does not slide, pass --init k_yz={held.values['k_yz']:.3g} and leave "
            "k_yz out of --estimate")
