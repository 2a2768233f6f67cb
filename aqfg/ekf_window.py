"""One EKF pass over a stretch of the history: the paper's Eq. 13 and the update errors of Eq. 11.

:func:`run_window` starts from a state ``(x0, P0)`` at knot ``k0`` (an anchor), predicts with
the shared vehicle model through every kernel step up to knot ``k1``, and applies every update
node on the way. It returns the update error ``e_i = K_i (z_i - h(X))`` of every node
(motor commands: zero, Eq. 11 and §III-B), the innovations, and optionally the state at
every knot. :func:`window_ref` is the readable numpy version; :func:`run_window` calls the
C++ mirror in ``cpp_factors/ekf.cpp`` when it is built, and tests hold them equal.

Prediction (Eqs. 7-10). Per kernel step of length ``h`` with raw attitude ``R_raw`` and
mean thrust demand ``d`` (thrust-lag filter carried across steps as the kernel does):
``a = kernel.accel(v, ...)`` (ground frame, the ONE model definition),
``x += h v + h^2/2 a``, ``v += h a`` -- the same integration as :func:`Model.propagate`,
so without updates the filter reproduces :func:`aqfg.retrace.rollout` exactly. The body
acceleration state is the model's (Eq. 10): ``a_b = R^T a`` of the knot's last step, with
``R = Rz(theta) R_raw`` (Eq. 6). The covariance of ``[x, v]`` is carried with the step
Jacobians accumulated between knots that hold an update (``Phi``; kinematic ``A = 0`` or the
model's ``A = d a / d v``, see ``EkfConfig.cov_model``), then
``P <- M (Phi P Phi^T + Q) M^T + diag(0, 0, sigma_ab^2)``, with ``M`` appending
``d a_b / d v = R^T A`` ("full") or nothing ("kinematic"); the old ``a_b`` is overwritten by
Eq. 10, so its rows drop.

Updates: GNSS (north, east of the antenna, lever arm included); USBL range/bearing
converted to a horizontal position (with the range-scale and bearing-bias parameters),
covariance ``Rot(b) diag(sigma_rh^2, (r_h sigma_b)^2) Rot(b)^T``, chi^2 gate; depth; IMU
acceleration (``a_b``). Joseph-form covariance update. A gated (rejected) node leaves the
state alone, and its update error is the one it would have at the gate boundary
(``K nu`` scaled to the Mahalanobis distance ``sqrt(gate)``): ``E`` stays continuous and
rejecting a fix never lowers ``E``, so the optimiser gains nothing by pushing fixes out of
the gate. After ``max_rejects`` consecutive rejections the next USBL fix is taken whatever
its distance (the counter is carried across windows in the anchors).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import kernel_ref as ref
from .ekf_history import DEPTH, GNSS, IMU_ACC, MOTOR, USBL, History
from .params import N_DYN

try:
    from . import _kernel as _cpp  # type: ignore[attr-defined]
    _HAVE_CPP_EKF = hasattr(_cpp, "ekf_window")
except ImportError:  # pragma: no cover - no build
    _cpp = None
    _HAVE_CPP_EKF = False

# node status codes
REJECTED, ACCEPTED, NOOP = 0, 1, 2


@dataclass
class WindowOut:
    """Result of one pass from knot ``k0`` to ``k1``.

    ``node_lo:node_hi`` index the history's nodes covered (knot in ``(k0, k1]``); per node
    ``e`` (n, 9) update error, ``nu`` (n, 3) innovation z - h (NaN-padded), ``nu_w`` (n, 3)
    innovation whitened by its covariance S (Cholesky), ``s`` (n, 3) sqrt(diag S),
    ``status`` (n,) REJECTED / ACCEPTED / NOOP (motor). ``x``/``P`` at ``k1``. With
    ``record``: ``X`` (k1 - k0 + 1, 9) state at every knot ``k0..k1`` after its updates and
    ``Pn`` (n, 9, 9) covariance after each node. ``rejects``: consecutive USBL rejections
    at ``k1`` (to carry into the next pass).
    """
    node_lo: int
    node_hi: int
    e: np.ndarray
    nu: np.ndarray
    nu_w: np.ndarray
    s: np.ndarray
    status: np.ndarray
    x: np.ndarray
    P: np.ndarray
    X: np.ndarray | None = None
    Pn: np.ndarray | None = None
    rejects: int = 0          # consecutive USBL rejections at k1

    def error(self) -> float:
        """E over this window (Eq. 14): sum of squared update errors."""
        return float(np.sum(self.e * self.e))


def corrected_attitude(R_raw: np.ndarray, tm: float, p: np.ndarray) -> np.ndarray:
    """Heading-corrected attitude ``Rz(theta_e + rate tm) R_raw`` (Eq. 6), as the kernel forms it."""
    th = p[ref.I_TH] + p[ref.I_HDR] * tm
    return ref.rot_z(th) @ R_raw


def _q_block(q: float, T: float) -> np.ndarray:
    return q * np.array([[T**3 / 3.0, T**2 / 2.0], [T**2 / 2.0, T]])


def process_noise(T: float, q_h: float, q_v: float, planar: bool) -> np.ndarray:
    """Q (6x6) on [x, v] over T seconds: white acceleration, exact for a double integrator."""
    Q = np.zeros((6, 6))
    for i, q in enumerate((q_h, q_h, 0.0 if planar else q_v)):
        b = _q_block(q, T)
        Q[np.ix_([i, i + 3], [i, i + 3])] = b
    return Q


def predict_covariance(P: np.ndarray, Sx: np.ndarray, Sv: np.ndarray, T: float, J_ab: np.ndarray,
                       cfg, planar: bool) -> np.ndarray:
    """Covariance at a knot from the one at the last propagation point (see module doc).

    ``Sx``, ``Sv``: d pos / d v0 and d vel / d v0 accumulated over the kernel steps since then
    (position does not feed back into the model, so ``Phi = [[I, Sx], [0, Sv]]``)."""
    Phi = np.eye(6)
    Phi[:3, 3:] = Sx
    Phi[3:, 3:] = Sv
    P6 = Phi @ P[:6, :6] @ Phi.T + process_noise(T, cfg.q_h, cfg.q_v, planar)
    M = np.zeros((9, 6))
    M[:6, :6] = np.eye(6)
    if cfg.cov_model == "full":
        M[6:, 3:] = J_ab
    Pn = M @ P6 @ M.T
    Pn[6:, 6:] += cfg.sigma_ab**2 * np.eye(3)
    return Pn


def usbl_to_position(z: np.ndarray, station: np.ndarray, p: np.ndarray, sigma_range: float,
                     sigma_bearing: float):
    """USBL (range, bearing, down) -> horizontal position (2,) and covariance (2x2).

    Range and bearing are first corrected by the ``usbl_range_scale`` and
    ``usbl_bearing_bias`` parameters (measured = scale * true; measured = true + bias).
    The horizontal range ``r_h = sqrt(r^2 - dz^2)``; its error ``sigma_r r / r_h`` is radial,
    the bearing error ``r_h sigma_b`` tangential (paper §IV-C, Fig. 5).
    """
    r = z[0] / p[ref.I_SCALE]
    b = z[1] - p[ref.I_BIAS]
    dz = z[2] - station[2]
    rh = float(np.sqrt(max(r * r - dz * dz, 0.0)))
    c, s = np.cos(b), np.sin(b)
    pos = np.array([station[0] + rh * c, station[1] + rh * s])
    sr = sigma_range * min(r / max(rh, 1e-6), 10.0)
    st = max(rh, 1e-3) * sigma_bearing
    Rot = np.array([[c, -s], [s, c]])
    return pos, Rot @ np.diag([sr * sr, st * st]) @ Rot.T


def _update(x, P, idx, z, hx, Rm, gate):
    """Kalman update of the state components ``idx`` measured directly (H = selection).

    Returns (accepted, e (9,), nu, nu_w, s, x, P)."""
    S = P[np.ix_(idx, idx)] + Rm
    nu = z - hx
    L = np.linalg.cholesky(S)
    nu_w = np.linalg.solve(L, nu)
    s = np.sqrt(np.diag(S))
    K = np.linalg.solve(S, P[idx, :]).T          # P H^T S^-1  (S symmetric)
    e = K @ nu
    m2 = float(nu_w @ nu_w)
    if np.isfinite(gate) and m2 > gate:
        return False, e * (gate / m2) ** 0.25, nu, nu_w, s, x, P
    IKH = np.eye(9)
    IKH[:, idx] -= K
    P = IKH @ P @ IKH.T + K @ Rm @ K.T
    return True, e, nu, nu_w, s, x + e, P


def window_ref(hist: History, p: np.ndarray, x0: np.ndarray, P0: np.ndarray, k0: int, k1: int,
               record: bool = False, rejects: int = 0) -> WindowOut:
    """Numpy reference of the EKF pass from knot ``k0`` to ``k1`` with parameters ``p`` (full
    vector of the model); ``rejects``: consecutive USBL rejections before ``k0``. See the
    module docstring for the maths."""
    cfg = hist.config
    model = hist.model
    geom = model.geometry
    user = model._user_layout()
    st = hist.steps
    planar = geom.planar
    full = cfg.cov_model == "full"

    tau = float(p[ref.I_TAU])
    s0 = int(hist.offsets[k0])
    w0 = hist.warm_start(k0)
    nst = len(st.h)
    f = st.dem[min(w0, nst - 1)].astype(float).copy() if nst else np.zeros(0)
    df = np.zeros_like(f)
    for j in range(w0, s0):
        _, _, f, df = ref.filter_step(f, df, st.dem[j].astype(float), float(st.h[j]), tau)

    x = np.array(x0, float)
    P = np.array(P0, float)
    pos, vel = x[:3].copy(), x[3:6].copy()
    ab = x[6:9].copy()
    Sx, Sv, T = np.zeros((3, 3)), np.eye(3), 0.0
    J_ab = np.zeros((3, 3))
    lo, hi = hist.nodes_between(k0, k1)
    n = hi - lo
    e_all = np.zeros((n, 9))
    nu_all = np.full((n, 3), np.nan)
    nuw_all = np.full((n, 3), np.nan)
    s_all = np.full((n, 3), np.nan)
    status = np.full(n, NOOP, dtype=np.int8)
    X = np.zeros((k1 - k0 + 1, 9)) if record else None
    Pn = np.zeros((n, 9, 9)) if record else None
    if record:
        X[0] = x
    m = lo
    for k in range(k0, k1):
        for j in range(int(hist.offsets[k]), int(hist.offsets[k + 1])):
            h = float(st.h[j])
            d, dd, f, df = ref.filter_step(f, df, st.dem[j].astype(float), h, tau)
            if h <= 0.0:
                continue
            R_raw = st.R[j].reshape(3, 3)
            tm = float(st.tm[j])
            a, A, Jp = ref.accel(vel, R_raw, d, dd, tm, p, geom)
            if user:
                a, A, Jp = ref._add_user(a, A, Jp, user, vel, R_raw, d, tm, p, geom)
            Rc = corrected_attitude(R_raw, tm, p)
            ab = Rc.T @ a                                  # Eq. 10 (model body acceleration)
            J_ab = Rc.T @ A
            Ac = A if full else np.zeros((3, 3))           # covariance Jacobian (cov_model)
            Sx = Sx + h * Sv + 0.5 * h * h * (Ac @ Sv)
            Sv = Sv + h * (Ac @ Sv)
            pos = pos + h * vel + 0.5 * h * h * a
            vel = vel + h * a
        T += float(hist.knots[k + 1] - hist.knots[k])
        x = np.concatenate([pos, vel, ab])
        b = m
        while b < hi and hist.node_knot[b] == k + 1:
            b += 1
        if any(hist.node_kind[i] != MOTOR for i in range(m, b)):
            P = predict_covariance(P, Sx, Sv, T, J_ab, cfg, planar)
            Sx, Sv, T = np.zeros((3, 3)), np.eye(3), 0.0
        for i in range(m, b):
            kind = int(hist.node_kind[i])
            z = hist.node_z[i]
            r = i - lo
            ok = None
            if kind == GNSS:
                zp = ref.sensor_position(x[:3], hist.node_R[i].reshape(3, 3), hist.node_tm[i], p)[0]
                ok, e, nu, nw, s, x, P = _update(x, P, [0, 1], z[:2], zp[:2],
                                                 z[2] ** 2 * np.eye(2), cfg.gate_gnss)
            elif kind == USBL:
                zpos, Rm = usbl_to_position(z, hist.station, p, cfg.sigma_range, cfg.sigma_bearing)
                zp = ref.sensor_position(x[:3], hist.node_R[i].reshape(3, 3), hist.node_tm[i], p)[0]
                gate = cfg.gate_usbl if rejects < cfg.max_rejects else np.inf
                ok, e, nu, nw, s, x, P = _update(x, P, [0, 1], zpos, zp[:2], Rm, gate)
                rejects = 0 if ok else rejects + 1
            elif kind == DEPTH:
                ok, e, nu, nw, s, x, P = _update(x, P, [2], z[:1], x[2:3],
                                                 np.array([[z[1] ** 2]]), np.inf)
            elif kind == IMU_ACC:
                ok, e, nu, nw, s, x, P = _update(x, P, [6, 7, 8], z[:3], x[6:9],
                                                 z[3] ** 2 * np.eye(3), np.inf)
            if ok is not None:
                status[r] = ACCEPTED if ok else REJECTED
                e_all[r] = e
                nu_all[r, :len(nu)] = nu
                nuw_all[r, :len(nu)] = nw
                s_all[r, :len(nu)] = s
            if record:
                Pn[r] = P
        pos, vel, ab = x[:3].copy(), x[3:6].copy(), x[6:9].copy()
        m = b
        if record:
            X[k + 1 - k0] = x
    if T > 0:
        P = predict_covariance(P, Sx, Sv, T, J_ab, cfg, planar)
    return WindowOut(lo, hi, e_all, nu_all, nuw_all, s_all, status,
                     np.concatenate([pos, vel, ab]), P, X, Pn, rejects)


def run_window(hist: History, p: np.ndarray, x0: np.ndarray, P0: np.ndarray, k0: int, k1: int,
               record: bool = False, use_cpp: bool | None = None, rejects: int = 0) -> WindowOut:
    """The EKF pass, in C++ when built (and no Python user effect is active), else numpy."""
    if use_cpp is None:
        use_cpp = _HAVE_CPP_EKF and not hist.model.user_effects
    if not use_cpp:
        return window_ref(hist, p, x0, P0, k0, k1, record, rejects)
    if not _HAVE_CPP_EKF:
        raise RuntimeError("the C++ EKF window (aqfg._kernel.ekf_window) is not built")
    g = hist.model.geometry
    st = hist.steps
    lo, hi = hist.nodes_between(k0, k1)
    p = np.asarray(p, float)
    pm = np.ascontiguousarray(p[[ref.I_SCALE, ref.I_BIAS, ref.I_LX, ref.I_LX + 1, ref.I_LX + 2]])
    out = _cpp.ekf_window(np.ascontiguousarray(x0, float), np.ascontiguousarray(P0, float),
                          int(k0), int(k1), np.ascontiguousarray(p[:N_DYN]), pm,
                          hist.config.vector(hist.model.lookback), st.h, st.R, st.dem, st.tm,
                          hist.offsets, hist.knots, int(hist.warm_start(k0)),
                          hist.node_knot, hist.node_kind, hist.node_z, hist.node_R,
                          hist.node_tm, hist.station, g.dirs, g.side, bool(g.planar),
                          int(lo), int(hi), bool(record), int(rejects))
    e, nu, nuw, s, status, x, P, X, Pn, rej = out
    return WindowOut(lo, hi, e, nu, nuw, s, status, x, P,
                     X if record else None, Pn if record else None, int(rej))
