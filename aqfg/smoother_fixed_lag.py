"""Online (fixed-lag) factor-graph smoothing: the factor-graph analogue of the paper's online
mode (§III-E): after each absolute fix, the states inside a window of ``window`` seconds and
the parameter nodes are re-estimated jointly.

Built on GTSAM's ``IncrementalFixedLagSmoother`` (ISAM2 underneath): states older than the
window are marginalised into a prior (a linear container factor), not forgotten; the
parameter keys are re-stamped with the current time at every update so they never leave the
window (gtsam-notes). Only the window's Values reach the CustomFactor callbacks, so the cost
per update does not grow with the mission.

Step-by-step use (live data)::

    fl = FixedLagSmoother(window=24.0)
    fl.start(mission)                 # at the first fix
    while fl.pending():               # or: fl.update(t_fix, mission=grown_mission)
        info = fl.update()            # processes inputs and measurements up to the next fix
    track = fl.corrected_track()      # past trajectory re-traced with the current parameters
    result = fl.result()

or simply ``FixedLagSmoother(...).run(mission) -> Result``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import gtsam
import numpy as np

from . import factors as fc
from .mission import Mission
from .model import Model
from .result import MissionResult, ParamHistory, Result, Track
from .smoother_common import (FGSettings, Measurements, check_missions, default_estimate,
                              first_knot_prior, initial_states, measurement_factors,
                              mission_model, piecewise_inertial, progress_fn, residuals)


@dataclass
class UpdateInfo:
    """What one update did: fix time (s), wall time (s), parameter estimate and 1-sigma."""
    t: float
    seconds: float
    values: dict
    sigma: dict
    n_new_knots: int


def _window_steps(model: Model, mission: Mission, knots: np.ndarray):
    """``model.steps(mission, knots)`` over a view of the mission cut to the knots' span
    (plus the thrust-lag look-back): build_steps sorts every input time of the mission it is
    given, which cost 0.3-0.7 ms per update on a 15-min mission, growing with its length."""
    import copy
    t_lo = knots[0] - model.lookback - 1.0
    t_hi = knots[-1] + 1.0
    imu, mot = mission.imu, mission.motors
    a = max(int(np.searchsorted(imu.t, t_lo)) - 1, 0)
    b = int(np.searchsorted(imu.t, t_hi, side="right")) + 1
    c = max(int(np.searchsorted(mot.t, t_lo, side="right")) - 1, 0)
    d = int(np.searchsorted(mot.t, t_hi, side="right")) + 1
    view = copy.copy(mission)
    view.imu = copy.copy(imu)
    view.imu.t, view.imu.q = imu.t[a:b], imu.q[a:b]
    view.motors = copy.copy(mot)
    view.motors.t, view.motors.u = mot.t[c:d], mot.u[c:d]
    steps, off = model.steps(view, knots)
    steps.tm = steps.tm + (view.t0 - mission.t0)    # time since the MISSION start
    return steps, off


class FixedLagSmoother:
    """Fixed-lag smoother over one mission; see the module docstring.

    ``estimate`` defaults to the variable parameters (theta_e, s_x, s_y and the variable
    effect parameters); the others are held at ``init`` (e.g. the fixed parameters of an
    offline batch fit). ``window`` in seconds.
    """

    def __init__(self, model: Model | None = None, *, effects=(), estimate=None, init=None,
                 window: float = 24.0, settings: FGSettings | None = None, progress=None):
        if not window or window <= 0:
            raise ValueError(f"window must be a positive number of seconds, got {window}")
        self.base_model = model
        self.effects = tuple(effects)
        self.estimate = None if estimate is None else tuple(estimate)
        self.init = dict(init or {})
        self.window = float(window)
        self.settings = settings or FGSettings()
        self.progress = progress_fn(progress)

    # ---------------------------------------------------------------- setup
    def start(self, mission: Mission, plan: bool = False) -> UpdateInfo:
        """Initialise at the mission's first fix (position from the fix, velocity zero).

        ``plan``: the mission is recorded (not growing): prepare the kernel steps of all its
        knots at once (:meth:`run` does)."""
        (mission,) = check_missions([mission])
        s = self.settings
        self._t_call = time.perf_counter()
        self.mission = mission
        self.model = mission_model(self.base_model, mission, self.effects)
        est = self.estimate if self.estimate is not None else default_estimate(self.model, "online")
        self.layout = fc.ParamLayout.build(self.model, est, self.init)
        self.fix_t = np.unique(mission.fix_times())
        if not len(self.fix_t):
            raise ValueError(f"mission {mission.name!r} has no GNSS or USBL fix")
        prm = gtsam.ISAM2Params()
        prm.findUnusedFactorSlots = True
        prm.relinearizeSkip = 1
        thr = gtsam.ISAM2ThresholdMap()
        thr.insert(("x", np.repeat([s.relin_pos, s.relin_vel], 3)))
        for g in self.layout.groups:
            thr.insert((fc._GROUP_CHAR[g], np.full(self.layout.dim(g), s.relin_param)))
        prm.setRelinearizeThreshold(thr)
        self.smoother = gtsam.IncrementalFixedLagSmoother(self.window, prm)
        self.knots: list[float] = []
        self.keys: list[int] = []
        self.filtered: list[np.ndarray] = []      # causal estimate per knot
        self.anchor_idx: list[int] = []           # knot index of each fix
        self.latest: dict[int, np.ndarray] = {}   # knot index -> latest estimate
        self.seg = 0
        self.seg_starts = [float(self.fix_t[0])]
        self.v_by_seg: dict[int, np.ndarray] = {}
        self.hist_t, self.hist_v, self.hist_s = [], [], []
        self.timings = {"update": [], "update_total": [], "correction": []}
        self.n_fix = 0
        self.pred_t: list[float] = []              # fix times after the first, and the
        self.pred_x: list[np.ndarray] = []        # state predicted there before the update
        self._noise: dict = {}
        self.warming = s.warmup_tol > 0
        self._plan = None
        if plan:
            self._make_plan()
        self.warmup_end = float("nan")
        # first knot: position from the first fix (interpolation of the fixes at t0)
        t0 = float(self.fix_t[0])
        x0 = initial_states(mission, np.array([t0, t0 + 1.0]))[0]
        x0[3:] = 0.0
        if mission.planar:
            x0[2] = 0.0
        graph = gtsam.NonlinearFactorGraph()
        vals = gtsam.Values()
        k0 = fc.state_key(0, 0)
        vals.insert(k0, x0)
        graph.add(first_knot_prior(mission, k0, x0, s))
        if mission.planar:
            graph.add(fc.surface_factor(k0, *s.surface_sigma))
        for g in self.layout.groups:
            k = self._node(g)
            vals.insert(k, self.layout.initial(g))
            graph.add(fc.param_prior(self.layout, g, k, s.prior_scale, sigma=s.prior_sigma))
            graph.add(fc.bound_factor(self.layout, g, k))
        self.knots.append(t0)
        self.keys.append(k0)
        self.filtered.append(x0.copy())
        meas = Measurements.of(mission, s, t0, t0)
        for f in measurement_factors(self.model, self.layout, meas, np.array([t0]),
                                     lambda i: k0,
                                     lambda stream, t: self._node_keys(self.layout.meas_groups(stream)),
                                     s):
            graph.add(f)
        return self._update(graph, vals, {k0: t0}, t0, 1)

    def _make_plan(self) -> None:
        """Knots of the whole recorded mission (the same rule as :meth:`update`) and their
        kernel steps in one build_steps call, sliced per update (saves ~0.3 ms per update)."""
        sp = self.settings.knot_spacing
        ks = [np.array([self.fix_t[0]])]
        t_last = float(self.fix_t[0])
        for t_fix in self.fix_t[1:]:
            ks.append(np.concatenate([np.arange(t_last + sp, t_fix - sp / 4, sp), [t_fix]]))
            t_last = float(t_fix)
        knots = np.concatenate(ks)
        if len(knots) < 2:
            self._plan = None
            return
        steps, off = self.model.steps(self.mission, knots)
        self._plan = (knots, {float(t): i for i, t in enumerate(knots)}, steps, off)

    def _steps(self, all_t: np.ndarray):
        """Kernel steps for the intervals of ``all_t``: from the plan when it has them."""
        if self._plan is not None:
            knots, index, steps, off = self._plan
            i = index.get(float(all_t[0]))
            j = None if i is None else i + len(all_t) - 1
            if j is not None and j < len(knots) and np.array_equal(knots[i:j + 1], all_t):
                return steps.slice(int(off[i]), int(off[j])), off[i:j + 1] - off[i]
        return _window_steps(self.model, self.mission, all_t)

    def _node(self, g: str, seg: int | None = None) -> int:
        """Key of a parameter node; the variable node of segment ``seg`` (default: the
        current random-walk segment)."""
        if g != "variable":
            return fc.node_key(g, 0)
        return fc.node_key(g, 0, self.seg if seg is None else seg)

    def _node_keys(self, groups, seg: int | None = None) -> tuple:
        return tuple((g, self._node(g, seg)) for g in groups)

    # ---------------------------------------------------------------- updates
    def pending(self) -> bool:
        """True while fixes remain to be processed."""
        return self.n_fix < len(self.fix_t)

    def params(self) -> np.ndarray:
        """Current full parameter vector."""
        nd = {g: self.smoother.calculateEstimateVector(self._node(g)) for g in self.layout.groups}
        return self.layout.full(nd)

    def update(self, t_fix: float | None = None, mission: Mission | None = None) -> UpdateInfo:
        """Process inputs and measurements up to the next fix (or up to ``t_fix``, which must
        be a fix time) and update the window. ``mission``: a newer copy of the mission with
        more samples (live use)."""
        if mission is not None:
            self.mission = mission
            self.fix_t = np.unique(mission.fix_times())
            self._plan = None                      # inputs may have changed: no plan
        if t_fix is None:
            if not self.pending():
                raise ValueError("no fix left to process")
            t_fix = float(self.fix_t[self.n_fix])
        self._t_call = time.perf_counter()
        t_last = self.knots[-1]
        if t_fix <= t_last + 1e-9:
            raise ValueError(f"fix time {t_fix} s is not after the last processed time {t_last} s")
        s = self.settings
        lay = self.layout
        # new knots on the grid up to the fix
        sp = s.knot_spacing
        grid = np.arange(t_last + sp, t_fix - sp / 4, sp)
        new_t = np.concatenate([grid, [t_fix]])
        all_t = np.concatenate([[t_last], new_t])
        steps, off = self._steps(all_t)
        graph = gtsam.NonlinearFactorGraph()
        vals = gtsam.Values()
        stamps = {}
        p = self.params()
        x = self.smoother.calculateEstimateVector(self.keys[-1])
        # random walk of the variable parameters: a new segment node when a boundary passes
        if s.walk_sigma and "variable" in lay.names:
            new_seg = int((t_fix - self.seg_starts[0]) // s.walk_segment)
            if new_seg > self.seg:
                kv_old = self._node("variable")
                v_old = self.smoother.calculateEstimateVector(kv_old)
                self.v_by_seg[self.seg] = v_old
                sig = np.array([s.walk_sigma.get(n, 0.0) for n in lay.names["variable"]])
                self.seg = new_seg
                self.seg_starts.append(self.seg_starts[0] + new_seg * s.walk_segment)
                kv = self._node("variable")
                vals.insert(kv, v_old)
                graph.add(fc.walk_factor(lay, kv_old, kv, np.maximum(sig, 1e-9), s.walk_segment))
                graph.add(fc.bound_factor(lay, "variable", kv))
        dyn_nodes = self._node_keys(lay.dyn_groups())
        i0 = len(self.knots)
        for j, t in enumerate(new_t):
            st = steps.slice(int(off[j]), int(off[j + 1]))
            x = self.model.propagate(x, p, st)[0]
            k = fc.state_key(0, i0 + j)
            vals.insert(k, x)
            stamps[k] = float(t)
            if self.mission.planar:
                graph.add(fc.surface_factor(k, *s.surface_sigma))
            dt = float(all_t[j + 1] - all_t[j])
            nk = (round(dt, 9), self.mission.planar)
            if nk not in self._noise:
                self._noise[nk] = s.process.noise_model(dt, self.mission.planar)
            graph.add(fc.dynamics_factor(self.model, lay, st, self.keys[-1] if j == 0 else
                                         fc.state_key(0, i0 + j - 1), k, dyn_nodes,
                                         self._noise[nk]))
            self.knots.append(float(t))
            self.keys.append(k)
            self.filtered.append(x.copy())
        self.pred_t.append(float(t_fix))
        self.pred_x.append(x.copy())
        meas = Measurements.of(self.mission, s, t_last + 1e-6, t_fix)
        local = np.asarray(all_t)
        for f in measurement_factors(self.model, lay, meas, local,
                                     lambda i: self.keys[i0 - 1 + i],
                                     lambda stream, t: self._node_keys(lay.meas_groups(stream)), s):
            graph.add(f)
        return self._update(graph, vals, stamps, t_fix, len(new_t))

    def _update(self, graph, vals, stamps, t_fix: float, n_new: int) -> UpdateInfo:
        lay = self.layout
        for g in lay.groups:                       # parameter nodes never leave the window
            stamps[self._node(g)] = float(t_fix)
        t_a = time.perf_counter()
        if self.warming:
            # warm-up: keep everything since the start in the window until the parameters
            # are known well enough to linearise the marginal priors near the truth
            self.smoother.setSmootherLag(max(self.window, t_fix - self.knots[0] + 1.0))
        self.smoother.update(graph, vals, stamps)
        for _ in range(self.settings.iterations_per_update - 1):
            self.smoother.update()
        values, sigma = {}, {}
        nv, ns = [], []
        for g in lay.groups:
            k = self._node(g)
            v = self.smoother.calculateEstimateVector(k)
            sg = np.sqrt(np.maximum(np.diag(self.smoother.marginalCovariance(k)), 0.0))
            for n, a, b in zip(lay.names[g], v, sg):
                values[n], sigma[n] = float(a), float(b)
            nv.append(v); ns.append(sg)
        if self.warming:
            sc = np.array([self.model.spec(n).scale for n in lay.estimated])
            done = np.all(np.concatenate(ns) < self.settings.warmup_tol * sc) if ns else True
            if done or t_fix - self.knots[0] >= self.settings.warmup_max:
                self.warming = False
                self.warmup_end = float(t_fix)
                self.smoother.setSmootherLag(self.window)
        t_b = time.perf_counter()
        dt = t_b - t_a
        self.timings["update"].append(dt)
        self.timings["update_total"].append(t_b - getattr(self, "_t_call", t_a))
        # the fix knot's estimate (causal), and the latest estimates of knots in the window
        i_fix = len(self.knots) - 1
        self.anchor_idx.append(i_fix)
        x_fix = self.smoother.calculateEstimateVector(self.keys[i_fix])
        self.filtered[i_fix] = x_fix
        for i in reversed(self.anchor_idx):
            if self.knots[i] < t_fix - self.window + 1e-6:
                break
            self.latest[i] = self.smoother.calculateEstimateVector(self.keys[i])
        self.hist_t.append(float(t_fix))
        self.hist_v.append(np.concatenate(nv) if nv else np.zeros(0))
        self.hist_s.append(np.concatenate(ns) if ns else np.zeros(0))
        self.n_fix = int(np.searchsorted(self.fix_t, t_fix + 1e-9))
        return UpdateInfo(float(t_fix), dt, values, sigma, n_new)

    # ---------------------------------------------------------------- past-trajectory correction
    def corrected_track(self, p: np.ndarray | None = None, t_end: float | None = None) -> Track:
        """The whole past trajectory re-traced with the parameters ``p`` (default: current).

        The paper's past-trajectory correction (§III-D): between consecutive fixes the model
        integrates the recorded inputs from the smoothed state at the earlier fix with the
        new parameters; the mismatch with the smoothed state at the later fix is spread
        linearly over the interval, so the track passes through the smoothed fix states.
        After the last fix the model runs on alone (up to ``t_end``, default the last knot).
        """
        t_a = time.perf_counter()
        if p is None:
            p = self.params()
        knots = np.array(self.knots)
        if t_end is not None and t_end > knots[-1] + 1e-6:
            sp = self.settings.knot_spacing
            knots = np.concatenate([knots, np.arange(knots[-1] + sp, t_end - sp / 4, sp), [t_end]])
        X = np.zeros((len(knots), 6))
        if len(knots) == 1:
            X[0] = self.latest.get(0, self.filtered[0])
            return Track(knots, X[:, :3], X[:, 3:])
        steps, off = self.model.steps(self.mission, knots)
        anchors = [i for i in self.anchor_idx]
        ax = {i: self.latest.get(i, self.filtered[i]) for i in anchors}
        seg_p = self._p_segments(p)
        seg_starts = np.array(self.seg_starts)
        X[0] = ax[anchors[0]]
        bounds = anchors + [len(knots) - 1] if anchors[-1] != len(knots) - 1 else anchors
        for a, b in zip(bounds[:-1], bounds[1:]):
            x = ax[a].copy()
            for i in range(a, b):
                j = int(np.clip(np.searchsorted(seg_starts, knots[i], side="right") - 1, 0,
                                len(seg_p) - 1))
                x = self.model.propagate(x, seg_p[j], steps.slice(int(off[i]), int(off[i + 1])))[0]
                X[i + 1] = x
            if b in ax:
                err = ax[b] - X[b]
                w = (knots[a + 1:b + 1] - knots[a]) / (knots[b] - knots[a])
                X[a + 1:b + 1] += w[:, None] * err[None, :]
        self.timings["correction"].append(time.perf_counter() - t_a)
        return Track(knots, X[:, :3], X[:, 3:])

    def _p_segments(self, p_now: np.ndarray) -> list[np.ndarray]:
        """Parameter vectors per random-walk segment (the current one for the last)."""
        if not self.v_by_seg:
            return [p_now]
        out = []
        for j in range(len(self.seg_starts)):
            if j in self.v_by_seg:
                q = p_now.copy()
                q[self.layout.idx["variable"]] = self.v_by_seg[j]
                out.append(q)
            else:
                out.append(p_now)
        return out

    def filtered_track(self) -> Track:
        """The causal track: each knot as first predicted, each fix knot right after its
        update."""
        X = np.array(self.filtered)
        return Track(np.array(self.knots), X[:, :3], X[:, 3:])

    # ---------------------------------------------------------------- whole runs
    def run(self, mission: Mission) -> Result:
        """Process a recorded mission fix by fix; returns the Result (corrected track,
        filtered track, parameter history with 1-sigma, time per update)."""
        t_start = time.perf_counter()
        self.start(mission, plan=True)
        n = len(self.fix_t)
        while self.pending():
            info = self.update()
            if self.n_fix % 10 == 0 or not self.pending():
                self.progress(self.n_fix / n, f"fix {self.n_fix}/{n}, t = {info.t:.1f} s")
        res = self.result()
        res.timings["run"] = [time.perf_counter() - t_start]
        return res

    def result(self) -> Result:
        """The Result so far: final parameters and marginals, tracks, residuals, history."""
        lay = self.layout
        p = self.params()
        t_end = max(self.mission.t1, self.knots[-1])
        track = self.corrected_track(p, t_end=t_end)
        filt = self.filtered_track()
        seg_p = self._p_segments(p)
        seg_starts = np.array(self.seg_starts)

        def p_at(t):
            j = int(np.clip(np.searchsorted(seg_starts, t, side="right") - 1, 0, len(seg_p) - 1))
            return seg_p[j]
        inertial = piecewise_inertial(self.model, self.mission, seg_p, seg_starts)
        res = residuals(self.model, self.mission, track, p_at, self.settings)
        sigma = {}
        if self.hist_s:
            sigma = dict(zip(lay.estimated, map(float, self.hist_s[-1])))
        hist = ParamHistory(np.array(self.hist_t), lay.estimated,
                            np.array(self.hist_v).reshape(len(self.hist_t), -1),
                            np.array(self.hist_s).reshape(len(self.hist_t), -1))
        mr = MissionResult(self.mission.name, track, inertial, p, res, filtered=filt)
        ups = self.timings["update"]
        return Result(method="fg", mode="online", estimated=lay.estimated,
                      values=dict(zip(self.model.all_names, map(float, p))), sigma=sigma,
                      missions=[mr], timings={k: list(v) for k, v in self.timings.items()},
                      history=hist,
                      info={"window": self.window, "n_updates": len(ups),
                            "warmup_end": self.warmup_end,
                            "predicted_at_fix": (np.array(self.pred_t),
                                                 np.array(self.pred_x).reshape(-1, 6)),
                            "update_median_s": float(np.median(ups)) if ups else float("nan"),
                            "kernel": "cpp" if self.model.uses_cpp else "numpy",
                            "settings": self.settings},
                      effects=tuple(e.name for e in self.model.effects), model=self.model)
