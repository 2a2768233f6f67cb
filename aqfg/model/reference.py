"""Plain-numpy reference of the vehicle-model kernel (mirrored by ``cpp_factors/kernel.hpp``).

This is the one place where a parameter enters the motion model: :func:`accel`.

Model (paper §II-D/E), per input step of length ``h`` with the attitude ``R_raw`` and the
commands held constant; every built-in effect (:mod:`aqfg.model.effects`) adds its term
where its class says:

* corrected attitude (Eq. 6): ``R = Rz(theta) @ R_raw`` with the heading offset ``theta``
  of :func:`aqfg.model.frames.heading` (heading terms);
* current (Eq. 3): ``s = [s_x, s_y, 0] + current terms``; relative velocity, body:
  ``v_r = R.T @ (v - s)``;
* thrust (Eq. 1): ``a_thrust = sum_i (g_i * d_i - loss_i) * dir_i`` with ``d_i`` the
  (lag-filtered) demand ``u_i|u_i|``, gain ``g_i = k * (product of the thrust-gain terms)``
  and ``loss_i`` the inflow terms' (of ``|u_i|`` and the speed over ground along ``dir_i``);
* drag (Eq. 2): ``a_drag = -[k_x, k_yz, k_yz] * sign(v_r) * v_r**2 + body-force terms``;
* net body acceleration (Eqs. 4, 10): ``a_b = a_thrust + a_drag``; ground acceleration
  (Eq. 9): ``a = R @ a_b + ground-force terms``, vertical zeroed for planar vehicles.

Integration (:func:`integrate_step`): constant acceleration over the step (Eqs. 8-9 with
the acceleration evaluated at the step start, as the paper's EKF does).
Thrust lag: each demand passes a first-order filter with the time constant ``tau`` of the
demand-lag term; the step uses the exact mean of the filter output over the step, so
``tau -> 0`` is smooth.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aqfg.model.effects import (
    BodyForceTerm,
    CurrentTerm,
    DemandLagTerm,
    GroundForceTerm,
    InflowTerm,
    ThrustGainTerm,
    abs_command,
)
from aqfg.model.frames import heading, heading_jacobian
from aqfg.model.frames import wrap_angle as wrap_angle  # re-exported for existing callers
from aqfg.model.params import DYNAMICS_EFFECTS, INDEX, N_DYN, SLICE
from aqfg.model.rotation import E_Z, rot_z

I_SX, I_SY, I_K, I_KX, I_KYZ = (INDEX[n] for n in ("s_x", "s_y", "k", "k_x", "k_yz"))
# indices of the catalogue's dynamics parameters, for the vectorised mirror
# (aqfg.model.batched), which evaluates the same terms for many segments at once
I_TH, I_HDR = INDEX["theta_e"], INDEX["heading_drift.rate"]
I_ASYM, I_REV, I_TAU = (INDEX[n] for n in ("thrust_asymmetry.ratio", "reverse_thrust.ratio",
                                            "thrust_lag.tau"))
I_CX, I_CYZ = INDEX["linear_drag.c_x"], INDEX["linear_drag.c_yz"]
I_DSX, I_DSY = INDEX["current_drift.ds_x"], INDEX["current_drift.ds_y"]
I_WN, I_WE = INDEX["wind_drag.a_n"], INDEX["wind_drag.a_e"]
I_GA = INDEX["ground_advance.c"]


def _terms(kind: type) -> tuple:
    """(effect, its slice of p) for the built-in dynamics effects whose term is ``kind``."""
    return tuple((e, SLICE[e.name]) for e in DYNAMICS_EFFECTS if isinstance(e, kind))


CURRENT_TERMS = _terms(CurrentTerm)
GAIN_TERMS = _terms(ThrustGainTerm)
LAG_TERMS = _terms(DemandLagTerm)
INFLOW_TERMS = _terms(InflowTerm)
BODY_TERMS = _terms(BodyForceTerm)
GROUND_TERMS = _terms(GroundForceTerm)
if len(LAG_TERMS) > 1:
    raise RuntimeError("the thrust demand has one lag filter: at most one DemandLagTerm effect")


@dataclass
class Geometry:
    """Thruster layout of a vehicle: unit axes (N, 3) body, side (N,) +1 starboard."""
    dirs: np.ndarray
    side: np.ndarray
    planar: bool


@dataclass
class Steps:
    """Input steps of one or more segments, as the kernel consumes them.

    Warm-up steps (``warm``) precede a segment: they only advance the thrust-lag filter
    over the commands before the segment start. ``R`` is the raw IMU attitude
    (body->ground, row-major 3x3 flattened to 9), ``dem`` the demand ``u|u|`` per thruster,
    ``tm`` the time since mission start at the step start (s).
    """
    h: np.ndarray       # (n,) s
    warm: np.ndarray    # (n,) bool
    R: np.ndarray       # (n, 9)
    dem: np.ndarray     # (n, N)
    tm: np.ndarray      # (n,)

    def slice(self, a: int, b: int) -> Steps:
        return Steps(self.h[a:b], self.warm[a:b], self.R[a:b], self.dem[a:b], self.tm[a:b])


def integrate_step(pos: np.ndarray, vel: np.ndarray, acc: np.ndarray, h: float):
    """One step of ``h`` s at constant acceleration (Eqs. 8-9): ``pos + h vel + h^2/2 acc``,
    ``vel + h acc``. Also carries sensitivities (``d pos``, ``d vel``, ``d acc`` as arrays)."""
    return pos + h * vel + 0.5 * h * h * acc, vel + h * acc


def filter_step(f, df, c, h, tau):
    """First-order filter over one step of constant input ``c``.

    Returns (mean output over the step, its d/dtau, new state, new d/dtau).
    """
    if tau < 1e-9:
        # limits tau -> 0: mean = c, d mean/dtau = (f - c)/h, state -> c, dstate/dtau = 0
        if h <= 0:  # ... except that a zero-length step leaves the state (and d/dtau) as is
            return c.copy(), df.copy(), f.copy(), df.copy()
        mean = c.copy()
        dmean = (f - c) / h if h > 0 else np.zeros_like(c)
        return mean, dmean, c.copy(), np.zeros_like(c)
    e = np.exp(-h / tau)
    phi = tau / h * (1.0 - e) if h > 0 else 1.0
    dphi = ((1.0 - e) / h - e / tau) if h > 0 else 0.0
    mean = c + (f - c) * phi
    dmean = df * phi + (f - c) * dphi
    de = e * h / tau**2
    fn = c + (f - c) * e
    dfn = df * e + (f - c) * de
    return mean, dmean, fn, dfn


def lag_time_constant(p: np.ndarray) -> float:
    """Time constant (s) of the thrust-demand filter (0 without a lag term)."""
    return sum((e.time_constant(p[sl]) for e, sl in LAG_TERMS), 0.0)


def thrust_gains(p: np.ndarray, side: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Thrust per unit demand of each propeller (Eq. 1 gain, m/s^2): ``k`` times the
    thrust-gain terms (asymmetry for starboard thrusters, reverse ratio for negative demand)."""
    g = np.full(len(side), p[I_K])
    for e, sl in GAIN_TERMS:
        g = g * e.gain(np.asarray(side), np.asarray(d), p[sl])
    return g


