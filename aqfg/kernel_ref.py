"""Plain-numpy reference of the vehicle-model kernel (mirrored by ``cpp_factors/kernel.cpp``).

This is the one place where a parameter enters the motion model: :func:`accel`.

Model (paper §II-D/E), per input step of length ``h`` with the attitude ``R_raw`` and the
commands held constant:

* corrected attitude (Eq. 6): ``R = Rz(theta) @ R_raw`` with
  ``theta = theta_e + heading_drift.rate * tm``;
* current (Eq. 3): ``s = [s_x, s_y, 0] + [ds_x, ds_y, 0] * tm``;
  relative velocity, body: ``v_r = R.T @ (v - s)``;
* thrust (Eq. 1): ``a_thrust = sum_i g_i * d_i * dir_i`` with ``d_i`` the (lag-filtered)
  demand ``u_i|u_i|`` and gain ``g_i = k * (ratio if starboard) * (reverse ratio if d_i < 0)``;
* drag (Eq. 2): ``a_drag = -[k_x, k_yz, k_yz] * sign(v_r) * v_r**2 - [c_x, c_yz, c_yz] * v_r``;
* net body acceleration (Eqs. 4, 10): ``a_b = a_thrust + a_drag``; ground acceleration
  (Eq. 9): ``a = R @ a_b + [a_n, a_e, 0]`` (wind), vertical zeroed for planar vehicles.

Integration: constant acceleration over the step, ``x += h v + h^2/2 a``, ``v += h a``
(Eqs. 8-9 with the acceleration evaluated at the step start, as the paper's EKF does).
Thrust lag: each demand passes a first-order filter with time constant ``tau``; the step
uses the exact mean of the filter output over the step, so ``tau -> 0`` is smooth.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .params import INDEX, N_DYN

I_TH, I_SX, I_SY, I_K, I_KX, I_KYZ = 0, 1, 2, 3, 4, 5
I_ASYM = INDEX["thrust_asymmetry.ratio"]
I_REV = INDEX["reverse_thrust.ratio"]
I_TAU = INDEX["thrust_lag.tau"]
I_CX = INDEX["linear_drag.c_x"]
I_CYZ = INDEX["linear_drag.c_yz"]
I_HDR = INDEX["heading_drift.rate"]
I_DSX = INDEX["current_drift.ds_x"]
I_DSY = INDEX["current_drift.ds_y"]
I_WN = INDEX["wind_drag.a_n"]
I_WE = INDEX["wind_drag.a_e"]

E_Z = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])  # dRz/dtheta = E_Z @ Rz


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

    def slice(self, a: int, b: int) -> "Steps":
        return Steps(self.h[a:b], self.warm[a:b], self.R[a:b], self.dem[a:b], self.tm[a:b])


def rot_z(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


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


def thrust_gains(p: np.ndarray, side: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Thrust per unit demand of each propeller (Eq. 1 gain, m/s^2): ``k`` times the
    asymmetry ratio (starboard thrusters) times the reverse ratio (negative demand)."""
    g = np.where(np.asarray(side) > 0, p[I_K] * p[I_ASYM], p[I_K])
    return np.where(np.asarray(d) < 0, g * p[I_REV], g)


