"""Online (fixed-lag) factor-graph smoothing: the factor-graph analogue of the paper's online
mode (§III-E): after each absolute fix, the states inside a window of ``window`` seconds and
the parameter nodes are re-estimated jointly.

One orchestration (:class:`FixedLagSmoother`: knots, causal and corrected tracks, history)
over parts with one job each: the window engine (:mod:`aqfg.fg.online.engine`: numpy by
default, GTSAM's ISAM2 where the configuration needs it, chosen by
``FGSettings.online.engine`` and :meth:`aqfg.fg.fastlag.LagWindow.unsupported`), the USBL
gate (:mod:`~aqfg.fg.online.gate`), the process-noise adaptation
(:mod:`~aqfg.fg.online.adapt`), the sigma reported (:mod:`~aqfg.fg.online.report`), the
hold / release / re-initialise policy (:mod:`~aqfg.fg.online.policy`) and its batch
re-initialisations and replays (:mod:`~aqfg.fg.online.recovery`), and the kinematic floor
of the causal track while the parameters are held (:mod:`aqfg.fg.kinematic`).
``engine`` / ``engine_note`` (and ``Result.engine``) say which engine ran and why.

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
from dataclasses import dataclass

import numpy as np

from aqfg.data.mission import Mission
from aqfg.fg import factors as fc
from aqfg.fg.common import (
    check_missions,
    default_estimate,
    initial_states,
    mission_model,
    piecewise_inertial,
    progress_fn,
    residuals,
)
from aqfg.fg.fastlag import LagWindow
from aqfg.fg.kinematic import CausalFloor, KinematicFilter
from aqfg.fg.online import recovery
from aqfg.fg.online.adapt import NoiseAdapter
from aqfg.fg.online.engine import WindowEngine
from aqfg.fg.online.gate import UsblGate
from aqfg.fg.online.gtsam_engine import GtsamEngine
from aqfg.fg.online.numpy_engine import NumpyEngine
from aqfg.fg.online.policy import HoldPolicy, Phase
from aqfg.fg.online.records import OnlineEvent, ReinitBatch
from aqfg.fg.online.report import ParamPriors, SigmaReport
from aqfg.fg.online.tracks import p_segments, retrace, with_tail
from aqfg.fg.online.views import StepSource
from aqfg.fg.settings import FGSettings
from aqfg.model.params import FIXED_BASE
from aqfg.model.vehicle import Model
from aqfg.result import MissionResult, OnlineEngine, ParamHistory, Result, Track

log = logging.getLogger(__name__)
VEHICLE = ("k", "k_x", "k_yz")


@dataclass
class UpdateInfo:
    """What one update did: fix time (s), wall time (s), parameter estimate and 1-sigma."""
    t: float
    seconds: float
    values: dict
    sigma: dict
    n_new_knots: int


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
        self.warnings: list[str] = []
        self.engine_note = ""
        self._estimate_vehicle = False
        self.policy = HoldPolicy(self.settings, self.settings.online.init_after)
        self.report = SigmaReport()
        self._t_call = time.perf_counter()

    # ---------------------------------------------------------------- setup
    def start(self, mission: Mission, plan: bool = False) -> UpdateInfo:
        """Initialise at the mission's first fix (position from the fix, velocity zero).

        ``plan``: the mission is recorded (not growing): prepare the kernel steps of all its
        knots at once (:meth:`run` does)."""
        info = self._start(mission, plan)
        self._kinematic_step(float(self.fix_t[0]))
        return info

    def _start(self, mission: Mission, plan: bool) -> UpdateInfo:
        """:meth:`start` but for the kinematic causal floor's first fix. A replay's
        restart (``policy.replaying``) calls :meth:`start` too and keeps the session's
        state (the policy, the sigma report, the noise floor, the gate's tables)."""
        (mission,) = check_missions([mission])
        self._t_call = time.perf_counter()
        self.mission = mission
        self.model = mission_model(self.base_model, mission, self.effects)
        replaying = self.policy.replaying
        if not replaying:
            self._warn_constants()
        est = self.estimate if self.estimate is not None else default_estimate(self.model, "online")
        if self._estimate_vehicle:
            est = tuple(dict.fromkeys((*est, *VEHICLE)))
        self.layout = fc.ParamLayout.build(self.model, est, self.init)
        # per-update constants of the layout (its properties build tuples on each call)
        self.theta_estimated = "theta_e" in self.layout.estimated
        self.bound_watch: list | None = None      # see recovery.implausible_released
        # no thrust/drag constant estimated (given by init, or held fixed)
        self.constants_given = not any(n in self.layout.estimated for n in FIXED_BASE)
        self._scales = np.array([self.model.spec(n).scale for n in self.layout.estimated])
        self.fix_t = np.unique(mission.fix_times())
        if not len(self.fix_t):
            raise ValueError(f"mission {mission.name!r} has no GNSS or USBL fix")
        hold = replaying or self.policy.scheduled(self.theta_estimated, self.init)
        if not replaying:
            self._new_session(mission, hold)
        self._reset_run(plan)
        self.priors = ParamPriors(self.model, self.layout, self.settings,
                                  self.policy.replay_prior, self.policy.replay_centre, replaying)
        # held parameters are reported with their prior's sigma (the batch's, replaying):
        # the hold priors' tiny marginal would claim a certainty no data gave
        self.report.held = self.priors.held_report() if hold else None
        # first knot: position from the first fix (interpolation of the fixes at t0)
        t0 = float(self.fix_t[0])
        x0 = initial_states(mission, np.array([t0, t0 + 1.0]))[0]
        x0[3:] = 0.0
        if mission.planar:
            x0[2] = 0.0
        self.backend = self._make_engine(x0, t0, hold)
        info = self._solve(t0, 1)
        self.policy.phase = Phase.HELD if self.backend.hold_placed else Phase.RELEASED
        return info

    def _warn_constants(self) -> None:
        """The warnings of a start without this vehicle's thrust/drag constants (logged),
        and whether they are estimated too (``_estimate_vehicle``)."""
        self.warnings = []
        given = [n for n in VEHICLE if n in self.init]
        est = self.estimate if self.estimate is not None else default_estimate(self.model, "online")
        self._estimate_vehicle = self.estimate is None and not given
        if self._estimate_vehicle:
            # no constants of this vehicle: the paper's values are another vehicle's;
            # estimate them too (held until the first batch re-initialisation)
            self.warnings.append(
                "no thrust/drag constants of this vehicle were given: the online fit "
                "estimates them too; for the paper's protocol pass --params-from a batch "
                "fit's parameters.json")
        elif not given and not any(n in est for n in VEHICLE):
            self.warnings.append(
                "the thrust/drag constants are held at the paper's values for another "
                "vehicle (none given): pass --params-from a batch fit's parameters.json or "
                "estimate them too")
        for w in self.warnings:
            log.warning("fg online: %s", w)

    def _new_session(self, mission: Mission, hold: bool) -> None:
        """The state that outlives a replay: the re-initialisation policy, the sigma
        report, the process noise's floor, the gate's tables, the kinematic floor."""
        s = self.settings
        self.policy = HoldPolicy(s, s.online.init_after)
        self.report = SigmaReport()
        self.noise = NoiseAdapter(s, bool(mission.planar))
        self.gate = UsblGate(mission, s)
        # the causal track's kinematic floor while the parameters are held
        # (aqfg.fg.kinematic); none where they are not, or the settings say so
        self._floor = CausalFloor(
            KinematicFilter.from_settings(s),
            until=math.inf if hold and s.online.kinematic_q > 0 else float(self.fix_t[0]))

    def _reset_run(self, plan: bool) -> None:
        """The state of one run of the smoother from the first fix (a start or a replay)."""
        s = self.settings
        self.steps = StepSource(self.model, self.mission, self.fix_t, s.graph.knot_spacing, plan)
        self.knots: list[float] = []
        self.filtered: list[np.ndarray] = []      # causal estimate per knot
        self.anchor_idx: list[int] = []           # knot index of each fix
        self.latest: dict[int, np.ndarray] = {}   # knot index -> latest estimate
        self.seg_starts = [float(self.fix_t[0])]   # random-walk segments (GTSAM engine)
        self.v_by_seg: dict[int, np.ndarray] = {}
        self.hist_t: list[float] = []
        self.hist_v: list[np.ndarray] = []
        self.hist_s: list[np.ndarray] = []
        self.timings: dict[str, list[float]] = {"update": [], "update_total": [], "correction": []}
        self.n_fix = 0
        self.pred_t: list[float] = []              # fix times after the first, and the
        self.pred_x: list[np.ndarray] = []        # state predicted there before the update
        self.events: list[OnlineEvent] = []        # recoveries and other notable events
        self.events_mark = 0
        self._diverged_at: set[tuple[float, float]] = set()   # corrected_track's, noted
        self.last_params: dict[str, np.ndarray] = {}   # last finite estimate per group
        self.policy.phase = Phase.RELEASED         # until the start's hold priors are in
        self.noise.restart()
        self.gate.restart()
        self.warming = s.online.warmup_tol > 0
        self.warmup_end = float("nan")

    def _make_engine(self, x0: np.ndarray, t0: float, hold: bool) -> WindowEngine:
        """The numpy engine where the configuration allows it, else GTSAM's (``engine_note``
        says why)."""
        s = self.settings
        reason = ("online.engine = 'gtsam'" if s.online.engine == "gtsam" else
                  LagWindow.unsupported(self.model, self.layout, self.mission, s))
        self.engine_note = reason
        if reason and s.online.current_walk > 0:
            self.engine_note += ("; the current is held constant in the window's past "
                                 "(online.current_walk needs the numpy engine)")
        if reason and s.online.heading_walk > 0:
            self.engine_note += ("; the heading offset is one constant "
                                 "(online.heading_walk needs the numpy engine)")
        cls = GtsamEngine if reason else NumpyEngine
        return cls(self, x0, t0, hold)

    # ---------------------------------------------------------------- updates
    @property
    def engine(self) -> str:
        """Which engine runs the window: "numpy" or "gtsam" (``engine_note`` says why)."""
        return self.backend.name

    @property
    def reinit_batches(self) -> list[ReinitBatch]:
        """A record per batch re-initialisation solved (``Result.reinit_batches``)."""
        return self.policy.reinit_batches

    @property
    def q_scale(self) -> float:
        """The process-noise variance factor in use (adaptive; ``Result.process_noise_scale``)."""
        return self.noise.q_scale

    @property
    def held(self) -> bool:
        """The parameters are held at their start values (hold priors)."""
        return self.policy.held

    def pending(self) -> bool:
        """True while fixes remain to be processed."""
        return self.n_fix < len(self.fix_t)

    def params(self) -> np.ndarray:
        """Current full parameter vector (inside the physical bounds)."""
        return self.backend.params()

    def update(self, t_fix: float | None = None, mission: Mission | None = None,
               recover: bool = True) -> UpdateInfo:
        """Process inputs and measurements up to the next fix (or up to ``t_fix``, which must
        be a fix time) and update the window. ``mission``: a newer copy of the mission with
        more samples (live use). ``recover=False``: the window's update only; the caller
        calls :meth:`recover` next, before anything else changes the smoother (live use:
        the fix is reported in between)."""
        if mission is not None:
            self.set_mission(mission)
        if t_fix is None:
            if not self.pending():
                raise ValueError("no fix left to process")
            t_fix = float(self.fix_t[self.n_fix])
        self._t_call = time.perf_counter()
        self.events_mark = len(self.events)
        t_last = self.knots[-1]
        if t_fix <= t_last + 1e-9:
            raise ValueError(f"fix time {t_fix} s is not after the last processed time {t_last} s")
        # new knots on the grid up to the fix
        sp = self.settings.graph.knot_spacing
        grid = np.arange(t_last + sp, t_fix - sp / 4, sp)
        all_t = np.concatenate([[t_last], grid, [t_fix]])
        info = self._advance(t_fix, t_last, all_t[1:], all_t)
        return self.recover(t_fix, info) if recover else info

    def recover(self, t_fix: float, info: UpdateInfo) -> UpdateInfo:
        """What follows the window's update at ``t_fix`` (``info``): a batch
        re-initialisation or re-seed where one is due (:func:`recovery.after_update`), then
        the causal track's kinematic floor. The update's info, or the restarted one's."""
        info = recovery.after_update(self, t_fix, info)
        self._kinematic_step(t_fix)
        return info

    def set_mission(self, mission: Mission) -> None:
        """A newer copy of the mission with more samples (live use): the inputs and fixes
        that the next update and :meth:`result` read (its track runs to the mission's end)."""
        self.mission = mission
        self.fix_t = np.unique(mission.fix_times())
        # inputs may have changed: no plan
        self.steps = StepSource(self.model, mission, self.fix_t, self.settings.graph.knot_spacing,
                                plan=False)
        self.gate.set_mission(mission)
        self.backend.set_mission(mission)

    def _advance(self, t_fix: float, t_last: float, new_t: np.ndarray, all_t: np.ndarray
                 ) -> UpdateInfo:
        """One update of the window: the model's prediction to the fix, the USBL gate and
        the process-noise adaptation on it, the fix's measurements, the solve."""
        eng = self.backend
        x_pred = eng.predict(t_fix, t_last, new_t, all_t)
        self.pred_t.append(float(t_fix))
        self.pred_x.append(x_pred.copy())
        dt = float(t_fix - t_last)
        drop_usbl = self.gate.check(t_fix, dt, x_pred, self.noise,
                                    held=self.policy.held and not self.policy.replaying)
        if self.settings.online.adapt_noise:
            self.noise.adapt(dt, self.gate.innovation(t_fix, x_pred), self.gate.left_out(t_fix))
        eng.measure(t_fix, t_last, all_t, drop_usbl, self.gate.forced_scale)
        info = self._solve(t_fix, len(new_t))
        eng.review(t_fix)
        return info

    def note_diverged_prediction(self, t: float) -> None:
        """An event where the model's prediction diverged (once per run of them)."""
        if not self.events or self.events[-1].event != "prediction diverged":
            self.events.append(OnlineEvent(float(t), "prediction diverged"))

    def _kinematic_step(self, t_fix: float) -> None:
        """The causal track's kinematic floor (:class:`aqfg.fg.kinematic.CausalFloor`) at
        this fix: fed while the parameters are held; at the first fix at which they are not
        (the first batch released them), the causal track follows the model from there on
        (an event says so). Not in a replay: it re-runs fixes already reported."""
        if self.policy.replaying:
            return
        if self._floor.step(t_fix, self.gate.fixes, self.policy.held):
            self.events.append(OnlineEvent(float(t_fix), "causal track follows the model "
                                           "from here (before: a constant-velocity filter on "
                                           "the fixes, while the parameters were held)"))

    def _solve(self, t_fix: float, n_new: int) -> UpdateInfo:
        """The engine's solve at a fix, and what is reported of it (values, sigma, the
        causal and latest states, history, timings)."""
        t_a = time.perf_counter()
        eng = self.backend
        if self.warming:
            # warm-up: keep everything since the start in the window until the parameters
            # are known well enough to linearise the marginal priors near the truth
            eng.set_lag(max(self.window, t_fix - self.knots[0] + 1.0))
        th, raw = eng.solve(t_fix)
        names = self.layout.estimated
        sh = self.report.reported(names, raw)
        values = dict(zip(names, th.tolist()))
        sigma = dict(zip(names, sh.tolist()))
        self.report.raw.update(zip(names, raw.tolist()))
        if self.warming:
            done = bool(np.all(raw < self.settings.online.warmup_tol * self._scales)) \
                and not self.policy.held
            if done or t_fix - self.knots[0] >= self.settings.online.warmup_max:
                self.warming = False
                self.warmup_end = float(t_fix)
                eng.set_lag(self.window)
        t_b = time.perf_counter()
        dt = t_b - t_a
        self.timings["update"].append(dt)
        self.timings["update_total"].append(t_b - self._t_call)
        # the fix knot's estimate (causal), and the latest estimates of knots in the window
        i_fix = len(self.knots) - 1
        self.anchor_idx.append(i_fix)
        eng.read_states(t_fix, i_fix)
        self.hist_t.append(float(t_fix))
        self.hist_v.append(th)
        self.hist_s.append(sh)
        self.n_fix = int(self.fix_t.searchsorted(t_fix + 1e-9))
        return UpdateInfo(float(t_fix), dt, values, sigma, n_new)

    def release(self, t_fix: float) -> None:
        """Remove the hold priors: the parameters follow the data from here."""
        held = self.policy.held
        self.policy.phase = Phase.RELEASED
        self.report.held = None
        if held:
            self.backend.release(t_fix)

    # ---------------------------------------------------------------- tracks
    def corrected_track(self, p: np.ndarray | None = None, t_end: float | None = None) -> Track:
        """The whole past trajectory re-traced with the parameters ``p`` (default: current).

        The paper's past-trajectory correction (§III-D): between consecutive fixes the model
        integrates the recorded inputs from the smoothed state at the earlier fix with the
        new parameters; the mismatch with the smoothed state at the later fix is spread
        linearly over the interval, so the track passes through the smoothed fix states.
        After the last fix the model runs on alone (up to ``t_end``, default the last knot).
        An interval the model cannot re-trace joins the smoothed states (an event).
        """
        t_a = time.perf_counter()
        if p is None:
            p = self.params()
        knots = np.array(self.knots)
        if t_end is not None and t_end > knots[-1] + 1e-6:
            sp = self.settings.graph.knot_spacing
            knots = np.concatenate([knots, np.arange(knots[-1] + sp, t_end - sp / 4, sp), [t_end]])
        if len(knots) == 1:
            X = np.zeros((1, 6))
            X[0] = self.latest.get(0, self.filtered[0])
            return Track(knots, X[:, :3], X[:, 3:])
        anchors = list(self.anchor_idx)
        ax = {i: self.latest.get(i, self.filtered[i]) for i in anchors}
        X = retrace(self.model, self.mission, knots, anchors, ax, self._p_segments(p),
                    np.array(self.seg_starts), self._note_diverged)
        self.timings["correction"].append(time.perf_counter() - t_a)
        return Track(knots, X[:, :3], X[:, 3:])

    def _note_diverged(self, t_a: float, t_b: float) -> None:
        """An event, once per interval, for a corrected-track interval the model could not
        re-trace (:meth:`corrected_track`)."""
        if (t_a, t_b) not in self._diverged_at:
            self._diverged_at.add((t_a, t_b))
            self.events.append(OnlineEvent(t_a, "corrected track: the model's re-trace "
                                           f"diverged between {t_a:.1f} and {t_b:.1f} s; the "
                                           "smoothed states joined there instead"))

    def _p_segments(self, p_now: np.ndarray) -> list[np.ndarray]:
        """Parameter vectors per random-walk segment (the current one for the last)."""
        return p_segments(p_now, self.seg_starts, self.v_by_seg,
                          self.layout.idx["variable"] if self.v_by_seg else None)

    def filtered_track(self) -> Track:
        """The causal track: each knot as first predicted, each fix knot right after its
        update; while the parameters were held, horizontally the kinematic floor's
        (:meth:`_kinematic_step`)."""
        self.backend.materialise()
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
        filt = with_tail(self.filtered_track(), track)
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
        return Result(method="fg", mode="online", estimated=lay.estimated,
                      values=dict(zip(self.model.all_names, map(float, p))), sigma=sigma,
                      missions=[mr], timings={k: list(v) for k, v in self.timings.items()},
                      history=hist, histories=[hist], info=self._info(),
                      warnings=list(self.warnings),
                      events=list(self.events), reinit_batches=list(self.policy.reinit_batches),
                      rejected_usbl=sorted(t for t, out in self.gate.rejected.items() if out),
                      process_noise_scale=float(self.noise.q_scale),
                      effects=tuple(e.name for e in self.model.effects), model=self.model,
                      engine=OnlineEngine(self.engine, self.engine_note),
                      sigma_inflation=dict(self.report.inflation))

    def _info(self) -> dict:
        """``Result.info`` of an online run."""
        ups = self.timings["update"]
        return {"window": self.window, "n_updates": len(ups),
                "warmup_end": self.warmup_end,
                "predicted_at_fix": (np.array(self.pred_t), np.array(self.pred_x).reshape(-1, 6)),
                "update_median_s": float(np.median(ups)) if ups else float("nan"),
                "kernel": "cpp" if self.model.uses_cpp else "numpy",
                "settings": self.settings}