def accel(v: np.ndarray, R_raw: np.ndarray, d: np.ndarray, dd_tau: np.ndarray, tm: float,
          p: np.ndarray, geom: Geometry):
    """Ground-frame acceleration (m/s^2) and its Jacobians w.r.t. ``v`` (3x3) and ``p`` (3xN_DYN).

    ``v``: ground velocity (m/s, NED); ``R_raw``: IMU attitude (3x3); ``d``: mean thrust
    demand per thruster over the step, ``dd_tau`` its derivative w.r.t. the lag's time
    constant. Every built-in dynamics effect adds its term where its class says.
    """
    Jp = np.zeros((3, N_DYN))
    R = rot_z(heading(p, tm)) @ R_raw
    w = v - _current(p, tm)
    vr = R.T @ w
    a_thr, g, g_rel, factors, M, dloss_dd, inflow_q = _thrust(v, R, d, p, geom)
    a_b, q2, D, body_q = _drag(vr, a_thr, p)
    a = R @ a_b
    RD = R @ D
    A = RD @ R.T                               # d a / d v (body part)
    _body_columns(Jp, R, d, dd_tau, p, geom, g, g_rel, factors, dloss_dd, q2, body_q + inflow_q)
    # heading: dR/dth = E_Z R; a = R a_b(vr, vg), vr = R^T (v - s), vg = R^T v
    RM = R @ M
    da_dth = E_Z @ a + RD @ (R.T @ (E_Z.T @ w)) + RM @ (R.T @ (E_Z.T @ v))
    # current: d a / d s = -A (the water part; the inflow terms see the speed over ground)
    Jp[:, I_SX] = -A[:, 0]
    Jp[:, I_SY] = -A[:, 1]
    for e, sl in CURRENT_TERMS:
        Jp[:, sl] = -A @ e.current_jacobian(tm, p[sl])
    A = A + RM @ R.T
    a, A, da_dth = _ground(Jp, a, A, da_dth, v, R, d, tm, p)
    for i, dth in heading_jacobian(p, tm):
        Jp[:, i] += da_dth * dth
    if geom.planar:
        a[2] = 0.0
        A[2, :] = 0.0
        Jp[2, :] = 0.0
    return a, A, Jp


