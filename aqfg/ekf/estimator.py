"""The paper's method: an EKF whose parameters are fitted by minimising the update error.

Reference: Quraishi & Martinoli, "Online kinematic and dynamic parameter estimation for
autonomous surface and underwater vehicles", §II-E and §III. This is aqfg's comparison
baseline for the factor-graph smoother; it uses the same vehicle model (one definition of
the physics, :mod:`aqfg.model.reference` / C++ ``aqfg._kernel``) and returns the same
:class:`aqfg.result.Result`.

Pieces (one module each):

* :mod:`aqfg.ekf.history` -- the timestamped history of update nodes and anchor states
  (§III-B) and the EKF noise settings (:class:`EkfConfig`);
* :mod:`aqfg.ekf.window` -- one EKF pass over a stretch of history (Eqs. 5-11, 13), numpy
  reference and C++ fast path;
* :mod:`aqfg.ekf.optim` -- ``E(P)`` (Eq. 14), its bounded minimisation (Eq. 15), the
  bound presets ("physical", "paper") and optimisers ("trf", "ceres", "gradient");
* :mod:`aqfg.ekf.uncertainty` -- sigma and per-parameter observability verdicts;
* :mod:`aqfg.ekf.report` -- the residuals and the info verdicts of a fit;
* this module -- the user API::

      est = UpdateErrorEstimator(None, missions)          # model built from the missions
      off = est.run_offline(estimate=("theta_e", "s_x", "s_y", "k", "k_x", "k_yz"))
      on = UpdateErrorEstimator(None, mission, init=off.values).run_online(
               window_fixes=3, estimate=("theta_e", "s_x", "s_y"))
      on.missions[0].track        # filtered-then-corrected trajectory
      on.history                  # parameter estimates after each fix
      on.timings["optimisation"]  # seconds per optimisation

  and :func:`fit_update_error`, the entry point ``aqfg fit --method update-error`` calls.

Modes. *Offline* ("batch", §III-E): one optimisation over whole missions, several missions
jointly; fixed-group parameters (k, k_x, k_yz, effect dynamics) are shared, variable-group
ones (theta_e, current) and sensor ones are one per mission. *Online*: after every
absolute fix (GNSS or USBL), minimise over the window from the anchor before the last
``window_fixes`` fixes of every active fix stream (or ``window`` seconds back) to now, at
least two fix updates in the window (§III-C), with the paper's gradient descent from the
previous estimate (§V-F), then re-run the window with the new parameters (past-trajectory
correction, §III-D) and carry on from the corrected state. The non-convergence measure is
the standard deviation of the last three estimates (§III-F). How this compares with the
paper, point by point: docs/update-error.md.

Choices the paper leaves open (details in the modules named):

* The filter starts at the first absolute fix, at rest (§II-E5); the thrust-lag filter
  state is warmed up over the inputs before a window, as the kernel does.
* Process noise: white ground acceleration, ``q = 1e-3 m^2/s^3`` per axis, and the body
  acceleration state's model error ``0.1 m/s^2`` (:class:`EkfConfig`).
* The covariance is carried with the kinematic Jacobian of Eqs. 8-9 (as the authors'
  public code does) while the mean uses the full model: with the drag Jacobian in the
  covariance the update error rewards over-confident filters (``EkfConfig.cov_model``).
* USBL: range and bearing become a horizontal position with covariance
  ``Rot(b) diag(sigma_r^2, (r sigma_b)^2) Rot(b)^T``, ``b`` and ``r`` those of the
  predicted position (:func:`aqfg.ekf.window.usbl_to_position`); gross outliers are dropped by a
  causal, parameter-free consistency pre-filter, smaller ones by a chi^2 gate whose rejected
  nodes still count in ``E`` at the gate boundary (so ``E`` stays continuous).
* IMU acceleration (when ``imu.acc`` is present): the specific force plus gravity rotated
  with the IMU's own roll/pitch, ``a_b = f + R_raw^T [0, 0, g]``, averaged to 10 Hz, updates
  the ``a_b`` state; its update error measures the model's acceleration error.
* ``sigma`` (:mod:`aqfg.ekf.uncertainty`): batch, the sandwich covariance of the
  update-error fit over blocks of fixes; online windows, the whitened-innovation
  Gauss-Newton sigma times the measured consistency. A parameter the data do not
  determine has no sigma (absent from ``Result.sigma``) and a reason in
  ``Result.sigma_notes``; ``Result.observability``, ``Result.converged`` (online: per
  parameter, ``info["converged"]``) and ``Result.warnings`` say what was (not) determined
  and whether the optimiser converged.
* Speed: the window runs in C++ (``cpp_factors/ekf.cpp``), the numpy reference
  (:func:`aqfg.ekf.window.window_ref`) only checks it; measured in docs/update-error.md.
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import numpy as np

from aqfg.data.mission import Mission
from aqfg.ekf.history import GNSS, USBL, EkfConfig, History, build_history
from aqfg.ekf.optim import (
    Counter,
    Entry,
    Objective,
    Solution,
    Window,
    bounds,
    default_optimiser,
    minimise,
)
from aqfg.ekf.report import NONCONV_N, NodeLog, mission_estimate, online_verdicts, verdict_info
from aqfg.ekf.uncertainty import Uncertainty, assess, no_motion_through_water
from aqfg.ekf.window import REJECTED, WindowOut, run_window
from aqfg.model.reference import wrap_angle
from aqfg.model.retrace import inertial_track
from aqfg.model.vehicle import Model
from aqfg.result import (
    SIGMA_ABSENT,
    Estimate,
    EstimateNote,
    MissionResult,
    ParamHistory,
    Result,
    SolveSummary,
    Track,
)

log = logging.getLogger(__name__)

ONLINE_DEFAULT = ("theta_e", "s_x", "s_y")
BATCH_DEFAULT = ("theta_e", "s_x", "s_y", "k", "k_x", "k_yz")
CORRECT = ("window", "all", "none")


def _as_list(missions) -> list[Mission]:
    if isinstance(missions, Mission):
        return [missions]
    ms = list(missions)
    if not ms:
        raise ValueError("no mission given")
    for i, m in enumerate(ms):
        if not isinstance(m, Mission):
            raise TypeError(f"missions[{i}] is a {type(m).__name__}, expected aqfg.Mission")
    veh = {m.vehicle for m in ms}
    if len(veh) > 1:
        raise ValueError(f"missions of different vehicle types ({', '.join(sorted(veh))}) "
                         "cannot share fixed parameters; fit them separately")
    return ms


class UpdateErrorEstimator:
    """The update-error method on one or several missions of one vehicle.

    ``model``: a :class:`Model` whose effects to use (its geometry is rebuilt per mission),
    or None (``Model.for_mission`` with ``effects``). ``init``: starting parameter values
    by name (others at the table's nominal, i.e. the paper's "old" k=8, k_x=2, k_yz=0.3).
    ``preset``: "physical" (default) or "paper" (see :mod:`aqfg.ekf.optim`); ``metric``:
    "update" (Eq. 14), "innovation" (the public code's, with preset "paper") or "whitened"
    (squared whitened innovations: not the paper's, see :mod:`aqfg.ekf.optim`).
    ``bounds``: ``{name: (lower, upper)}`` replacing the preset's bounds.
    ``use_cpp``: force the C++ (True) or numpy (False) window evaluation (default: C++ when
    built and no Python user effect is active).
    """

    def __init__(self, model: Model | None, missions: Mission | Sequence[Mission], *,
                 effects: Sequence = (), config: EkfConfig | None = None,
                 preset: str = "physical", metric: str = "update",
                 init: dict[str, float] | None = None,
                 bounds: dict[str, tuple[float, float]] | None = None,
                 progress: bool = False, use_cpp: bool | None = None):
        self.missions = _as_list(missions)
        effs = tuple(model.effects) if model is not None else ()
        self.models = [Model.for_mission(m, effs).with_effects(*effects) for m in self.missions]
        from aqfg.model.effects import FixDelayTerm
        late = [e.name for e in self.models[0].effects if isinstance(e, FixDelayTerm)]
        if late:
            raise ValueError(f"the update-error EKF does not model fix time offsets ({', '.join(late)}); "
                             "fit them with the factor graph (method fg)")
        self.config = config or EkfConfig()
        if preset not in ("physical", "paper"):
            raise ValueError(f"unknown preset {preset!r}; choose 'physical' or 'paper'")
        self.preset = preset
        if metric not in ("update", "innovation", "whitened"):
            raise ValueError(f"unknown metric {metric!r}; choose 'update' (Eq. 14), "
                             "'innovation' (the public code's) or 'whitened'")
        if metric == "innovation" and preset != "paper":
            raise ValueError("metric='innovation' (the public code's scalar cost) needs preset='paper'")
        self.metric = metric
        self.user_bounds = dict(bounds or {})
        self.progress = progress
        self.use_cpp = use_cpp
        init = {k: float(v) for k, v in (init or {}).items()}
        for k in init:
            self.models[0].index(k)   # raises KeyError naming an unknown parameter
        self.init = init
        self.p0 = [mo.nominal({k: v for k, v in init.items() if k in mo.all_names})
                   for mo in self.models]
        self.histories: list[History] = [build_history(mo, m, self.config)
                                         for mo, m in zip(self.models, self.missions)]
        self.counter = Counter()

    # ------------------------------------------------------------------ Eq. 13 / 14
    def state_at(self, t: float, p: np.ndarray | None = None, mission: int = 0,
                 ) -> tuple[np.ndarray, np.ndarray]:
        """State ``[x_g, v_g, a_b]`` and covariance at the last history knot at or before
        ``t`` (knots: every update node and a ``config.output_rate`` grid), recomputed with
        parameters ``p`` (full vector; default the initial ones) from the anchor at or
        before it (Eq. 13)."""
        h = self.histories[mission]
        k = h.knot_of(t)
        if k < h.k_start:
            raise ValueError(f"t={t} is before the filter start t={h.t_start} (first fix)")
        a = h.anchor_at_or_before(k)
        out = run_window(h, self.p0[mission] if p is None else p, a.x, a.P, a.k, k,
                         use_cpp=self.use_cpp, rejects=a.rejects)
        return out.x, out.P

    def window_error(self, p: np.ndarray, t1: float, t2: float, mission: int = 0) -> float:
        """``E_[t1, t2](P)`` (Eq. 14) from the anchor at or before ``t1`` to ``t2``."""
        h = self.histories[mission]
        a = h.anchor_at_or_before(h.knot_of(t1))
        return run_window(h, p, a.x, a.P, a.k, h.knot_of(t2), use_cpp=self.use_cpp,
                          rejects=a.rejects).error()

    # ------------------------------------------------------------------ helpers
    def _entries(self, estimate: Sequence[str], n_windows: int, joint: bool) -> list[Entry]:
        """Estimated numbers: one per name, or with ``joint`` (several missions) one per
        mission for variable- and sensor-group parameters."""
        model = self.models[0]
        names = list(dict.fromkeys(estimate))
        if not names:
            raise ValueError("nothing to estimate: give at least one parameter name")
        out = []
        for n in names:
            if n not in model.active_names:
                raise ValueError(f"parameter {n!r} is not estimable with this model; active: "
                                 f"{', '.join(model.active_names)} (add its effect first)")
            if joint and model.spec(n).group in ("variable", "sensor") and n_windows > 1:
                out += [Entry(n, (w,)) for w in range(n_windows)]
            else:
                out.append(Entry(n, tuple(range(n_windows))))
        return out

    def _theta(self, entries: list[Entry], ps: list[np.ndarray]) -> np.ndarray:
        return np.array([ps[e.windows[0]][self.models[e.windows[0]].index(e.name)]
                         for e in entries])

    def _scales(self, entries: list[Entry]) -> np.ndarray:
        return np.array([self.models[0].spec(e.name).scale for e in entries])

    def _log(self, msg: str) -> None:
        log.log(logging.INFO if self.progress else logging.DEBUG, "update-error: %s", msg)

    # ------------------------------------------------------------------ offline
    def run_offline(self, estimate: Sequence[str] = BATCH_DEFAULT, max_nfev: int | None = None,
                    sigma: bool = True) -> Result:
        """Offline ("batch") estimation over whole missions (§III-E), jointly.

        Returns a :class:`Result` with mode "batch": final values, ``sigma`` from
        :func:`aqfg.ekf.uncertainty.assess` (empty with ``sigma=False``), observability
        verdicts and convergence in ``info`` (module doc), per mission the EKF
        re-run with the final parameters (``track``), the inertial re-trace, residuals, and
        timings of every error evaluation and of the optimisation."""
        hs = self.histories
        wins = [Window(h, h.k_start, len(h.knots) - 1, h.anchors[h.k_start].x,
                       h.anchors[h.k_start].P, p.copy()) for h, p in zip(hs, self.p0)]
        entries = self._entries(estimate, len(wins), joint=True)
        obj = Objective(wins, entries, self.metric, self.use_cpp, self.counter)
        theta0 = self._theta(entries, self.p0)
        lo, hi = bounds(self.preset, entries, self.models[0], theta0, self.user_bounds)
        self._log(f"offline: {len(wins)} mission(s), estimating {len(entries)} numbers")
        sol = minimise(obj, theta0, lo, hi, self.preset, self._scales(entries), max_nfev)
        t_eval = list(obj.counter.times[-sol.evaluations:])
        self._log(f"offline: E={sol.E:.4g} after {sol.evaluations} evaluations, "
                  f"{sol.seconds:.2f} s ({sol.message})")
        specs = [self.models[0].spec(e.name) for e in entries]
        unc = (assess(Objective(wins, entries, self.metric, self.use_cpp), sol.theta,
                      self._scales(entries), specs, lo, hi) if sigma else None)
        if unc is not None:
            unc = no_motion_through_water(unc, specs, any(_thrust_in(h, w.k0, w.k1)
                                                          for h, w in zip(hs, wins)))
        ps = obj.params(sol.theta)
        outs = obj.run(sol.theta, record=True)
        mres = [self._mission_result(h, p, o.recorded()[0], None, o) for h, p, o in zip(hs, ps, outs)]
        per_mission = {m.name: {e.name: mission_estimate(float(sol.theta[i]), unc, i)
                                for i, e in enumerate(entries) if wi in e.windows}
                       for wi, m in enumerate(self.missions)}
        first = [i for i, e in enumerate(entries) if 0 in e.windows]
        names = [entries[i].name for i in first]
        sigma_d = ({n: float(unc.sigma[i]) for n, i in zip(names, first)
                    if np.isfinite(unc.sigma[i])} if unc else {})
        info: dict[str, Any] = {"evaluations": sol.evaluations, "E": sol.E, "status": sol.status,
                "message": sol.message, "preset": self.preset, "metric": self.metric,
                "optimiser": sol.optimiser,
                "bounds": {e.name: (float(lo[i]), float(hi[i])) for i, e in enumerate(entries)}}
        info.update(verdict_info(unc, names, first, sol, sigma))
        warnings = info.pop("warnings")
        solve = SolveSummary(info.pop("converged"))
        obs, notes = info.pop("observability", None), info.pop("sigma_notes", None)
        for w in warnings:
            log.warning("update-error: %s", w)
        return Result(
            method="update-error", mode="batch",
            estimated=tuple(dict.fromkeys(e.name for e in entries)),
            values=dict(zip(self.models[0].all_names, map(float, ps[0]))), sigma=sigma_d,
            missions=mres,
            timings={"evaluation": t_eval, "optimisation": [sol.seconds]},
            info=info, warnings=warnings, solve=solve, observability=obs, sigma_notes=notes,
            effects=tuple(e.name for e in self.models[0].effects), model=self.models[0],
            per_mission=per_mission)

    # ------------------------------------------------------------------ online
    def run_online(self, estimate: Sequence[str] = ONLINE_DEFAULT, window_fixes: int = 3,
                   window: float | None = None, min_fixes: int = 2, correct: str = "window",
                   every: int = 1, max_nfev: int | None = None, sigma: bool = True,
                   optimiser: str | None = None, per_stream: bool = True) -> Result:
        """Online estimation, mission by mission (each from ``init``).

        After every ``every``-th absolute fix: minimise ``E`` over the window if it holds at
        least ``min_fixes`` fix updates, then correct the past (``correct``: "window" re-runs
        the window, "all" the whole history from the start anchor, "none" keeps the
        filtered past) and continue from the corrected state. The window starts at the
        anchor before the last ``window_fixes`` fixes of every active fix stream (GNSS,
        USBL; :func:`window_start`; with ``per_stream=False`` the last ``window_fixes`` of
        the merged stream), or ``window`` seconds back when given. ``optimiser``:
        default the paper's gradient descent ("paper" preset: the public code's solver),
        see :func:`aqfg.ekf.optim.minimise`. The heading offset is carried wrapped into
        (-180, 180] deg.

        Returns a :class:`Result` with mode "online": ``track`` filtered-then-corrected,
        ``filtered`` the causal track, ``history`` the estimates after each optimisation
        (first mission; all in ``histories``; ``history.sigma`` NaN where a window
        does not determine a parameter), ``timings["optimisation"]`` and
        ``timings["evaluation"]``, ``info["nonconvergence"]`` (§III-F: the standard
        deviation of the last three estimates) and ``info["converged"]`` (per parameter:
        that deviation within twice the last window's sigma)."""
        if correct not in CORRECT:
            raise ValueError(f"correct must be one of {', '.join(CORRECT)}, got {correct!r}")
        if window is None and window_fixes < 1:
            raise ValueError(f"window_fixes must be >= 1, got {window_fixes}")
        if window is not None and not window > 0:
            raise ValueError(f"window must be a positive number of seconds, got {window}")
        optimiser = optimiser or default_optimiser(self.preset, "online")
        mres, hists, t_eval, t_opt, n_eval, nonconv, uncs = [], [], [], [], [], [], []
        for mi in range(len(self.missions)):
            r = self._online_one(mi, estimate, window_fixes, window, min_fixes, correct, every,
                                 max_nfev, sigma, optimiser, per_stream)
            mres.append(r["mission"])
            hists.append(r["history"])
            t_eval += r["t_eval"]
            t_opt += r["t_opt"]
            n_eval += r["n_eval"]
            nonconv.append(r["nonconv"])
            uncs.append(r["last"])
        last = mres[0].p
        hist0 = hists[0]
        names = list(hist0.names)
        unc0 = uncs[0]
        sig0 = ({n: float(unc0.sigma[i]) for i, n in enumerate(names)
                 if np.isfinite(unc0.sigma[i])} if unc0 is not None else {})
        info = {"evaluations": int(sum(n_eval)), "evaluations_per_optimisation": n_eval,
                "optimisations": len(t_opt), "nonconvergence": nonconv[0].tolist(),
                "nonconvergence_all": [n.tolist() for n in nonconv],
                "preset": self.preset, "metric": self.metric, "optimiser": optimiser,
                "window_fixes": window_fixes, "window": window, "per_stream": per_stream,
                "correct": correct}
        absent = EstimateNote(sigma_missing=SIGMA_ABSENT)    # no sigma per mission
        per_mission = {m.name: {n: Estimate(float(r.p[self.models[i].index(n)]), note=absent)
                                for n in estimate}
                       for i, (m, r) in enumerate(zip(self.missions, mres))}
        info.update(online_verdicts(unc0, names, nonconv[0], sigma))
        warnings = info.pop("warnings")
        obs, notes = info.pop("observability", None), info.pop("sigma_notes", None)
        for w in warnings:
            log.warning("update-error: %s", w)
        return Result(
            method="update-error", mode="online", estimated=tuple(dict.fromkeys(estimate)),
            values=dict(zip(self.models[0].all_names, map(float, last))), sigma=sig0,
            missions=mres, timings={"evaluation": t_eval, "optimisation": t_opt},
            history=hist0, histories=hists, info=info, warnings=warnings, observability=obs,
            sigma_notes=notes, per_mission=per_mission,
            effects=tuple(e.name for e in self.models[0].effects), model=self.models[0])

    def _online_one(self, mi: int, estimate, window_fixes, window, min_fixes, correct, every,
                    max_nfev, sigma, optimiser, per_stream) -> dict:
        h = self.histories[mi]
        model = self.models[mi]
        h.anchors = {h.k_start: h.anchors[h.k_start]}
        p = self.p0[mi].copy()
        F = h.fix_knots()
        streams = fix_streams(h, F)
        K = len(h.knots)
        X_filt = np.full((K, 9), np.nan)
        X_corr = np.full((K, 9), np.nan)
        a0 = h.anchors[h.k_start]
        X_filt[h.k_start] = X_corr[h.k_start] = a0.x
        nodes = NodeLog(h)
        entries = self._entries(estimate, 1, joint=False)
        idx = [model.index(e.name) for e in entries]
        i_th = [i for i, e in enumerate(entries) if e.name == "theta_e"]
        t_hist, v_hist, s_hist, nonconv, t_eval, t_opt, n_eval = [], [], [], [], [], [], []
        unc = None
        x, P, rej = a0.x, a0.P, a0.rejects
        for n in range(1, len(F)):
            out = run_window(h, p, x, P, F[n - 1], F[n], record=True, use_cpp=self.use_cpp,
                             rejects=rej)
            X_filt[F[n - 1]:F[n] + 1] = out.X
            X_corr[F[n - 1]:F[n] + 1] = out.X
            nodes.store(out)
            self.store_anchors(h, out, F[n - 1], rej)
            x, P, rej = out.x, out.P, out.rejects
            j = _window_from(h.knots[F], streams, n, window, window_fixes, per_stream)
            if n - j < min_fixes or n % every:
                continue
            a = h.anchors[int(F[j])]
            win = Window(h, int(F[j]), int(F[n]), a.x, a.P, p.copy(), a.rejects)
            theta, sol, evals, unc = self._fit_window(win, model, p[idx], entries, i_th,
                                                      max_nfev, optimiser, sigma)
            p[idx] = theta
            t_eval += evals
            t_opt.append(sol.seconds)
            n_eval.append(sol.evaluations)
            t_hist.append(float(h.knots[F[n]]))
            v_hist.append(theta)
            s_hist.append(unc.sigma if unc is not None else np.full(len(idx), np.nan))
            nonconv.append(_last_spread(v_hist, i_th, len(idx)))
            # past-trajectory correction (§III-D) and the state to carry on from
            out = self._correct(h, p, int(F[j]), int(F[0]), int(F[n]), correct, X_corr)
            x, P, rej = out.x, out.P, out.rejects
            self._log(f"{h.mission.name} t={h.knots[F[n]]:.1f}: "
                      + ", ".join(f"{e.name}={v:.4g}" for e, v in zip(entries, theta))
                      + f" ({sol.evaluations} evaluations, {1e3 * sol.seconds:.1f} ms)")
        # after the last fix: predict to the end of the mission
        out = run_window(h, p, x, P, int(F[-1]), K - 1, record=True, use_cpp=self.use_cpp,
                         rejects=rej)
        X_filt[F[-1]:] = out.X
        X_corr[F[-1]:] = out.X
        nodes.store(out)
        names = tuple(e.name for e in entries)
        hist = ParamHistory(np.array(t_hist), names,
                            np.array(v_hist).reshape(-1, len(names)),
                            np.array(s_hist).reshape(-1, len(names)))
        mr = self._mission_result(h, p, X_corr[h.k_start:], X_filt[h.k_start:], None, nodes)
        return {"mission": mr, "history": hist, "t_eval": t_eval, "t_opt": t_opt,
                "n_eval": n_eval, "nonconv": np.array(nonconv).reshape(-1, len(names)),
                "last": unc}

    def _fit_window(self, win: Window, model: Model, theta0: np.ndarray, entries: list[Entry],
                    i_th: list[int], max_nfev: int | None, optimiser: str, sigma: bool
                    ) -> tuple[np.ndarray, Solution, list[float], Uncertainty | None]:
        """Minimise ``E`` over the window ``win`` from ``theta0`` (the entries' current
        values; the heading offset wrapped): the estimate (wrapped), the solution, the
        times of its evaluations and, with ``sigma``, its uncertainty (else None)."""
        obj = Objective([win], entries, self.metric, self.use_cpp, self.counter)
        for i in i_th:
            theta0[i] = wrap_angle(theta0[i])
        scales = self._scales(entries)
        lo, hi = bounds(self.preset, entries, model, theta0, self.user_bounds)
        sol = minimise(obj, theta0, lo, hi, self.preset, scales, max_nfev, optimiser)
        theta = sol.theta.copy()
        for i in i_th:
            theta[i] = wrap_angle(theta[i])
        evals = obj.counter.times[-sol.evaluations:]
        if not sigma:
            return theta, sol, evals, None
        specs = [model.spec(e.name) for e in entries]
        unc = assess(Objective([win], entries, self.metric, self.use_cpp), sol.theta,
                     scales, specs, lo, hi)
        unc = no_motion_through_water(unc, specs, _thrust_in(win.hist, win.k0, win.k1))
        return theta, sol, evals, unc

    def _correct(self, h: History, p: np.ndarray, k_window: int, k_first: int, k_fix: int,
                 correct: str, X_corr: np.ndarray) -> WindowOut:
        """The past re-run with the parameters ``p`` up to the fix knot ``k_fix`` (from the
        window's start ``k_window``, or the first fix ``k_first`` where ``correct`` is
        "all") into ``X_corr`` (not where "none"), with the anchors it passes stored; the
        pass, whose end is the state to carry on from."""
        k_from = {"window": k_window, "all": k_first, "none": k_window}[correct]
        a = h.anchors[k_from]
        out = run_window(h, p, a.x, a.P, k_from, k_fix, record=True, use_cpp=self.use_cpp,
                         rejects=a.rejects)
        if correct != "none":
            X_corr[k_from:k_fix + 1] = out.X
        self.store_anchors(h, out, k_from, a.rejects)
        return out

    @staticmethod
    def store_anchors(h: History, out: WindowOut, k0: int, rejects: int) -> None:
        """Anchor states after every absolute fix of a recorded pass from knot ``k0``
        (state and covariance after the last node of that knot, and the USBL rejection
        counter, given ``rejects`` at ``k0``)."""
        kinds = h.node_kind[out.node_lo:out.node_hi]
        knots = h.node_knot[out.node_lo:out.node_hi]
        X, Pn = out.recorded()
        for r in np.nonzero((kinds == GNSS) | (kinds == USBL))[0]:
            if kinds[r] == USBL:
                rejects = rejects + 1 if out.status[r] == REJECTED else 0
            k = int(knots[r])
            last = r + int(np.searchsorted(knots[r:], k, side="right")) - 1
            if kinds[last] in (GNSS, USBL) and last != r:
                continue          # the anchor goes after the last fix of this knot
            h.set_anchor(k, X[k - k0], Pn[last], rejects)

    # ------------------------------------------------------------------ result
    def _mission_result(self, h: History, p: np.ndarray, X: np.ndarray, X_filt, out, nodes=None
                        ) -> MissionResult:
        t = h.knots[h.k_start:]
        track = Track(t.copy(), X[:, :3].copy(), X[:, 3:6].copy())
        filt = None if X_filt is None else Track(t.copy(), X_filt[:, :3].copy(),
                                                 X_filt[:, 3:6].copy())
        if nodes is None:
            nodes = NodeLog(h)
            nodes.store(out)
        res = nodes.residuals()
        inertial = inertial_track(h.model, h.mission, p)
        return MissionResult(h.mission.name, track, inertial, p.copy(), res, filtered=filt)


def fix_streams(h: History, F: np.ndarray) -> dict[int, np.ndarray]:
    """Per fix kind present (GNSS, USBL): the indices into ``F`` (fix knots) holding one."""
    out = {}
    for kind in (GNSS, USBL):
        ks = np.unique(h.node_knot[h.node_kind == kind])
        pos = np.nonzero(np.isin(F, ks))[0]
        if len(pos):
            out[kind] = pos
    return out


def window_start(t_fix: np.ndarray, streams: dict[int, np.ndarray], n: int, w: int) -> int:
    """Index into the fix knots of the window's start anchor for an optimisation at fix
    ``n``: the anchor before the last ``w`` fixes of every *active* stream.

    The paper's window is "the last three fixes" of its one fix stream, i.e. three update
    intervals (§V-B: 24 s at one GNSS fix per 8 s; §V-D: 15 s of USBL). With GNSS and USBL
    together, three fixes of the merged stream span far less (9 s on a mission with GNSS
    every 8 s and USBL every 4.5 s); here the window holds ``w`` fixes of each stream, so
    the sparsest one sets its length. A stream is active when its last fix is no older than
    twice its median interval so far (a stream that has stopped, e.g. GNSS after a dive,
    does not stretch the window). Index 0 (the start) when a stream has fewer fixes."""
    j = n - w
    t_n = t_fix[n]
    for pos in streams.values():
        mine = pos[pos <= n]
        if not len(mine):
            continue
        if len(mine) >= 2:
            gap = float(np.median(np.diff(t_fix[mine])))
            if t_n - t_fix[mine[-1]] > 2.0 * gap:
                continue
        j = min(j, int(mine[-w - 1]) if len(mine) > w else 0)
    return max(j, 0)


def _thrust_in(h: History, k0: int, k1: int) -> bool:
    """Whether any motor command in force between knots ``k0`` and ``k1`` is non-zero."""
    m = h.mission.motors
    t0, t1 = h.knots[k0], h.knots[k1]
    i0 = max(int(np.searchsorted(m.t, t0, side="right")) - 1, 0)
    i1 = int(np.searchsorted(m.t, t1, side="right"))
    return bool(np.any(np.abs(m.u[i0:i1]) > 0.0))

def _window_from(t_fix: np.ndarray, streams: dict[int, np.ndarray], n: int,
                 window: float | None, window_fixes: int, per_stream: bool) -> int:
    """Index into the fix times ``t_fix`` where the window ending at fix ``n`` starts: the
    fix ``window`` seconds back when given, else :func:`window_start` (``per_stream``) or
    ``window_fixes`` fixes back in the merged stream."""
    if window is not None:
        t_lo = t_fix[n] - window
        j = int(np.searchsorted(t_fix[:n + 1], t_lo + 1e-9, side="right") - 1)
        return max(j, 0)
    if per_stream:
        return window_start(t_fix, streams, n, window_fixes)
    return max(0, n - window_fixes)


def _last_spread(v_hist: list[np.ndarray], i_th: list[int], n: int) -> np.ndarray:
    """§III-F's non-convergence measure: the standard deviation of the last
    ``NONCONV_N`` estimates (the heading offset's about the last one, wrapped); NaN before
    there are that many."""
    last = np.array(v_hist[-NONCONV_N:])
    if i_th and len(last):       # spread of a circular quantity: about the last one
        last[:, i_th] = last[-1, i_th] + wrap_angle(last[:, i_th] - last[-1, i_th])
    return last.std(axis=0) if len(last) == NONCONV_N else np.full(n, np.nan)


def fit_update_error(missions: list[Mission], *, mode: str = "batch",
                     estimate: Sequence[str] | None = None, init: dict[str, float] | None = None,
                     effects: Sequence = (), window: float | None = None,
                     preset: str = "physical", progress: bool = False,
                     config: EkfConfig | None = None, **kwargs) -> Result:
    """Fit with the update-error method; the entry point of ``aqfg fit --method update-error``.

    ``mode``: "batch" (the paper's offline mode, whole missions jointly) or "online" (after
    each fix, window of the last 3 fixes of each fix stream, or of ``window`` seconds).
    ``estimate``: parameter names (default batch: theta_e, s_x, s_y, k, k_x, k_yz; online:
    theta_e, s_x, s_y). ``init``: starting values (others nominal). ``effects``: model
    effects by name. ``preset``: "physical" or "paper" (:mod:`aqfg.ekf.optim`). Extra
    keyword arguments go to :meth:`UpdateErrorEstimator.run_offline` /
    :meth:`~UpdateErrorEstimator.run_online`. Result: sigma from
    :mod:`aqfg.ekf.uncertainty`; a parameter without sigma has a reason in
    ``Result.sigma_notes``.
    """
    if mode not in ("batch", "online"):
        raise ValueError(f"mode must be 'batch' or 'online', got {mode!r}")
    est = UpdateErrorEstimator(None, missions, effects=effects, config=config, preset=preset,
                               init=init, progress=progress)
    if mode == "batch":
        r = est.run_offline(estimate=tuple(estimate or BATCH_DEFAULT), **kwargs)
    else:
        r = est.run_online(estimate=tuple(estimate or ONLINE_DEFAULT), window=window, **kwargs)
    return r
