"""Online (fixed-lag) factor-graph smoothing: the factor-graph analogue of the paper's online
mode (§III-E): after each absolute fix, the states inside a window of ``window`` seconds and
the parameter nodes are re-estimated jointly.

One orchestration (holding the parameters until a batch re-initialisation, replays,
adaptive process noise, events, history, causal and corrected tracks), two engines chosen
by ``FGSettings.online_engine``:

* "numpy" (default where the configuration allows it, :mod:`aqfg.fg.fastlag`): knots at
  the fixes only, one Gauss-Newton step per update on the window's dense normal equations,
  knots older than the window folded into a Gaussian prior by a Schur complement; no Python
  callback per factor;
* "gtsam" (and the fallback: measurement effects, random-walk parameters, a thrust
  lag): GTSAM's ``IncrementalFixedLagSmoother`` (ISAM2 underneath) on 1-s knots:
  states older than the window are marginalised into a prior (a linear container factor),
  not forgotten; the parameter keys are re-stamped with the current time at every update
  so they never leave the window (gtsam-notes). Only the window's Values reach the
  CustomFactor callbacks, so the cost per update does not grow with the mission.

``engine`` / ``engine_note`` (and ``Result.info``) say which engine ran and why.

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

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import gtsam
import numpy as np

from aqfg.data.mission import Mission
from aqfg.fg import factors as fc
from aqfg.fg import noise, observability, plausibility
from aqfg.fg.common import (
    FGSettings,
    Measurements,
    check_missions,
    default_estimate,
    first_knot_prior,
    initial_states,
    knot_times,
    measurement_factors,
    mission_model,
    piecewise_inertial,
    progress_fn,
    residuals,
    robust_fix_table,
)
from aqfg.fg.fastlag import LagWindow
from aqfg.fg.kinematic import CausalFloor, KinematicFilter
from aqfg.model.params import FIXED_BASE, difference
from aqfg.model.vehicle import Model
from aqfg.result import MissionResult, ParamHistory, Result, Track

# parameter groups whose start prior a replay keeps as the batch had it (the user's prior,
# centred on the original start values): the heading offset, the current and the sensor
# parameters. The thrust/drag constants ("fixed") are replayed with the batch's marginals
# as priors instead (see FixedLagSmoother._replay_sigmas)
BATCH_PRIOR_GROUPS = ("variable", "sensor")
log = logging.getLogger(__name__)

# what GTSAM's wrapper raises when elimination or a marginal fails (indeterminate
# system, a key missing from the Bayes tree after marginalisation, ...)
GTSAM_ERRORS = (RuntimeError, IndexError, ValueError)

# a held heading offset this far from the closed-form one of the fixes so far is re-seeded
# while the held model fails (FixedLagSmoother._reseed)
RESEED_GAP = np.radians(20.0)
RESEED_RHO = (0.8, 1.25)     # a re-seed also rescales an estimated thrust gain outside this
RESEED_EARLY_FIXES = 3     # the fewest fixes the closed form takes (the current held at zero)


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
    given, a cost per update that grows with the mission's length (docs/architecture.md)."""
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
        info = self._start(mission, plan)
        self._kinematic_step(float(self.fix_t[0]))
        return info

    def _start(self, mission: Mission, plan: bool) -> UpdateInfo:
        """:meth:`start` but for the kinematic causal floor's first fix (two return
        paths). A replay's restart calls :meth:`start` too; the floor skips replays."""
        (mission,) = check_missions([mission])
        s = self.settings
        self._t_call = time.perf_counter()
        self.mission = mission
        self.model = mission_model(self.base_model, mission, self.effects)
        est = self.estimate if self.estimate is not None else default_estimate(self.model, "online")
        vehicle = ("k", "k_x", "k_yz")
        if not getattr(self, "_replaying", False):
            self.warnings = []
            given = [n for n in vehicle if n in self.init]
            self._estimate_vehicle = self.estimate is None and not given
            if self._estimate_vehicle:
                # no constants of this vehicle: the paper's values are another vehicle's;
                # estimate them too (held until the first batch re-initialisation)
                self.warnings.append(
                    "no thrust/drag constants of this vehicle were given: the online fit "
                    "estimates them too; for the paper's protocol pass --params-from a batch "
                    "fit's parameters.json")
            elif not given and not any(n in est for n in vehicle):
                self.warnings.append(
                    "the thrust/drag constants are held at the paper's values for another "
                    "vehicle (none given): pass --params-from a batch fit's parameters.json or "
                    "estimate them too")
            for w in self.warnings:
                log.warning("fg online: %s", w)
        if self._estimate_vehicle:
            est = tuple(dict.fromkeys((*est, *vehicle)))
        self.layout = fc.ParamLayout.build(self.model, est, self.init)
        # per-update constants of the layout (its properties build tuples on each call)
        self._theta_est = "theta_e" in self.layout.estimated
        self._bound_watch: list | None = None      # see _implausible_released
        # no thrust/drag constant estimated (given by init, or held fixed)
        self._constants_given = not any(n in self.layout.estimated for n in FIXED_BASE)
        self._scales = np.array([self.model.spec(n).scale for n in self.layout.estimated])
        self.fix_t = np.unique(mission.fix_times())
        if not len(self.fix_t):
            raise ValueError(f"mission {mission.name!r} has no GNSS or USBL fix")
        prm = gtsam.ISAM2Params()
        prm.findUnusedFactorSlots = True
        prm.relinearizeSkip = 1
        thr = gtsam.ISAM2ThresholdMap()
        thr.insert(("x", np.repeat([s.relin_pos, s.relin_vel], 3)))
        for g in self.layout.groups:
            thr.insert((fc.GROUP_CHAR[g], np.full(self.layout.dim(g), s.relin_param)))
        prm.setRelinearizeThreshold(thr)
        self._isam_params = prm
        self.smoother = gtsam.IncrementalFixedLagSmoother(self.window, prm)
        self.knots: list[float] = []
        self.keys: list[int] = []
        self.filtered: list[np.ndarray] = []      # causal estimate per knot
        self._pending: list[tuple] = []            # numpy engine: deferred causal states
        self.anchor_idx: list[int] = []           # knot index of each fix
        self.latest: dict[int, np.ndarray] = {}   # knot index -> latest estimate
        self.seg = 0
        self.seg_starts = [float(self.fix_t[0])]
        self.v_by_seg: dict[int, np.ndarray] = {}
        self.hist_t: list[float] = []
        self.hist_v: list[np.ndarray] = []
        self.hist_s: list[np.ndarray] = []
        self.timings: dict[str, list[float]] = {"update": [], "update_total": [], "correction": []}
        self.n_fix = 0
        self.pred_t: list[float] = []              # fix times after the first, and the
        self.pred_x: list[np.ndarray] = []        # state predicted there before the update
        self._noise: dict = {}
        self.events: list[dict] = []               # recoveries and other notable events
        self._diverged_at: set[tuple[float, float]] = set()   # corrected_track's, noted
        self._n_committed = 0                      # knots the smoother holds (keys[:n])
        replaying = getattr(self, "_replaying", False)
        if not replaying:
            self._next_reinit = s.online_init_after    # s after the start (see _reinit_due)
            self._batch_tried = False              # no batch re-initialisation yet
            self.reinit_batches: list[dict] = []   # every re-initialisation batch solved
        self._hold_idx: list[int] = []             # factor indices of the hold priors
        self._last_new_idx: list[int] = []
        self._last_params: dict[str, np.ndarray] = {}   # last finite estimate per group
        if not replaying:
            self._q_floor = 1.0                    # the last re-initialisation batch's factor
            self._inflation: dict[str, float] = {}   # sigma reported / marginal, per name
            self._ambiguity: dict[str, float] = {}   # variance added: other basins, per name
            self._raw_sigma: dict[str, float] = {}   # the latest marginal sigma per name
            self._forced_at = -np.inf              # time of the last forced re-initialisation
        self.q_scale = self._q_floor               # process-noise variance factor (adaptive)
        # fix innovations (e2, R, Q_pos, noise.lr_gain of them)
        self._innov: list[tuple[float, float, float, float]] = []
        if not replaying:                          # a replay has the same mission
            self._fixes = robust_fix_table(mission, s)
            self._usbl_tab = self._gate_table(mission)
        self._under_review: list[float] = []       # USBL fixes left out, still in the window
        self._under_review_g: list[tuple[float, int]] = []   # the same, GTSAM engine: (t, key)
        self._taken_m2: list[float] = []           # _gate's statistic of the fixes taken
        self._rejects = 0                          # consecutive USBL fixes left out (_gate)
        self._forced_scale = 1.0                   # _gate's sigma factor of a forced fix
        if not replaying:
            self._rejected: dict[float, bool] = {}   # USBL fix time -> left out (_gate)
        self.warming = s.warmup_tol > 0
        self._plan: tuple[np.ndarray, dict[float, int], Any, np.ndarray] | None = None
        if plan:
            self._make_plan()
        self.warmup_end = float("nan")
        # first knot: position from the first fix (interpolation of the fixes at t0)
        t0 = float(self.fix_t[0])
        x0 = initial_states(mission, np.array([t0, t0 + 1.0]))[0]
        x0[3:] = 0.0
        if mission.planar:
            x0[2] = 0.0
        hold = replaying or self._reinit_scheduled()
        if not replaying:
            # the causal track's kinematic floor while the parameters are held
            # (aqfg.fg.kinematic); none where they are not, or the settings say so
            self._floor = CausalFloor(
                KinematicFilter.from_settings(s),
                until=math.inf if hold and s.online_kinematic_q > 0 else float(self.fix_t[0]))
        # held parameters are reported with their prior's sigma (the batch's, replaying):
        # the hold priors' tiny marginal would claim a certainty no data gave
        self._held_sigma = self._held_report_sigma(replaying) if hold else None
        reason = ("online_engine = 'gtsam'" if s.online_engine == "gtsam" else
                  LagWindow.unsupported(self.model, self.layout, mission, s))
        self.engine = "gtsam" if reason else "numpy"
        self.engine_note = reason
        if reason and s.online_current_walk > 0:
            self.engine_note += ("; the current is held constant in the window's past "
                                 "(online_current_walk needs the numpy engine)")
        if reason and s.online_heading_walk > 0:
            self.engine_note += ("; the heading offset is one constant "
                                 "(online_heading_walk needs the numpy engine)")
        self._fast: LagWindow | None = None
        if not reason:
            return self._start_fast(mission, t0, x0, hold, replaying)
        graph = gtsam.NonlinearFactorGraph()
        vals = gtsam.Values()
        k0 = fc.state_key(0, 0)
        vals.insert(k0, x0)
        graph.add(first_knot_prior(mission, k0, x0, s))
        if mission.planar:
            graph.add(fc.surface_factor(k0, *s.surface_sigma))
        hold_pos = []
        for g in self.layout.groups:
            k = self._node(g)
            vals.insert(k, self.layout.initial(g))
            graph.add(self._start_prior(g, k, replaying))
            graph.add(fc.bound_factor(self.layout, g, k))
            if hold:
                # held at their start values (or at the batch's, replaying) until the batch
                # re-initialisation releases them: from rest, the first fixes barely
                # determine the heading offset and the constants, and single incremental
                # Gauss-Newton steps on them run off (by 100 deg and more)
                hold_pos.append(graph.size())
                graph.add(self._hold_prior(g, k))
        self.knots.append(t0)
        self.keys.append(k0)
        self.filtered.append(x0.copy())
        meas = Measurements.of(mission, s, t0, t0)
        for f in measurement_factors(self.model, self.layout, meas, np.array([t0]),
                                     lambda i: k0,
                                     lambda stream, t: self._node_keys(self.layout.meas_groups(stream)),
                                     s):
            graph.add(f)
        info = self._update(graph, vals, {k0: t0}, t0, 1)
        if hold_pos and len(self._last_new_idx) == graph.size():
            self._hold_idx = [int(self._last_new_idx[i]) for i in hold_pos]
        return info

    def _start_prior(self, g: str, k: int, replaying: bool) -> gtsam.PriorFactorVector:
        """The weak prior of parameter group ``g`` at node ``k`` in a fresh smoother (see
        :meth:`_prior_sigmas` and :meth:`_prior_mean`)."""
        sig = dict(self.settings.prior_sigma)
        sig.update(self._replay_sigmas() if replaying else {})
        return fc.param_prior(self.layout, g, k, self.settings.prior_scale,
                              mean=self._prior_mean(g, replaying), sigma=sig)

    def _prior_mean(self, g: str, replaying: bool) -> np.ndarray:
        """Centre of parameter group ``g``'s start prior: its start values; in a replay, for
        the groups of ``BATCH_PRIOR_GROUPS``, the values the smoother first started from
        (``_prior_centre``, the original ``init``), as the batch had it. The replay holds
        them at the batch's values and, released, the window solves the batch's problem
        (centred on the batch's values, the current's zero-mean prior is gone and the
        released estimate slides along the offset-current ridge; measured in
        docs/independent-vehicle.md)."""
        centre = getattr(self, "_prior_centre", None) \
            if replaying and g in BATCH_PRIOR_GROUPS else None
        if centre is None:
            return self.layout.initial(g)
        return self.layout.project(g, self.model.nominal(centre)[self.layout.idx[g]])

    def _hold_prior(self, g: str, k: int) -> gtsam.PriorFactorVector:
        """The removable prior that holds group ``g`` at its start values (1e-3 x scale)."""
        return fc.param_prior(self.layout, g, k, 1.0, sigma={
            n: 1e-3 * self.model.spec(n).scale for n in self.layout.names[g]})

    def _prior_sigmas(self, replaying: bool) -> tuple[np.ndarray, np.ndarray]:
        """Sigmas of the parameter priors (as :func:`fc.param_prior`) and of the hold
        priors, in the layout's order."""
        prior = self._sigmas_with(self._replay_sigmas() if replaying else {})
        hold = np.array([1e-3 * self.model.spec(n).scale for n in self.layout.estimated])
        return prior, hold

    def _sigmas_with(self, override: dict[str, float]) -> np.ndarray:
        """The settings' prior sigmas (``prior_sigma``, else ``prior_scale`` x the
        parameter's scale, as :func:`fc.param_prior`) with ``override``, in the layout's
        order."""
        s = self.settings
        sig = {**s.prior_sigma, **override}
        return np.array([sig.get(n, s.prior_scale * self.model.spec(n).scale)
                         for n in self.layout.estimated])

    def _replay_sigmas(self) -> dict[str, float]:
        """A replay's prior sigmas that are not the settings': the batch's marginals (x2)
        of the thrust/drag constants, centred on the batch's values: the window's single
        steps on constants the first minutes barely determine wander from the settings'
        flat prior (docs/independent-vehicle.md)."""
        ov = getattr(self, "_prior_override", {})
        return {n: v for n, v in ov.items() if self.model.spec(n).group not in BATCH_PRIOR_GROUPS}

    def _held_report_sigma(self, replaying: bool) -> np.ndarray:
        """The sigmas a held parameter is reported with: its prior's, and in a replay the
        batch's (``_prior_override``; the hold priors' tiny marginal would claim a
        certainty no data gave)."""
        return self._sigmas_with(getattr(self, "_prior_override", {}) if replaying else {})

    def _start_fast(self, mission: Mission, t0: float, x0: np.ndarray, hold: bool,
                    replaying: bool) -> UpdateInfo:
        """:meth:`start` on the numpy engine (:mod:`aqfg.fg.fastlag`)."""
        s = self.settings
        pf = first_knot_prior(mission, fc.state_key(0, 0), x0, s)
        prior, hold_sig = self._prior_sigmas(replaying)
        mean = (np.concatenate([self._prior_mean(g, replaying) for g in self.layout.groups])
                if self.layout.groups else np.zeros(0))
        self._fast = LagWindow(self.model, self.layout, s, mission, self.window, prior,
                               hold_sig if hold else None, x0, np.asarray(pf.prior()),
                               np.asarray(pf.noiseModel().sigmas()), t0, 0, prior_mean=mean)
        self.knots.append(t0)
        self.filtered.append(x0.copy())
        info = self._update(None, None, {}, t0, 1)
        if hold:
            self._hold_idx = [-1]              # the engine's hold priors
        return info

    def _make_plan(self) -> None:
        """Knots of the whole recorded mission (the same rule as :meth:`update`) and their
        kernel steps in one build_steps call, sliced per update (docs/architecture.md)."""
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
        """Current full parameter vector (inside the physical bounds)."""
        if self._fast is not None:
            return self._fast.full_params()
        nd = {}
        for g in self.layout.groups:
            try:
                v = self.smoother.calculateEstimateVector(self._node(g))
            except GTSAM_ERRORS:
                v = None
            if v is None or not np.all(np.isfinite(v)):
                v = self._last_params.get(g, self.layout.initial(g))
            nd[g] = self.layout.project(g, v)
        return self.layout.full(nd)

    def update(self, t_fix: float | None = None, mission: Mission | None = None) -> UpdateInfo:
        """Process inputs and measurements up to the next fix (or up to ``t_fix``, which must
        be a fix time) and update the window. ``mission``: a newer copy of the mission with
        more samples (live use)."""
        if mission is not None:
            self.mission = mission
            self.fix_t = np.unique(mission.fix_times())
            self._plan = None                      # inputs may have changed: no plan
            self._fixes = robust_fix_table(mission, self.settings)
            self._usbl_tab = self._gate_table(mission)
            if self._fast is not None:
                self._fast.set_mission(mission)
        if t_fix is None:
            if not self.pending():
                raise ValueError("no fix left to process")
            t_fix = float(self.fix_t[self.n_fix])
        self._t_call = time.perf_counter()
        self._ev_mark = len(self.events)
        t_last = self.knots[-1]
        if t_fix <= t_last + 1e-9:
            raise ValueError(f"fix time {t_fix} s is not after the last processed time {t_last} s")
        # new knots on the grid up to the fix
        sp = self.settings.knot_spacing
        grid = np.arange(t_last + sp, t_fix - sp / 4, sp)
        all_t = np.concatenate([[t_last], grid, [t_fix]])
        new_t = all_t[1:]
        step = self._update_fast if self._fast is not None else self._update_gtsam
        info = step(t_fix, t_last, new_t, all_t)
        due = self._reinit_due(t_fix)
        if due:
            info = self._reinitialise(t_fix, rescue=due == "rescue") or info
        elif self._troubled(t_fix) or self._implausible_released(t_fix):
            info = self._reinitialise(t_fix, force=True) or info
        if self._held_failing() or self._held_missed_early():
            info = self._reseed(t_fix) or info
        self._kinematic_step(t_fix)
        return info

    def _kinematic_step(self, t_fix: float) -> None:
        """The causal track's kinematic floor (:class:`aqfg.fg.kinematic.CausalFloor`) at
        this fix: fed while the parameters are held; at the first fix at which they are not
        (the first batch released them), the causal track follows the model from there on
        (an event says so). Not in a replay: it re-runs fixes already reported."""
        if getattr(self, "_replaying", False):
            return
        if self._floor.step(t_fix, self._fixes, bool(self._hold_idx)):
            self.events.append({"t": float(t_fix), "event": "causal track follows the model "
                                "from here (before: a constant-velocity filter on the fixes, "
                                "while the parameters were held)"})

    def _update_gtsam(self, t_fix: float, t_last: float, new_t: np.ndarray, all_t: np.ndarray
                      ) -> UpdateInfo:
        """:meth:`update` on the GTSAM engine: the knots on the grid up to the fix, their
        dynamics factors and the fixes' factors, one ISAM2 update."""
        s = self.settings
        lay = self.layout
        steps, off = self._steps(all_t)
        graph = gtsam.NonlinearFactorGraph()
        vals = gtsam.Values()
        stamps = {}
        p = self.params()
        try:
            x = self.smoother.calculateEstimateVector(self.keys[-1])
        except GTSAM_ERRORS:
            x = np.asarray(self.filtered[-1], float)
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
            x_new = self.model.propagate(x, p, st)[0]
            if not np.all(np.isfinite(x_new)):
                # the model diverged at these parameters: hold the last finite state
                x_new = np.where(np.isfinite(x), x, 0.0)
                x_new[3:] = 0.0
                if not self.events or self.events[-1].get("event") != "prediction diverged":
                    self.events.append({"t": float(t), "event": "prediction diverged"})
            x = x_new
            k = fc.state_key(0, i0 + j)
            vals.insert(k, x)
            stamps[k] = float(t)
            if self.mission.planar:
                graph.add(fc.surface_factor(k, *s.surface_sigma))
            dt = float(all_t[j + 1] - all_t[j])
            nk = (round(dt, 9), self.mission.planar, self.q_scale)
            if nk not in self._noise:
                self._noise[nk] = s.process.noise_model(dt, self.mission.planar, self.q_scale)
            graph.add(fc.dynamics_factor(self.model, lay, st, self.keys[-1] if j == 0 else
                                         fc.state_key(0, i0 + j - 1), k, dyn_nodes,
                                         self._noise[nk]))
            self.knots.append(float(t))
            self.keys.append(k)
            self.filtered.append(x.copy())
        self.pred_t.append(float(t_fix))
        self.pred_x.append(x.copy())
        drop_usbl = self._gate(t_fix, float(t_fix - t_last), x)
        if s.adapt_process:
            self._adapt(t_fix, float(t_fix - t_last), x)
        meas = Measurements.of(self.mission, s, t_last + 1e-6, t_fix)
        self._review_left_out_gtsam(graph, t_fix)
        if self._forced_scale != 1.0:
            here = np.abs(meas.usbl_t - t_fix) <= 1e-6
            sig = meas.usbl_sigma.copy()
            sig[here] *= self._forced_scale
            meas = replace(meas, usbl_sigma=sig)
        if drop_usbl:
            keep = np.abs(meas.usbl_t - t_fix) > 1e-6
            meas = replace(meas, usbl_t=meas.usbl_t[keep], usbl_z=meas.usbl_z[keep],
                           usbl_sigma=meas.usbl_sigma[keep], usbl_R=meas.usbl_R[keep])
            self._under_review_g.append((float(t_fix), int(self.keys[-1])))
        local = np.asarray(all_t)
        for f in measurement_factors(self.model, lay, meas, local,
                                     lambda i: self.keys[i0 - 1 + i],
                                     lambda stream, t: self._node_keys(lay.meas_groups(stream)), s):
            graph.add(f)
        return self._update(graph, vals, stamps, t_fix, len(new_t))

    def _troubled(self, t_fix: float) -> bool:
        """This update skipped its fix, saw the model's prediction diverge or needed a
        restart with broad priors, and no
        forced re-initialisation ran in the last 30 s: the smoother's own recoveries are not
        enough (a track that ran to 1e7 m after a failed release), so the fixes so far are
        solved as a batch and replayed."""
        bad = any(e["event"] in ("fix skipped", "prediction diverged", "restarted (broad priors)")
                  for e in self.events[self._ev_mark:])
        return bad and self._may_force(t_fix)

    def _may_force(self, t_fix: float) -> bool:
        """A forced re-initialisation may run at this fix: six fixes in, the heading offset
        not given, and none forced in the last 30 s (:meth:`_troubled`,
        :meth:`_implausible_released`)."""
        return self.n_fix >= 6 and "theta_e" not in self.init and t_fix - self._forced_at >= 30.0

    def _implausible_released(self, t_fix: float) -> bool:
        """The released parameters have become a vehicle whose prediction nothing bounds
        (the batch's bounds check, :func:`aqfg.fg.plausibility.bounds`, on the thrust, the
        surge drag and the current: no thrust or no drag along the thrust axis, a current
        at its bound), and no forced re-initialisation ran in the last 30 s: the event is
        recorded and the fixes so far are solved as a batch and replayed (as for
        :meth:`_troubled`). On an Otter in a 0.23 m/s current with the paper's constants
        and all six free, the released thrust and drags fell to zero after a 160-s batch,
        and the causal track ran 45 km off in the next 60 s (docs/independent-vehicle.md).
        A sway drag at its bound (a hull that slides) is left to the batches' slip checks:
        it happens on the Otter, and the predictions stay bounded."""
        if self._hold_idx or not self._may_force(t_fix):
            return False
        # (a few comparisons on the latest estimates per update, against the bounds check's
        # own limits; the check in words only where one is at its bound)
        lay = self.layout
        watch = self._bound_watch
        if watch is None:
            watch = self._bound_watch = [
                (g, lay.names[g].index(n), *plausibility.limits(self.model, n))
                for g in lay.groups for n in lay.names[g] if n in ("k", "k_x", "s_x", "s_y")]
        if not any(g in self._last_params and not lo < abs(self._last_params[g][j]) < hi
                   for g, j, lo, hi in watch):
            return False
        est = tuple(n for n in lay.estimated if n != "k_yz")
        pinned, why = plausibility.bounds(self.model, self.params(), est)
        if not pinned:
            return False
        self.events.append({"t": float(t_fix), "event": "released parameters implausible",
                            "reasons": why})
        self._forced_at = float(t_fix)        # one attempt per 30 s, used or not
        return True

    def _update_fast(self, t_fix: float, t_last: float, new_t: np.ndarray, all_t: np.ndarray
                     ) -> UpdateInfo:
        """:meth:`update` on the numpy engine: one knot at the fix (its dynamics factor over
        every input since the last one); the knots between join the causal track as the
        model's prediction from the last fix, computed when the track is read
        (:meth:`_materialise`)."""
        eng = self._fast
        assert eng is not None
        s = self.settings
        i0 = len(self.knots)
        n_new = len(new_t)
        if n_new > 1:
            # the parameters of now (params_view: a new array per estimate, never written)
            self._pending.append((i0, all_t, eng.z[-6:].copy(), eng.params_view()))
            self.filtered.extend([None] * (n_new - 1))      # type: ignore[list-item]
        x_fix = eng.add(float(t_fix), i0 + n_new - 1, self._interval_steps(all_t),
                        self.q_scale)
        eng.take_fixes(usbl=not self._gate(t_fix, float(t_fix - t_last), x_fix),
                       usbl_scale=self._forced_scale)
        if not eng.last_ok:
            if not self.events or self.events[-1].get("event") != "prediction diverged":
                self.events.append({"t": float(t_fix), "event": "prediction diverged"})
        self.filtered.append(x_fix)
        self.knots.extend(new_t.tolist())
        self.pred_t.append(float(t_fix))
        self.pred_x.append(x_fix.copy())
        if s.adapt_process:
            self._adapt(t_fix, float(t_fix - t_last), x_fix)
        info = self._update(None, None, {}, t_fix, n_new)
        if self._under_review:
            self._review_left_out(t_fix)
        return info

    def _review_left_out(self, t_fix: float) -> None:
        """USBL fixes the gate left out, seen again against their knot's smoothed estimate
        once later fixes are in (the numpy engine): a fix that agrees now (the same gate,
        without the prediction's process noise) was good and the track was off -- it joins
        the window; one whose knot has left the window stays out. The gate alone cannot
        tell a 8-m range outlier from a track 8 m off; a smoother can, a few fixes later."""
        eng = self._fast
        assert eng is not None
        keep = []
        for t in self._under_review:
            if t >= t_fix - 1e-9:
                keep.append(t)
                continue
            i = eng.index_at(t)
            if i is None:
                continue                           # left the window: stays out
            x = eng.z[eng.P + 6 * i:eng.P + 6 * i + 6]
            if self._gate_m2(t, x, 0.0) <= self.settings.online_gate_usbl \
                    and eng.readmit_usbl(t):
                self._rejected[t] = False
                continue
            keep.append(t)
        self._under_review = keep

    def _review_left_out_gtsam(self, graph: gtsam.NonlinearFactorGraph, t_fix: float) -> None:
        """:meth:`_review_left_out` on the GTSAM engine: a USBL fix the gate left out whose
        knot is still in the window and whose smoothed estimate now agrees with it (the
        same gate, without the prediction's process noise) gets its factor in this update
        (``graph``); one whose knot has been marginalised stays out."""
        if not self._under_review_g:
            return
        s, lay = self.settings, self.layout
        keep = []
        for t, k in self._under_review_g:
            if t >= t_fix - 1e-9:
                keep.append((t, k))
                continue
            try:
                x = np.asarray(self.smoother.calculateEstimateVector(k), float)
            except GTSAM_ERRORS:
                continue                           # left the window: stays out
            if x.shape != (6,) or not np.all(np.isfinite(x)):
                continue
            if self._gate_m2(t, x, 0.0) > s.online_gate_usbl:
                keep.append((t, k))
                continue
            m = Measurements.of(self.mission, s, t - 1e-6, t + 1e-6)
            m = replace(m, gnss_t=m.gnss_t[:0], gnss_z=m.gnss_z[:0], gnss_sigma=m.gnss_sigma[:0],
                        gnss_R=m.gnss_R[:0], depth_t=m.depth_t[:0], depth_z=m.depth_z[:0])
            def knot_key(_i: int, k: int = k) -> int:
                return k
            for f in measurement_factors(self.model, lay, m, np.array([t]), knot_key,
                                         lambda stream, tt: self._node_keys(
                                             lay.meas_groups(stream)), s):
                graph.add(f)
            self._rejected[t] = False
        self._under_review_g = keep

    def _interval_steps(self, all_t: np.ndarray):
        """Kernel steps from ``all_t[0]`` to ``all_t[-1]`` in one piece (the numpy engine's
        dynamics factor): a slice of the plan when it has both knots."""
        if self._plan is not None:
            _, index, steps, off = self._plan
            i, j = index.get(float(all_t[0])), index.get(float(all_t[-1]))
            if i is not None and j is not None and j > i:
                return steps.slice(int(off[i]), int(off[j]))
        steps, off = self._steps(all_t)
        return steps.slice(int(off[0]), int(off[-1]))

    def _materialise(self) -> None:
        """The numpy engine's deferred causal states between fixes: the model's prediction
        from the fix before them with the parameters of then (one kernel roll-out each)."""
        pending, self._pending = getattr(self, "_pending", []), []
        for i0, all_t, x, p in pending:
            steps, off = self._steps(all_t)
            with np.errstate(all="ignore"):
                Xi = self.model.rollout_segments(x, p, steps, off)[1:-1]
            if not np.all(np.isfinite(Xi)):
                Xi = np.where(np.isfinite(Xi), Xi, np.where(np.isfinite(x), x, 0.0))
            self.filtered[i0:i0 + len(Xi)] = list(Xi)

    def _fast_step(self, t_fix: float) -> None:
        """The numpy engine's Gauss-Newton step(s), surviving a system that is not positive
        definite: the marginal is replaced by broad priors around the current estimate and
        the step retried; if that fails too, the step is skipped (recorded in ``events``)."""
        eng = self._fast
        assert eng is not None
        for _ in range(max(self.settings.iterations_per_update, 1)):
            try:
                eng.step()
            except np.linalg.LinAlgError as exc:
                err = str(exc) or type(exc).__name__
                eng.broaden(np.array([10.0, 10.0, 1.0, 2.0, 2.0, 0.5]),
                            self.settings.prior_scale)
                try:
                    eng.step()
                    self.events.append({"t": float(t_fix), "event": "restarted (broad priors)",
                                        "error": err})
                except np.linalg.LinAlgError:
                    self.events.append({"t": float(t_fix), "event": "fix skipped",
                                        "error": err})
                return

    # ---------------------------------------------------------------- causal initialisation
    def _reinit_scheduled(self) -> bool:
        """Online without a given heading offset: batch re-initialisations are scheduled
        (the parameters are held until the first)."""
        return (self.settings.online_init_after > 0 and self._theta_est
                and "theta_e" not in self.init)

    def _reinit_due(self, t_fix: float) -> str:
        """"" (no batch re-initialisation due at this fix), "scheduled", or "rescue": one
        brought forward because the held model fails, which keeps the schedule of checks."""
        s = self.settings
        el = t_fix - self.knots[0]
        # the first batch: after online_init_after s, or online_init_fixes fixes if sooner,
        # or at every fix from the 4th while the held model fails: its process noise
        # adapted to the bound, its last two fixes beyond the USBL gate's quantile, or two
        # of its last three beyond chi-square(2)'s 99 % one -- not their sum, which one
        # USBL outlier decides (a held heading 127-150 deg off ran the causal track 27-43
        # m off the fixes while the first batch waited for six fixes; a batch of 6.5 s
        # whose last fix was a 34-m outlier came out 100 deg off, sigma 3 deg;
        # docs/independent-vehicle.md)
        failing = self._held_failing()
        first = (((not self._batch_tried and self.n_fix >= s.online_init_fixes) or failing)
                 and not getattr(self, "_replaying", False))
        due = (self._reinit_scheduled() and (el >= self._next_reinit or first)
               and (el <= s.online_reinit_until or bool(self._hold_idx))
               and self.n_fix >= (4 if failing and self._constants_given else 6))
        # (from the 4th fix only with the thrust/drag constants given: with all six free,
        # a batch of the first 8 s of heldout-32 came out 60 deg off and the released
        # estimates ran the causal track 545 m off)
        # a batch brought forward because the held model fails is a rescue: the schedule
        # of checks stays (moved with it, the later batches of heldout-06 at 4 s fell where
        # a free fit slides)
        if not due:
            return ""
        return "rescue" if failing and el < self._next_reinit else "scheduled"

    def _held_failing(self) -> bool:
        """The parameters are held and the held model fails: its process noise adapted to
        the bound, its last two fixes beyond the USBL gate's quantile, or two of its last
        three beyond chi-square(2)'s 99 % one (see :meth:`_reinit_due`)."""
        s = self.settings
        recent = self._taken_m2[-3:]
        return (bool(self._hold_idx)
                and (self.q_scale >= s.adapt_max
                     or (len(recent) >= 2 and min(recent[-2:]) > s.online_gate_usbl)
                     or (len(recent) == 3 and sorted(recent)[1] > noise.CHI2_2_99)))

    def _held_missed_early(self) -> bool:
        """The parameters are held and the third fix, the first that gives two legs, is
        beyond the USBL gate's quantile (later fixes: :meth:`_held_failing`, two misses)."""
        return (bool(self._hold_idx) and self.n_fix == RESEED_EARLY_FIXES
                and len(self._taken_m2) > 0
                and self._taken_m2[-1] > self.settings.online_gate_usbl)

    def _reseed(self, t_fix: float) -> UpdateInfo | None:
        """While the parameters are held and the held model fails before a batch can take
        over: re-hold the heading offset and the current at the closed-form start of the
        fixes so far (:func:`aqfg.fg.init.candidate_starts` at the held constants, global in
        theta_e) and replay, if it differs from the held heading by more than
        ``RESEED_GAP``. The batch needs more fixes than the closed form (six with the
        constants free); in between, a held heading 160 deg off ran the causal track 25-40
        m off the fixes (docs/independent-vehicle.md)."""
        from aqfg.fg.init import candidate_starts, current_prior
        t_re = time.perf_counter()
        if (getattr(self, "_replaying", False) or not self._hold_idx
                or "theta_e" not in self.layout.estimated or self.n_fix < RESEED_EARLY_FIXES):
            return None
        view = _mission_until(self.mission, t_fix)
        knots = knot_times(view, self.settings.knot_spacing)
        p = self.params()
        try:
            starts = candidate_starts(self.model, view, knots, p, search=False,
                                      current_sigma=current_prior(self.settings.prior_sigma))
        except (ValueError, FloatingPointError, np.linalg.LinAlgError):
            starts = []
        if not starts:
            return None
        st = starts[0]
        th0 = float(p[self.model.index("theta_e")])
        gap = abs(float(np.angle(np.exp(1j * (st.theta_e - th0)))))
        # The thrust gain too, where it is estimated (not given): the closed form's speed
        # scale rho says the held model's steady speed sqrt(k / k_x) is 1 / rho times the
        # vehicle's (aqfg.fg.init.candidate_starts); a heading re-seeded at 2.4x the
        # vehicle's speed still ran the track 6-11 m off its GNSS-only fixes. Only where
        # the fixes determine rho: off 1 by more than 2 of its sigma (the fixes' median
        # variance through the closed form's) and detected at 3 sigma (sigma below
        # rho / 3); from three fixes of a vehicle that had barely moved, rho came out
        # 13 +- 6.5 (k x 170).
        v_fix = float(np.median(self._fixes[2][self._fixes[0] <= t_fix + 1e-9]))
        sd_rho = math.sqrt(max(v_fix * st.rho_var, 0.0)) if math.isfinite(st.rho_var) else math.inf
        # ... and where no fix can be an undetected outlier: three fixes have none to
        # spare, so there only if none is a USBL fix (the stream with outliers, which the
        # gate exists for; a 17-m USBL outlier among the first three gave rho = 13 +- 3.8,
        # k x 170, and the causal track ran 190 m off; docs/independent-vehicle.md)
        n_usbl = 0 if view.usbl is None else int(np.sum(view.usbl.t <= t_fix + 1e-9))
        spare = len(np.unique(view.fix_times())) > RESEED_EARLY_FIXES or n_usbl == 0
        scale_k = ("k" in self.layout.estimated and "k" not in self.init and spare
                   and not RESEED_RHO[0] <= st.rho <= RESEED_RHO[1]
                   and abs(st.rho - 1.0) > 2.0 * sd_rho and 3.0 * sd_rho < st.rho)
        # ... and the heading as well: from a hull that had moved 2 m with a 0.29-m/s
        # current, three fixes (one a USBL fix 14 m long in range) re-seeded a heading 140
        # deg off, and the causal track ran 20 m off the fixes: the held heading waits for
        # a fourth. (Refusing closed forms whose heading sigma is large was worse: the held
        # heading is arbitrary, and an uncertain one from four fixes mostly beat it on the
        # runs it would have refused; docs/independent-vehicle.md)
        if not spare or (gap < RESEED_GAP and not scale_k):
            return None
        new_init = {n: float(p[self.model.index(n)]) for n in self.layout.estimated}
        new_init.update(self.init)
        new_init["theta_e"] = float(st.theta_e)
        for n, v in zip(("s_x", "s_y"), st.current):
            if n in self.layout.estimated and n not in self.init:
                new_init[n] = float(v)
        k0 = float(p[self.model.index("k")])
        if scale_k:
            sp = self.model.spec("k")
            new_init["k"] = float(np.clip(k0 * st.rho ** 2, sp.lower, sp.upper))
        # held with their start priors (the settings'), as at the start
        return self._replay(t_fix, new_init, {}, {
            "t": float(t_fix), "event": "held heading re-seeded from the fixes so far",
            "theta_e_before": th0, "theta_e_after": float(st.theta_e),
            "speed_scale": float(st.rho), "speed_scale_sigma": sd_rho, "k_before": k0,
            "k_after": new_init.get("k", k0),
            "misfit_m": float(st.misfit)}, t_re)

    def _release(self, t_fix: float) -> None:
        """Remove the hold priors: the parameters follow the data from here."""
        idx, self._hold_idx = self._hold_idx, []
        self._held_sigma = None
        if not idx:
            return
        if self._fast is not None:
            self._fast.release()
            for _ in range(2):
                self._fast_step(t_fix)
            self.events.append({"t": float(t_fix), "event": "parameters released"})
            return
        # only hold priors still on a parameter node in the window: a hold prior on a walk
        # segment's node that has left the window was marginalised, and ISAM2 reuses its
        # slot (removing that index removed a marginal factor)
        fg = self.smoother.getFactors()
        nodes = {self._node(g) for g in self.layout.groups}
        idx = [i for i in idx if fg.exists(i) and isinstance(fg.at(i), gtsam.PriorFactorVector)
               and set(fg.at(i).keys()) <= nodes]
        try:
            self.smoother.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), {}, idx)
            for _ in range(2):
                self.smoother.update()
            self.events.append({"t": float(t_fix), "event": "parameters released"})
        except GTSAM_ERRORS as exc:
            self.events.append({"t": float(t_fix), "event": "release failed; restarted",
                                "error": (str(exc).strip().splitlines() or [""])[0]})
            self._restart(t_fix)

    def _reinitialise(self, t_fix: float, force: bool = False, rescue: bool = False
                      ) -> UpdateInfo | None:
        """Solve the fixes so far as a batch (global heading start, :mod:`aqfg.fg.batch`).
        If its heading offset disagrees with the smoother's by more than 3 of the batch's
        sigmas (within 1-10 deg; 1 deg while the parameters are still held at their start
        values), or ``force`` (the smoother is in trouble), restart from the batch
        solution: replay the fixes so far with the parameters held at the batch's values
        and the batch's own priors (the constants: their batch marginals, x4 in variance;
        :meth:`_prior_mean`, :meth:`_replay_sigmas`), then release them. Otherwise
        release them where they are. An incremental solver cannot leave a wrong heading
        basin by itself; the batch of the data so far does not start in one. A ``rescue``
        (:meth:`_reinit_due`) leaves the schedule of later checks where it was."""
        from aqfg.fg.batch import as_good_a_basin
        t_re = time.perf_counter()
        el = t_fix - self.knots[0]
        self._batch_tried = True
        if not force:
            self._next_reinit = self._next_reinit if rescue else 2.0 * el
        view = _mission_until(self.mission, t_fix)
        p = self.params()
        try:
            if len(np.unique(view.fix_times())) < 4:
                raise ValueError("too few fixes")
            # solved from the closed-form start and from the smoother's own estimate (once
            # released): the lower cost wins, so a batch of part of the data that lands in
            # a wrong basin cannot pull a good online estimate into it
            own = (None if self._hold_idx else
                   {n: float(p[self.model.index(n)]) for n in self.layout.estimated})
            # the process noise by the evidence only where the fixes so far are too short for
            # the sandwich (the batch's default rule), else measured only: over 640 s of an
            # Otter mission the evidence-chosen noise freed a hull sliding sideways, theta_e
            # 44 deg off, which replaced a right online estimate (docs/independent-vehicle.md)
            bres = self._batch(self.layout.estimated, also_start=own).run([view])
        except (ValueError, *GTSAM_ERRORS) as exc:
            self._batch_not_used(t_fix, {
                "event": "batch re-initialisation failed",
                "error": (str(exc).strip().splitlines() or [""])[0]})
            return None
        if not bres.info.get("plausible", True):
            # a batch of a short stretch with the constants free can land on a vehicle no
            # hull is (thrust 500x, currents at their bounds on a 40-s crop of an Otter
            # mission); replayed with such values held, every prediction diverged
            self._batch_not_used(t_fix, {
                "event": "batch re-initialisation implausible: not used",
                "reasons": [r for v in bres.info.get("plausibility", {}).values()
                            for r in v.get("reasons", [])]})
            return None
        if self._hold_idx and not self._constants_given \
                and float(bres.info.get("process_noise_scale", 1.0)) >= self.settings.adapt_max:
            # the evidence put the process noise at its bound: the model explains none of
            # the fixes so far, and its free constants and heading are whatever the noise
            # leaves (12 s of heldout-42, all six free: a top speed 4x the hull's, theta_e
            # 70 deg off, sigma 19 deg; released, the causal track ran 33 m off); still
            # held. (Not with the constants given: there it made more runs worse than it
            # mended, docs/independent-vehicle.md)
            self._batch_not_used(t_fix, {
                "event": "batch re-initialisation explains no fix (process noise at its "
                         "bound): not used"})
            return None
        # the process noise this model needs, measured on all the fixes so far by the
        # evidence, is the floor of the online factor from here (aqfg.fg.noise); a batch
        # long enough for the sandwich is solved with the nominal noise (above) and only
        # measures it (with the floor reset to 1 by such a batch, a 6.7-m USBL range
        # outlier passed the gate in the replay of otter-dev-yawdrift)
        q_meas = bres.info.get("process_noise_measured")
        self._q_floor = float(q_meas if q_meas is not None
                              else bres.info.get("process_noise_scale", 1.0))
        # the online marginal's sigma against the batch's honest one, on the same data:
        # the factor by which the online sigma is reported from here
        # (within the chosen basin; the spread of the basins that fit as well is added to
        # the reported sigma until the next batch, the solve itself stays in one basin)
        uni = {**bres.sigma, **bres.info.get("sigma_unimodal", {})}
        self._ambiguity = {n: max(float(bres.sigma[n]) ** 2 - float(v) ** 2, 0.0)
                           for n, v in bres.info.get("sigma_unimodal", {}).items()}
        self._inflation = {}
        for n in (() if self._hold_idx else self.layout.estimated):   # held: no marginal
            raw, ref = self._raw_sigma.get(n, np.nan), uni.get(n, np.nan)
            if np.isfinite(raw) and np.isfinite(ref) and raw > 0 and ref > raw:
                self._inflation[n] = float(ref / raw)
        self.q_scale = max(self.q_scale, self._q_floor)
        held = bool(self._hold_idx)
        slip = max((v.get("slip_deg") or 0.0
                    for v in bres.info.get("plausibility", {}).values()), default=0.0)
        # a batch sliding off its thrust axis (plausibility.SUSPECT_SLIP) that names a
        # non-sliding alternative explaining the fixes almost as well (the sway drag held
        # high): the alternative is the reference. A 256-s batch of heldout-52 slid 16 deg
        # with theta_e 53 deg off and sigma 3 deg; its alternative was 9 deg off, and the
        # restart to the sliding one ran the causal track up to 6 m off for 250 s
        # ... unless the batch does not determine the heading offset (its observability
        # verdict: one heading kept, so a heading offset and a cross current look alike):
        # then its alternative has no more evidence than the sliding fit. A 160-s batch of
        # heldout-111 (8-s fixes) that kept one heading named an alternative 146 deg off
        # (sigma 41 deg); it replaced an online heading 23 deg off (the batch's own was 24
        # deg off), and the causal track ran up to 15 m off for 160 s
        # (docs/independent-vehicle.md)
        undetermined = bres.info.get("observability", {}).get(
            "theta_e", {}).get("verdict") == observability.NOT
        alt = bres.info.get("alternative_held_sway") \
            if slip > plausibility.SUSPECT_SLIP and not undetermined else None
        ref_v, ref_s = (alt["values"], alt.get("sigma_unimodal", alt["sigma"])) if alt \
            else (bres.values, uni)
        # the batch solved from the smoother's own estimate ends in another basin that
        # explains the fixes as well as the best (within the batch's ambiguity margin): the
        # data do not decide between them, and that solution is the reference. A 160-s
        # batch of heldout-73 (all six free, the offset drifting) chose a basin 46 deg off
        # by 2.0 in cost over the one the smoother's estimate (2 deg off) led to; the
        # restart ran the causal track up to 17 m off for 150 s
        # (docs/independent-vehicle.md)
        own_b = next((b for b in bres.info.get("basins", ()) if b["start"] == "given start"),
                     None)
        own_ref = bool(own is not None and own_b is not None and own_b["plausible"]
                       and not alt and as_good_a_basin(
                           own_b, float(bres.info.get("cost", np.inf)),
                           {"theta_e": dict.fromkeys(own_b["theta_e"], bres.values["theta_e"])}))
        if own_ref:
            assert own_b is not None
            ref_v = {**bres.values, **own_b["values"]}
        th_b = ref_v["theta_e"]
        free = self._constants_discrepancy(view, ref_v) if self._constants_given else None
        if free:
            for n, d in free["difference"].items():
                if not free["theta_e_determined"]:
                    # a free solve that does not determine the heading offset (one heading
                    # kept) moves by about its own sigma; beyond that its value is noise (on
                    # heldout-136 44-165 deg from a held answer within 8 deg, sigma 7-51 deg)
                    d = min(d, free["sigma"].get(n, d))
                self._ambiguity[n] = self._ambiguity.get(n, 0.0) + d * d
        gap = abs(float(np.angle(np.exp(1j * (th_b - p[self.model.index("theta_e")])))))
        # released: restart when the online heading is outside the batch's 3 sigma (its
        # honest sigma; at least 1 deg) -- the smoother's marginal priors, linearised when
        # the heading was still uncertain, keep it biased by 3-5 deg on the Otter, where a
        # batch of the same data is within 1 deg
        sb = float(ref_s.get("theta_e", np.nan))
        tol = np.radians(1.0) if held else float(np.clip(3.0 * sb if np.isfinite(sb) else np.inf,
                                                          np.radians(1.0), np.radians(10.0)))
        # a sliding batch without such an alternative restarts a released smoother only
        # where its heading differs by more than its own 3 sigma: the 10-deg cap let
        # sliding 640-s batches (k_yz 0.005-0.015, sigma 22 deg) replace online headings
        # 13-44 deg closer to the truth on two fresh missions
        if not held and not alt and slip > plausibility.SUSPECT_SLIP and np.isfinite(sb):
            tol = max(tol, 3.0 * sb)
        self.reinit_batches.append({
            "t": float(t_fix), "theta_e": float(bres.values["theta_e"]),
            "sigma_theta_e": float(bres.sigma.get("theta_e", np.nan)),
            "process_noise_scale": float(bres.info.get("process_noise_scale", 1.0)),
            "process_noise_measured": None if q_meas is None else float(q_meas),
            "noise_by_evidence": bool(bres.info.get("process_noise_evidence")),
            "cost": float(bres.info.get("cost", np.nan)), "slip_deg": float(slip),
            "gap": float(gap), "tolerance": float(tol),
            "restarted": bool(force or gap >= tol),
            "theta_e_determined": not undetermined,
            "reference": ("solution from the online estimate (as good a basin)" if own_ref
                          else "non-sliding alternative" if alt else "batch"),
            "reference_theta_e": float(th_b), "reference_sigma_theta_e": sb,
            **({"constants_free": free} if free is not None else {})})
        if force:
            self._forced_at = float(t_fix)
        elif gap < tol:
            self._release(t_fix)
            return None
        new_init = dict(self.init)
        prior = {}
        for n in self.layout.estimated:
            if n in self.init:
                continue
            new_init[n] = float(ref_v[n])
            sg = ref_s.get(n)
            if sg is not None and np.isfinite(sg) and sg > 0:
                prior[n] = 2.0 * float(sg)
        info = self._replay(t_fix, new_init, prior, {
            "t": float(t_fix), "event": "re-initialised from a batch solve of the fixes so far",
            "theta_e_before": float(p[self.model.index("theta_e")]), "theta_e_after": float(th_b)},
            t_re)
        self._release(t_fix)
        return info

    def _batch(self, estimate: Sequence[str], also_start: dict[str, float] | None = None):
        """A re-initialisation batch solver of the fixes so far (its warnings not logged):
        the process noise by the evidence only where the fixes are too short for the
        sandwich, else measured only (see :meth:`_reinitialise`)."""
        from aqfg.fg.batch import BatchSmoother
        bs = BatchSmoother(self.base_model, effects=self.effects, estimate=tuple(estimate),
                           init=self.init,
                           settings=replace(self.settings, online_init_after=0.0,
                                            adapt_batch=None, measure_noise=True,
                                            adapt_track=False),
                           also_start=also_start)
        bs.log_warnings = False
        return bs

    def _constants_discrepancy(self, view: Mission, ref: dict[str, float]) -> dict | None:
        """The thrust/drag constants given (another mission's fit, or by hand) may not be
        this mission's: the fixes so far solved again with them free (from the given
        values), and each variable parameter's difference from the batch ``ref`` with them
        held: ``{"difference": {name: value}, "theta_e", "sigma_theta_e", "sigma",
        "theta_e_determined", "free", "cost"}``, None where that solve fails or is
        implausible. Its square is added to the reported variance until the next
        batch (``_ambiguity``): the held constants' sigma assumes them right, and with a
        weak-propeller mission's constants a 16-s batch put theta_e 42 deg off with sigma
        12 deg where the free solve was 17 deg off (docs/independent-vehicle.md)."""
        consts = tuple(n for n in self.model.active_names
                       if self.model.spec(n).group == "fixed" and n not in self.layout.estimated)
        if not consts:
            return None
        # all free; where that is implausible (on a short stretch the sway drag often falls
        # to its bound, a hull sliding sideways), all but the sway drag
        tries = [consts]
        if "k_yz" in consts and len(consts) > 1:
            tries.append(tuple(n for n in consts if n != "k_yz"))
        res = None
        for free in tries:
            try:
                res = self._batch((*self.layout.estimated, *free)).run([view])
            except (ValueError, np.linalg.LinAlgError, *GTSAM_ERRORS):
                res = None
            if res is not None and res.info.get("plausible", True):
                break
            res = None
        if res is None:
            return None
        diff = {}
        for n in self.layout.estimated:
            if n in ref and n in res.values and self.model.spec(n).group == "variable":
                diff[n] = abs(difference(n, float(res.values[n]), float(ref[n])))
        return {"difference": diff, "theta_e": float(res.values.get("theta_e", np.nan)),
                "sigma_theta_e": float(res.sigma.get("theta_e", np.nan)),
                "sigma": {n: float(res.sigma[n]) for n in diff if n in res.sigma},
                "theta_e_determined": res.info.get("observability", {}).get(
                    "theta_e", {}).get("verdict") != observability.NOT,
                "free": list(free), "cost": float(res.info.get("cost", np.nan))}

    def _batch_not_used(self, t_fix: float, event: dict) -> None:
        """A re-initialisation batch that failed or is not used: recorded (``event``); the
        parameters stay as they are, and held ones are released once the schedule of
        batches has passed half its length (none would come to release them)."""
        self.events.append({"t": float(t_fix), **event})
        if self._hold_idx and 2.0 * (t_fix - self.knots[0]) > self.settings.online_reinit_until:
            self._release(t_fix)

    def _replay(self, t_fix: float, new_init: dict[str, float], prior: dict[str, float],
                event: dict, t_re: float) -> UpdateInfo | None:
        """Restart the smoother and replay the fixes up to ``t_fix`` with the parameters held
        at ``new_init`` (``prior``: their start priors' sigmas); what was reported causally
        before stays as it was reported. The parameters stay held (the caller releases
        them or not). ``t_re``: when the restart began (``time.perf_counter``)."""
        events = list(self.events) + [event]
        timings = {k: list(v) for k, v in self.timings.items()}
        self._materialise()
        # what was reported causally before the restart stays as it was reported
        causal = (list(self.hist_t), list(self.hist_v), list(self.hist_s),
                  list(self.filtered), list(self.pred_t), list(self.pred_x))
        saved = self.init
        self.init = new_init
        self._prior_override = prior
        self._prior_centre = dict(saved)
        try:
            self._replaying = True
            self.start(self.mission, plan=self._plan is not None)
            info = None
            while self.pending() and self.fix_t[self.n_fix] <= t_fix + 1e-9:
                info = self.update()
        finally:
            self.init = saved
            self._replaying = False
        self.events = events + self.events
        n_kept = len(causal[3])
        if len(self.filtered) >= n_kept and self.hist_t[:len(causal[0])] == causal[0]:
            last = (self.hist_t[-1], self.hist_v[-1], self.hist_s[-1]) if self.hist_t else None
            self.hist_t, self.hist_v, self.hist_s = causal[0], causal[1], causal[2]
            # the restart's own fix reports the restarted estimate: the batch used the fixes
            # up to it and none later (it was the start value, with its prior's sigma)
            if last is not None and self.hist_t and abs(last[0] - self.hist_t[-1]) < 1e-9 \
                    and abs(last[0] - t_fix) < 1e-9:
                self.hist_v[-1], self.hist_s[-1] = last[1], last[2]
            # and so does its knot on the causal track (the fixes before it stay as reported)
            n_old = n_kept - 1 if abs(self.knots[n_kept - 1] - t_fix) < 1e-9 else n_kept
            self.filtered[:n_old] = causal[3][:n_old]
            self._pending = [q for q in self._pending if q[0] >= n_kept]
            self.pred_t, self.pred_x = causal[4], causal[5]
        # per-update timings stay aligned with the (replayed) history; the updates before
        # the restart and the restart itself (solve + replay) are kept apart
        self.timings["before_reinit"] = timings.get("before_reinit", []) + timings.get("update", [])
        self.timings["reinit"] = timings.get("reinit", []) + [time.perf_counter() - t_re]
        return info

    def _update(self, graph, vals, stamps, t_fix: float, n_new: int) -> UpdateInfo:
        lay = self.layout
        for g in (lay.groups if self._fast is None else ()):
            stamps[self._node(g)] = float(t_fix)   # parameter nodes never leave the window
        t_a = time.perf_counter()
        eng = self._fast
        if self.warming:
            # warm-up: keep everything since the start in the window until the parameters
            # are known well enough to linearise the marginal priors near the truth
            lag = max(self.window, t_fix - self.knots[0] + 1.0)
            if eng is not None:
                eng.lag = lag
            else:
                self.smoother.setSmootherLag(lag)
        values, sigma = {}, {}
        nv, ns, nh = [], [], []
        if eng is not None:
            self._fast_step(t_fix)
            self._n_committed = len(self.knots)
            th, sg_all = eng.z[:eng.P].copy(), eng.sigma()      # th: inside the bounds
            for g, sl in eng.slices.items():
                self._last_params[g] = th[sl]
            names = eng.names
            sh_all = self._reported_sigma(names, sg_all)
            if self._held_sigma is not None:
                sh_all = self._with_ambiguity(names, self._held_sigma)
            sg_l = sg_all.tolist()
            values = dict(zip(names, th.tolist()))
            sigma = dict(zip(names, sh_all.tolist() if sh_all is not sg_all else sg_l))
            nv, ns, nh = [th], [sg_all], [sh_all]
            self._raw_sigma.update(zip(names, sg_l))
        else:
            self._guarded_update(graph, vals, stamps, t_fix)
            self._n_committed = len(self.keys)
        for g in (lay.groups if eng is None else ()):
            k = self._node(g)
            try:
                v = self.smoother.calculateEstimateVector(k)
            except GTSAM_ERRORS:
                v = np.asarray(self._last_params.get(g, lay.initial(g)), float)
            sg = self._marginal_sigma(k, len(v))
            if np.all(np.isfinite(v)):
                self._last_params[g] = lay.project(g, v)
            sh = self._reported_sigma(lay.names[g], sg)
            if self._held_sigma is not None:
                sh = self._with_ambiguity(lay.names[g], self._held_sigma[
                    [lay.estimated.index(n) for n in lay.names[g]]])
            for n, a, b in zip(lay.names[g], v, sh):
                values[n], sigma[n] = float(a), float(b)
            nv.append(v); ns.append(sg); nh.append(sh)
            self._raw_sigma.update(zip(lay.names[g], map(float, sg)))
        if self.warming:
            sc = self._scales
            done = (np.all(np.concatenate(ns) < self.settings.warmup_tol * sc) if ns else True
                    ) and not self._hold_idx
            if done or t_fix - self.knots[0] >= self.settings.warmup_max:
                self.warming = False
                self.warmup_end = float(t_fix)
                if eng is not None:
                    eng.lag = self.window
                else:
                    self.smoother.setSmootherLag(self.window)
        t_b = time.perf_counter()
        dt = t_b - t_a
        self.timings["update"].append(dt)
        self.timings["update_total"].append(t_b - getattr(self, "_t_call", t_a))
        # the fix knot's estimate (causal), and the latest estimates of knots in the window
        i_fix = len(self.knots) - 1
        self.anchor_idx.append(i_fix)
        if eng is not None:
            self.filtered[i_fix] = eng.z[-6:].copy()
            for i in reversed(self.anchor_idx):
                if self.knots[i] < t_fix - self.window + 1e-6:
                    break
                x = eng.state(i)
                if x is None:
                    break
                self.latest[i] = x
            return self._record(t_fix, dt, values, sigma, nv, nh, n_new)
        try:
            self.filtered[i_fix] = self.smoother.calculateEstimateVector(self.keys[i_fix])
        except GTSAM_ERRORS:
            pass                                  # keep the prediction
        for i in reversed(self.anchor_idx):
            if self.knots[i] < t_fix - self.window + 1e-6:
                break
            try:
                self.latest[i] = self.smoother.calculateEstimateVector(self.keys[i])
            except GTSAM_ERRORS:                  # left behind by a restart
                break
        return self._record(t_fix, dt, values, sigma, nv, nh, n_new)

    def _record(self, t_fix, dt, values, sigma, nv, nh, n_new) -> UpdateInfo:
        self.hist_t.append(float(t_fix))
        self.hist_v.append(nv[0] if len(nv) == 1 else np.concatenate(nv) if nv else np.zeros(0))
        self.hist_s.append(nh[0] if len(nh) == 1 else np.concatenate(nh) if nh else np.zeros(0))
        self.n_fix = int(self.fix_t.searchsorted(t_fix + 1e-9))
        return UpdateInfo(float(t_fix), dt, values, sigma, n_new)

    # ---------------------------------------------------------------- robustness
    def _innovation(self, t_fix: float, x_pred: np.ndarray) -> tuple[float, float] | None:
        """Squared horizontal innovation (m^2) of the fix at ``t_fix`` (the first, GNSS
        before USBL) against ``x_pred``, and its per-axis variance; None: no fix there. In
        scalars: this runs at every update (numpy calls cost microseconds each)."""
        t, pos, var, _ = self._fixes
        i = int(t.searchsorted(t_fix - 1e-6))
        if i >= len(t) or abs(float(t[i]) - t_fix) > 1e-6:
            return None
        p0, p1 = pos[i, :2].tolist()
        x0, x1 = x_pred[:2].tolist()
        return (p0 - x0) ** 2 + (p1 - x1) ** 2, float(var[i])

    def _left_out(self, t_fix: float) -> bool:
        """The fix :meth:`_innovation` reads at ``t_fix`` is a USBL fix the gate left out."""
        t, _, _, is_u = self._fixes
        i = int(t.searchsorted(t_fix - 1e-6))
        return (i < len(t) and bool(is_u[i])
                and bool(self._rejected.get(float(t_fix), False)))

    def _q_pos(self, dt: float) -> float:
        """The nominal process noise's per-axis position variance over ``dt`` s (m^2),
        cached per interval."""
        key = round(dt, 9)
        q = self._noise.get(key)
        if q is None:
            q = self._noise[key] = float(self.settings.process.cov(dt, self.mission.planar)[0, 0])
        return q

    def _gate_table(self, mission: Mission) -> dict:
        """Per USBL fix time (rounded to the microsecond): range, bearing, range variance,
        bearing sigma, the previous fix's per-axis variance and the station, for
        :meth:`_gate` (in Python floats: it runs at every USBL update). Empty without
        USBL or with the gate off."""
        u, s = mission.usbl, self.settings
        if u is None or not len(u.t) or not math.isfinite(s.online_gate_usbl):
            return {}
        t, _, var, _ = self._fixes
        st = tuple(float(c) for c in np.asarray(mission.usbl_station, float)[:3])
        out = {}
        for k in range(len(u.t)):
            i = int(t.searchsorted(u.t[k] - 1e-6))
            sr, sb = s.sensors.usbl_sigmas(float(u.range[k]))
            out[round(float(u.t[k]), 6)] = (float(u.range[k]), float(u.bearing[k]),
                                            float(sr) ** 2, float(sb),
                                            float(var[i - 1]) if i > 0
                                            else s.sensors.gnss_sigma ** 2, st)
        return out

    def _gate(self, t_fix: float, dt: float, x_pred: np.ndarray) -> bool:
        """True when the USBL fix at ``t_fix`` is to be left out: its range and bearing
        innovation against the model's prediction ``x_pred`` is beyond
        ``settings.online_gate_usbl`` (chi-square(2)), and fewer than
        ``online_max_rejects`` USBL fixes in a row were left out before it (the EKF's rule,
        :mod:`aqfg.ekf.window`). Recorded in ``info["rejected_usbl"]``.

        The prediction's per-axis variance is that of the process noise in use over the
        interval, plus the previous fix's (GNSS sigma^2, or a USBL fix's tangential one: an
        upper bound along its range); the range and the tangential innovation each add it
        to their own sensor variance. In range and bearing, not as a position: the USBL
        outliers are mostly in range (7-16 m on a 0.15-m range sigma), which a position's
        isotropic tangential variance (2.6 m at 100 m) hides.

        No gate while the parameters are held at their start values (before the first
        batch): the prediction of a model whose heading is not known yet is 7-22 m off on
        a crop of `otter-dev-calm-b`, and good fixes were left out. A track can be off
        after that too (a turn the model gets wrong): the fixes left out are
        seen again by :meth:`_review_left_out` once later fixes are in. And only where the
        model has shown what it is: the process noise adapted up (the model fails, the
        dynamics are loose, and the Huber loss no longer bounds an outlier's pull), or the
        last fixes taken all within the 99 % quantile (the model holds; a burst of
        outliers would drag it). With the noise still nominal while a model starts to
        fail (the adaptation lags), good fixes 5-22 m from the prediction were left out on
        Otter crops and the causal track suffered (`otter-dev-current-weakprop` from 150 s:
        2.22 -> 3.45 m; `otter-dev-calm-a` from 300 s, whose released constants ran off:
        3.39 -> 11.3 m)."""
        s = self.settings
        self._forced_scale = 1.0
        if dt <= 0:
            return False
        # (GNSS fixes are scored without USBL too: a GNSS-only mission's held model is
        # judged by them, _held_failing and _held_missed_early)
        q = self._q_pos(dt)
        usbl = round(float(t_fix), 6) in self._usbl_tab
        if usbl:
            m2 = self._gate_m2(t_fix, x_pred, self.q_scale * q)
        else:                 # a GNSS fix (never left out): its statistic, as a position
            inn = self._innovation(t_fix, x_pred)
            if inn is None:
                return False
            # the adaptation's (noise.innovation_u: the previous state as uncertain as
            # this fix)
            m2 = noise.innovation_u(inn[0], inn[1], self.q_scale * q)
        # the model has shown it fails (the process noise adapted up) or that it does not
        # (the last fixes taken were all within the 99 % quantile)
        recent = self._taken_m2[-s.adapt_window:]
        known = self.q_scale > 1.0 or (len(recent) >= 3 and max(recent) <= noise.CHI2_2_99)
        gating = (usbl and known
                  and not (self._hold_idx and not getattr(self, "_replaying", False)))
        forced = gating and self._rejects >= s.online_max_rejects
        out = gating and not forced and m2 > s.online_gate_usbl
        # a fix taken by the count enters at the robust loss's edge: its sigmas scaled so
        # that its whitened residual at the prediction is the Huber threshold, a pull
        # falling with the residual (k^2 / |r|). The Huber loss bounds a fix's pull
        # (k / sigma), not how far it moves a track loosened by the fixes left out before
        # it: a 12-m range outlier forced after three moved the numpy engine's track 9 m
        # and its current 0.5 m/s, and the good fixes after it were left out
        # (docs/independent-vehicle.md). A track that is off gets to the fixes too: by the
        # adaptation (the forced fixes' innovations) and the review of those left out.
        if forced and m2 > s.online_gate_usbl:
            k = s.sensors.robust_k if s.sensors.robust != "none" else 1.0
            self._forced_scale = max(1.0, math.sqrt(self._gate_m2(t_fix, x_pred, None)) / k)
        if not out and not forced:          # (a fix taken by the count says nothing)
            self._taken_m2.append(m2)
            if len(self._taken_m2) > 4 * s.adapt_window:
                del self._taken_m2[:-s.adapt_window]
        if usbl:
            self._rejects = self._rejects + 1 if out else 0
            self._rejected[float(t_fix)] = out
        if out and self._fast is not None:
            self._under_review.append(float(t_fix))
        return out

    def _gate_m2(self, t_fix: float, x: np.ndarray, q_pos: float | None) -> float:
        """The gate's statistic (chi-square(2)) of the USBL fix at ``t_fix`` against the
        state ``x``, whose per-axis variance is ``q_pos`` plus the previous fix's
        (:meth:`_gate`); ``q_pos`` None: the state exact, the sensor's sigmas alone (the
        fix's squared whitened residual at ``x``)."""
        z_r, z_b, sr2, sb, v_prev, (n0, e0, d0) = self._usbl_tab[round(float(t_fix), 6)]
        pv = 0.0 if q_pos is None else q_pos + v_prev
        dn, de, dd = float(x[0]) - n0, float(x[1]) - e0, float(x[2]) - d0
        rh = math.hypot(dn, de)
        er = z_r - math.sqrt(rh * rh + dd * dd)
        et = math.remainder(z_b - math.atan2(de, dn), 2.0 * math.pi) * rh
        return er * er / (sr2 + pv) + et * et / max((rh * sb) ** 2 + pv, 1e-300)

    def _adapt(self, t_fix: float, dt: float, x_pred: np.ndarray) -> None:
        """Adapt the process-noise variance factor to how well the model predicts the fixes:
        :func:`aqfg.fg.noise.variance_factor` of the last ``adapt_window`` fix
        innovations (the model's prediction from the previous fix),
        never below the last re-initialisation batch's factor. A model that explains the
        fixes keeps its nominal noise; one that does not lets the fixes pull the track (a
        wrong model then costs accuracy gracefully, towards a kinematic smoother, instead
        of dragging the track off the fixes). A USBL fix the gate left out is not counted:
        the gate judged it an outlier of the fix, and counting a run of them as the model's
        error raised the noise to its bound, which opened the gate to the rest of the run."""
        s = self.settings
        inn = self._innovation(t_fix, x_pred)
        if inn is None or dt <= 0 or self._left_out(t_fix):
            return
        e2, v = inn
        q = self._q_pos(dt)
        if not (math.isfinite(e2) and math.isfinite(v) and q > 0):
            return
        self._innov.append((e2, v, q, noise.lr_gain(e2, v, q)))
        if len(self._innov) > 4 * s.adapt_window:         # a long stream keeps what it uses
            del self._innov[:-s.adapt_window]
        last = self._innov[-s.adapt_window:]
        if noise.gains_suffice(g[3] for g in last):
            self.q_scale = max(1.0, self._q_floor)
            return
        # arrays: variance_factor's own nominal_suffices shortcut (lists) is known to fail
        ea, va, qa = (np.array(a) for a in list(zip(*last))[:3])
        self.q_scale = max(noise.variance_factor(ea, va, qa, s), self._q_floor)

    def _guarded_update(self, graph, vals, stamps, t_fix: float) -> None:
        """``smoother.update`` that survives GTSAM's failures (indeterminate systems after
        marginalisation, ill-conditioned windows, non-finite estimates): the smoother is
        restarted from the current estimates with marginal priors and the update retried;
        then from the last finite state with broad priors; if that fails too, the fix's
        factors are dropped. Every recovery is recorded in ``events``."""
        check = [self._node(g) for g in self.layout.groups] + [self.keys[-1]]

        def attempt(graph=graph, vals=vals) -> str:
            try:
                self.smoother.update(graph, vals, stamps)
                self._last_new_idx = list(self.smoother.getISAM2Result().getNewFactorsIndices())
                for _ in range(self.settings.iterations_per_update - 1):
                    self.smoother.update()
                for k in check:                   # failures can surface only here
                    if not np.all(np.isfinite(self.smoother.calculateEstimateVector(k))):
                        return "non-finite estimate"
                return ""
            except GTSAM_ERRORS as exc:
                return (str(exc).strip().splitlines() or [type(exc).__name__])[0]

        err = attempt()
        if not err:
            return
        for hard in (False, True):
            self._restart(t_fix, hard=hard)
            err2 = attempt(*self._after_restart(graph, vals))
            if not err2:
                self.events.append({"t": float(t_fix), "event": "restarted" + (
                    " (broad priors)" if hard else ""), "error": err})
                return
        self._restart(t_fix, hard=True)
        keep = gtsam.Values()
        prior = gtsam.NonlinearFactorGraph()
        for k in self._after_restart(gtsam.NonlinearFactorGraph(), vals)[1].keys():
            v = vals.atVector(k)
            if not np.all(np.isfinite(v)):
                v = self._last_finite_state()
            keep.insert(k, v)
            prior.add(gtsam.PriorFactorVector(k, v, gtsam.noiseModel.Isotropic.Sigma(len(v), 10.0)))
        self.smoother.update(prior, keep, stamps)
        self.events.append({"t": float(t_fix), "event": "fix skipped", "error": err})

    def _after_restart(self, graph, vals):
        """The new factors and values of an update, fitted to a restarted smoother: the
        values it already holds (the parameter node of a random-walk segment opened by
        this update) are left out, and so are the factors on keys it no longer has (the
        walk factor from the previous segment's node)."""
        have = set(self.smoother.calculateEstimate().keys())
        v2 = gtsam.Values()
        for k in vals.keys():
            if k not in have:
                v2.insert(k, vals.atVector(k))
        known = have | set(v2.keys())
        g2 = gtsam.NonlinearFactorGraph()
        for i in range(graph.size()):
            f = graph.at(i)
            if f is not None and all(k in known for k in f.keys()):
                g2.add(f)
        return g2, v2

    def _last_finite_state(self) -> np.ndarray:
        """The newest finite causal state (position held, velocity zero if none)."""
        for x in reversed(self.filtered[:max(self._n_committed, 1)]):
            if x is not None and np.all(np.isfinite(x)):
                return np.asarray(x, float)
        return np.zeros(6)

    def _reported_sigma(self, names, sg: np.ndarray) -> np.ndarray:
        """The sigma reported for the parameters ``names`` from their marginal ``sg``: scaled
        to the last re-initialisation batch's honest sigma of the same data (the marginal
        assumes the model is right and the window's noise), and widened by the spread of
        the basins that batch found fitting as well (docs/independent-vehicle.md); ``sg``
        itself where neither applies."""
        sh = sg * np.array([self._inflation.get(n, 1.0) for n in names]) \
            if self._inflation else sg
        return self._with_ambiguity(names, sh)

    def _with_ambiguity(self, names, sh: np.ndarray) -> np.ndarray:
        """``sh`` widened by the spread of the basins the last re-initialisation batch
        found fitting as well (``_ambiguity``), also while the parameters are held at that
        batch's values: the restart's own fix reported the hold prior's sigma alone, 19.5
        deg at a heading 159 deg off where the batch's two basins gave 81 deg
        (docs/independent-vehicle.md)."""
        if not self._ambiguity:
            return sh
        return np.hypot(sh, np.sqrt([self._ambiguity.get(n, 0.0) for n in names]))

    def _marginal_sigma(self, key: int, dim: int) -> np.ndarray:
        """1-sigma of a node from the smoother's marginal; NaN (recorded) if GTSAM cannot
        give it (a known failure after marginalisation)."""
        try:
            C = self.smoother.marginalCovariance(key)
            return np.sqrt(np.maximum(np.diag(C), 0.0))
        except GTSAM_ERRORS as exc:
            self.events.append({"t": float(self.knots[-1]), "event": "marginal unavailable",
                                "error": str(exc).splitlines()[0] if str(exc) else ""})
            return np.full(dim, np.nan)

    def _restart(self, t_fix: float, hard: bool = False) -> None:
        """A fresh smoother holding the last knot and the parameter nodes at their current
        estimates, each with a prior from its marginal (inflated x4 in variance, or a
        broad one where the marginal is unavailable). Parameters still held keep their
        start (or replay) prior and get new hold priors: the old ones' factor indices mean
        nothing in the new smoother (removing them at the release removed the knot's prior:
        every later update was indeterminate), and a marginal taken under a hold prior
        would hold them for good."""
        s = self.settings
        held = bool(self._hold_idx)
        hold_pos: list[int] = []
        last = self.keys[self._n_committed - 1]     # the newest knot the smoother holds
        keys = [last] + [self._node(g) for g in self.layout.groups]
        est: dict[int, np.ndarray | None] = {}
        cov: dict[int, np.ndarray | None] = {}
        for k in keys:
            est[k] = cov[k] = None
            if hard:
                continue
            try:
                v = self.smoother.calculateEstimateVector(k)
                est[k] = v if np.all(np.isfinite(v)) else None
            except GTSAM_ERRORS:
                pass
            try:
                cov[k] = self.smoother.marginalCovariance(k)
            except GTSAM_ERRORS:
                pass
        lag = self.window if not self.warming else max(self.window, t_fix - self.knots[0] + 1.0)
        self.smoother = gtsam.IncrementalFixedLagSmoother(lag, self._isam_params)
        graph = gtsam.NonlinearFactorGraph()
        vals = gtsam.Values()
        stamps: dict[Any, float] = {}
        for k in keys:
            e = est[k]
            if k == last:
                x = e if e is not None else self._last_finite_state()
                broad = np.array([10.0, 10.0, 1.0, 2.0, 2.0, 0.5])
            else:
                g = next(g for g in self.layout.groups if self._node(g) == k)
                x = self.layout.project(g, e) if e is not None else \
                    self.layout.initial(g) if hard else \
                    self.layout.project(g, np.asarray(self._last_params.get(g, self.layout.initial(g))))
                broad = np.array([s.prior_scale * self.model.spec(n).scale
                                  for n in self.layout.names[g]])
                graph.add(fc.bound_factor(self.layout, g, k))
                if held:
                    graph.add(self._start_prior(g, k, getattr(self, "_replaying", False)))
                    hold_pos.append(graph.size())
                    graph.add(self._hold_prior(g, k))
                    vals.insert(k, np.asarray(x, float))
                    stamps[k] = float(t_fix)
                    continue
            C = cov[k]
            noise: gtsam.noiseModel.Base
            if C is None or not np.all(np.isfinite(C)) or np.min(np.linalg.eigvalsh(C)) <= 0:
                noise = gtsam.noiseModel.Diagonal.Sigmas(broad)
            else:
                noise = gtsam.noiseModel.Gaussian.Covariance(4.0 * C + 1e-12 * np.eye(len(x)))
            vals.insert(k, np.asarray(x, float))
            graph.add(gtsam.PriorFactorVector(k, np.asarray(x, float), noise))
            stamps[k] = float(t_fix)
        if self.mission.planar:
            graph.add(fc.surface_factor(last, *s.surface_sigma))
        self.smoother.update(graph, vals, stamps)
        if held:
            new_idx = list(self.smoother.getISAM2Result().getNewFactorsIndices())
            self._hold_idx = ([int(new_idx[i]) for i in hold_pos]
                              if len(new_idx) == graph.size() else [])

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
            if _diverged(X[a + 1:b + 1]):
                # the model cannot be integrated from this smoothed state (e.g. a stiff
                # drag: k_yz 93 1/m with a 1-m/s sway made the explicit steps oscillate to
                # inf): the smoothed states, joined by a cubic, stand here
                X[a + 1:b + 1] = _joined(knots[a:b + 1], ax[a], ax.get(b))
                self._note_diverged(float(knots[a]), float(knots[b]))
                continue
            if b in ax:
                err = ax[b] - X[b]
                w = (knots[a + 1:b + 1] - knots[a]) / (knots[b] - knots[a])
                X[a + 1:b + 1] += w[:, None] * err[None, :]
        self.timings["correction"].append(time.perf_counter() - t_a)
        return Track(knots, X[:, :3], X[:, 3:])

    def _note_diverged(self, t_a: float, t_b: float) -> None:
        """An event, once per interval, for a corrected-track interval the model could not
        re-trace (:meth:`corrected_track`)."""
        if (t_a, t_b) not in self._diverged_at:
            self._diverged_at.add((t_a, t_b))
            self.events.append({"t": t_a, "event": "corrected track: the model's re-trace "
                                f"diverged between {t_a:.1f} and {t_b:.1f} s; the smoothed "
                                "states joined there instead"})

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
        update; while the parameters were held, horizontally the kinematic floor's
        (:meth:`_kinematic_step`)."""
        self._materialise()
        X = np.array(self.filtered)
        kn = np.array(self.knots)
        self._floor.apply(kn, X, (np.array(self.pred_t), np.array(self.pred_x).reshape(-1, 6)))
        return Track(kn, X[:, :3], X[:, 3:])

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
                            "events": list(self.events),
                            "warnings": list(getattr(self, "warnings", [])),
                            "process_noise_scale": float(self.q_scale),
                            "rejected_usbl": sorted(t for t, out in self._rejected.items()
                                                    if out),
                            "sigma_inflation": dict(self._inflation),
                            "reinit_batches": list(self.reinit_batches),
                            "kernel": "cpp" if self.model.uses_cpp else "numpy",
                            "engine": getattr(self, "engine", "gtsam"),
                            "engine_note": getattr(self, "engine_note", ""),
                            "settings": self.settings},
                      effects=tuple(e.name for e in self.model.effects), model=self.model)


# m/s: a re-traced speed beyond this is the integration diverging, not a vehicle
DIVERGED_SPEED = 50.0


def _diverged(X: np.ndarray) -> bool:
    """Whether re-traced states (n, 6) left what any small vehicle can do (non-finite, or a
    speed beyond :data:`DIVERGED_SPEED`)."""
    return bool(len(X)) and (not np.all(np.isfinite(X))
                             or float(np.max(np.linalg.norm(X[:, 3:], axis=1))) > DIVERGED_SPEED)


def _joined(t: np.ndarray, xa: np.ndarray, xb: np.ndarray | None) -> np.ndarray:
    """States at ``t[1:]`` joining the state ``xa`` at ``t[0]`` to ``xb`` at ``t[-1]``: the
    cubic Hermite curve through both positions and velocities (velocity its derivative);
    without ``xb``, constant velocity from ``xa``."""
    from scipy.interpolate import CubicHermiteSpline
    t = np.asarray(t, float)
    xa = np.asarray(xa, float)
    if xb is None:
        out = np.tile(xa, (len(t) - 1, 1))
        out[:, :3] += (t[1:] - t[0])[:, None] * out[:, 3:]
        return out
    curve = CubicHermiteSpline([t[0], t[-1]], np.stack([xa[:3], xb[:3]]),
                               np.stack([xa[3:], xb[3:]]))
    return np.hstack([curve(t[1:]), curve.derivative()(t[1:])])


def _mission_until(mission: Mission, t: float) -> Mission:
    """A shallow view of ``mission`` without the fixes and inputs after ``t`` (what was
    known at ``t``)."""
    import copy
    view = copy.copy(mission)
    a = int(np.searchsorted(mission.imu.t, t + 1e-9, side="right"))
    b = int(np.searchsorted(mission.motors.t, t + 1e-9, side="right"))
    if a >= 2 and b >= 1:
        view.imu = copy.copy(mission.imu)
        for f in ("t", "q", "acc", "gyro"):
            x = getattr(mission.imu, f, None)
            if isinstance(x, np.ndarray) and len(x) == len(mission.imu.t):
                setattr(view.imu, f, x[:a])
        view.motors = copy.copy(mission.motors)
        view.motors.t, view.motors.u = mission.motors.t[:b], mission.motors.u[:b]
    if mission.gnss is not None:
        g = copy.copy(mission.gnss)
        k = mission.gnss.t <= t + 1e-9
        g.t, g.ne = mission.gnss.t[k], mission.gnss.ne[k]
        if mission.gnss.sigma is not None:
            g.sigma = mission.gnss.sigma[k]
        if mission.gnss.latlon is not None:
            g.latlon = mission.gnss.latlon[k]
        view.gnss = g
    if mission.usbl is not None:
        u = copy.copy(mission.usbl)
        k = mission.usbl.t <= t + 1e-9
        u.t, u.range, u.bearing = mission.usbl.t[k], mission.usbl.range[k], mission.usbl.bearing[k]
        if mission.usbl.elevation is not None:
            u.elevation = mission.usbl.elevation[k]
        view.usbl = u
    return view