def accel(v: np.ndarray, R_raw: np.ndarray, d: np.ndarray, dd_tau: np.ndarray, tm: float,
          p: np.ndarray, geom: Geometry):
    """Ground-frame acceleration (m/s^2) and its Jacobians w.r.t. ``v`` (3x3) and ``p`` (3xN_DYN).

    ``v``: ground velocity (m/s, NED); ``R_raw``: IMU attitude (3x3); ``d``: mean thrust
    demand per thruster over the step, ``dd_tau`` its derivative w.r.t. ``thrust_lag.tau``.
    """
    th = p[I_TH] + p[I_HDR] * tm
    R = rot_z(th) @ R_raw
    s = np.array([p[I_SX] + p[I_DSX] * tm, p[I_SY] + p[I_DSY] * tm, 0.0])
    vr = R.T @ (v - s)

    # thrust (Eq. 1) with asymmetry and reverse-thrust ratios
    stb = geom.side > 0
    neg = d < 0
    g_asym = np.where(stb, p[I_ASYM], 1.0)
    g_rev = np.where(neg, p[I_REV], 1.0)
    g = thrust_gains(p, geom.side, d)
    a_thr = geom.dirs.T @ (g * d)

    # drag (Eq. 2) quadratic + linear
    kq = np.array([p[I_KX], p[I_KYZ], p[I_KYZ]])
    kl = np.array([p[I_CX], p[I_CYZ], p[I_CYZ]])
    a_drag = -kq * np.sign(vr) * vr**2 - kl * vr
    a_b = a_thr + a_drag
    a = R @ a_b + np.array([p[I_WN], p[I_WE], 0.0])

    D = np.diag(-2.0 * kq * np.abs(vr) - kl)   # d a_drag / d vr
    A = R @ D @ R.T                             # d a / d v
    Jp = np.zeros((3, N_DYN))
    # heading: dR/dth = E_Z R; a = R a_b(vr), vr = R^T (v - s)
    da_dth = E_Z @ (R @ a_b) + R @ D @ (R.T @ E_Z.T @ (v - s))
    Jp[:, I_TH] = da_dth
    Jp[:, I_HDR] = da_dth * tm
    Jp[:, I_SX] = -A[:, 0]
    Jp[:, I_SY] = -A[:, 1]
    Jp[:, I_DSX] = -A[:, 0] * tm
    Jp[:, I_DSY] = -A[:, 1] * tm
    Jp[:, I_K] = R @ (geom.dirs.T @ (g_asym * g_rev * d))
    Jp[:, I_KX] = R @ np.array([-np.sign(vr[0]) * vr[0] ** 2, 0.0, 0.0])
    Jp[:, I_KYZ] = R @ np.array([0.0, -np.sign(vr[1]) * vr[1] ** 2, -np.sign(vr[2]) * vr[2] ** 2])
    Jp[:, I_CX] = R @ np.array([-vr[0], 0.0, 0.0])
    Jp[:, I_CYZ] = R @ np.array([0.0, -vr[1], -vr[2]])
    Jp[:, I_ASYM] = R @ (geom.dirs.T @ np.where(stb, p[I_K] * g_rev * d, 0.0))
    Jp[:, I_REV] = R @ (geom.dirs.T @ np.where(neg, p[I_K] * g_asym * d, 0.0))
    Jp[:, I_TAU] = R @ (geom.dirs.T @ (g * dd_tau))
    Jp[0, I_WN] = 1.0
    Jp[1, I_WE] = 1.0
    if geom.planar:
        a[2] = 0.0
        A[2, :] = 0.0
        Jp[2, :] = 0.0
    return a, A, Jp


def propagate(x0: np.ndarray, p: np.ndarray, steps: Steps, geom: Geometry, user=()):
    """Integrate state ``x = [pos(3), vel(3)]`` (NED) over ``steps``.

    Returns ``x1`` (6,), ``J_x0`` (6, 6) and ``J_p`` (6, N_DYN + n_user) = d x1 / d p, where
    ``user`` lists ``(UserEffect, index of its first parameter in p)``; the user columns
    follow the N_DYN built-in ones in the order given.
    """
    p = np.asarray(p, dtype=float)
    pos = np.array(x0[:3], dtype=float)
    vel = np.array(x0[3:6], dtype=float)
    n_user = sum(len(e.param_names) for e, _ in user)
    ncol = 3 + N_DYN + n_user             # sensitivities w.r.t. v0 and p
    Sx = np.zeros((3, ncol))
    Sv = np.zeros((3, ncol))
    Sv[:, :3] = np.eye(3)
    tau = float(p[I_TAU])
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
            a, A, Jp = _add_user(a, A, Jp, user, vel, R_raw, d, tm, p, geom)
        dA = A @ Sv
        dA[:, 3:] += Jp
        pos = pos + h * vel + 0.5 * h * h * a
        vel = vel + h * a
        Sx = Sx + h * Sv + 0.5 * h * h * dA
        Sv = Sv + h * dA
    x1 = np.concatenate([pos, vel])
    Jx = np.eye(6)
    Jx[:3, 3:] = Sx[:, :3]
    Jx[3:, 3:] = Sv[:, :3]
    Jp_out = np.vstack([Sx[:, 3:], Sv[:, 3:]])
    return x1, Jx, Jp_out


