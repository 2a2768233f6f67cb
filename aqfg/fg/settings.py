"""Settings of the factor-graph smoothers, grouped by concern: the problem both smoothers
solve (:class:`GraphSettings`), the batch's Levenberg-Marquardt solver
(:class:`SolverSettings`), what the batch fit does around its solve (:class:`BatchSettings`)
and the online fixed-lag smoother (:class:`OnlineSettings`).

The defaults were measured on simulated and real missions; the measurements behind them are
in docs/independent-vehicle.md (the fits' honesty and the online smoother), docs/real-vehicle.md
(sway-drag prior, GNSS noise), docs/architecture.md and docs/speed.md (solver and engine
settings). One setting is changed with :meth:`FGSettings.with_`.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import Any

from aqfg.fg.factors import ProcessNoise, SensorNoise


@dataclass(frozen=True)
class GraphSettings:
    """The problem both smoothers solve: knots, noise, priors.

    knot_spacing: s between state knots (default 1; fix times are added as knots). Inputs
        between knots are integrated inside the dynamics factor, so the result depends
        little on it.
    process: the dynamics factors' process noise (:class:`~aqfg.fg.factors.ProcessNoise`).
    process_scale_max: the largest process-noise variance factor any adaptation adopts
        (default 256: a white acceleration of 0.32 m/s^2/sqrt(Hz), a small vehicle's own
        acceleration; beyond it the newest velocity follows the fixes' noise).
    sensors: the measurement noise and robust loss (:class:`~aqfg.fg.factors.SensorNoise`).
    gnss_noise: the GNSS error the fixes are weighted by (:mod:`aqfg.fg.gnss_noise`), a
        first-order Gauss-Markov error of sigma and correlation time tau: "measure"
        (default) measures it on the missions' own fixes where they are dense (median
        spacing <= 1 s; about a constant-velocity track of PSD ``OnlineSettings.kinematic_q``),
        else the stated sigma; a :class:`~aqfg.fg.gnss_noise.GnssNoise` (e.g. another
        mission's of the same receiver); None: the stated sigma. Online each fix is
        weighted by sigma, the batch by variance sigma^2 (1 + rho) / (1 - rho),
        rho = exp(-spacing / tau), never below the stated sigma: dense fixes' errors are
        correlated (docs/real-vehicle.md).
    prior_scale: a parameter's prior sigma is ``prior_scale`` x its ParamSpec.scale
        (default 3: weak), except for the names in ``prior_sigma``.
    prior_sigma: ``{name: sigma}`` of the parameters with a prior of their own (default: the
        currents 0.3 m/s, so that on a straight leg the heading offset, not the current,
        takes what the two explain alike; the sway drag k_yz 30 1/m, which damps a 0.1-m/s
        sideslip within 0.3 s and keeps the 0.05-s integration stable; docs/real-vehicle.md).
    walk_sigma: ``{name: sigma per sqrt(s)}`` of a random walk of variable parameters over
        segments of ``walk_segment`` s (default None: one constant value per mission).
    walk_segment: s per segment of that walk (default 60).
    surface_sigma: (m, m/s) of the surface constraint down = 0, vd = 0 of planar vehicles
        (default 0.01, 0.01).
    init_pos_sigma, init_vel_sigma: m and m/s of the prior at the first knot, around the
        first fix and zero velocity (defaults 20 and 1; paper §II-E5).
    """
    knot_spacing: float = 1.0
    process: ProcessNoise = field(default_factory=ProcessNoise)
    process_scale_max: float = 256.0
    sensors: SensorNoise = field(default_factory=SensorNoise)
    gnss_noise: object = "measure"
    prior_scale: float = 3.0
    prior_sigma: dict = field(default_factory=lambda: {"s_x": 0.3, "s_y": 0.3, "k_yz": 30.0})
    walk_sigma: dict | None = None
    walk_segment: float = 60.0
    surface_sigma: tuple[float, float] = (0.01, 0.01)
    init_pos_sigma: float = 20.0
    init_vel_sigma: float = 1.0


@dataclass(frozen=True)
class SolverSettings:
    """The batch's Levenberg-Marquardt solve.

    max_iterations: the most iterations (default 60).
    rel_tol, abs_tol: it stops when an accepted step lowers the cost (0.5 chi-square) by
        less than max(rel_tol x cost, abs_tol) (defaults 1e-6, 1e-3).
    fast_lm: solve on the numpy form of the graph (:mod:`aqfg.fg.fastlm`) where the graph has
        its shape (default True: the same iterates, 8-25x faster; docs/speed.md); False:
        on GTSAM's linearisation.
    """
    max_iterations: int = 60
    rel_tol: float = 1e-6
    abs_tol: float = 1e-3
    fast_lm: bool = True


@dataclass(frozen=True)
class BatchSettings:
    """What the batch fit (:func:`aqfg.fg.fit.fit_fg`) does around its solve to keep its
    sigma honest where the model is not the vehicle; why each is on:
    docs/independent-vehicle.md, "The batch".

    sandwich_block: s per time block of the sandwich covariance (:mod:`aqfg.fg.covariance`;
        default 60; 0: the Hessian alone). Data with fewer blocks than parameters + 2 are
        "too short for the sandwich" below.
    adapt_noise: choose the process-noise variance factor by the evidence
        (:func:`aqfg.fg.noise.evidence_search`): True, False, or None (default) for data
        too short for the sandwich only, where the nominal noise turns the model's error
        into a confident heading error; over longer data the nominal noise gives the
        better estimates. The diagnosis sets False (a noise that explains the fixes would
        hide the misfit it shows).
    measure_noise: also measure that factor where it is not adopted
        (``Result.process_noise_measured``; default False). The online
        re-initialisations set True: it is the floor of their online noise.
    adapt_track: smooth the tracks once more, the parameters held, under the process-noise
        factor the evidence chooses for the states (``Result.track_noise_scale``; default
        True: the track follows the fixes where the model is not the vehicle). The
        diagnosis and the online re-initialisations set False: they need the nominal fit's
        states.
    rank_by_evidence: where the noise is chosen by the evidence, rank the heading basins by
        their evidence, each under its own noise (:func:`aqfg.fg.noise.basin_evidence`;
        default True); False: by their cost.
    heading_profile: where the data are too short for the sandwich and theta_e is
        estimated (one mission), also solve with theta_e held on a grid over the circle
        (:mod:`aqfg.fg.profile`) and widen each sigma to the evidence-weighted spread of
        those solutions where larger (default True). The online re-initialisations carry
        the spread until their next batch.
    structural_sigma: widen the sigma of the heading offset and the current by the shift
        the best-supported missing effect would cause, where the fixes are not explained
        (or the data are too short to tell) and the data call for one
        (:mod:`aqfg.fg.structure`, ``Result.sigma_structure``; default True): the sandwich
        does not see a bias that holds all mission.
    auto_effect: with the default parameters (no ``estimate``), where the structural test
        names a missing effect of the dynamics, fit again with it and keep the better
        plausible fit (:func:`aqfg.fg.fit.adopt_effect`, ``Result.effect_step``; default
        True); False fits the model as given.
    block_jackknife: one mission too short for the sandwich is fitted again with each of
        4-8 time blocks' fixes left out, and each sigma widened to the refits' spread where
        larger (:mod:`aqfg.fg.jackknife`, ``Result.block_jackknife``; default True). The
        online re-initialisations do not run it.
    dr_horizon: s, re-estimate the estimated constants (thrust, drag) by the error of the
        model's own prediction over this horizon from the smoothed states, where that
        differs significantly from the smoother's (:mod:`aqfg.fg.dead_reckoning`;
        default 60: the constants a vehicle dead-reckons with); 0: the smoother's.
    """
    sandwich_block: float = 60.0
    adapt_noise: bool | None = None
    measure_noise: bool = False
    adapt_track: bool = True
    rank_by_evidence: bool = True
    heading_profile: bool = True
    structural_sigma: bool = True
    auto_effect: bool = True
    block_jackknife: bool = True
    dr_horizon: float = 60.0


@dataclass(frozen=True)
class OnlineSettings:
    """The online fixed-lag smoother (:class:`~aqfg.fg.fixed_lag.FixedLagSmoother`); why
    each default: docs/independent-vehicle.md, "Online".

    engine: "numpy" (default: :mod:`aqfg.fg.fastlag`, knots at the fixes) where the
        configuration allows it, else "gtsam" (ISAM2 on 1-s knots), which "gtsam" forces.
    init_after: s; without a given heading offset the estimated parameters are held at
        their start values until the fixes span this long, then a batch of the fixes so far
        (global heading start) re-initialises the smoother and releases them (default 20;
        0 disables the holding and the re-initialisations).
    init_fixes: that first batch also runs once this many fixes are in, if sooner
        (default 10: dense fixes outrun what a held model explains).
    reinit_until: s; the re-initialising batch is repeated each time the elapsed time
        doubles, up to this (default 960), and restarts the smoother where the heading
        offsets disagree.
    adapt_noise: the process-noise variance factor follows the fixes' innovations
        (default True; at most ``GraphSettings.process_scale_max``).
    adapt_window: fixes whose median normalised innovation sets that factor (default 10).
    gate_usbl: chi-square(2) quantile beyond which a USBL fix's range/bearing innovation,
        under the process noise in use, leaves it out (default 13.8: p = 0.999, the EKF's
        gate; ``inf``: no gate): the robust loss bounds an outlier's pull only while the
        dynamics are stiff.
    max_rejects: a USBL fix is taken anyway after this many left out in a row (default 3:
        a track that is off must not reject every fix), at the robust loss's threshold.
    kinematic_q: m^2/s^3 per horizontal axis, the white-acceleration PSD of the
        constant-velocity filter on the fixes alone that gives the causal track while the
        parameters are held (:mod:`aqfg.fg.kinematic`; default 0.1: about 0.3 m/s^2 over a
        second); 0: the model's track from the start. The smoother does not see it.
    current_walk: m/s per sqrt(s), the current the window's past has informed moves as a
        first-order Gauss-Markov process, stationary sigma the current's prior (numpy
        engine; default 0.03: correlation time 200 s with 0.3 m/s): it takes up a current
        that changes and a model's persistent velocity error; 0: one constant current.
    heading_walk: rad per sqrt(s), the heading offset likewise walks (numpy engine; default
        0.003: 1.7 deg over 5 min): an AHRS offset drifts; 0: one constant offset.
    warmup_tol, warmup_max: until every estimated parameter's sigma is below
        ``warmup_tol`` x ParamSpec.scale (default 0.1), or ``warmup_max`` s have passed
        (default 300), the window holds everything since the start, so that its marginal
        priors are linearised near converged parameters (0 disables; docs/architecture.md).
    relin_pos, relin_vel: m and m/s, relinearisation thresholds of the states (defaults
        1 and 0.05: positions enter the dynamics linearly; docs/architecture.md).
    relin_param: parameter units, ISAM2's parameter relinearisation threshold (default 0.001).
    relin_param_fraction: the numpy engine's parameter relinearisation threshold, a fraction
        of each parameter's ParamSpec.scale (default 0.05: a held linearisation's error is
        ~1.5 % of an 8-s dynamics factor's sigma; docs/speed.md).
    iterations_per_update: solver iterations after each fix (default 1).
    cpp_block: the numpy engine linearises, solves and marginalises its window in the C++
        kernel (default True); False: numpy and LAPACK, the reference it is tested against.
    """
    engine: str = "numpy"
    init_after: float = 20.0
    init_fixes: int = 10
    reinit_until: float = 960.0
    adapt_noise: bool = True
    adapt_window: int = 10
    gate_usbl: float = 13.8
    max_rejects: int = 3
    kinematic_q: float = 0.1
    current_walk: float = 0.03
    heading_walk: float = 0.003
    warmup_tol: float = 0.1
    warmup_max: float = 300.0
    relin_pos: float = 1.0
    relin_vel: float = 0.05
    relin_param: float = 0.001
    relin_param_fraction: float = 0.05
    iterations_per_update: int = 1
    cpp_block: bool = True


@dataclass(frozen=True)
class FGSettings:
    """Settings of the factor-graph smoothers, one group per concern (each documented on
    its class). Change settings with :meth:`with_`."""
    graph: GraphSettings = field(default_factory=GraphSettings)
    solver: SolverSettings = field(default_factory=SolverSettings)
    batch: BatchSettings = field(default_factory=BatchSettings)
    online: OnlineSettings = field(default_factory=OnlineSettings)

    def with_(self, **groups: dict[str, Any]) -> FGSettings:
        """A copy with the named settings changed, group by group:
        ``settings.with_(batch={"auto_effect": False}, online={"init_after": 30.0})``."""
        names = {f.name for f in fields(self)}
        for g in groups:
            if g not in names:
                raise TypeError(f"FGSettings has no group {g!r} (groups: {sorted(names)})")
        return replace(self, **{g: replace(getattr(self, g), **kw) for g, kw in groups.items()})


__all__ = ["BatchSettings", "FGSettings", "GraphSettings", "OnlineSettings", "SolverSettings"]
