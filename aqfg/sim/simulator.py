"""Mission simulator: an ASV or AUV on a waypoint mission, with optional hidden effects.

The translational physics is the shared model: every 100 Hz step is integrated by
:meth:`aqfg.model.vehicle.Model.propagate` (C++ kernel when built, else the numpy reference) with
the TRUE parameter vector, hidden effects included (:mod:`aqfg.model.params`). Only the
simulator has rotational dynamics (:mod:`aqfg.sim.vehicle`: yaw from the differential
thrust, roll/pitch wobble) and the waypoint controller; sensor streams are produced by
:mod:`aqfg.sim.sensors` through the model's measurement functions.

Time: the controller ticks at 10 Hz (motor rows, truth rows), the truth is integrated at
100 Hz, the IMU reports at 50 Hz. Deterministic given ``seed``: each random part (plan,
parameters, each sensor's noise) draws from its own child of ``np.random.SeedSequence(seed)``,
so switching a sensor or a measurement effect on or off leaves the other streams unchanged.

Defaults (documented here, used when not given):

* base parameters (:func:`true_params`): k, k_x, k_yz of paper Table II (ASV.3 / AUV);
  theta_e = 0.5 rad (about 30 deg, as in the paper's experiments) and a 0.1 m/s current.
  Unless ``params`` gives them, theta_e is drawn in 0.5 +- 0.15 rad and the current with
  speed 0.07-0.13 m/s in a random direction, by seed. k, k_x, k_yz are never randomised
  (they are the vehicle's fixed parameters, shared by all its missions).
* hidden effect values when a value is omitted: :data:`EFFECT_DEFAULTS`.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from aqfg.data.importers.frames import euler_to_quat
from aqfg.data.mission import Mission, Motors, Truth
from aqfg.model import reference as ref
from aqfg.model.effects import BUILTIN
from aqfg.model.frames import heading
from aqfg.model.params import BASE_NAMES, INDEX, NAMES, SPEC, as_dict, vector
from aqfg.model.reference import Geometry, Steps, thrust_gains
from aqfg.model.rotation import rot_z
from aqfg.model.vehicle import Model, demand, quat_to_rot
from aqfg.sim.plan import depth_profile, depth_reference, waypoint_pattern
from aqfg.sim.sensors import Run, depth_stream, gnss_stream, imu_stream, truth_track, usbl_stream
from aqfg.sim.vehicle import VEHICLES, Controller, Wobble

H_FINE = 0.01            # s, truth integration step (100 Hz)
SUBSTEPS = 10            # integration steps per controller tick (10 Hz)
TICK = H_FINE * SUBSTEPS
STATION = np.array([0.0, 0.0, 1.5])   # USBL base station, NED m

# Values of the hidden effects' parameters when an effect is named without them: each
# parameter's typical value, declared with the effect (aqfg.model.effects).
EFFECT_DEFAULTS: dict[str, float] = {
    s.name: float(s.typical) for e in BUILTIN.values() for s in e.specs() if s.typical is not None}


def true_params(vehicle: str) -> dict[str, float]:
    """The default truth: every parameter by full name (effects at their null values).

    Base parameters: k, k_x, k_yz from paper Table II (ASV.3 for "asv"), theta_e = 0.5 rad,
    current (s_x, s_y) = (0.08, -0.06) m/s. :func:`simulate` randomises theta_e and the
    current mildly by seed unless its ``params`` gives them.
    """
    spec = _spec(vehicle)
    p = as_dict(vector({**spec.base, "theta_e": 0.5, "s_x": 0.08, "s_y": -0.06}))
    return p


def effect_values(effects) -> dict[str, float]:
    """Full parameter names and values of the hidden effects in ``effects``.

    Accepts ``{"thrust_asymmetry": 0.8}`` (the effect's first parameter),
    ``{"lever_arm": {"x": 0.3}}`` (named parameters), ``{"lever_arm.x": 0.3}`` (full
    names), ``{"lever_arm": [0.3, 0.1, 0.0]}`` (all parameters in order) and
    ``{"thrust_lag": None}`` (defaults). Parameters of a named effect that are not given
    take :data:`EFFECT_DEFAULTS`. Raises KeyError (unknown name) or ValueError (bad value).
    """
    out: dict[str, float] = {}
    given: dict[str, float] = {}
    for key, val in (effects or {}).items():
        if key in BUILTIN:
            eff = BUILTIN[key]
            short = [n.split(".", 1)[1] for n in eff.params]
            if val is None or (isinstance(val, str) and val.strip() == ""):
                pass
            elif isinstance(val, dict):
                for sk, sv in val.items():
                    if sk not in short:
                        raise KeyError(f"effect {key!r} has no parameter {sk!r}; "
                                       f"its parameters: {', '.join(short)}")
                    given[f"{key}.{sk}"] = _num(sv, f"{key}.{sk}")
            elif isinstance(val, (list, tuple, np.ndarray)):
                if not 1 <= len(val) <= len(eff.params):
                    raise ValueError(f"effect {key!r} takes 1 to {len(eff.params)} values "
                                     f"({', '.join(short)}), got {len(val)}")
                for n, v in zip(eff.params, val):
                    given[n] = _num(v, n)
            else:
                given[eff.params[0]] = _num(val, eff.params[0])
        elif key in SPEC and key not in BASE_NAMES:
            eff = BUILTIN[key.split(".", 1)[0]]
            given[key] = _num(val, key)
        else:
            raise KeyError(f"unknown effect or effect parameter {key!r}; effects: "
                           f"{', '.join(BUILTIN)}; parameters: "
                           f"{', '.join(n for n in NAMES if n not in BASE_NAMES)}")
        for n in eff.params:
            out.setdefault(n, EFFECT_DEFAULTS[n])
    out.update(given)
    for n, v in out.items():
        _check_bounds(n, v)
    return out


def _num(v, name: str) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise ValueError(f"value of {name!r} must be a number, got {v!r}") from None
    if not np.isfinite(x):
        raise ValueError(f"value of {name!r} must be finite, got {v!r}")
    return x


def _check_bounds(name: str, v: float) -> None:
    s = SPEC[name]
    if not s.lower <= v <= s.upper:
        raise ValueError(f"{name} = {v} is outside its bounds [{s.lower}, {s.upper}] {s.unit}")


def _spec(vehicle: str):
    if vehicle not in VEHICLES:
        raise ValueError(f"unknown vehicle {vehicle!r}; expected one of: {', '.join(VEHICLES)}")
    return VEHICLES[vehicle]


def _active_effects(values: dict[str, float]) -> list[str]:
    return [e for e in BUILTIN if any(n in values for n in BUILTIN[e].params)]


def simulate(vehicle: str = "asv", *, seed: int = 0, duration: float = 600.0,
             params: dict[str, float] | None = None,
             effects: dict[str, float | dict[str, float]] | None = None,
             gnss_period: float | None = 1.0,
             usbl: bool = False, usbl_period: float = 4.5,
             usbl_sigma_range: float = 0.15, usbl_sigma_bearing: float = np.radians(1.5),
             usbl_outlier_rate: float = 0.03, gnss_sigma: float = 1.0,
             waypoints: np.ndarray | None = None,
             progress: Callable[[float], None] | None = None) -> tuple[Mission, Truth]:
    """Simulate one mission; returns the mission (what the vehicle logged) and its truth.

    ``duration`` s (rounded to the 0.1 s controller tick); the vehicle starts at rest.

    ``params``: true parameters by name (base or effect parameters) overriding the
    defaults; ``effects``: hidden effects (see :func:`effect_values`). ``gnss_period`` s
    between GNSS fixes (None or 0: no GNSS), ``gnss_sigma`` m per axis. USBL: range
    (``usbl_sigma_range`` m) and bearing (``usbl_sigma_bearing`` rad) every ``usbl_period``
    s from the station at NED [0, 0, 1.5], a fraction ``usbl_outlier_rate`` gross outliers.
    ``waypoints`` (n >= 2, 2) north/east m: the vehicle starts at rest on row 0, visits
    rows 1.. and cycles back to row 1; default a seeded lawn-mower/star pattern beside the
    station scaled to the duration. ``progress(fraction)`` is called during the run.
    The AUV also logs depth (1 Hz) and follows a seeded depth profile (1-4 m); its GNSS
    fixes are recorded whatever its depth (a generic absolute-position sensor, as for the
    paper's surface runs): for a realistic submerged mission pass ``gnss_period=None,
    usbl=True``.
    """
    spec = _spec(vehicle)
    duration = _checked_options(duration, gnss_period, usbl, usbl_period, usbl_outlier_rate,
                                gnss_sigma, usbl_sigma_range, usbl_sigma_bearing)
    seq = np.random.SeedSequence(int(seed))
    r_plan, r_par, r_imu, r_gnss, r_usbl, r_depth = (np.random.default_rng(s)
                                                     for s in seq.spawn(6))

    p, active = _true_vector(vehicle, r_par, params, effects)

    # ---- plan
    v_lo, v_hi = spec.speed_range
    wps = _waypoints(waypoints, r_plan, 0.85 * 0.5 * (v_lo + v_hi) * duration)
    leg_speed = r_plan.uniform(v_lo, v_hi, len(wps))
    yaw0 = float(np.arctan2(*(wps[1] - wps[0])[::-1]) + r_plan.uniform(-np.pi / 2, np.pi / 2))
    wobble = Wobble.random(r_plan, spec.wobble_deg)
    profile = None if spec.planar else depth_profile(r_plan, duration)

    run = _closed_loop(spec, p, active, wps, leg_speed, yaw0, wobble, profile, duration, progress)

    # ---- streams
    shell = _mission_shell(spec, seed)
    model = Model.for_mission(shell)
    shell.imu = imu_stream(run, p, r_imu)
    shell.motors = Motors(t=run.t_tick[:-1].copy(), u=run.U)
    if gnss_period:
        shell.gnss = gnss_stream(run, p, model, r_gnss, float(gnss_period), gnss_sigma)
    if usbl:
        shell.usbl, _ = usbl_stream(run, p, model, r_usbl, float(usbl_period), STATION,
                                    usbl_sigma_range, usbl_sigma_bearing, usbl_outlier_rate)
        shell.usbl_station = STATION.copy()
    if profile is not None:
        shell.depth = depth_stream(run, model, r_depth)
    tp = {**as_dict(p), "effects": active, "seed": int(seed), "vehicle": vehicle,
          "source": "aqfg.sim.simulator", "waypoints": wps.tolist()}
    if profile is not None:
        tp["depth_profile"] = profile.tolist()
    return shell, truth_track(run, tp)


def _checked_options(duration, gnss_period, usbl, usbl_period, usbl_outlier_rate, gnss_sigma,
                     usbl_sigma_range, usbl_sigma_bearing) -> float:
    """:func:`simulate`'s options checked (ValueError naming the bad one); the duration (s)
    as a float."""
    duration = _num(duration, "duration")
    if duration < 1.0:
        raise ValueError(f"duration must be at least 1 s, got {duration}")
    if gnss_period is not None and (not np.isfinite(gnss_period) or gnss_period < 0):
        raise ValueError(f"gnss_period must be >= 0 (0 or None: no GNSS), got {gnss_period}")
    if usbl and not usbl_period > 0:
        raise ValueError(f"usbl_period must be > 0, got {usbl_period}")
    if not 0.0 <= usbl_outlier_rate <= 1.0:
        raise ValueError(f"usbl_outlier_rate must be in [0, 1], got {usbl_outlier_rate}")
    if gnss_sigma < 0 or usbl_sigma_range < 0 or usbl_sigma_bearing < 0:
        raise ValueError("noise sigmas must be >= 0")
    return duration


def _true_vector(vehicle: str, r_par, params, effects) -> tuple[np.ndarray, list]:
    """The true parameter vector (seeded heading offset and current, ``params`` and the
    ``effects``' values over the vehicle's defaults) and the active effects."""
    eff_vals = effect_values(effects)
    values = true_params(vehicle)
    values["theta_e"] = 0.5 + r_par.uniform(-0.15, 0.15)
    cur_speed, cur_dir = r_par.uniform(0.07, 0.13), r_par.uniform(0.0, 2 * np.pi)
    values["s_x"], values["s_y"] = cur_speed * np.cos(cur_dir), cur_speed * np.sin(cur_dir)
    for n, v in (params or {}).items():
        if n not in SPEC:
            raise KeyError(f"unknown parameter {n!r}; known: {', '.join(NAMES)}")
        values[n] = _num(v, n)
        _check_bounds(n, values[n])
    extra_eff = {n: v for n, v in (params or {}).items()
                 if n not in BASE_NAMES and v != SPEC[n].null}
    values.update(eff_vals)
    active = _active_effects({**eff_vals, **extra_eff})
    for e in active:
        if vehicle not in BUILTIN[e].vehicles:
            raise ValueError(f"effect {e!r} does not apply to an {vehicle} "
                             f"(only: {', '.join(BUILTIN[e].vehicles)})")
    p = vector(values)
    return p, active


def _waypoints(waypoints, r_plan, length: float) -> np.ndarray:
    """The plan's waypoints (n, 2) north/east m: ``waypoints`` checked, or a seeded pattern
    of about ``length`` m."""
    if waypoints is None:
        wps = waypoint_pattern(r_plan, length)
    else:
        wps = np.asarray(waypoints, dtype=float)
        if wps.ndim != 2 or wps.shape[0] < 2 or wps.shape[1] != 2 or not np.isfinite(wps).all():
            raise ValueError(f"waypoints must be a finite (n >= 2, 2) array of north/east "
                             f"metres, got shape {wps.shape}")
    return wps


def _mission_shell(spec, seed: int) -> Mission:
    from aqfg.data.mission import Imu
    return Mission(name=f"sim-{spec.name}-seed{seed}", vehicle=spec.name,
                   thruster_dir=spec.thruster_dir.copy(),
                   imu=Imu(np.zeros(1), np.array([[1.0, 0, 0, 0]])),
                   motors=Motors(np.zeros(1), np.zeros((1, spec.n))),
                   thruster_pos=spec.thruster_pos.copy())


def _closed_loop(spec, p, effects, wps, leg_speed, yaw0, wobble, profile, duration,
                 progress) -> Run:
    """Integrate vehicle + controller: yaw model per 100 Hz step in Python, translation
    by the shared kernel over each 10 Hz tick (10 steps of 0.01 s, commands held)."""
    n_ticks = int(round(duration / TICK))
    n_fine = n_ticks * SUBSTEPS
    t_fine = np.arange(n_fine + 1) * H_FINE
    t_tick = t_fine[::SUBSTEPS]
    roll, pitch, droll, dpitch = wobble.angles(t_fine)
    r_mid, p_mid, _, _ = wobble.angles(t_fine[:-1] + 0.5 * H_FINE)
    RyRx_mid = quat_to_rot(euler_to_quat(r_mid, p_mid, np.zeros(n_fine)))
    th_start = heading(p, t_fine[:-1])

    geom = Geometry(dirs=spec.thruster_dir, side=spec.side, planar=spec.planar)
    model = Model(spec.name, geom, (), 0.0).with_effects(*effects)  # C++ if all are in it
    tau = ref.lag_time_constant(p)
    arm, side = spec.yaw_arm, spec.side
    gyr2, c1, c2 = spec.gyration2, spec.yaw_damp_lin, spec.yaw_damp_quad
    ctrl = Controller(spec, wps, leg_speed, k=float(p[INDEX["k"]]), k_x=float(p[INDEX["k_x"]]),
                      k_yz=float(p[INDEX["k_yz"]]))

    N = spec.n
    yaw = np.empty(n_fine + 1)
    r = np.empty(n_fine + 1)
    yaw[0], r[0] = yaw0, 0.0
    X = np.empty((n_ticks + 1, 6))
    z0 = 0.0 if profile is None else float(profile[0, 1])
    X[0] = [wps[0, 0], wps[0, 1], z0, 0.0, 0.0, 0.0]
    U = np.empty((n_ticks, N))
    f = np.zeros(N)                       # thrust-lag filter state (demand units)
    zeros = np.zeros(N)
    h_arr = np.full(SUBSTEPS + (1 if tau > 0 else 0), H_FINE)
    warm = np.zeros(len(h_arr), bool)
    if tau > 0:
        warm[0] = True                    # carries the filter state into the tick
    report_every = max(1, n_ticks // 50)

    for k in range(n_ticks):
        i0 = k * SUBSTEPS
        t = t_tick[k]
        x = X[k]
        R_now = rot_z(yaw[i0:i0 + 1])[0] @ quat_to_rot(euler_to_quat(roll[i0], pitch[i0], 0.0))
        dref = None
        if profile is not None:
            z_ref, vz_ref = depth_reference(profile, t)
            dref = (float(z_ref), float(vz_ref))
        u = ctrl.command(t, x[:3], x[3:], float(yaw[i0]), float(r[i0]), R_now, dref)
        U[k] = u
        c = demand(u)
        f_start = f
        if tau > 0:                       # lagged thrust: the kernel's filter, per step
            means = np.empty((SUBSTEPS, N))
            for j in range(SUBSTEPS):
                means[j], _, f, _ = ref.filter_step(f, zeros, c, H_FINE, tau)
            moments = ((thrust_gains(p, side, means) * means) @ arm / gyr2).tolist()
        else:
            f = c
            moments = [float(arm @ (thrust_gains(p, side, c) * c)) / gyr2] * SUBSTEPS
        for j, m in enumerate(moments):   # rotational dynamics, semi-implicit Euler
            i = i0 + j
            ri = r[i]
            r[i + 1] = ri + H_FINE * (m - c1 * ri - c2 * ri * abs(ri))
            yaw[i + 1] = yaw[i] + H_FINE * r[i + 1]
        # translation: the shared kernel over the tick
        sl = slice(i0, i0 + SUBSTEPS)
        yaw_mid = 0.5 * (yaw[sl] + yaw[i0 + 1:i0 + SUBSTEPS + 1])
        R_raw = (rot_z(yaw_mid - th_start[sl]) @ RyRx_mid[sl]).reshape(-1, 9)
        dem = np.tile(c, (SUBSTEPS, 1))
        tm = t_fine[sl]
        if tau > 0:
            R_raw = np.vstack([R_raw[:1], R_raw])
            dem = np.vstack([f_start, dem])
            tm = np.concatenate([tm[:1], tm])
        X[k + 1] = model.propagate(x, p, Steps(h_arr, warm, R_raw, dem, tm))[0]
        if progress is not None and (k % report_every == 0):
            progress(k / n_ticks)
    if progress is not None:
        progress(1.0)
    return Run(t_tick=t_tick, X=X, U=U, t_fine=t_fine, yaw=yaw, r=r, roll=roll, pitch=pitch,
               droll=droll, dpitch=dpitch)
