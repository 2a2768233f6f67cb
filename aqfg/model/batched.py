"""The kernel for models with a user effect: every segment integrated in lockstep, numpy.

A user effect is Python, so the C++ kernel cannot run it, and the per-step numpy mirror
(:func:`aqfg.model.reference.propagate`) pays Python's overhead at every input sample of
every dynamics factor. Here the K segments of a batch (all dynamics factors of a mission
between two linearisations) advance together: step ``j`` of every segment is one set of
array operations over K, and the user effect's acceleration is evaluated once per step
index for all segments at once. The arithmetic is :func:`aqfg.model.reference.accel` /
``propagate`` line by line (tests hold the two equal to 1e-10); segments of different
lengths are padded with zero-length steps, which change nothing.

Derivatives of a user effect: central differences, all perturbations stacked into the one
call per step (the velocity's 3 axes, each parameter, and a turn of the attitude about
down: ``1 + 2 (4 + m)`` samples per segment, m parameters). Truncation error O(eps^2) and
rounding O(1e-16 / eps) put them within ~1e-9 of the exact derivatives, far below what a
Gauss-Newton step needs. Complex-step differentiation would be exact but silently wrong
for functions using ``abs``, ``sign`` or comparisons, which drag laws do; automatic
differentiation would need the user to write in its framework. A user may pass analytic
``jac`` instead.

A user effect written for one sample (``accel(v (3,), R (3, 3), d (N,), tm, q)``) is called
sample by sample; with ``vectorized=True`` it receives ``v (n, 3)``, ``R (n, 3, 3)``,
``d (n, N)``, ``tm (n,)`` and returns ``(n, 3)``, which is what makes it fast.
"""
from __future__ import annotations

import numpy as np

from aqfg.model.effects import abs_command
from aqfg.model.frames import heading
from aqfg.model.params import N_DYN
from aqfg.model.reference import (
    I_ASYM,
    I_CX,
    I_CYZ,
    I_DSX,
    I_DSY,
    I_GA,
    I_HDR,
    I_K,
    I_KX,
    I_KYZ,
    I_REV,
    I_SX,
    I_SY,
    I_TAU,
    I_TH,
    I_WE,
    I_WN,
    Geometry,
    Steps,
)

EPS = 1e-6


def _rot_z(th: np.ndarray) -> np.ndarray:
    c, s = np.cos(th), np.sin(th)
    R = np.zeros(th.shape + (3, 3))
    R[..., 0, 0] = c
    R[..., 0, 1] = -s
    R[..., 1, 0] = s
    R[..., 1, 1] = c
    R[..., 2, 2] = 1.0
    return R


def _mv(M: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``M[k] @ x[k]`` for M (K, 3, 3), x (K, 3)."""
    return (M @ x[:, :, None])[:, :, 0]


def _mtv(M: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``M[k].T @ x[k]``."""
    return (x[:, None, :] @ M)[:, 0, :]


def _ez(x: np.ndarray) -> np.ndarray:
    """``E_Z @ x`` for x (..., 3): (-x1, x0, 0)."""
    out = np.zeros_like(x)
    out[..., 0] = -x[..., 1]
    out[..., 1] = x[..., 0]
    return out


def _ezt(x: np.ndarray) -> np.ndarray:
    """``E_Z^T @ x``: (x1, -x0, 0)."""
    out = np.zeros_like(x)
    out[..., 0] = x[..., 1]
    out[..., 1] = -x[..., 0]
    return out


def filter_step(f, df, c, h, tau: float):
    """:func:`aqfg.model.reference.filter_step` for K segments at once (``h`` (K,))."""
    h = h[:, None]
    if tau < 1e-9:
        pos = h > 0
        mean = np.where(pos, c, f)
        dmean = np.where(pos, (f - c) / np.where(pos, h, 1.0), df)
        return mean, dmean, np.where(pos, c, f), np.where(pos, 0.0, df)
    e = np.exp(-h / tau)
    pos = h > 0
    hs = np.where(pos, h, 1.0)
    phi = np.where(pos, tau / hs * (1.0 - e), 1.0)
    dphi = np.where(pos, (1.0 - e) / hs - e / tau, 0.0)
    mean = c + (f - c) * phi
    dmean = df * phi + (f - c) * dphi
    de = e * h / tau ** 2
    return mean, dmean, c + (f - c) * e, df * e + (f - c) * de


def accel(v, R_raw, d, dd_tau, tm, p, geom: Geometry, jac: bool = True):
    """:func:`aqfg.model.reference.accel` for K samples: v (K, 3), R_raw (K, 3, 3), d and
    dd_tau (K, N), tm (K,). Returns a (K, 3), A (K, 3, 3), Jp (K, 3, N_DYN) and the
    heading-corrected attitude R (K, 3, 3); with ``jac=False`` only a and R."""
    K = len(v)
    th = heading(p, tm)
    R = _rot_z(th) @ R_raw
    s = np.zeros((K, 3))
    s[:, 0] = p[I_SX] + p[I_DSX] * tm
    s[:, 1] = p[I_SY] + p[I_DSY] * tm
    w = v - s
    vr = _mtv(R, w)
    stb = np.asarray(geom.side) > 0
    neg = d < 0
    g_asym = np.where(stb, p[I_ASYM], 1.0)
    g_rev = np.where(neg, p[I_REV], 1.0)
    g = p[I_K] * g_asym * g_rev
    dirs = np.asarray(geom.dirs, float)
    a_thr = (g * d) @ dirs
    # ground_advance: thrust lost with |u| and the advance speed over ground
    c_ga = p[I_GA]
    if c_ga != 0.0 or jac:       # (its Jacobian column is needed at c = 0 too: the tests)
        va = _mtv(R, v) @ dirs.T
        n_abs, dn_dd = abs_command(d)
    if c_ga != 0.0:
        a_thr = a_thr - (c_ga * n_abs * va) @ dirs
    kq = np.array([p[I_KX], p[I_KYZ], p[I_KYZ]])
    kl = np.array([p[I_CX], p[I_CYZ], p[I_CYZ]])
    sq = np.sign(vr) * vr ** 2
    a_b = a_thr - kq * sq - kl * vr
    Rab = _mv(R, a_b)
    a = Rab.copy()
    a[:, 0] += p[I_WN]
    a[:, 1] += p[I_WE]
    if not jac:
        if geom.planar:
            a[:, 2] = 0.0
        return a, R
    Dg = -2.0 * kq * np.abs(vr) - kl
    Rt = np.transpose(R, (0, 2, 1))
    A = (R * Dg[:, None, :]) @ Rt
    Jp = np.zeros((K, 3, N_DYN))
    da_dth = _ez(Rab) + _mv(A, _ezt(w))
    if c_ga != 0.0:
        RM = R @ np.einsum("ki,ij,il->kjl", -c_ga * n_abs, dirs, dirs)  # R d a_b / d vg
        da_dth = da_dth + _mv(RM, _mtv(R, _ezt(v)))
        dloss_dd = c_ga * va * dn_dd
    else:
        dloss_dd = 0.0
    Jp[:, :, I_TH] = da_dth
    Jp[:, :, I_HDR] = da_dth * tm[:, None]
    Jp[:, :, I_SX] = -A[:, :, 0]
    Jp[:, :, I_SY] = -A[:, :, 1]
    Jp[:, :, I_DSX] = -A[:, :, 0] * tm[:, None]
    Jp[:, :, I_DSY] = -A[:, :, 1] * tm[:, None]

    def body(x):            # R @ x for x (K, 3)
        return _mv(R, x)
    Jp[:, :, I_K] = body((g_asym * g_rev * d) @ dirs)
    Jp[:, :, I_KX] = R[:, :, 0] * -sq[:, 0:1]
    Jp[:, :, I_KYZ] = R[:, :, 1] * -sq[:, 1:2] + R[:, :, 2] * -sq[:, 2:3]
    Jp[:, :, I_CX] = R[:, :, 0] * -vr[:, 0:1]
    Jp[:, :, I_CYZ] = R[:, :, 1] * -vr[:, 1:2] + R[:, :, 2] * -vr[:, 2:3]
    Jp[:, :, I_ASYM] = body(np.where(stb, p[I_K] * g_rev * d, 0.0) @ dirs)
    Jp[:, :, I_REV] = body(np.where(neg, p[I_K] * g_asym * d, 0.0) @ dirs)
    Jp[:, :, I_TAU] = body(((g - dloss_dd) * dd_tau) @ dirs)
    Jp[:, 0, I_WN] = 1.0
    Jp[:, 1, I_WE] = 1.0
    Jp[:, :, I_GA] = body(-(n_abs * va) @ dirs)
    if c_ga != 0.0:
        A = A + RM @ Rt        # after the current's columns: the inflow sees the ground speed
    if geom.planar:
        a[:, 2] = 0.0
        A[:, 2, :] = 0.0
        Jp[:, 2, :] = 0.0
    return a, A, Jp, R


def _is_user(eff) -> bool:
    """A :class:`~aqfg.model.effects.UserEffect` (``accel`` callable); other ground-force
    terms give ``ground_accel`` / ``ground_jacobians`` per sample."""
    return hasattr(eff, "accel") and hasattr(eff, "vectorized")


def _call(eff, v, R, d, tm, q) -> np.ndarray:
    """The effect's acceleration (n, 3) at n samples."""
    if not _is_user(eff):
        return np.array([np.asarray(eff.ground_accel(v[i], R[i], d[i], float(tm[i]), q), float)
                         for i in range(len(v))]).reshape(len(v), 3)
    if getattr(eff, "vectorized", False):
        out = np.asarray(eff.accel(v, R, d, tm, q), dtype=float)
        if out.shape != (len(v), 3):
            raise ValueError(f"user effect {eff.name!r} (vectorized) returned shape "
                             f"{out.shape} for {len(v)} samples, expected ({len(v)}, 3)")
        return out
    return np.array([np.asarray(eff.accel(v[i], R[i], d[i], float(tm[i]), q), dtype=float)
                     for i in range(len(v))]).reshape(len(v), 3)


def user_terms(eff, v, R, d, tm, q):
    """A user effect's acceleration (K, 3) and its derivatives: d/dv (K, 3, 3), d/dq
    (K, 3, m), d/dtheta (K, 3) (a turn of ``R`` about down), by central differences: the
    value, the velocity and the attitude perturbations in one stacked call, each parameter
    perturbation in one call (``eff.jac`` replaces the first two when given)."""
    K = len(v)
    q = np.asarray(q, float)
    m = len(q)
    if not _is_user(eff):          # a term with its own derivatives, sample by sample
        a_u = _call(eff, v, R, d, tm, q)
        Jv, Jq, Jth = np.empty((K, 3, 3)), np.empty((K, 3, m)), np.empty((K, 3))
        for n in range(K):
            Jv[n], Jq[n], Jth[n] = eff.ground_jacobians(v[n], R[n], d[n], float(tm[n]), q)
        return a_u, Jv, Jq, Jth
    # value, v +- eps e_i (i = 0..2), R turned by +- eps about down
    V = np.repeat(v[None], 9, axis=0)
    RR = np.repeat(R[None], 9, axis=0)
    for i in range(3):
        V[1 + 2 * i, :, i] += EPS
        V[2 + 2 * i, :, i] -= EPS
    RR[7] = _rot_z(np.full(K, EPS)) @ R
    RR[8] = _rot_z(np.full(K, -EPS)) @ R
    out = _call(eff, V.reshape(-1, 3), RR.reshape(-1, 3, 3), np.tile(d, (9, 1)),
                np.tile(tm, 9), q).reshape(9, K, 3)
    a_u = out[0]
    Jv = np.stack([(out[1 + 2 * i] - out[2 + 2 * i]) / (2 * EPS) for i in range(3)], axis=2)
    Jth = (out[7] - out[8]) / (2 * EPS)
    Jq = np.empty((K, 3, m))
    for i in range(m):
        e = np.zeros(m)
        e[i] = EPS * max(1.0, abs(q[i]))
        Jq[:, :, i] = (_call(eff, v, R, d, tm, q + e) - _call(eff, v, R, d, tm, q - e)) / (2 * e[i])
    if eff.jac is not None:
        if getattr(eff, "vectorized", False):
            Jv, Jq = (np.asarray(x, float) for x in eff.jac(v, R, d, tm, q))
        else:
            for n in range(K):
                jv, jq = eff.jac(v[n], R[n], d[n], float(tm[n]), q)
                Jv[n], Jq[n] = jv, jq
    return a_u, Jv, Jq, Jth


def propagate_many(X0: np.ndarray, p: np.ndarray, steps: Steps, offsets: np.ndarray,
                   geom: Geometry, user=()):
    """:func:`aqfg.model.reference.propagate_many`: segment i integrates steps
    ``offsets[i]:offsets[i+1]`` from ``X0[i]``; all segments in lockstep. ``user``:
    ``(UserEffect, index of its first parameter in p)``. Returns X1 (K, 6), JX (K, 6, 6),
    JP (K, 6, N_DYN + n_user)."""
    p = np.asarray(p, float)
    X0 = np.atleast_2d(np.asarray(X0, float))
    offsets = np.asarray(offsets, np.int64)
    K = len(offsets) - 1
    n_user = sum(len(e.params) for e, _ in user)
    ncol = 3 + N_DYN + n_user
    lens = np.diff(offsets)
    L = int(lens.max()) if K else 0
    pos = X0[:, :3].copy()
    vel = X0[:, 3:6].copy()
    Sx = np.zeros((K, 3, ncol))
    Sv = np.zeros((K, 3, ncol))
    Sv[:, :, :3] = np.eye(3)
    tau = float(p[I_TAU])
    nthr = steps.dem.shape[1] if steps.dem.ndim == 2 else 0
    first = np.where(lens > 0, offsets[:-1], 0)
    f = steps.dem[first].astype(float) if len(steps.h) else np.zeros((K, nthr))
    f[lens == 0] = 0.0
    df = np.zeros_like(f)
    for j in range(L):
        live = j < lens
        ix = np.where(live, offsets[:-1] + j, 0)
        h = np.where(live, steps.h[ix], 0.0)
        c = np.where(live[:, None], steps.dem[ix], f)
        d, dd, f, df = filter_step(f, df, c, h, tau)
        act = live & ~steps.warm[ix].astype(bool) & (h > 0.0)
        if not act.any():
            continue
        k = slice(None) if act.all() else np.flatnonzero(act)
        hk = h[k]
        R_raw = steps.R[ix[k]].reshape(-1, 3, 3)
        tm = steps.tm[ix[k]].astype(float)
        a, A, Jp, R = accel(vel[k], R_raw, d[k], dd[k], tm, p, geom)
        if user:
            cols = [Jp]
            for eff, i0 in user:
                q = p[i0:i0 + len(eff.params)]
                a_u, Jv, Jq, Jth = user_terms(eff, vel[k], R, d[k], tm, q)
                Jp = cols[0]
                Jp[:, :, I_TH] += Jth
                Jp[:, :, I_HDR] += Jth * tm[:, None]
                if geom.planar:
                    a_u[:, 2] = 0.0
                    Jv[:, 2] = 0.0
                    Jq[:, 2] = 0.0
                    Jp[:, 2] = 0.0
                a = a + a_u
                A = A + Jv
                cols.append(Jq)
            Jp = np.concatenate(cols, axis=2)
        dA = A @ Sv[k]
        dA[:, :, 3:] += Jp
        h1 = hk[:, None]
        h2 = 0.5 * hk[:, None] ** 2
        pos[k] = pos[k] + h1 * vel[k] + h2 * a
        vel[k] = vel[k] + h1 * a
        Sx[k] = Sx[k] + h1[:, :, None] * Sv[k] + h2[:, :, None] * dA
        Sv[k] = Sv[k] + h1[:, :, None] * dA
    X1 = np.concatenate([pos, vel], axis=1)
    JX = np.repeat(np.eye(6)[None], K, axis=0)
    JX[:, :3, 3:] = Sx[:, :, :3]
    JX[:, 3:, 3:] = Sv[:, :, :3]
    JP = np.concatenate([Sx[:, :, 3:], Sv[:, :, 3:]], axis=1)
    return X1, JX, JP


def propagate(x0: np.ndarray, p: np.ndarray, steps: Steps, geom: Geometry, user=()):
    """:func:`aqfg.model.reference.propagate` (one segment) through :func:`propagate_many`."""
    X1, JX, JP = propagate_many(np.asarray(x0, float)[None], p, steps,
                                np.array([0, len(steps.h)]), geom, user)
    return X1[0], JX[0], JP[0]


def rollout(x0: np.ndarray, p: np.ndarray, steps: Steps, offsets: np.ndarray,
            geom: Geometry, user=()) -> np.ndarray:
    """States (K + 1, 6) at the segment boundaries of one trajectory integrated from ``x0``
    through the K consecutive segments (no Jacobians: the model-only re-trace). What does
    not depend on the state (attitude, current, thrust after the lag filter, wind) is
    computed for every step at once; only the velocity-dependent drag, inflow and user terms
    are stepped."""
    p = np.asarray(p, float)
    offsets = np.asarray(offsets, np.int64)
    K = len(offsets) - 1
    n = len(steps.h)
    X = np.zeros((K + 1, 6))
    X[0] = x0
    if n == 0:
        X[1:] = x0
        return X
    # the thrust-lag filter restarts at each segment start (as propagate does)
    tau = float(p[I_TAU])
    seg_of = np.searchsorted(offsets, np.arange(n), side="right") - 1
    dem = steps.dem.astype(float)
    if tau < 1e-9:
        d = dem.copy()
        warm_f = None
    else:
        d = np.empty_like(dem)
        f = df = None
        for j in range(n):
            if j == offsets[seg_of[j]]:
                f = dem[j:j + 1].copy()
                df = np.zeros_like(f)
            dj, _, f, df = filter_step(f, df, dem[j:j + 1], steps.h[j:j + 1], tau)
            d[j] = dj[0]
        warm_f = True
    del warm_f
    tm = steps.tm.astype(float)
    th = heading(p, tm)
    R = _rot_z(th) @ steps.R.reshape(-1, 3, 3)
    Rt = np.transpose(R, (0, 2, 1))
    s = np.zeros((n, 3))
    s[:, 0] = p[I_SX] + p[I_DSX] * tm
    s[:, 1] = p[I_SY] + p[I_DSY] * tm
    stb = np.asarray(geom.side) > 0
    g = p[I_K] * np.where(stb, p[I_ASYM], 1.0) * np.where(d < 0, p[I_REV], 1.0)
    a_fix = _mv(R, (g * d) @ np.asarray(geom.dirs, float))
    a_fix[:, 0] += p[I_WN]
    a_fix[:, 1] += p[I_WE]
    kq = np.array([p[I_KX], p[I_KYZ], p[I_KYZ]])
    kl = np.array([p[I_CX], p[I_CYZ], p[I_CYZ]])
    dirs = np.asarray(geom.dirs, float)
    c_ga = float(p[I_GA])
    n_ga = c_ga * abs_command(d)[0] if c_ga != 0.0 else None     # (n, N)
    qs = [(eff, p[i0:i0 + len(eff.params)]) for eff, i0 in user]
    live = ~steps.warm.astype(bool) & (steps.h > 0.0)
    planar = geom.planar
    pos = np.asarray(x0[:3], float).copy()
    vel = np.asarray(x0[3:6], float).copy()
    ends = offsets[1:]
    seg = 0
    while seg < K and ends[seg] == 0:
        X[seg + 1, :3], X[seg + 1, 3:] = pos, vel
        seg += 1
    for j in range(n):
        if live[j]:
            h = float(steps.h[j])
            vr = Rt[j] @ (vel - s[j])
            a_b = -kq * np.abs(vr) * vr - kl * vr
            if n_ga is not None:
                a_b = a_b - (n_ga[j] * (dirs @ (Rt[j] @ vel))) @ dirs
            a = a_fix[j] + R[j] @ a_b
            for eff, q in qs:
                a = a + _call(eff, vel[None], R[j:j + 1], d[j:j + 1], tm[j:j + 1], q)[0]
            if planar:
                a[2] = 0.0
            pos += h * vel + (0.5 * h * h) * a
            vel += h * a
        while seg < K and ends[seg] == j + 1:
            X[seg + 1, :3], X[seg + 1, 3:] = pos, vel
            seg += 1
    return X