def _current(p: np.ndarray, tm: float) -> np.ndarray:
    """The current (m/s, NED; Eq. 3) with the current terms at time ``tm``."""
    s = np.array([p[I_SX], p[I_SY], 0.0])
    for e, sl in CURRENT_TERMS:
        s = s + e.current(tm, p[sl])
    return s


def _thrust(v: np.ndarray, R: np.ndarray, d: np.ndarray, p: np.ndarray, geom: Geometry):
    """Thrust (Eq. 1) with the gain terms and the inflow terms (thrust lost with |u| and the
    advance speed over ground): body-frame acceleration ``a_thr``, the gains ``g`` and
    ``g / k``, the gain factors, ``d a_b / d vg``, the loss's derivative w.r.t. the demand
    and the inflow terms' parameter columns ``[(slice, d a_b / d q)]``."""
    side = geom.side
    k = p[I_K]
    factors = [e.gain(side, d, p[sl]) for e, sl in GAIN_TERMS]
    g_rel = np.ones(len(d))                    # gain / k
    for f in factors:
        g_rel = g_rel * f
    g = k * g_rel
    a_thr = geom.dirs.T @ (g * d)
    # inflow terms: thrust lost with |u| and the advance speed over ground
    vg = R.T @ v
    va = geom.dirs @ vg
    n_abs, dn_dd = abs_command(d)
    M = np.zeros((3, 3))                       # d a_b / d vg
    dloss_dd = np.zeros(len(d))
    inflow_q = []
    for e, sl in INFLOW_TERMS:
        L = e.loss(n_abs, va, p[sl])
        Ln, Lva, Lq = e.loss_jacobians(n_abs, va, p[sl])
        a_thr = a_thr - geom.dirs.T @ L
        M = M - geom.dirs.T @ (Lva[:, None] * geom.dirs)
        dloss_dd = dloss_dd + Ln * dn_dd
        inflow_q.append((sl, -geom.dirs.T @ Lq))
    return a_thr, g, g_rel, factors, M, dloss_dd, inflow_q


def _drag(vr: np.ndarray, a_thr: np.ndarray, p: np.ndarray):
    """Quadratic drag (Eq. 2) and the body-force terms at the water-relative body velocity
    ``vr``: body-frame acceleration ``a_b``, ``sign(v_r) v_r^2``, ``d a_b / d vr`` and the
    body-force terms' parameter columns ``[(slice, d a_b / d q)]``."""
    kq = np.array([p[I_KX], p[I_KYZ], p[I_KYZ]])
    q2 = np.abs(vr) * vr                       # sign(v_r) v_r^2
    a_b = a_thr - kq * q2
    D = np.diag(-2.0 * kq * np.abs(vr))        # d a_b / d vr
    body_q = []
    for e, sl in BODY_TERMS:
        f, Fv, Fq = e.body_force(vr, p[sl])
        a_b = a_b + f
        D = D + Fv
        body_q.append((sl, Fq))
    return a_b, q2, D, body_q


def _body_columns(Jp: np.ndarray, R: np.ndarray, d: np.ndarray, dd_tau: np.ndarray,
                  p: np.ndarray, geom: Geometry, g: np.ndarray, g_rel: np.ndarray,
                  factors: list, dloss_dd: np.ndarray, q2: np.ndarray, body_cols: list) -> None:
    """The body-frame columns of ``Jp`` (written in place): thrust gain ``k``, drag ``k_x``,
    ``k_yz``, the gain, lag, body-force and inflow terms."""
    k = p[I_K]
    side = geom.side
    Rdirs = R @ geom.dirs.T                    # thrust directions, ground frame (3, n_thr)
    Jp[:, I_K] = Rdirs @ (g_rel * d)
    Jp[:, I_KX] = -R[:, 0] * q2[0]
    Jp[:, I_KYZ] = -R[:, 1] * q2[1] - R[:, 2] * q2[2]
    for j, (e, sl) in enumerate(GAIN_TERMS):
        others = np.full(len(d), k)            # k times the other gain factors
        for i, f in enumerate(factors):
            if i != j:
                others = others * f
        Jp[:, sl] = Rdirs @ ((others * d)[:, None] * e.gain_jacobian(side, d, p[sl]))
    for e, sl in LAG_TERMS:
        Jp[:, sl] = np.outer(Rdirs @ ((g - dloss_dd) * dd_tau), e.time_constant_jacobian(p[sl]))
    for sl, Fq in body_cols:
        Jp[:, sl] = R @ Fq


def _ground(Jp: np.ndarray, a: np.ndarray, A: np.ndarray, da_dth: np.ndarray, v: np.ndarray,
            R: np.ndarray, d: np.ndarray, tm: float, p: np.ndarray):
    """The ground-frame terms added to the acceleration ``a``, ``d a / d v`` and
    ``d a / d heading`` (returned), their parameter columns written into ``Jp``."""
    for e, sl in GROUND_TERMS:
        q = p[sl]
        a = a + e.ground_accel(v, R, d, tm, q)
        Jv, Jq, Jth = e.ground_jacobians(v, R, d, tm, q)
        A = A + Jv
        Jp[:, sl] = Jq
        da_dth = da_dth + Jth
    return a, A, da_dth


def propagate(x0: np.ndarray, p: np.ndarray, steps: Steps, geom: Geometry, user=()):
    """Integrate state ``x = [pos(3), vel(3)]`` (NED) over ``steps``.

    Returns ``x1`` (6,), ``J_x0`` (6, 6) and ``J_p`` (6, N_DYN + n_user) = d x1 / d p, where
    ``user`` lists ``(UserEffect, index of its first parameter in p)``; the user columns
    follow the N_DYN built-in ones in the order given.
    """
    p = np.asarray(p, dtype=float)
    pos = np.array(x0[:3], dtype=float)
    vel = np.array(x0[3:6], dtype=float)
    n_user = sum(len(e.params) for e, _ in user)
    ncol = 3 + N_DYN + n_user             # sensitivities w.r.t. v0 and p
    Sx = np.zeros((3, ncol))
    Sv = np.zeros((3, ncol))
    Sv[:, :3] = np.eye(3)
    tau = lag_time_constant(p)
    n = len(steps.h)
    f = steps.dem[0].astype(float).copy() if n else np.zeros(0)
    df = np.zeros_like(f)
    for j in range(n):
        h = float(steps.h[j])
        c = steps.dem[j].astype(float)
        d, dd, f, df = filter_step(f, df, c, h, tau)
        if steps.warm[j] or h <= 0.0:
            continue
        R_raw = steps.R[j].reshape(3, 3)
        tm = float(steps.tm[j])
        a, A, Jp = accel(vel, R_raw, d, dd, tm, p, geom)
        if user:
            a, A, Jp = add_user(a, A, Jp, user, vel, R_raw, d, tm, p, geom)
        dA = A @ Sv
        dA[:, 3:] += Jp
        pos, vel = integrate_step(pos, vel, a, h)
        Sx, Sv = integrate_step(Sx, Sv, dA, h)
    x1 = np.concatenate([pos, vel])
    Jx = np.eye(6)
    Jx[:3, 3:] = Sx[:, :3]
    Jx[3:, 3:] = Sv[:, :3]
    Jp_out = np.vstack([Sx[:, 3:], Sv[:, 3:]])
    return x1, Jx, Jp_out


def add_user(a, A, Jp, user, vel, R_raw, d, tm, p, geom):
    """Add the terms of effects whose parameters follow the table (``user``: ``(effect,
    index of its first parameter in p)``, ground-force terms such as
    :class:`~aqfg.model.effects.UserEffect`): acceleration, d/dv, and their columns appended
    to ``Jp`` (the heading columns get their d/dtheta)."""
    R = rot_z(heading(p, tm)) @ R_raw
    cols = [Jp]
    for eff, i0 in user:
        q = p[i0:i0 + len(eff.params)]
        a_u = eff.ground_accel(vel, R, d, tm, q)
        Jv, Jq, a_th = eff.ground_jacobians(vel, R, d, tm, q)
        Jp = cols[0]
        for i, dth in heading_jacobian(p, tm):
            Jp[:, i] += a_th * dth
        if geom.planar:
            a_u = a_u.copy(); a_u[2] = 0.0
            Jv = Jv.copy(); Jv[2] = 0.0
            Jq = Jq.copy(); Jq[2] = 0.0
            Jp[2] = 0.0
        a = a + a_u
        A = A + Jv
        cols.append(Jq)
    return a, A, np.hstack(cols)


def propagate_many(X0: np.ndarray, p: np.ndarray, steps: Steps, offsets: np.ndarray,
                   geom: Geometry, user=()):
    """:func:`propagate` for K segments; segment i uses steps ``offsets[i]:offsets[i+1]``."""
    K = len(offsets) - 1
    n_user = sum(len(e.params) for e, _ in user)
    X1 = np.zeros((K, 6))
    JX = np.zeros((K, 6, 6))
    JP = np.zeros((K, 6, N_DYN + n_user))
    for i in range(K):
        X1[i], JX[i], JP[i] = propagate(X0[i], p, steps.slice(offsets[i], offsets[i + 1]),
                                        geom, user)
    return X1, JX, JP