def _add_user(a, A, Jp, user, vel, R_raw, d, tm, p, geom):
    """Add the user effects' accelerations and Jacobians (finite differences if not given)."""
    th = p[I_TH] + p[I_HDR] * tm
    R = rot_z(th) @ R_raw
    cols = [Jp]
    for eff, i0 in user:
        q = p[i0:i0 + len(eff.param_names)]
        a_u = np.asarray(eff.accel(vel, R, d, tm, q), dtype=float)
        Jv, Jq = eff.jacobians(vel, R, d, tm, q)
        eps = 1e-6
        a_th = (np.asarray(eff.accel(vel, rot_z(eps) @ R, d, tm, q))
                - np.asarray(eff.accel(vel, rot_z(-eps) @ R, d, tm, q))) / (2 * eps)
        Jp = cols[0]
        Jp[:, I_TH] += a_th
        Jp[:, I_HDR] += a_th * tm
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
    n_user = sum(len(e.param_names) for e, _ in user)
    X1 = np.zeros((K, 6))
    JX = np.zeros((K, 6, 6))
    JP = np.zeros((K, 6, N_DYN + n_user))
    for i in range(K):
        X1[i], JX[i], JP[i] = propagate(X0[i], p, steps.slice(offsets[i], offsets[i + 1]),
                                        geom, user)
    return X1, JX, JP


# ---------------------------------------------------------------- measurement functions
I_SCALE = INDEX["usbl_range_scale.scale"]
I_BIAS = INDEX["usbl_bearing_bias.bias"]
I_LX = INDEX["lever_arm.x"]


def sensor_position(pos: np.ndarray, R_raw: np.ndarray, tm: float, p: np.ndarray):
    """Position (NED, m) of the position sensor (GNSS antenna / USBL transponder).

    ``pos + R @ l`` with ``l`` the lever arm (body) and ``R`` the heading-corrected attitude.
    Returns the position, d/dpos (3x3) and d/dp (3 x N_PARAMS).
    """
    from .params import N_PARAMS
    l = p[I_LX:I_LX + 3]
    th = p[I_TH] + p[I_HDR] * tm
    R = rot_z(th) @ R_raw
    Rl = R @ l
    Jp = np.zeros((3, N_PARAMS))
    Jp[:, I_TH] = E_Z @ Rl
    Jp[:, I_HDR] = E_Z @ Rl * tm
    Jp[:, I_LX:I_LX + 3] = R
    return pos + Rl, np.eye(3), Jp


def h_gnss(pos, R_raw, tm, p):
    """GNSS fix model: north, east of the antenna. Returns z (2,), d/dpos (2x3), d/dp."""
    ps, Jx, Jp = sensor_position(pos, R_raw, tm, p)
    return ps[:2], Jx[:2], Jp[:2]


def h_depth(pos):
    """Depth sensor model: down coordinate of the centre of mass."""
    return np.array([pos[2]]), np.array([[0.0, 0.0, 1.0]])


def h_usbl(pos, R_raw, tm, p, station):
    """USBL model: slant range (m, times the range scale) and bearing (rad, from north,
    clockwise, plus the bias) of the transponder seen from ``station`` (NED).

    Returns z (2,), d/dpos (2x3), d/dp (2 x N_PARAMS).
    """
    ps, Jx, Jp = sensor_position(pos, R_raw, tm, p)
    d = ps - np.asarray(station, dtype=float)
    r = float(np.linalg.norm(d))
    rh2 = d[0] ** 2 + d[1] ** 2
    scale = p[I_SCALE]
    z = np.array([scale * r, np.arctan2(d[1], d[0]) + p[I_BIAS]])
    dr = scale * d / max(r, 1e-9)
    db = np.array([-d[1], d[0], 0.0]) / max(rh2, 1e-12)
    Hd = np.vstack([dr, db])
    Jpos = Hd @ Jx
    Jpp = Hd @ Jp
    Jpp[0, I_SCALE] += r
    Jpp[1, I_BIAS] += 1.0
    return z, Jpos, Jpp


def wrap_angle(a):
    """Angles (rad) wrapped into [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi
