"""What the batch and fixed-lag smoothers share: settings, knots, initial values, measurement
factors of a mission, residuals and the inertial re-trace.

Times are seconds on the mission clock; states are ``[north, east, down, vn, ve, vd]``.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import gtsam
import numpy as np

from aqfg.data.mission import Mission
from aqfg.fg import factors as fc
from aqfg.model import retrace as retrace
from aqfg.model.params import BASE_NAMES
from aqfg.model.vehicle import Model, attitude_at
from aqfg.result import Residuals, Track


@dataclass(frozen=True)
class FGSettings:
    """Settings of the factor-graph smoothers (defaults measured on simulated missions).

    knot_spacing: s between state knots (fix times are added as knots); inputs between knots
        are integrated inside the dynamics factor, so the result depends little on it.
    prior_scale: parameter prior sigma = prior_scale x ParamSpec.scale (weak), except the
        names in ``prior_sigma`` (default: currents 0.3 m/s, so that on a straight leg,
        where a heading offset and a cross current look alike, the heading takes it; the
        sway drag k_yz 30 1/m: sway drag has no scale of its own relative to surge drag (a
        twin or keeled hull's is 100x its surge drag), and a prior of 0.9 1/m held a
        catamaran's at 1-2 1/m where its fixes asked for 30-250: a model that let a turn's
        sideslip persist, and dead-reckoned 1.5-2.5x worse than the update-error method's.
        30 1/m damps a 0.1-m/s sideslip within 0.3 s, where more changes no prediction,
        and keeps the explicit integration stable (``h k_yz |v| < 1``, h = 0.05 s;
        docs/independent-vehicle.md).
    walk_sigma: ``{name: sigma per sqrt(s)}`` of a random walk of variable parameters over
        time segments of ``walk_segment`` s (None: one constant value per mission).
    surface_sigma: (m, m/s) of the surface constraint down = 0, vd = 0 of planar vehicles.
    init_vel_sigma, init_pos_sigma: prior at the first knot (m/s, m) around the first fix
        and zero velocity (paper §II-E5).
    sandwich_block: s per time block of the sandwich covariance that keeps the parameter
        sigma honest when the model is wrong (:mod:`aqfg.fg.covariance`; 0 = Hessian only).
    adapt_process, adapt_window, adapt_max: online, the process-noise variance factor
        follows the median normalised fix innovation of the last ``adapt_window`` fixes
        (at least 1, at most ``adapt_max``; :class:`~aqfg.fg.fixed_lag.FixedLagSmoother`).
        ``adapt_max`` bounds the unmodelled acceleration a vehicle can have: 256 x the
        nominal variance is a white acceleration of 0.32 m/s^2/sqrt(Hz), the order of a
        small vehicle's own acceleration; beyond it the noise stops describing the model's
        error and makes the newest velocity follow the fixes' noise (a USBL fix 0.5 s
        after a GNSS fix set velocities of 5 m/s; docs/independent-vehicle.md).
    adapt_batch: the batch chooses the process-noise variance factor by its evidence
        (:func:`aqfg.fg.noise.evidence_search`): True, False, or None (default) for
        only where the data are too short for the sandwich (below). Over a whole mission the
        nominal noise gave the better estimates and a larger one freed degenerate solutions
        (so also for the online re-initialisations once the fixes so far are that long: a
        640-s one slid 44 deg off); on where the data are short (the default rule, the
        early re-initialisations among them), where the tight noise turned the model's error
        into a confident heading error; that is, for data too short for the sandwich's
        time blocks (fewer than the parameters + 2), where the Hessian sigma alone was
        6-15 times too small on Otter crops of 2.5-5 min (docs/independent-vehicle.md).
        The diagnosis sets False: a noise chosen to explain the fixes would hide the misfit
        it is there to show.
    rank_by_evidence: where the batch chooses the noise by its evidence, its heading basins
        are ranked by their evidence, each under the noise its own misfit asks for
        (:func:`aqfg.fg.noise.basin_evidence`), not by their cost under the noise the first
        one chose, which favoured a hull sliding sideways 43 deg off on a 5-min Otter crop
        (docs/independent-vehicle.md). False ranks them by cost everywhere (as before).
    heading_profile: where the data are too short for the sandwich and theta_e is estimated
        (one mission), the batch also solves with theta_e held on a grid over the whole
        circle (:mod:`aqfg.fg.profile`) and widens each sigma to the spread of the
        solutions weighted by their evidence, where that is the larger: one basin's
        curvature claimed 12 deg at a heading 147 deg off over 11 s of data
        (docs/independent-vehicle.md). The online smoother's re-initialisation batches
        walk it too: the spread is added to the sigma it reports until its next batch.
    measure_noise: the batch also measures the process-noise factor by the evidence where
        it does not adopt it (``Result.process_noise_measured``; the solution stays the
        nominal noise's): the online re-initialisations take it as the floor of the online
        noise while solving a long stretch with the nominal noise.
    adapt_track: the batch's tracks (and their residuals) are smoothed once more, the
        parameters held at the fit, under the process-noise factor the evidence chooses for
        the states given them (``Result.track_noise_scale``). The parameters come from the
        nominal noise (above); the track then follows the fixes where the model is not the
        vehicle instead of the model's error: on Otter missions 2-5x closer to the truth,
        on a vehicle that is the model the same track (factor 1; docs/independent-vehicle.md).
        The diagnosis and the online re-initialisations set False: they need the nominal
        fit's states.
    structural_sigma: the batch fit (:func:`aqfg.fg.fit.fit_fg`) widens the sigma of the
        heading offset and the current by the shift the best-supported missing effect
        would cause, where the fixes are not explained and the data call for one
        (:mod:`aqfg.fg.structure`; ``Result.sigma_structure``): the sandwich covers
        the model's error that varies over time, not a bias that holds all mission.
    auto_effect: the batch fit with the default parameters (:func:`aqfg.fg.fit.fit_fg`,
        no ``estimate``) runs the structural test even where the fixes are explained, and
        where it names a missing effect of the vehicle's dynamics (not a drift of the
        heading offset or the current) fits again with that effect added (and with the
        dynamics effect of largest score statistic, if another), returning the lower-cost
        fit of those that lower the cost, are plausible and keep the heading offset and
        current within 3 sigma (:func:`aqfg.fg.fit.adopt_effect`; ``Result.effect_step``);
        False fits the model as given.
    block_jackknife: a one-mission batch fit (:func:`aqfg.fg.fit.fit_fg`) on data too
        short for the sandwich is run again with each of 4-8 time blocks' fixes left out,
        and each sigma widened to the spread of those refits where that is larger
        (:mod:`aqfg.fg.jackknife`; ``Result.block_jackknife``): on 2.5-5 min Otter crops
        the current was up to 15 of its sigmas off (docs/independent-vehicle.md). The
        online re-initialisations do not run it.
    online_init_after, online_reinit_until: online without a given heading offset, the
        estimated parameters are held at their start values until ``online_init_after`` s
        of fixes are in; then a batch solve of the fixes so far (global heading start)
        re-initialises the smoother, which releases them. The check is repeated each time
        the elapsed time doubles, up to ``online_reinit_until`` s, and restarts from the
        batch when the heading offsets disagree (0 disables all of this).
    online_init_fixes: the first batch also runs once this many fixes are in, if that
        comes before ``online_init_after`` (dense fixes: with 1-s GNSS a held heading 30 deg
        off dragged the causal track 5 m RMS off the fixes for 14 s; the held model's error
        over 1-s intervals is beyond what the adaptive process noise allows).
    online_gate_usbl, online_max_rejects: online, a USBL fix whose range/bearing innovation
        against the model's prediction is beyond this chi-square(2) quantile (13.8:
        p = 0.999, the EKF's gate, :class:`aqfg.ekf.history.EkfConfig`) under the process
        noise in use is left out, unless the ``online_max_rejects`` USBL fixes before it
        were left out too (a track that is off must not reject every fix; such a fix
        enters with its sigmas scaled to put it at the Huber threshold). The Huber loss
        bounds an outlier's pull while the dynamics are stiff; once the adaptive process
        noise has loosened them (a wrong model), a 15-m range outlier moved the smoothed
        track 14 m (docs/independent-vehicle.md). ``inf``: no gate.
    online_kinematic_q: online, while the parameters are held (before the first batch has
        estimated the heading offset), the causal track is a constant-velocity filter's on
        the fixes alone (:mod:`aqfg.fg.kinematic`), with white acceleration of this power
        spectral density per horizontal axis (m^2/s^3; 0.1: about 0.3 m/s^2 sustained
        over a second); 0: the model's from the start. Only the causal track: the
        smoother and its estimates do not see it.
    online_current_walk: online (numpy engine), the current the window's past has informed
        moves before it meets the window's data: a first-order Gauss-Markov process, m/s
        per sqrt(s) over short times, stationary sigma the current's prior (0.03 with
        0.3 m/s: correlation time 200 s). It follows a current that changes, and the
        persistent velocity error of a model that is not the vehicle, which white process
        noise cannot: with the current constant, the causal track of an Otter mission at
        1-s fixes stayed 3-5 m off the fixes for 20 s at a time and the current's sigma
        claimed 0.006 m/s against an error of 0.06 on a drifting current
        (docs/independent-vehicle.md). 0: the current is one constant.
    online_heading_walk: online (numpy engine), the heading offset the window's past has
        informed moves as a random walk before it meets the window's data, rad per
        sqrt(s) (0.003: 1.7 deg over 5 min). An AHRS heading offset is not a constant
        (a gyro's unreferenced yaw drifts, a compass's offset changes with the motors'
        currents); with one constant the online heading of a mission drifting by
        0.03 deg/s ended 14-16 deg behind, with the walk 7 (docs/independent-vehicle.md).
        0: one heading offset per mission.
    dr_horizon: s, the batch fit (:func:`aqfg.fg.fit.fit_fg`) re-estimates the estimated
        fixed parameters (thrust/drag constants) by the error of the model's own
        prediction over this horizon from the smoothed states, where that differs
        significantly from the smoother's (:mod:`aqfg.fg.dead_reckoning`): the constants a
        vehicle dead-reckons with between fixes. On the Otter the smoother's own constants
        dead-reckoned 2-5x worse than the update-error method's (docs/independent-vehicle.md).
        0: the smoother's constants.
    max_iterations, rel_tol, abs_tol: batch Levenberg-Marquardt stops when an accepted step
        lowers the cost (0.5 chi-square) by less than max(rel_tol x cost, abs_tol).
    fast_lm: batch LM on the numpy form of the graph (:mod:`aqfg.fg.fastlm`) where the
        graph has its shape (else, or when False, on GTSAM's linearisation; same algorithm).
    relin_pos, relin_vel, relin_param, iterations_per_update: fixed-lag ISAM2 relinearisation
        thresholds (m, m/s, parameter units) and the number of ISAM2 iterations after each
        fix (coarse thresholds and one iteration: positions enter the dynamics linearly, so
        their linearisation point matters little; measured in docs/architecture.md).
    online_engine: the fixed-lag smoother's engine: "numpy" (:mod:`aqfg.fg.fastlag`, knots at
        the fixes, no Python callback per factor) where the configuration allows it, else
        "gtsam" (ISAM2 with CustomFactors on 1-s knots), which "gtsam" forces.
    fast_relin_param: the numpy engine's parameter relinearisation threshold, a fraction of
        each parameter's ParamSpec.scale (0.05: 0.025 rad of heading offset; a dynamics
        factor's error from a held linearisation is second order in the parameters' move:
        0.025 rad on an 8-s interval is ~1.5 % of its noise sigma; docs/speed.md).
    fast_cpp_block: the numpy engine linearises a dynamics factor into its Gauss-Newton
        block in one C++ call (kernel ``linearise_into``) and solves and marginalises its
        window in C++ (``window_step``, ``schur_drop``); False: numpy products of the
        kernel's Jacobians and LAPACK (the reference the C++ is tested against; the same
        results to rounding).
    gnss_noise: the GNSS error the fixes are weighted by (:mod:`aqfg.fg.gnss_noise`): a
        first-order Gauss-Markov error of sigma and correlation time tau. "measure"
        (default): measured on the missions' own fixes where they are dense (median spacing
        <= 1 s; about a constant-velocity track of PSD ``online_kinematic_q``), else their
        stated sigma; a :class:`~aqfg.fg.gnss_noise.GnssNoise` (e.g. measured on other
        missions of the same receiver); None: the stated sigma. The online smoother weighs
        each fix by sigma (its own error: its output is the track); the batch by variance
        sigma^2 (1 + rho) / (1 - rho), rho = exp(-spacing / tau), never below the fix's
        stated sigma (the constants: it only down-weights dense fixes). On a 5-Hz
        receiver the fixes' wander about such a track was 0.02-0.24 m with tau 1-12 s: a
        stated 1.5 m made the model, not the fixes, set the online track between sparse
        fixes, and on dense fixes counted 5 shared errors a second as independent.
    warmup_tol, warmup_max: fixed-lag warm-up. Until every estimated parameter's sigma is
        below ``warmup_tol`` x ParamSpec.scale (or ``warmup_max`` s have passed), the
        window holds everything since the start, so the marginal priors are linearised
        near converged parameters (0 disables; why: docs/architecture.md).
    """
    knot_spacing: float = 1.0
    sandwich_block: float = 60.0
    adapt_process: bool = True
    adapt_batch: bool | None = None
    rank_by_evidence: bool = True
    heading_profile: bool = True
    measure_noise: bool = False
    adapt_track: bool = True
    structural_sigma: bool = True
    auto_effect: bool = True
    block_jackknife: bool = True
    online_init_after: float = 20.0
    online_init_fixes: int = 10
    online_reinit_until: float = 960.0
    adapt_window: int = 10
    adapt_max: float = 256.0
    online_gate_usbl: float = 13.8
    online_kinematic_q: float = 0.1
    online_current_walk: float = 0.03
    online_heading_walk: float = 0.003
    online_max_rejects: int = 3
    process: fc.ProcessNoise = field(default_factory=fc.ProcessNoise)
    sensors: fc.SensorNoise = field(default_factory=fc.SensorNoise)
    prior_scale: float = 3.0
    prior_sigma: dict = field(default_factory=lambda: {"s_x": 0.3, "s_y": 0.3, "k_yz": 30.0})
    walk_sigma: dict | None = None
    walk_segment: float = 60.0
    surface_sigma: tuple[float, float] = (0.01, 0.01)
    init_vel_sigma: float = 1.0
    init_pos_sigma: float = 20.0
    dr_horizon: float = 60.0
    max_iterations: int = 60
    fast_lm: bool = True
    rel_tol: float = 1e-6
    abs_tol: float = 1e-3
    relin_pos: float = 1.0
    relin_vel: float = 0.05
    relin_param: float = 0.001
    iterations_per_update: int = 1
    online_engine: str = "numpy"
    fast_relin_param: float = 0.05
    fast_cpp_block: bool = True
    warmup_tol: float = 0.1
    warmup_max: float = 300.0
    gnss_noise: object = "measure"

    def with_(self, **kw) -> FGSettings:
        return replace(self, **kw)


ProgressFn = Callable[[float, str], None]


def progress_fn(progress) -> ProgressFn:
    """A ``(fraction, message)`` callback from ``None`` / ``False`` (silent), ``True``
    (a line on stderr) or a callable."""
    if callable(progress):
        return progress
    if progress:
        import sys

        def show(frac: float, msg: str) -> None:
            print(f"\r[{100 * frac:5.1f}%] {msg:<60s}", end="" if frac < 1 else "\n",
                  file=sys.stderr, flush=True)
        return show
    return lambda frac, msg: None


def default_estimate(model: Model, mode: str) -> tuple[str, ...]:
    """Batch: the six base parameters and those of the active effects; online: the
    variable group only (the paper's online mode, fixed parameters held)."""
    if mode == "online":
        return tuple(n for n in model.active_names if model.spec(n).group == "variable")
    return tuple(model.active_names)


def mission_model(model: Model | None, mission: Mission, effects=()) -> Model:
    """The model for one mission: the given model (effects, geometry) on its clock, or one
    built from the mission."""
    if model is None:
        return Model.for_mission(mission, effects)
    m = replace(model, t0=mission.t0)
    return m.with_effects(*effects) if effects else m


# ---------------------------------------------------------------- knots and initial values
def knot_times(mission: Mission, spacing: float, t_start: float | None = None,
               t_end: float | None = None) -> np.ndarray:
    """Regular grid of ``spacing`` s merged with the fix times (so each fix is a knot).

    Starts at the first fix (the paper's initial position); grid points closer than
    ``spacing / 4`` to a fix are dropped.
    """
    if spacing <= 0:
        raise ValueError(f"knot spacing must be positive, got {spacing}")
    tf = mission.fix_times()
    if not len(tf):
        raise ValueError(f"mission {mission.name!r} has no GNSS or USBL fix: nothing anchors "
                         "the trajectory")
    if not np.any((tf >= mission.t0) & (tf <= mission.t1)):
        raise ValueError(f"mission {mission.name!r}: no GNSS or USBL fix inside the inputs "
                         f"(t {mission.t0:.6g} .. {mission.t1:.6g} s): nothing anchors the "
                         "trajectory")
    t0 = tf[0] if t_start is None else t_start
    t1 = mission.t1 if t_end is None else t_end
    tf = np.unique(tf[(tf >= t0) & (tf <= t1)])
    grid = np.arange(t0, t1 + 1e-9, spacing)
    if len(grid) == 0 or grid[-1] < t1 - 1e-6:
        grid = np.append(grid, t1)
    if len(tf):
        j = np.searchsorted(tf, grid)
        d = np.minimum(np.abs(tf[np.clip(j, 0, len(tf) - 1)] - grid),
                       np.abs(grid - tf[np.clip(j - 1, 0, len(tf) - 1)]))
        grid = grid[d > spacing / 4]
    k = np.unique(np.concatenate([grid, tf]))
    keep = np.concatenate([[True], np.diff(k) > 1e-6])
    return k[keep]


def robust_fixes(mission: Mission) -> tuple[np.ndarray, np.ndarray]:
    """Fix times and NED positions with gross outliers removed (for initial values only:
    the factors keep every fix under the robust loss)."""
    t, p = retrace.fixes(mission)
    if len(t) < 5:
        return t, p
    n = len(t)
    keep = np.ones(n, bool)

    def judge(i: np.ndarray, nb: np.ndarray) -> np.ndarray:
        # fixes i (m,) against their neighbours nb (m, j): within 6 median spreads (+1 m)
        # of the neighbours' median, plus 1.5 m per second of the neighbourhood
        q = p[nb, :2]                                        # (m, j, 2)
        med = np.median(q, axis=1)
        spread = np.median(np.abs(q - med[:, None, :]).reshape(len(i), -1), axis=1) + 1.0
        dt = np.max(np.abs(t[nb] - t[i][:, None]), axis=1)
        return np.linalg.norm(p[i, :2] - med, axis=1) < 6 * spread + 1.5 * dt

    inner = np.arange(3, n - 3)               # six neighbours each: vectorised
    if len(inner):
        off = np.array([-3, -2, -1, 1, 2, 3])
        keep[inner] = judge(inner, inner[:, None] + off)
    for i in sorted(set(range(min(3, n))) | set(range(max(n - 3, 0), n))):
        lo, hi = max(0, i - 3), min(n, i + 4)
        nb = np.delete(np.arange(lo, hi), i - lo)
        keep[i] = judge(np.array([i]), nb[None, :])[0]
    return t[keep], p[keep]


def robust_fix_table(mission: Mission, settings: FGSettings
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Fix times, horizontal NED positions (n, 2), their per-axis variance (m^2) (GNSS
    sigma, or the USBL tangential sigma at the fix's range) and whether each is a USBL fix,
    for innovation statistics."""
    t, p = retrace.fixes(mission)
    g, u, sn = mission.gnss, mission.usbl, settings.sensors
    # retrace.fixes' order: GNSS then USBL, stably sorted by time
    gt = g.t if g is not None else np.zeros(0)
    ut = u.t if u is not None else np.zeros(0)
    order = np.argsort(np.concatenate([gt, ut]), kind="stable")
    is_u = np.concatenate([np.zeros(len(gt), bool), np.ones(len(ut), bool)])[order]
    var = np.full(len(t), sn.gnss_sigma ** 2)
    if u is not None and len(ut):
        rng = np.interp(t, ut, u.range)
        var[is_u] = np.hypot(sn.usbl_range_sigma, rng[is_u] * sn.usbl_bearing_sigma) ** 2
    if g is not None and len(gt) and g.sigma is not None:
        sg = np.interp(t, gt, np.nan_to_num(g.sigma, nan=sn.gnss_sigma))
        var[~is_u] = sg[~is_u] ** 2
    return t, p[:, :2], var, is_u


def initial_states(mission: Mission, knots: np.ndarray) -> np.ndarray:
    """Initial knot states: positions interpolated between fixes, velocities from their
    central differences over one typical fix interval, depth from the depth sensor."""
    tf, pf = robust_fixes(mission)
    X = np.zeros((len(knots), 6))
    for a in range(2):
        X[:, a] = np.interp(knots, tf, pf[:, a])
    w = max(float(np.median(np.diff(tf))) if len(tf) > 1 else 1.0, 1.0)
    for a in range(2):
        X[:, 3 + a] = (np.interp(knots + w, tf, pf[:, a]) - np.interp(knots - w, tf, pf[:, a])) / (2 * w)
    if not mission.planar and mission.depth is not None and len(mission.depth.t):
        X[:, 2] = np.interp(knots, mission.depth.t, mission.depth.depth)
        X[:, 5] = (np.interp(knots + 1, mission.depth.t, mission.depth.depth)
                   - np.interp(knots - 1, mission.depth.t, mission.depth.depth)) / 2
    return X


def first_knot_term(mission: Mission, key: int, x0: np.ndarray, settings: FGSettings
                    ) -> fc.LinearTerm:
    """Prior at the first knot: around the first fix, velocity zero (paper §II-E5)."""
    s = settings
    vert = s.surface_sigma if mission.planar else (max(s.init_pos_sigma, 1.0), s.init_vel_sigma)
    sig = np.array([s.init_pos_sigma, s.init_pos_sigma, vert[0],
                    s.init_vel_sigma, s.init_vel_sigma, vert[1]])
    mean = np.array(x0, float).copy()
    mean[3:] = 0.0
    if mission.planar:
        mean[2] = 0.0
    return fc.prior_term(key, mean, sig)


def first_knot_prior(mission: Mission, key: int, x0: np.ndarray, settings: FGSettings):
    """:func:`first_knot_term` as a factor."""
    return first_knot_term(mission, key, x0, settings).factor()


# ---------------------------------------------------------------- measurements of a mission
@dataclass
class Measurements:
    """The fixes and depth readings of a mission in [t_start, t_end], with what their
    factors need (attitude at the measurement time, noise sigmas)."""
    gnss_t: np.ndarray
    gnss_z: np.ndarray          # (n, 2)
    gnss_sigma: np.ndarray      # (n,)
    gnss_R: np.ndarray          # (n, 3, 3)
    usbl_t: np.ndarray
    usbl_z: np.ndarray          # (n, 2) range, bearing
    usbl_sigma: np.ndarray      # (n, 2)
    usbl_R: np.ndarray
    station: np.ndarray | None
    depth_t: np.ndarray
    depth_z: np.ndarray

    @classmethod
    def of(cls, mission: Mission, settings: FGSettings, t_start: float = -np.inf,
           t_end: float = np.inf, attitudes: bool = True) -> Measurements:
        sn = settings.sensors
        z2 = np.zeros((0, 2))
        g = mission.gnss
        if g is not None and len(g.t):
            sel = (g.t >= t_start - 1e-9) & (g.t <= t_end + 1e-9)
            gt, gz = g.t[sel], g.ne[sel]
            gs = (np.where(np.isfinite(g.sigma[sel]) & (g.sigma[sel] > 0), g.sigma[sel],
                           sn.gnss_sigma)          # the column is optional per row (NaN)
                  if g.sigma is not None else np.full(len(gt), sn.gnss_sigma))
        else:
            gt, gz, gs = np.zeros(0), z2, np.zeros(0)
        u = mission.usbl
        if u is not None and len(u.t):
            sel = (u.t >= t_start - 1e-9) & (u.t <= t_end + 1e-9)
            ut, uz = u.t[sel], np.column_stack([u.range[sel], u.bearing[sel]])
            us = np.array([sn.usbl_sigmas(r) for r in uz[:, 0]]).reshape(-1, 2)
            station = np.asarray(mission.usbl_station, float)
        else:
            ut, uz, us, station = np.zeros(0), z2, z2, None
        d = mission.depth
        if d is not None and len(d.t) and not mission.planar:
            sel = (d.t >= t_start - 1e-9) & (d.t <= t_end + 1e-9)
            dt_, dz = d.t[sel], d.depth[sel]
        else:
            dt_, dz = np.zeros(0), np.zeros(0)

        def att(t):
            return attitude_at(mission, t) if len(t) and attitudes else np.zeros((0, 3, 3))
        return cls(gt, gz, gs, att(gt), ut, uz, us, att(ut), station, dt_, dz)


def knot_index(knots: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Index of the knot nearest to each time."""
    if len(knots) == 1:
        return np.zeros(len(np.atleast_1d(t)), int)
    j = np.clip(np.searchsorted(knots, t), 1, len(knots) - 1)
    return np.where(np.abs(knots[j - 1] - t) <= np.abs(knots[j] - t), j - 1, j)


def depth_assignment(knots: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each knot with a depth reading nearby: (reading index, knot index); the reading
    nearest to the knot is kept (one depth factor per knot)."""
    if not len(t):
        return np.zeros(0, int), np.zeros(0, int)
    k = knot_index(knots, t)
    d = np.abs(knots[k] - t)
    best: dict[int, int] = {}
    for i in np.argsort(d, kind="stable"):
        best.setdefault(int(k[i]), int(i))
    ki = np.array(sorted(best), dtype=np.int64)
    return np.array([best[j] for j in ki], dtype=int), ki


def measurement_factors(model: Model, layout: fc.ParamLayout, meas: Measurements,
                        knots: np.ndarray, kx: Callable[[int], int],
                        node_keys: Callable[[str, float], tuple], settings: FGSettings,
                        base: np.ndarray | None = None) -> list:
    """GNSS, USBL and depth factors (fix times must be knots). ``kx(i)`` = key of knot i;
    ``node_keys(stream, t)`` = ((group, key), ...) of the nodes a measurement reads."""
    sn = settings.sensors
    out = []
    kg = knot_index(knots, meas.gnss_t)
    ku = knot_index(knots, meas.usbl_t)
    for i in range(len(meas.gnss_t)):
        t = float(meas.gnss_t[i])
        k = int(kg[i])
        noise = sn.wrap(gtsam.noiseModel.Isotropic.Sigma(2, float(meas.gnss_sigma[i])), "gnss")
        out.append(fc.gnss_factor(model, layout, kx(k), node_keys("gnss", t), meas.gnss_z[i],
                                  meas.gnss_R[i], t, noise, base))
    for i in range(len(meas.usbl_t)):
        assert meas.station is not None, "USBL fixes come with the station position"
        t = float(meas.usbl_t[i])
        k = int(ku[i])
        noise = sn.wrap(gtsam.noiseModel.Diagonal.Sigmas(meas.usbl_sigma[i]), "usbl")
        out.append(fc.usbl_factor(model, layout, kx(k), node_keys("usbl", t), meas.usbl_z[i],
                                  meas.usbl_R[i], t, meas.station, noise, base))
    ri, ki = depth_assignment(knots, meas.depth_t)
    noise = sn.wrap(gtsam.noiseModel.Isotropic.Sigma(1, sn.depth_sigma), "depth")
    for r, k in zip(ri, ki):
        out.append(fc.depth_factor(kx(int(k)), float(meas.depth_z[r]),
                                   float(meas.depth_t[r] - knots[k]), noise))
    return out


# ---------------------------------------------------------------- results
def interp_states(track: Track, t: np.ndarray) -> np.ndarray:
    """States (n, 6) at times ``t``: linear interpolation of the track (exact at knots)."""
    X = np.column_stack([track.pos, track.vel])
    return np.column_stack([np.interp(t, track.t, X[:, a]) for a in range(6)]).reshape(-1, 6)


def residuals(model: Model, mission: Mission, track: Track, p_at: Callable[[float], np.ndarray],
              settings: FGSettings) -> dict:
    """Residuals (measured - predicted) of every GNSS, USBL and depth measurement against
    ``track``, raw and divided by the sensor sigma. ``p_at(t)``: full parameters at time t."""
    meas = Measurements.of(mission, settings, track.t[0], track.t[-1])
    out = {}
    if len(meas.gnss_t):
        X = interp_states(track, meas.gnss_t)
        ps = [p_at(t) for t in (meas.gnss_t[0], meas.gnss_t[-1])]
        moving = np.array([0.0, 0.0, 0.0, 1.0, 1.0, 0.0])       # shows a time offset
        if all(np.array_equal(model.h_gnss(moving, np.eye(3), 0.0, q)[0], np.zeros(2))
               for q in ps) and np.array_equal(ps[0], ps[-1]):
            pred = X[:, :2].copy()            # no sensor offset: the fix is the position
        else:
            pred = np.array([model.h_gnss(X[i], meas.gnss_R[i], t, p_at(t))[0]
                             for i, t in enumerate(meas.gnss_t)])
        raw = meas.gnss_z - pred
        out["gnss"] = Residuals(meas.gnss_t, raw, raw / meas.gnss_sigma[:, None], meas.gnss_z, pred)
    if len(meas.usbl_t):
        X = interp_states(track, meas.usbl_t)
        pred = np.array([model.h_usbl(X[i], meas.usbl_R[i], t, p_at(t), meas.station)[0]
                         for i, t in enumerate(meas.usbl_t)])
        raw = meas.usbl_z - pred
        raw[:, 1] = fc.wrap_angle(raw[:, 1])
        out["usbl"] = Residuals(meas.usbl_t, raw, raw / meas.usbl_sigma, meas.usbl_z, pred)
    if len(meas.depth_t):
        X = interp_states(track, meas.depth_t)
        pred = X[:, 2:3]
        raw = meas.depth_z[:, None] - pred
        out["depth"] = Residuals(meas.depth_t, raw, raw / settings.sensors.depth_sigma,
                                 meas.depth_z[:, None], pred)
    return out


def piecewise_inertial(model: Model, mission: Mission, p_segments: list[np.ndarray],
                       seg_starts: np.ndarray, rate: float = 10.0) -> Track:
    """The paper's inertial trajectory (from the first fix, model only); with parameters
    that change over time segments the rollout switches parameters at ``seg_starts``."""
    if len(p_segments) == 1:
        return retrace.inertial_track(model, mission, p_segments[0], rate)
    tf, pf = retrace.fixes(mission)
    t_out = np.arange(tf[0], mission.t1 + 1e-9, 1.0 / rate)
    x = np.concatenate([pf[0], np.zeros(3)])
    ts, P, V = [np.array([tf[0]])], [pf[0][None]], [np.zeros((1, 3))]
    t_cur = tf[0]
    for j, p in enumerate(p_segments):
        t_next = seg_starts[j + 1] if j + 1 < len(seg_starts) else np.inf
        sel = t_out[(t_out > t_cur + 1e-9) & (t_out <= t_next + 1e-9)]
        if not len(sel):
            continue
        tr = retrace.rollout(model, mission, p, x, t_cur, sel)
        ts.append(tr.t[1:]); P.append(tr.pos[1:]); V.append(tr.vel[1:])
        x = np.concatenate([tr.pos[-1], tr.vel[-1]])
        t_cur = tr.t[-1]
    return Track(np.concatenate(ts), np.vstack(P), np.vstack(V))


def check_missions(missions) -> list[Mission]:
    if isinstance(missions, Mission):
        missions = [missions]
    missions = list(missions)
    if not missions:
        raise ValueError("no mission given")
    for m in missions:
        if not isinstance(m, Mission):
            raise ValueError(f"expected aqfg.data.mission.Mission objects, got {type(m).__name__}")
        if m.usbl is not None and len(m.usbl.t) and m.usbl_station is None:
            raise ValueError(f"mission {m.name!r}: usbl data without a [usbl] station")
    veh = {m.vehicle for m in missions}
    if len(veh) > 1:
        raise ValueError(f"missions of one fit must share the vehicle type, got {sorted(veh)}")
    return missions


__all__ = ["FGSettings", "default_estimate", "knot_times", "initial_states", "Measurements",
           "measurement_factors", "residuals", "piecewise_inertial", "BASE_NAMES"]


def outliers(res: dict, threshold: float = 5.0) -> dict[str, list[dict]]:
    """Fixes whose whitened residual exceeds ``threshold`` sigma (the robust loss has
    down-weighted them): ``{stream: [{"t", "sigmas"}, ...]}`` for GNSS and USBL."""
    out: dict[str, list[dict]] = {}
    for stream in ("gnss", "usbl"):
        r = res.get(stream)
        if r is None or not len(r.t):
            continue
        z = np.linalg.norm(np.nan_to_num(r.normalised, nan=0.0), axis=1)
        idx = np.flatnonzero(z > threshold)
        if len(idx):
            out[stream] = [{"t": float(r.t[i]), "sigmas": round(float(z[i]), 1)} for i in idx]
    return out
